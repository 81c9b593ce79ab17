"""The ERVA quarter car, written once in CasADi and shared by every user.

Nonlinear ERVA (paper eqs. (9)-(10) and the compact form (11), Φ(x)ẋ = f(x, u, w)):

    x = [z_s, ż_s, z_us, ż_us, z_d, ż_d]   (m, m/s)
    u = c_e     electrical damping (Ns/m), w = z_r road height at the tyre (m)

Linear benchmark (paper eq. (15)), generator rigidly coupled to the screw:

    x = [z_s, ż_s, z_us, ż_us],  m_x = m_b + m_r + m_d

Both models expose the same numeric CasADi functions (built once, evaluated
without Python overhead): ``ode`` (ẋ), ``sprung_accel`` (z̈_s, paper x_a = ẋ_2),
``power`` (harvested electrical power P = u·v_gen², eq. (12)), ``energy`` (stored
mechanical energy), ``generator`` (its position, v_gen, P), ``deflection``
(z_s − z_us), ``measurements`` (what the ECU's sensors see), and a discrete
``step`` (RK4 with sub-steps; the road is interpolated linearly inside the interval
so the tyre force is continuous).

Why sub-steps: the dynamics are stiff at high c_e (fastest eigenvalue ≈ -1300 1/s
at 50 kNs/m, docs/model.md); explicit RK4 is stable only for h·|λ| < 2.78, so
the plant integrates at 0.5 ms by default and :func:`rk4_stable_substeps`
tells a caller how many sub-steps a given damping bound needs.
"""

from dataclasses import dataclass
from functools import lru_cache
from typing import Optional, Tuple

import casadi as ca
import numpy as np

from erva_ros.core.model.params import ERVAParams
from erva_ros.core.settings.loop import MODEL_KINDS

#: Default plant integration sub-step (s): 0.5 ms keeps RK4 accurate up to c_e ≈ 100 kNs/m.
PLANT_SUBSTEP_S = 5e-4

STATE_NAMES = {
    'erva': ('z_s', 'zdot_s', 'z_us', 'zdot_us', 'z_d', 'zdot_d'),
    'benchmark': ('z_s', 'zdot_s', 'z_us', 'zdot_us'),
}


def state_names_of(n_states: int) -> Tuple[str, ...]:
    """Return the state names of the model whose state has ``n_states`` values (recorded data)."""
    for names in STATE_NAMES.values():
        if len(names) == n_states:
            return names
    raise ValueError(f'no model has {n_states} states')


def kind_of_joints(joints) -> str:
    """Return the model kind whose state has these JointState names (a recorded state)."""
    for kind, names in STATE_NAMES.items():
        if tuple(joints) == names[0::2]:
            return kind
    raise ValueError(f'no model has the state joints {list(joints)}')


#: Scales of the states in the NMPC's decision variables (positions m, velocities m/s).
STATE_SCALES = {'erva': (1e-2, 0.1, 1e-2, 0.1, 1e-2, 0.1), 'benchmark': (1e-2, 0.1, 1e-2, 0.1)}


def _solve3(m, b):
    """Solve a 3x3 linear system by the adjugate.

    Φ(x) of eq. (11) reduces to a 3x3 block on (ẋ_2, ẋ_4, ẋ_6).  Its determinant is
    A·((M_s+m_b)(M_us+m_b) - m_b²) + g·|E|·(M_s+M_us) > 0 for all x (A, g > 0, E ≤ 0),
    so the closed form never divides by zero, unlike a symbolic QR that can produce
    0/0 where E(x) = 0 (at rest).
    """
    cof = ca.SX.zeros(3, 3)
    for i in range(3):
        for j in range(3):
            r = [k for k in range(3) if k != i]
            c = [k for k in range(3) if k != j]
            minor = m[r[0], c[0]] * m[r[1], c[1]] - m[r[0], c[1]] * m[r[1], c[0]]
            cof[i, j] = (-1) ** (i + j) * minor
    det = m[0, 0] * cof[0, 0] + m[0, 1] * cof[0, 1] + m[0, 2] * cof[0, 2]
    return ca.mtimes(cof.T, b) / det


@dataclass(frozen=True)
class NonlinearTerms:
    """Symbolic h, g, A, B, C, D, E of paper eq. (10) for a given state."""

    h: ca.SX
    g: ca.SX
    A: ca.SX
    B: ca.SX
    C: ca.SX
    D: ca.SX
    E: ca.SX


def erva_terms(p: ERVAParams, x) -> NonlinearTerms:
    """Return the state-dependent coefficients h, g, A..E of paper eq. (10).

    r_1 = φ², r_1' = 2φ, r_1'' = 2 with φ = [z_d - (z_s - z_us)] / l.
    """
    l, eps, m_d, m_r = p.l, p.epsilon, p.m_d, p.m_r
    rel = x[4] - (x[0] - x[2])
    r1 = (rel / l) ** 2
    r1p = 2 * rel / l
    r1pp = 2.0
    h = 2 * m_d * (eps * r1p + eps ** 2 * r1 * r1p) / l
    g = m_r + m_d * (1 + eps * r1) ** 2
    A = m_r + m_d * (1 + eps * r1) ** 2 + m_d * eps ** 2 * r1p ** 2
    B = m_d * (eps * r1p + eps ** 2 * (r1 * r1p + r1p * r1pp)) / l
    C = -2 * B
    D = m_d * eps ** 2 * r1p * r1pp / l
    E = -m_d * eps ** 2 * r1p ** 2
    return NonlinearTerms(h, g, A, B, C, D, E)


@dataclass(frozen=True)
class ErvaCorner:
    """One ERVA corner of paper eq. (11), in its local state [z_s, ż_s, z_us, ż_us, z_d, ż_d].

    z_s is the body point the strut holds: the quarter car's sprung mass, or a point of a
    whole car's body (erva_ros/core/model/full_car.py).  The rows of Φ(x)·ẋ = f are
    (M_s + m_b)·z̈_s − m_b·z̈_us + g·z̈_d = f2, −m_b·z̈_s + (M_us + m_b)·z̈_us − g·z̈_d = f4
    and E·(z̈_s − z̈_us) + A·z̈_d = f6.
    """

    terms: NonlinearTerms
    f2: ca.SX
    f4: ca.SX
    f6: ca.SX
    v_gen: ca.SX            # rotor relative to screw, l·φ̇ (m/s)
    position: ca.SX         # rotor relative to screw, z_d − (z_s − z_us) (m)
    deflection: ca.SX       # z_s − z_us (m)
    power: ca.SX            # harvested, u·v_gen² (W)
    #: 2 × the kinetic energy of the wheel, screw and rotor: four terms, in the order the
    #: quarter car adds them after the sprung mass's M_s·ż_s² (kept, so its graph is unchanged).
    kinetic2: Tuple[ca.SX, ca.SX, ca.SX, ca.SX]
    potential: ca.SX        # springs k_s, k_t, k_d (J)


def erva_corner(p: ERVAParams, x, u, w) -> ErvaCorner:
    """Return one corner's right-hand sides, generator, power and energy (paper eq. (11))."""
    t = erva_terms(p, x)
    v24 = x[1] - x[3]           # suspension velocity ż_s - ż_us
    d13 = x[0] - x[2]           # suspension deflection z_s - z_us
    v_gen = x[5] - v24          # rotor relative to screw, l·φ̇
    f2 = -t.h * x[5] * (x[5] - v24) - p.c * v24 - p.k_s * d13
    f4 = t.h * x[5] * (x[5] - v24) + p.c * v24 + p.k_s * d13 - p.k_t * x[2] + p.k_t * w
    f6 = (-t.B * x[5] ** 2 - t.C * x[5] * v24 - t.D * v24 ** 2
          - u * v_gen - p.k_d * (x[4] - d13))
    power = u * v_gen ** 2
    position = x[4] - d13       # rotor relative to screw, z_d - (z_s - z_us)
    # Kinetic energy of eq. (1) in the paper's translational variables (eq. (10)):
    # m r² ψ̇² → m_d (1+εr_1)² ż_d², m (r'φ̇)² → m_d ε² r_1'² v_gen², J_b θ̇² → m_b v24².
    r1 = ((x[4] - d13) / p.l) ** 2
    r1p = 2 * (x[4] - d13) / p.l
    kinetic2 = (p.M_us * x[3] ** 2, p.m_b * v24 ** 2,
                (p.m_r + p.m_d * (1 + p.epsilon * r1) ** 2) * x[5] ** 2,
                p.m_d * p.epsilon ** 2 * r1p ** 2 * v_gen ** 2)
    potential = 0.5 * (p.k_s * d13 ** 2 + p.k_t * (x[2] - w) ** 2 + p.k_d * (x[4] - d13) ** 2)
    return ErvaCorner(t, f2, f4, f6, v_gen, position, d13, power, kinetic2, potential)


def _erva_symbolic(p: ERVAParams):
    """ẋ, P and stored energy of the nonlinear ERVA (paper eq. (11))."""
    x = ca.SX.sym('x', 6)
    u = ca.SX.sym('u')
    w = ca.SX.sym('w')
    k = erva_corner(p, x, u, w)
    t = k.terms
    mass = ca.SX(3, 3)
    mass[0, 0] = p.M_s + p.m_b
    mass[0, 1] = -p.m_b
    mass[0, 2] = t.g
    mass[1, 0] = -p.m_b
    mass[1, 1] = p.M_us + p.m_b
    mass[1, 2] = -t.g
    mass[2, 0] = t.E
    mass[2, 1] = -t.E
    mass[2, 2] = t.A
    acc = _solve3(mass, ca.vertcat(k.f2, k.f4, k.f6))
    xdot = ca.vertcat(x[1], acc[0], x[3], acc[1], x[5], acc[2])
    kinetic = 0.5 * (p.M_s * x[1] ** 2 + k.kinetic2[0] + k.kinetic2[1] + k.kinetic2[2]
                     + k.kinetic2[3])
    return (x, u, w, xdot, k.power, kinetic + k.potential, k.v_gen, k.position,
            k.deflection)


def _benchmark_symbolic(p: ERVAParams):
    """ẋ, P and stored energy of the linear benchmark (paper eq. (15))."""
    x = ca.SX.sym('x', 4)
    u = ca.SX.sym('u')
    w = ca.SX.sym('w')
    mx = p.m_x
    v24 = x[1] - x[3]
    d13 = x[0] - x[2]
    f2 = -(p.c + u) * v24 - p.k_s * d13
    f4 = (p.c + u) * v24 + p.k_s * d13 - p.k_t * x[2] + p.k_t * w
    a, b, d = p.M_s + mx, -mx, p.M_us + mx
    det = a * d - b * b
    acc_s = (d * f2 - b * f4) / det
    acc_us = (a * f4 - b * f2) / det
    xdot = ca.vertcat(x[1], acc_s, x[3], acc_us)
    power = u * v24 ** 2
    energy = (0.5 * (p.M_s * x[1] ** 2 + p.M_us * x[3] ** 2 + mx * v24 ** 2)
              + 0.5 * (p.k_s * d13 ** 2 + p.k_t * (x[2] - w) ** 2))
    return x, u, w, xdot, power, energy, v24, d13, d13


@dataclass(frozen=True)
class SymbolicModel:
    """The expressions of one model kind in its primitives x, u, w.

    Built from symbolic parameters they depend on those symbols too (:func:`symbolic`).
    """

    x: ca.SX
    u: ca.SX
    w: ca.SX
    xdot: ca.SX
    power: ca.SX
    energy: ca.SX
    v_gen: ca.SX
    position: ca.SX
    deflection: ca.SX
    #: What the ECU measures: [z̈_s (m/s²), z_s − z_us (m), v_gen / l (rad/s)].
    measurements: ca.SX


def symbolic(params: ERVAParams, kind: str = 'erva') -> SymbolicModel:
    """Return the model's expressions for ``params``.

    ``params`` may hold CasADi symbols instead of numbers (``ERVAParams(**symbols)``):
    the same equations then depend on them, which is how the identification
    (erva_ros/core/identify/fit.py) differentiates the model with respect to its parameters.
    """
    build = _erva_symbolic if kind == 'erva' else _benchmark_symbolic
    x, u, w, xdot, power, energy, v_gen, position, deflection = build(params)
    return SymbolicModel(x, u, w, xdot, power, energy, v_gen, position, deflection,
                         ca.vertcat(xdot[1], deflection, v_gen / params.l))


def rk4(rhs, z, w0, w1, h, substeps: int):
    """Return z after ``substeps`` RK4 steps of ``h`` of ż = rhs(z, w), w linear from w0 to w1."""
    for i in range(substeps):
        wa = w0 + (w1 - w0) * (i / substeps)
        wm = w0 + (w1 - w0) * ((i + 0.5) / substeps)
        wb = w0 + (w1 - w0) * ((i + 1) / substeps)
        k1 = rhs(z, wa)
        k2 = rhs(z + h / 2 * k1, wm)
        k3 = rhs(z + h / 2 * k2, wm)
        k4 = rhs(z + h * k3, wb)
        z = z + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    return z


class QuarterCarModel:
    """The quarter car of one kind and parameter set: its states and CasADi functions.

    The one model object every user takes (do-mpc's shape): the plant, the NMPC's OCP,
    the EKF and the road EKF, the predictor, identification, the bound and the studies.
    Build it with :func:`make_model`, the one place a model is chosen by name (the
    functions are immutable, so one instance per (params, kind) is shared).
    """

    def __init__(self, params: ERVAParams, kind: str = 'erva'):
        if kind not in MODEL_KINDS:
            raise ValueError(
                f'model kind {kind!r} unknown; choose one of {", ".join(MODEL_KINDS)}')
        self.params = params
        self.kind = kind
        sym = symbolic(params, kind)
        x, u, w, xdot, power, energy = sym.x, sym.u, sym.w, sym.xdot, sym.power, sym.energy
        v_gen, position, deflection = sym.v_gen, sym.position, sym.deflection
        self.nx = int(x.shape[0])
        self.state_names = STATE_NAMES[kind]
        #: The JointState names of the state: one joint (position, velocity) per body.
        self.joints = self.state_names[0::2]
        #: Scales of the states in the NMPC's decision variables.
        self.x_scale = STATE_SCALES[kind]
        #: Symbolic primitives, for users that build bigger graphs (NMPC, estimator).
        self.x_sym, self.u_sym, self.w_sym, self.xdot_sym = x, u, w, xdot
        self.ode = ca.Function('ode', [x, u, w], [xdot], ['x', 'u', 'w'], ['xdot'])
        self.sprung_accel = ca.Function('sprung_accel', [x, u, w], [xdot[1]],
                                        ['x', 'u', 'w'], ['sprung_accel'])
        self.power = ca.Function('power', [x, u], [power], ['x', 'u'], ['power'])
        self.generator_velocity = ca.Function('generator_velocity', [x], [v_gen],
                                              ['x'], ['v_gen'])
        #: The generator's relative displacement (m; the benchmark's is the suspension
        #: deflection), velocity v_gen (m/s) and harvested power u·v_gen² (W): what the
        #: ``generator`` topic carries, for every publisher of it.
        self.generator = ca.Function('generator', [x, u], [position, v_gen, power],
                                     ['x', 'u'], ['position', 'v_gen', 'power'])
        self.energy = ca.Function('energy', [x, w], [energy], ['x', 'w'], ['energy'])
        #: Suspension deflection z_s - z_us (m), what a ride-height sensor measures.
        self.deflection = ca.Function('deflection', [x], [deflection], ['x'], ['deflection'])
        #: What the ECU measures (erva_ros.core.model.estimator.MEASUREMENTS): sprung acceleration
        #: (m/s^2), deflection (m) and generator speed v_gen / l (rad/s).
        self.measurements = ca.Function('measurements', [x, u, w], [sym.measurements],
                                        ['x', 'u', 'w'], ['y'])
        #: [sprung_accel, power] for many samples at once: columns are samples.
        self.outputs = ca.Function('outputs', [x, u, w], [xdot[1], power],
                                   ['x', 'u', 'w'], ['sprung_accel', 'power'])

    def with_params(self, params: ERVAParams) -> 'QuarterCarModel':
        """Return the same kind of model with other parameters (an identified device)."""
        return make_model(params, self.kind)

    def symbolic_with(self, params: ERVAParams) -> SymbolicModel:
        """Return this model's expressions for ``params``, which may be CasADi symbols.

        How identification (erva_ros/core/identify/fit.py) differentiates the model with
        respect to its parameters: the same equations, the parameters as inputs.
        """
        return symbolic(params, self.kind)

    def rk4_step(self, dt: float, substeps: int = 1) -> ca.Function:
        """Discrete step x⁺ = F_d(x, u, w0, w1) over ``dt`` with ``substeps`` RK4 stages.

        u is held over the interval (zero-order hold, as the controller applies it);
        the road moves linearly from w0 to w1.
        """
        return _rk4_step(self, float(dt), int(substeps))

    def plant_step(self, dt: float, substeps: int) -> ca.Function:
        """Like :meth:`rk4_step`, plus the energy harvested over the interval (J).

        (x, u, w0, w1) -> (x⁺, E_h, A): E_h = ∫ u·v_gen² dt (J) and A = ∫ z̈_s² dt
        (m²/s³) are integrated as extra RK4 states, so average power and the
        continuous-time RMS acceleration are exact to the integrator's order rather
        than sampled at the control period (where the command switches).
        """
        return _rk4_step(self, float(dt), int(substeps), True)

    def rk4_flow(self, substeps: int = 1) -> ca.Function:
        """Like :meth:`rk4_step`, the duration an input: (x, u, w0, w1, dt) -> x⁺.

        For steps whose length is known only at run time (the NMPC's command delay);
        ``substeps`` must keep h = dt/substeps stable for the largest dt used.
        """
        return _rk4_step(self, None, int(substeps))

    def rk4_loop(self, dt: Optional[float], substeps: int) -> ca.Function:
        """Like :meth:`rk4_step` (``dt`` None: :meth:`rk4_flow`), as a loop over the sub-steps.

        One RK4 sub-step called ``substeps`` times (``mapaccum``): the same x⁺ bit for bit,
        but its derivatives (an EKF's Jacobian) generate to a loop of a few kB of C where
        those of the unrolled step are a MB (gcc: 1.6 s instead of 32 s of CPU).  Call it
        with MX arguments, and take derivatives of the MX graph.
        """
        return _rk4_loop(self, None if dt is None else float(dt), int(substeps))

    def simulate(self, x0, u, w, dt: float, substeps: int = 1) -> np.ndarray:
        """Integrate over samples: u[k] held on [t_k, t_k+1), w sampled at t_k (len(u)+1 values).

        Returns the state trajectory, shape (len(u)+1, nx).  One CasADi call for the
        whole horizon (``mapaccum``), so long sweeps cost no Python per step.
        """
        u = np.asarray(u, dtype=float).ravel()
        w = np.asarray(w, dtype=float).ravel()
        n = u.size
        if w.size != n + 1:
            raise ValueError(f'need len(w) == len(u) + 1, got {w.size} and {n}')
        sim = _mapaccum(self, float(dt), int(substeps), n)
        inputs = np.vstack([u, w[:-1], w[1:]])
        xs = np.asarray(sim(np.asarray(x0, dtype=float), inputs))
        return np.vstack([np.asarray(x0, dtype=float).reshape(1, -1), xs.T])

    def outputs_along(self, xs: np.ndarray, u, w) -> Tuple[np.ndarray, np.ndarray]:
        """Chassis acceleration and harvested power at each sample of a trajectory."""
        n = xs.shape[0]
        u = np.broadcast_to(np.asarray(u, dtype=float), (n,))
        w = np.broadcast_to(np.asarray(w, dtype=float), (n,))
        acc, pw = _outputs_map(self, n)(xs.T, u.reshape(1, -1), w.reshape(1, -1))
        return np.asarray(acc).ravel(), np.asarray(pw).ravel()

    def zero_state(self) -> np.ndarray:
        return np.zeros(self.nx)


@lru_cache(maxsize=64)
def _rk4_step(model: QuarterCarModel, dt, substeps: int,
              with_energy: bool = False) -> ca.Function:
    x = ca.SX.sym('x', model.nx)
    u = ca.SX.sym('u')
    w0 = ca.SX.sym('w0')
    w1 = ca.SX.sym('w1')
    dt_in = [] if dt is not None else [ca.SX.sym('dt')]    # None: dt is an input
    h = (dt if dt is not None else dt_in[0]) / substeps
    # Augmented state [x; E_h; A] with Ė_h = P(x, u), Ȧ = z̈_s²: one RK4 for all.
    nx = model.nx

    def rhs(z, w):
        xdot = model.ode(z[:nx], u, w)
        return ca.vertcat(xdot, model.power(z[:nx], u), xdot[1] ** 2)

    zk = rk4(rhs, ca.vertcat(x, 0, 0), w0, w1, h, substeps)
    if with_energy:
        return ca.Function(f'plant_step_{model.kind}', [x, u, w0, w1],
                           [zk[:nx], zk[nx], zk[nx + 1]], ['x', 'u', 'w0', 'w1'],
                           ['xn', 'harvested_j', 'accel_sq_int'])
    return ca.Function(f'rk4_{model.kind}', [x, u, w0, w1] + dt_in, [zk[:nx]],
                       ['x', 'u', 'w0', 'w1'] + ['dt'] * len(dt_in), ['xn'])


@lru_cache(maxsize=64)
def _rk4_loop(model: QuarterCarModel, dt: Optional[float], substeps: int) -> ca.Function:
    z, u = ca.SX.sym('z', model.nx), ca.SX.sym('u')
    wa, wm, wb, h = ca.SX.sym('wa'), ca.SX.sym('wm'), ca.SX.sym('wb'), ca.SX.sym('h')
    # rk4()'s sub-step, with the road at its start, middle and end given.
    k1 = model.ode(z, u, wa)
    k2 = model.ode(z + h / 2 * k1, u, wm)
    k3 = model.ode(z + h / 2 * k2, u, wm)
    k4 = model.ode(z + h * k3, u, wb)
    one = ca.Function(f'rk4_substep_{model.kind}', [z, ca.vertcat(u, wa, wm, wb, h)],
                      [z + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)])
    loop = one.mapaccum(f'rk4_substeps_{model.kind}', substeps)
    x, um, w0, w1 = (ca.MX.sym(n, model.nx if n == 'x' else 1) for n in ('x', 'u', 'w0', 'w1'))
    dt_in = [] if dt is not None else [ca.MX.sym('dt')]
    i = np.arange(substeps)
    dw = w1 - w0                   # the road at each sub-step as rk4() computes it
    roads = [w0 + dw * ca.DM(f).T for f in (i / substeps, (i + 0.5) / substeps,
                                            (i + 1) / substeps)]
    h_in = (dt if dt is not None else dt_in[0]) / substeps
    xs = loop(x, ca.vertcat(ca.repmat(um, 1, substeps), *roads, ca.repmat(h_in, 1, substeps)))
    return ca.Function(f'rk4_loop_{model.kind}', [x, um, w0, w1] + dt_in, [xs[:, -1]],
                       ['x', 'u', 'w0', 'w1'] + ['dt'] * len(dt_in), ['xn'])


@lru_cache(maxsize=64)
def _mapaccum(model: QuarterCarModel, dt: float, substeps: int, n: int) -> ca.Function:
    step = _rk4_step(model, dt, substeps)
    x = ca.SX.sym('x', model.nx)
    uw = ca.SX.sym('uw', 3)
    one = ca.Function('one', [x, uw], [step(x, uw[0], uw[1], uw[2])])
    return one.mapaccum('sim', n)


@lru_cache(maxsize=64)
def _outputs_map(model: QuarterCarModel, n: int) -> ca.Function:
    return model.outputs.map(n)


def make_model(params: ERVAParams, kind: str = 'erva') -> QuarterCarModel:
    """Return the model ``kind`` (MODEL_KINDS: ``--model``) for ``params``, built once.

    The one place a model is chosen by its name; everything else takes the object.
    """
    return _shared_model(params, kind)


@lru_cache(maxsize=16)
def _shared_model(params: ERVAParams, kind: str) -> QuarterCarModel:
    # One key per (params, kind), however the caller spelled the call.
    return QuarterCarModel(params, kind)


def linearize(model: QuarterCarModel, x0=None, u0: float = 0.0, w0: float = 0.0):
    """Jacobians (A, B_u, B_w) of ẋ = F(x, u, w) at an operating point."""
    x0 = model.zero_state() if x0 is None else np.asarray(x0, dtype=float)
    jac = ca.Function('linearization', [model.x_sym, model.u_sym, model.w_sym],
                      [ca.jacobian(model.xdot_sym, model.x_sym),
                       ca.jacobian(model.xdot_sym, model.u_sym),
                       ca.jacobian(model.xdot_sym, model.w_sym)])
    a, bu, bw = jac(x0, u0, w0)
    return np.asarray(a), np.asarray(bu), np.asarray(bw)


def rk4_stable_substeps(model: QuarterCarModel, dt: float, u_max: float,
                        margin: float = 0.5) -> int:
    """Fewest RK4 sub-steps over ``dt`` that keep the linearised plant stable at u_max.

    Uses the fastest eigenvalue at rest and RK4's real-axis stability limit 2.785,
    with a safety ``margin`` (0.5 → h·|λ| ≤ 1.39).
    """
    a, _, _ = linearize(model, u0=u_max)
    lam = float(np.max(np.abs(np.linalg.eigvals(a))))
    return max(1, int(np.ceil(dt * lam / (2.785 * margin))))
