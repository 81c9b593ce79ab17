r"""The NMPC's optimal control problem: direct collocation of the shared model, its costs.

Solved at every sample t_k (paper eq. (14)):

    min_u  Σ_i ℓ_i + V(x_B)   s.t.  x_0 = x(t_k),  ẋ = Φ(x)⁻¹ f(x, u_i, w)  on each interval,
                                u_i ∈ [u_min, u_max]

Prediction -- direct collocation, multiple shooting.  Each interval (``blocks``: its
length in samples, the command held over it) is one Radau IIA collocation step
(degree 3, order 5) of the shared model's ``ode`` (:mod:`erva_ros.core.model.quarter_car`; no
second copy of the equations).  Radau IIA is L-stable, so the prediction is stable
for every damping in the box, and an optimizer cannot "harvest" the integration
error of a too coarse explicit step: ``test_ctrl_nmpc.py`` checks it against the
plant's 0.5 ms RK4 over the whole box (for bang-bang switching between the box
corners degree 3 *under*-predicts the harvested energy by ~2 %, never over-predicts;
degree 5 agrees to 0.1 %).  The road is linear between preview samples, as in the plant.

Stage cost ℓ_i (``cost``):

``paper``       as printed after eq. (14): α1/Ts²·[x_a(k) − x_a(k−1)]² − α2·u_k·v_gen(k)²,
                x_a(k) = ẋ_2 at node k with u_k (a decision variable), x_a(−1) the
                previous sample's acceleration: a jerk-like comfort term, the power
                sampled at the nodes.
``continuous``  the running cost of eq. (12) integrated over each interval with the
                collocation quadrature: (1/Ts)∫ α1·z̈_s² − α2·P dt.
``bound``       the clairvoyant bound's objective: α1·x_a(t_k)² − α2·E_k/Ts.

Terminal cost V: ``tail`` (:func:`passive_tail`) values what lies beyond the horizon
as if the passive damping c_e0 took over, α1·ξᵀQ_aξ − α2·ξᵀQ_Pξ with ξ the deviation
of x_B from rest on the last road height; ``terminal_weight`` > 0 adds a credit
α2·weight·E_stored(x_B)/Ts for the mechanical energy stored at the end.

Command delay (``delayed``): the command computed at t_k acts from t_k + d on, the
previous one u_acting until then.  A prefix interval [t_k, t_k + d] with u_acting and
no cost (nothing in it can be decided), then the plan's intervals on the grid
t_k + d + j·Ts, the road interpolated on it (linear between preview samples, held
past the last).  d and u_acting are parameters: d may change between solves.

Variables are scaled (u by 10 kNs/m, positions by 1 cm, velocities by 0.1 m/s).
:func:`build_ocp` builds the NLP once per model and :class:`OCPSpec`; the solvers
(:mod:`erva_ros.core.controllers.sqp`, :mod:`erva_ros.core.controllers.reference`)
and the clairvoyant bound use it through :class:`OCP`.
"""

from dataclasses import dataclass
from functools import cached_property, lru_cache
from typing import NamedTuple, Optional, Tuple

import casadi as ca
import numpy as np

from erva_ros.core.model.quarter_car import linearize, QuarterCarModel
from erva_ros.core.model.params import ParamError

#: Scale of the input in the decision variables (Ns/m; the states': the model's x_scale).
U_SCALE = 1e4
#: Radau IIA collocation degree of the prediction model (order 2·d − 1 = 5, L-stable).
COLLOCATION_DEGREE = 3
#: Longest RK4 sub-step of the rollout (s); shortened if needed for stability at u_max.
ROLLOUT_SUBSTEP_S = 2.5e-3


def stable_rollout_substep(model: QuarterCarModel, u_max: float) -> float:
    """Return an RK4 sub-step (s) with h·|λ_max| ≤ 1.39 (half the limit) at ``u_max``."""
    a, _, _ = linearize(model, u0=u_max)
    lam = float(np.max(np.abs(np.linalg.eigvals(a))))
    return min(ROLLOUT_SUBSTEP_S, 1.39 / lam)


def _road_weights(blocks: Tuple[int, ...], taus) -> Tuple[np.ndarray, np.ndarray]:
    """Return interpolation matrices: road at interval starts and at collocation points.

    The road is linear between preview samples (as in the plant), so w at any time is
    a fixed linear combination of the H + 1 preview values.
    """
    horizon = int(sum(blocks))
    starts = np.cumsum((0,) + tuple(blocks[:-1]))
    eye = np.eye(horizon + 1)

    def row(sample_time):
        i = min(int(np.floor(sample_time)), horizon - 1)
        f = sample_time - i
        return (1 - f) * eye[i] + f * eye[i + 1]

    w_start = np.array([row(s) for s in starts])
    w_col = np.array([[row(s + tau * m) for tau in taus] for s, m in zip(starts, blocks)])
    return w_start, w_col


def _road_points(w, blocks: Tuple[int, ...], taus, delta=None):
    """Return the road heights of every interval: at its start and its collocation points.

    A (1 + degree) x B SX matrix, column i for interval i, and the height at the end
    of the horizon.  The road is linear between preview samples, as in the plant.
    With a command delay (``delta`` = d/Ts, symbolic, in [0, 1)) every interval starts
    d later: a point s + delta (s in samples) lies before or after the next preview
    sample depending on delta (if_else); heights past the last sample hold it.
    """
    horizon = int(sum(blocks))
    if delta is None:
        w_start, w_col = _road_weights(blocks, taus)
        cols = [ca.vertcat(ca.mtimes(w_start[i:i + 1, :], w),
                           *[ca.mtimes(w_col[i, r:r + 1, :], w) for r in range(len(taus))])
                for i in range(len(blocks))]
        return ca.horzcat(*cols), w[horizon]

    def at(s):
        j = int(np.floor(s + 1e-12))
        f = s - j
        w_at = [w[min(j + n, horizon)] for n in range(3)]
        early = w_at[0] + (w_at[1] - w_at[0]) * (f + delta)
        late = w_at[1] + (w_at[2] - w_at[1]) * (f + delta - 1)
        return ca.if_else(f + delta < 1, early, late)

    starts = np.cumsum((0,) + tuple(blocks[:-1]))
    cols = [ca.vertcat(at(s), *[at(s + tau * m) for tau in taus])
            for s, m in zip(starts, blocks)]
    return ca.horzcat(*cols), w[horizon]


def _interval(model: QuarterCarModel, cost: str, ts: float, xt_s, v, k_s, wv, h, alpha,
              a=None):
    """Transcribe one interval of length h: collocation defects, end state, stage cost.

    The single definition of the OCP's intervals, used by the NLP (IPOPT, the bound)
    and by the real-time SQP.  ``xt_s`` is the scaled state at the interval start
    (plus x_a(k−1) for the paper cost), v = u/U_SCALE held over the interval, ``k_s``
    the scaled collocation states, ``wv`` the road at the start and at the collocation
    points.  ``a`` is x_a(k) (a variable of the NLP), else the node acceleration.
    Returns (defects, x_end_s, node acceleration, residuals r, weights c, econ): the
    stage cost is α1·Σ c·r² + econ.
    """
    nx = model.nx
    degree = wv.numel() - 1
    c_mat, d_vec, b_vec, _ = _collocation(degree)
    xs_col = ca.DM(model.x_scale)
    x = xt_s[:nx] * xs_col
    u = U_SCALE * v
    k = ca.reshape(k_s, nx, degree)
    xc = [k[:, r] * xs_col for r in range(degree)]
    pts = [x] + xc
    a_node = model.sprung_accel(x, u, wv[0])
    a = a_node if a is None else a
    defects, res, res_w, econ = [], [], [], 0
    for r in range(degree):
        slope = sum(c_mat[s, r] * pts[s] for s in range(degree + 1))
        defects.append((slope - h * model.ode(xc[r], u, wv[1 + r])) / xs_col)
        if cost == 'continuous':
            res.append(model.sprung_accel(xc[r], u, wv[1 + r]))
            res_w.append(h * b_vec[r] / ts)
        if cost in ('continuous', 'bound'):
            econ -= h * b_vec[r] * alpha[1] * model.power(xc[r], u) / ts
    if cost == 'paper':
        res.append(a - xt_s[nx])
        res_w.append(1 / (h * ts))
        econ -= alpha[1] * h / ts * model.power(x, u)
    elif cost == 'bound':
        res.append(a)
        res_w.append(h / ts)
    x_end = sum(d_vec[s] * pts[s] for s in range(degree + 1)) / xs_col
    return ca.vertcat(*defects), x_end, a_node, res, res_w, econ


@lru_cache(maxsize=8)
def _collocation(degree: int):
    """Return the Radau IIA collocation matrices (C, D, B) of ``degree`` and its points."""
    taus = [float(t) for t in ca.collocation_points(degree, 'radau')]
    return tuple(np.asarray(m) for m in ca.collocation_coeff(taus)) + (taus,)


class StageSlices(NamedTuple):
    """Where one interval's variables sit in z (in the order build_ocp appends them)."""

    x: slice                   # x_i, the scaled stage state (with x_a(k−1): paper, bound)
    v: int                     # v_i, the scaled input
    acc: Optional[int]         # x_a(k), the node acceleration (paper and bound costs)
    k: slice                   # K_i, the collocation states
    x_next: slice              # x_{i+1}, the next stage state


@dataclass(eq=False)   # hashed by identity: one OCP per configuration (lru_cache)
class OCP:
    """The collocation NLP of one configuration, its layout and its pieces (shareable).

    Decision vector z: [prefix: x(t_k)/scale (+ x_a(k−1)), its collocation states] if
    the OCP models a command delay, then stage by stage: x_k = [state/scale, x_a(k−1)],
    u_k = [u/U_SCALE, x_a(k), collocation states/scale]; then x_B (x_a only with the
    paper cost).  Constraints per stage: the shooting gap x_{k+1} − [last collocation
    state, x_a(k)], then the path equalities (collocation, x_a(k) = ẋ_2(x_k, u_k, w_k)).
    Parameters p = [w (H + 1 preview heights), α1, α2], plus [d, u_acting] with a delay.
    """

    nlp: ca.Function             # (z, p) -> (f, g)
    rollout: ca.Function         # (x0, a_prev, u per interval, q) -> z, by RK4
    blocks: Tuple[int, ...]
    nx: int
    degree: int
    with_acc: bool
    u_min: float
    u_max: float
    x_scale: np.ndarray
    ts: float
    delayed: bool
    interval: ca.Function        # (xt, v, k, wv, h, alpha) -> (defects, phi, cost, r, c, e)
    prefix: ca.Function          # (xt, v, k, wv, h) -> (defects, phi): the delay
    terminal: ca.Function        # (x_B, w_end, alpha) -> terminal cost
    road: ca.Function            # p -> (road per interval, w_end, prefix road, d, v_acting)
    key: str = ''                # what it is built from: model and spec (codegen.load_or_build)

    @property
    def horizon(self) -> int:
        """Return the number of samples H = Σ blocks."""
        return int(sum(self.blocks))

    @property
    def nxa(self) -> int:
        """Return the stage state size (model states, plus x_a(k−1) for the paper cost)."""
        return self.nx + int(self.with_acc)

    @property
    def nk(self) -> int:
        """Return the number of collocation states per interval."""
        return self.degree * self.nx

    @property
    def stage(self) -> int:
        """Return the number of decision variables per stage."""
        return self.nxa + 1 + int(self.with_acc) + self.nk

    @property
    def offset(self) -> int:
        """Return where the first stage starts in z (after the delay prefix)."""
        return (self.nxa + self.nk) if self.delayed else 0

    @property
    def nz(self) -> int:
        """Return the size of the decision vector."""
        return self.offset + len(self.blocks) * self.stage + self.nxa

    @property
    def n_p(self) -> int:
        """Return the size of the parameter vector p."""
        return self.horizon + 3 + 2 * int(self.delayed)

    @property
    def n_pb(self) -> int:
        """Return the size of the solvers' parameters: p, then the input box (scaled)."""
        return self.n_p + 2

    def with_box(self, p, u_min: Optional[float] = None, u_max: Optional[float] = None
                 ) -> np.ndarray:
        """Return the solvers' parameters: ``p``, then the box [u_min, u_max] (default: spec's).

        The box is a parameter of the real-time SQP and of the reference's bounds, so it
        may change between solves; the NLP itself (``nlp``) takes only ``p``.
        """
        lo = self.u_min if u_min is None else u_min
        hi = self.u_max if u_max is None else u_max
        return np.r_[p, lo / U_SCALE, hi / U_SCALE]

    @property
    def v_min(self) -> float:
        """Return the lower input bound, scaled (v = u/U_SCALE)."""
        return self.u_min / U_SCALE

    @property
    def v_max(self) -> float:
        """Return the upper input bound, scaled."""
        return self.u_max / U_SCALE

    def stage_slices(self, i: int) -> StageSlices:
        """Return where interval ``i``'s variables sit in z (the one map of the layout)."""
        o, nxa = self.offset + i * self.stage, self.nxa
        return StageSlices(slice(o, o + nxa), o + nxa, o + nxa + 1 if self.with_acc else None,
                           slice(o + self.stage - self.nk, o + self.stage),
                           slice(o + self.stage, o + self.stage + nxa))

    @cached_property
    def u_index(self) -> np.ndarray:
        """Return the positions of the scaled inputs in z (computed once: per-solve use)."""
        return np.array([self.stage_slices(i).v for i in range(len(self.blocks))])

    def params(self, w, alpha, delay_s: float = 0.0, u_acting: float = 0.0) -> np.ndarray:
        """Return p for preview ``w`` (H + 1 heights), weights, and the delay if modelled."""
        extra = [delay_s, u_acting / U_SCALE] if self.delayed else []
        return np.r_[w, alpha, extra]

    def road_params(self, p):
        """Return the rollout's q: p without the weights."""
        h1 = self.horizon + 1
        return ca.vertcat(p[:h1], p[h1 + 2:]) if self.delayed else p[:h1]

    def bounds(self, x0: np.ndarray, a_prev: float, box: Optional[Tuple[float, float]] = None
               ) -> Tuple[np.ndarray, np.ndarray]:
        """Return (lbz, ubz): the input box, and the first stage state fixed to x(t_k).

        ``box``: the scaled bounds (v_min, v_max) (:meth:`with_box`'s tail), else the spec's.
        """
        lbz = np.full(self.nz, -np.inf)
        ubz = np.full(self.nz, np.inf)
        lbz[self.u_index], ubz[self.u_index] = box if box is not None else (self.v_min,
                                                                            self.v_max)
        x0s = np.r_[x0 / self.x_scale, [a_prev] if self.with_acc else []]
        lbz[:self.nxa] = ubz[:self.nxa] = x0s
        return lbz, ubz

    def nodes(self, z: np.ndarray) -> np.ndarray:
        """Return the predicted states at the interval starts and the end, (B + 1, nx), SI."""
        nb = len(self.blocks)
        z = z[self.offset:]
        body = z[:nb * self.stage].reshape(nb, self.stage)
        xs = np.vstack([body[:, :self.nx], z[nb * self.stage:][None, :self.nx]])
        return xs * self.x_scale


def _road_rest(model: QuarterCarModel) -> np.ndarray:
    """Return the rest state per metre of a held road height (body and wheel follow)."""
    return np.array([1.0, 0, 1.0, 0] + [0.0] * (model.nx - 4))


def passive_tail(model: QuarterCarModel, c_e0: float):
    """Return (Q_a, Q_P): ∫₀^∞ z̈_s² dt = ξᵀQ_aξ and ∫₀^∞ P dt = ξᵀQ_Pξ under c_e0.

    The free response from a deviation ξ of the linearised model with the passive
    damping c_e0: Lyapunov equations AᵀQ + QA + CᵀC = 0, C the acceleration row of A,
    resp. c_e0·GᵀG with v_gen = G·x.  A principled terminal cost: what a finite horizon
    leaves out, valued as if the passive damping took over.
    """
    a, _, _ = linearize(model, u0=c_e0)
    n = model.nx
    v_gen = model.generator_velocity(model.x_sym)      # linear in x
    gen = np.asarray(ca.evalf(ca.jacobian(v_gen, model.x_sym))).reshape(1, n)
    out = []
    for c in (a[1:2, :], np.sqrt(c_e0) * gen):
        lhs = np.kron(np.eye(n), a.T) + np.kron(a.T, np.eye(n))
        q = np.linalg.solve(lhs, -(c.T @ c).reshape(-1, order='F')).reshape(n, n, order='F')
        out.append(tuple(map(tuple, 0.5 * (q + q.T))))
    return tuple(out)


@dataclass(frozen=True)
class OCPSpec:
    """What defines one OCP (with the model): the key :func:`build_ocp` caches on.

    ``cost`` is 'paper', 'continuous' or 'bound' (the module doc); the bound's
    Σ_k α1·x_a(t_k)² − α2·E_k/Ts is n·(α1·acc_rms² − α2·P_avg) with the acceleration
    sampled at t_k and the energy E_k integrated.
    ``blocks`` are the interval lengths in samples; ``terminal_weight`` the stored-
    energy credit (preview_long); ``tail`` the passive-tail quadratic forms
    (:func:`passive_tail`) or None; ``delayed`` models a command delay d (parameter):
    over [t_k, t_k + d] the acting command u_acting (parameter), then the plan's
    intervals from t_k + d on.
    """

    ts: float
    blocks: Tuple[int, ...]
    cost: str
    u_min: float
    u_max: float
    terminal_weight: float = 0.0
    degree: int = COLLOCATION_DEGREE
    rollout_substep_s: float = ROLLOUT_SUBSTEP_S
    delayed: bool = False
    tail: Optional[tuple] = None

    def __post_init__(self):
        if self.cost not in ('paper', 'continuous', 'bound'):
            raise ParamError(f'OCP cost {self.cost!r} unknown: paper, continuous or bound')
        object.__setattr__(self, 'blocks', tuple(int(m) for m in self.blocks))


@lru_cache(maxsize=32)
def build_ocp(model: QuarterCarModel, spec: OCPSpec) -> OCP:
    """Build (once per model and :class:`OCPSpec`) the collocation NLP and the RK4 rollout."""
    ts, blocks, cost = spec.ts, spec.blocks, spec.cost
    u_min, u_max, terminal_weight = spec.u_min, spec.u_max, spec.terminal_weight
    degree, rollout_substep_s = spec.degree, spec.rollout_substep_s
    delayed, tail = spec.delayed, spec.tail
    nx = model.nx
    horizon = int(sum(blocks))
    xs = np.array(model.x_scale)
    xs_col = ca.DM(xs)
    taus = _collocation(degree)[3]
    with_acc = cost in ('paper', 'bound')
    nxa = nx + int(with_acc)
    nk = nx * degree

    # One interval, as a Function of its data (the real-time SQP differentiates it).
    xt_sym, v_sym = ca.SX.sym('xt', nxa), ca.SX.sym('v')
    k_sym, wv_sym = ca.SX.sym('k', nk), ca.SX.sym('wv', degree + 1)
    h_sym, a_sym = ca.SX.sym('h'), ca.SX.sym('alpha', 2)
    defects, x_end, a_node, res, res_w, econ = _interval(
        model, cost, ts, xt_sym, v_sym, k_sym, wv_sym, h_sym, a_sym)
    weight = a_sym[0] * ca.vertcat(*res_w)
    res = ca.vertcat(*res)
    cost_i = ca.dot(weight, res ** 2) + econ
    phi = ca.vertcat(x_end, a_node) if with_acc else x_end
    interval = ca.Function('interval', [xt_sym, v_sym, k_sym, wv_sym, h_sym, a_sym],
                           [defects, phi, cost_i, res, weight, econ],
                           ['xt', 'v', 'k', 'wv', 'h', 'alpha'],
                           ['defects', 'phi', 'cost', 'res', 'weight', 'econ'])
    # The delay's prefix: the acting command, no cost (nothing in it can be decided);
    # x_a(k−1) passes through.
    phi_pre = ca.vertcat(x_end, xt_sym[nx]) if with_acc else x_end
    prefix = ca.Function('prefix', [xt_sym, v_sym, k_sym, wv_sym, h_sym],
                         [defects, phi_pre], ['xt', 'v', 'k', 'wv', 'h'], ['defects', 'phi'])
    w_end_sym = ca.SX.sym('w_end')
    stored = model.energy(xt_sym[:nx] * xs_col, w_end_sym) / ts
    # Stored mechanical energy is worth harvesting later: credit a share of it.
    term = -terminal_weight * a_sym[1] * stored if terminal_weight > 0 else ca.SX(0)
    if tail is not None:
        # The cost beyond the horizon if the passive damping took over (linearised,
        # road held): α1·∫a² − α2·∫P from the deviation of x_N from rest on the road.
        comfort, harvest = (ca.DM(np.array(m)) for m in tail)
        dev = xt_sym[:nx] * xs_col - w_end_sym * ca.DM(_road_rest(model))
        term += (a_sym[0] * ca.bilin(comfort, dev, dev)
                 - a_sym[1] * ca.bilin(harvest, dev, dev)) / ts
    terminal = ca.Function('terminal', [xt_sym, w_end_sym, a_sym], [term],
                           ['xt', 'w_end', 'alpha'], ['cost'])

    w = ca.SX.sym('w', horizon + 1)
    alpha = ca.SX.sym('alpha', 2)
    extra = ca.SX.sym('delay', 2 if delayed else 0)    # [d, u_acting/U_SCALE]
    delta = extra[0] / ts if delayed else None
    road_mat, w_end = _road_points(w, blocks, taus, delta)
    if delayed:
        road_pre = ca.vertcat(w[0], *[w[0] + (w[1] - w[0]) * delta * tau for tau in taus])
        h_pre, v_pre = extra[0], extra[1]
    else:
        road_pre, h_pre, v_pre = ca.DM.zeros(degree + 1), ca.SX(0), ca.SX(0)
    p_sym = ca.vertcat(w, alpha, extra)
    road = ca.Function('road', [p_sym], [road_mat, w_end, road_pre, h_pre, v_pre],
                       ['p'], ['w', 'w_end', 'w_pre', 'h_pre', 'v_pre'])

    z, g = [], []
    obj = 0
    xk_s = ca.SX.sym('x0', nxa)
    z.append(xk_s)
    if delayed:
        kp = ca.SX.sym('k_pre', nk)
        dfc, phi_k = prefix(xk_s, v_pre, kp, road_pre, h_pre)
        xk_s = ca.SX.sym('x_acts', nxa)
        z += [kp, xk_s]
        g += [xk_s - phi_k, dfc]
    for i, m in enumerate(blocks):
        v = ca.SX.sym(f'v{i}')
        z.append(v)
        a = None
        if with_acc:
            # x_a(k) as a variable: the jerk-like term is a convex quadratic inside
            # the stage (x_a(k−1) is carried in the stage state).
            a = ca.SX.sym(f'a{i}')
            z.append(a)
        k = ca.SX.sym(f'xc{i}', nk)
        z.append(k)
        dfc, x_end, a_node, res, res_w, econ = _interval(
            model, cost, ts, xk_s, v, k, road_mat[:, i], m * ts, alpha, a)
        obj += alpha[0] * ca.dot(ca.vertcat(*res_w), ca.vertcat(*res) ** 2) + econ
        xk_s = ca.SX.sym(f'x{i + 1}', nxa)
        z.append(xk_s)
        g.append(xk_s - (ca.vertcat(x_end, a) if with_acc else x_end))
        g.append(ca.vertcat(dfc, a - a_node) if with_acc else dfc)
    obj += terminal(xk_s, w_end, alpha)
    nlp = ca.Function('nlp', [ca.vertcat(*z), p_sym], [obj, ca.vertcat(*g)],
                      ['z', 'p'], ['f', 'g'])

    # Rollout: the decision vector of a plan, by the model's RK4 through every
    # collocation point (a point with tiny collocation defects).
    x0 = ca.SX.sym('x0', nx)
    a_prev = ca.SX.sym('a_prev')
    ub = ca.SX.sym('ub', len(blocks))
    xr = x0
    a_last = a_prev
    zr = [xr / xs_col] + ([a_last] if with_acc else [])

    def through_points(u, wv, h, fixed=True):
        nonlocal xr
        tau_prev = 0.0
        for r in range(degree):
            dt = (taus[r] - tau_prev) * (h if fixed else ts)
            n_sub = max(1, int(np.ceil(dt / rollout_substep_s - 1e-9)))
            if fixed:
                xr = model.rk4_step(dt, n_sub)(xr, u, wv[r], wv[r + 1])
            else:     # the prefix: h = d < Ts, sub-steps for the longest
                xr = model.rk4_flow(n_sub)(xr, u, wv[r], wv[r + 1], (taus[r] - tau_prev) * h)
            zr.append(xr / xs_col)
            tau_prev = taus[r]

    if delayed:
        through_points(U_SCALE * v_pre, road_pre, h_pre, fixed=False)
        zr += [xr / xs_col] + ([a_last] if with_acc else [])
    for i, m in enumerate(blocks):
        wv = road_mat[:, i]
        acc = model.sprung_accel(xr, U_SCALE * ub[i], wv[0])
        zr += [ub[i]] + ([acc] if with_acc else [])
        a_last = acc
        through_points(U_SCALE * ub[i], wv, m * ts)
        zr += [xr / xs_col] + ([a_last] if with_acc else [])
    q = ca.vertcat(w, extra)
    rollout = ca.Function('rollout', [x0, a_prev, ub, q], [ca.vertcat(*zr)],
                          ['x0', 'a_prev', 'u', 'q'], ['z'])
    return OCP(nlp, rollout, tuple(blocks), nx, degree, with_acc, float(u_min), float(u_max),
               xs, float(ts), bool(delayed), interval, prefix, terminal, road,
               f'{model.kind}|{model.params!r}|{spec!r}')


__all__ = ['COLLOCATION_DEGREE', 'OCP', 'OCPSpec', 'ROLLOUT_SUBSTEP_S', 'StageSlices', 'U_SCALE',
           'build_ocp', 'passive_tail', 'stable_rollout_substep']
