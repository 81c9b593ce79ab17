"""The whole car: four ERVA corners on one body (issue 39), written once in CasADi.

Axes ISO 8855 (x forward, y left, z up), small angles, deviations from static equilibrium
(gravity cancels against the springs' preload, as in the quarter car):

    x = [z_c, ż_c, θ, θ̇, φ, φ̇,  z_us, ż_us, z_d, ż_d (FL),  … (FR),  … (RL),  … (RR)]  (22)
    u = [c_e,FL, c_e,FR, c_e,RL, c_e,RR]   electrical damping of each corner (Ns/m)
    w = [z_r,FL, z_r,FR, z_r,RL, z_r,RR]   road height under each tyre (m)

z_c is the heave of the body's centre of gravity, θ its pitch (positive nose down), φ its
roll (positive left side up).  Corner i's strut sits at (x_i, y_i) (CarParams.positions) and
holds the body point z_s,i = z_c − x_i·θ + y_i·φ; below it is the paper's ERVA corner
(core/model/quarter_car.py ``erva_corner``: spring, damper, ball screw, rotor with its inertia
nonlinearity, generator, tyre) with its own command and road.

Equations (Lagrange, docs/car.md "The whole car"): the body rows are
diag(M, I_θ, I_φ)·q̈ = Σ_i J_iᵀ F_i with q = (z_c, θ, φ), J_i = (1, −x_i, y_i) and F_i the
force corner i's strut puts on its body point, whose inertial part is the quarter car's
first row without M_s·z̈_s.  Each corner's other two rows give z̈_us,i and z̈_d,i as affine
functions of z̈_s,i = J_i·q̈, so F_i = F0_i − m_i·z̈_s,i (m_i ≥ 0: the strut's inertia seen
from the body); the body solves (diag(M, I_θ, I_φ) + Σ m_i J_iᵀJ_i)·q̈ = Σ J_iᵀF0_i, a 3x3
positive definite system, in closed form.  With a rigid symmetric body and equal corners,
commands and roads this is exactly four quarter cars (test/test_vehicle_model.py).

The numeric functions mirror QuarterCarModel's, one value per corner where the quarter car
has one: ``ode``, ``body_accel`` (z̈_c, θ̈, φ̈), ``sprung_accel`` (z̈_s,i), ``power`` and
``total_power``, ``generator``, ``energy``, ``deflection``, ``measurements`` (each corner's
ECU: z̈_s,i, z_s,i − z_us,i, v_gen,i / l_i), the discrete ``rk4_step`` / ``plant_step`` /
``rk4_flow`` and ``simulate``.  ``erva_ros.core.model.quarter_car.linearize`` and
``rk4_stable_substeps`` take a FullCarModel as they take a quarter car.
"""

from functools import lru_cache
from typing import Optional, Sequence, Tuple

import casadi as ca
import numpy as np

from erva_ros.core.model.car_params import CarParams, CORNERS
from erva_ros.core.model.estimator import MEASUREMENTS as ECU_MEASUREMENTS
from erva_ros.core.model.quarter_car import _solve3, erva_corner, linearize, rk4

BODY_STATE_NAMES = ('z_c', 'zdot_c', 'theta', 'thetadot', 'phi', 'phidot')
CORNER_STATE_NAMES = ('z_us', 'zdot_us', 'z_d', 'zdot_d')
#: 'z_c' … 'phidot', then 'z_us_FL', 'zdot_us_FL', 'z_d_FL', 'zdot_d_FL', … RR.
STATE_NAMES = BODY_STATE_NAMES + tuple(f'{n}_{c}' for c in CORNERS
                                       for n in CORNER_STATE_NAMES)
NX = len(STATE_NAMES)
#: What each corner's ECU measures, in this order: the quarter car's ``measurements``.
MEASUREMENTS = ECU_MEASUREMENTS

#: Road patterns of unit amplitude under FL, FR, RL, RR that excite one body motion each:
#: in phase (heave), front against rear (pitch), left against right (roll).
ROAD_PATTERNS = {'heave': (1.0, 1.0, 1.0, 1.0), 'pitch': (1.0, 1.0, -1.0, -1.0),
                 'roll': (1.0, -1.0, 1.0, -1.0)}


def corner_slice(i: int) -> slice:
    """Return where corner ``i``'s [z_us, ż_us, z_d, ż_d] are in the state."""
    return slice(6 + 4 * i, 10 + 4 * i)


def body_points(p: CarParams, q) -> list:
    """z_s,i = z_c − x_i·θ + y_i·φ of each corner for q = (z_c, θ, φ) (or their rates)."""
    return [q[0] - xi * q[1] + yi * q[2] for xi, yi in p.positions()]


def _car_symbolic(p: CarParams):
    """ẋ and every output of the car, in its primitives x, u, w."""
    x = ca.SX.sym('x', NX)
    u = ca.SX.sym('u', len(CORNERS))
    w = ca.SX.sym('w', len(CORNERS))
    zs = body_points(p, (x[0], x[2], x[4]))
    vs = body_points(p, (x[1], x[3], x[5]))
    body = ca.SX(3, 3)
    body[0, 0], body[1, 1], body[2, 2] = p.M, p.I_theta, p.I_phi
    rhs = ca.SX.zeros(3)
    corners = []
    for i, (cp, (xi, yi)) in enumerate(zip(p.corners, p.positions())):
        c = x[corner_slice(i)]
        k = erva_corner(cp, ca.vertcat(zs[i], vs[i], c[0], c[1], c[2], c[3]), u[i], w[i])
        t = k.terms
        # Rows 2 and 3 of the corner, [[M_us + m_b, −g], [−E, A]]·(z̈_us, z̈_d) =
        # (f4 + m_b·z̈_s, f6 − E·z̈_s): det = (M_us + m_b)·A + g·|E| > 0 (A, g > 0, E ≤ 0).
        det = (cp.M_us + cp.m_b) * t.A - t.g * t.E
        us0, us1 = (t.A * k.f4 + t.g * k.f6) / det, (t.A * cp.m_b - t.g * t.E) / det
        d0, d1 = (t.E * k.f4 + (cp.M_us + cp.m_b) * k.f6) / det, -t.E * cp.M_us / det
        # Row 1 without M_s·z̈_s: the strut's force on the body, F0 − m·z̈_s.
        f0 = k.f2 + cp.m_b * us0 - t.g * d0
        m_in = cp.M_us * (t.A * cp.m_b - t.g * t.E) / det
        arm = (1.0, -xi, yi)
        for r in range(3):
            rhs[r] += arm[r] * f0
            for s in range(3):
                body[r, s] += m_in * arm[r] * arm[s]
        corners.append((k, c, us0, us1, d0, d1))
    qdd = _solve3(body, rhs)
    acc_s = body_points(p, qdd)
    xdot = [x[1], qdd[0], x[3], qdd[1], x[5], qdd[2]]
    kinetic2 = p.M * x[1] ** 2 + p.I_theta * x[3] ** 2 + p.I_phi * x[5] ** 2
    potential = 0
    for i, (k, c, us0, us1, d0, d1) in enumerate(corners):
        xdot += [c[1], us0 + us1 * acc_s[i], c[3], d0 + d1 * acc_s[i]]
        kinetic2 += k.kinetic2[0] + k.kinetic2[1] + k.kinetic2[2] + k.kinetic2[3]
        potential += k.potential
    ks = [c[0] for c in corners]
    ls = [cp.l for cp in p.corners]
    measurements = ca.vertcat(*[ca.vertcat(acc_s[i], ks[i].deflection, ks[i].v_gen / ls[i])
                                for i in range(len(CORNERS))])
    return dict(x=x, u=u, w=w, xdot=ca.vertcat(*xdot), body_accel=qdd,
                sprung_accel=ca.vertcat(*acc_s), body_points=ca.vertcat(*zs),
                body_point_rates=ca.vertcat(*vs),
                power=ca.vertcat(*[k.power for k in ks]),
                v_gen=ca.vertcat(*[k.v_gen for k in ks]),
                position=ca.vertcat(*[k.position for k in ks]),
                deflection=ca.vertcat(*[k.deflection for k in ks]),
                energy=0.5 * kinetic2 + potential, measurements=measurements)


class FullCarModel:
    """Numeric CasADi functions of the whole car, built once per parameter set.

    Use :func:`get_car_model` to share instances (the functions are immutable).
    """

    kind = 'car'

    def __init__(self, params: CarParams):
        self.params = params
        s = _car_symbolic(params)
        x, u, w, xdot = s['x'], s['u'], s['w'], s['xdot']
        self.nx, self.nu, self.nw = NX, len(CORNERS), len(CORNERS)
        self.state_names = STATE_NAMES
        #: Symbolic primitives, for users that build bigger graphs (NMPC, estimator) and
        #: for erva_ros.core.model.quarter_car.linearize.
        self.x_sym, self.u_sym, self.w_sym, self.xdot_sym = x, u, w, xdot
        xuw, names = [x, u, w], ['x', 'u', 'w']
        self.ode = ca.Function('car_ode', xuw, [xdot], names, ['xdot'])
        #: (z̈_c (m/s²), θ̈, φ̈ (rad/s²)) of the body.
        self.body_accel = ca.Function('car_body_accel', xuw, [s['body_accel']], names,
                                      ['body_accel'])
        #: z̈_s,i of the body at each corner's strut (m/s²): what its accelerometer sees.
        self.sprung_accel = ca.Function('car_sprung_accel', xuw, [s['sprung_accel']], names,
                                        ['sprung_accel'])
        #: z_s,i and ż_s,i of each corner's body point (m, m/s), from (z_c, θ, φ).
        self.body_points = ca.Function('car_body_points', [x], [s['body_points'],
                                       s['body_point_rates']], ['x'], ['z_s', 'zdot_s'])
        self.power = ca.Function('car_power', [x, u], [s['power']], ['x', 'u'], ['power'])
        self.total_power = ca.Function('car_total_power', [x, u], [ca.sum1(s['power'])],
                                       ['x', 'u'], ['total_power'])
        self.generator_velocity = ca.Function('car_generator_velocity', [x], [s['v_gen']],
                                              ['x'], ['v_gen'])
        #: Each corner's generator: relative displacement (m), v_gen (m/s), u·v_gen² (W).
        self.generator = ca.Function('car_generator', [x, u],
                                     [s['position'], s['v_gen'], s['power']], ['x', 'u'],
                                     ['position', 'v_gen', 'power'])
        #: Stored mechanical energy of the whole car (J).
        self.energy = ca.Function('car_energy', [x, w], [s['energy']], ['x', 'w'],
                                  ['energy'])
        #: Each corner's suspension deflection z_s,i − z_us,i (m).
        self.deflection = ca.Function('car_deflection', [x], [s['deflection']], ['x'],
                                      ['deflection'])
        #: Each corner's ECU (MEASUREMENTS), corner after corner: 3 values × FL, FR, RL, RR.
        self.measurements = ca.Function('car_measurements', xuw, [s['measurements']], names,
                                        ['y'])
        #: [body_accel, sprung_accel, power] for many samples at once: columns are samples.
        self.outputs = ca.Function('car_outputs', xuw,
                                   [s['body_accel'], s['sprung_accel'], s['power']], names,
                                   ['body_accel', 'sprung_accel', 'power'])

    def rk4_step(self, dt: float, substeps: int = 1) -> ca.Function:
        """Discrete step x⁺ = F_d(x, u, w0, w1) over ``dt`` with ``substeps`` RK4 stages.

        u (4) is held over the interval; each road height moves linearly from w0 to w1.
        """
        return _car_step(self, float(dt), int(substeps))

    def plant_step(self, dt: float, substeps: int) -> ca.Function:
        """Like :meth:`rk4_step`, plus what the plant integrates over the interval.

        (x, u, w0, w1) -> (x⁺, E_h, A, A_body): per corner the harvested energy
        E_h = ∫ u·v_gen² dt (J) and A = ∫ z̈_s,i² dt (m²/s³), and A_body = ∫ (z̈_c², θ̈²,
        φ̈²) dt, integrated as extra RK4 states (as the quarter car's plant does).
        """
        return _car_step(self, float(dt), int(substeps), True)

    def rk4_flow(self, substeps: int = 1) -> ca.Function:
        """Like :meth:`rk4_step`, the duration an input: (x, u, w0, w1, dt) -> x⁺."""
        return _car_step(self, None, int(substeps))

    def simulate(self, x0, u, w, dt: float, substeps: int = 1) -> np.ndarray:
        """Integrate over samples: u[k] (4) held on [t_k, t_k+1), w[k] (4) at t_k.

        ``u`` has shape (n, 4), ``w`` (n + 1, 4); returns the states, shape (n + 1, 22).
        One CasADi call for the whole run (``mapaccum``).
        """
        u, w = np.asarray(u, dtype=float), np.asarray(w, dtype=float)
        if u.ndim != 2 or u.shape[1] != self.nu or w.shape != (u.shape[0] + 1, self.nw):
            raise ValueError(f'need u of shape (n, {self.nu}) and w of shape (n + 1, '
                             f'{self.nw}), got {u.shape} and {w.shape}')
        n = u.shape[0]
        x0 = np.asarray(x0, dtype=float)
        xs = np.asarray(_car_mapaccum(self, float(dt), int(substeps), n)(
            x0, np.hstack([u, w[:-1], w[1:]]).T))
        return np.vstack([x0.reshape(1, -1), xs.T])

    def outputs_along(self, xs: np.ndarray, u, w) -> Tuple[np.ndarray, ...]:
        """Return body accelerations (n, 3), corner accelerations (n, 4), powers (n, 4)."""
        n = xs.shape[0]
        u = np.broadcast_to(np.asarray(u, dtype=float), (n, self.nu))
        w = np.broadcast_to(np.asarray(w, dtype=float), (n, self.nw))
        out = self.outputs.map(n)(xs.T, u.T, w.T)
        return tuple(np.asarray(o).T for o in out)

    def zero_state(self) -> np.ndarray:
        return np.zeros(self.nx)


@lru_cache(maxsize=32)
def _car_step(model: FullCarModel, dt: Optional[float], substeps: int,
              with_energy: bool = False) -> ca.Function:
    nx, nc = model.nx, model.nu
    x = ca.SX.sym('x', nx)
    u = ca.SX.sym('u', nc)
    w0 = ca.SX.sym('w0', nc)
    w1 = ca.SX.sym('w1', nc)
    dt_in = [] if dt is not None else [ca.SX.sym('dt')]    # None: dt is an input
    h = (dt if dt is not None else dt_in[0]) / substeps

    def rhs(z, w):
        xz = z[:nx]
        body_acc, acc_s, power = model.outputs(xz, u, w)
        return ca.vertcat(model.ode(xz, u, w), power, acc_s ** 2, body_acc ** 2)

    zk = rk4(rhs, ca.vertcat(x, ca.SX.zeros(2 * nc + 3)), w0, w1, h, substeps)
    if with_energy:
        return ca.Function('plant_step_car', [x, u, w0, w1],
                           [zk[:nx], zk[nx:nx + nc], zk[nx + nc:nx + 2 * nc], zk[nx + 2 * nc:]],
                           ['x', 'u', 'w0', 'w1'],
                           ['xn', 'harvested_j', 'accel_sq_int', 'body_accel_sq_int'])
    return ca.Function('rk4_car', [x, u, w0, w1] + dt_in, [zk[:nx]],
                       ['x', 'u', 'w0', 'w1'] + ['dt'] * len(dt_in), ['xn'])


@lru_cache(maxsize=32)
def _car_mapaccum(model: FullCarModel, dt: float, substeps: int, n: int) -> ca.Function:
    step = _car_step(model, dt, substeps)
    nc = model.nu
    x = ca.SX.sym('x', model.nx)
    uw = ca.SX.sym('uw', 3 * nc)
    one = ca.Function('one', [x, uw], [step(x, uw[:nc], uw[nc:2 * nc], uw[2 * nc:])])
    return one.mapaccum('car_sim', n)


@lru_cache(maxsize=8)
def get_car_model(params: CarParams) -> FullCarModel:
    """Shared model instance for ``params``; CasADi functions are built once."""
    return FullCarModel(params)


def body_modes(p: CarParams) -> Tuple[np.ndarray, np.ndarray]:
    """Return the body's modal masses (kg, largest first) and shapes (columns z_c, θ, φ).

    K_J·v = λ·diag(M, I_θ, I_φ)·v with K_J = Σ J_iᵀJ_i: on four equal corners the car
    linearised at rest moves in body mode k as the quarter car whose sprung mass is 1/λ_k
    (docs/car.md, "The whole car").
    """
    j = np.array([[1.0, -xi, yi] for xi, yi in p.positions()])
    lam, vec = np.linalg.eig(np.linalg.solve(np.diag([p.M, p.I_theta, p.I_phi]), j.T @ j))
    order = np.argsort(lam.real)
    return 1 / lam.real[order], vec.real[:, order]


def body_response(model: FullCarModel, freqs: Sequence[float], pattern: Sequence[float],
                  damping, amplitude_m: float = 1.0) -> np.ndarray:
    """Steady-state (z̈_c, θ̈, φ̈) amplitudes of the car linearised at rest, shape (n, 3).

    The road under corner i is ``amplitude_m · pattern[i] · sin(2πft)`` (ROAD_PATTERNS) and
    each corner's damping is held at ``damping`` (Ns/m, one value or four).
    """
    a, _, bw = linearize(model, u0=damping)
    bw = bw @ np.asarray(pattern, dtype=float).reshape(-1, 1)
    rows = [1, 3, 5]                            # z̈_c, θ̈, φ̈ are ẋ's rows 1, 3, 5
    out = []
    for f in freqs:
        xw = np.linalg.solve(2j * np.pi * f * np.eye(model.nx) - a, bw)
        out.append(np.abs(a[rows] @ xw + bw[rows]).ravel() * amplitude_m)
    return np.array(out)
