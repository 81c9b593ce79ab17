r"""The NMPC's real-time solver: an SQP on the collocation NLP, condensed onto the N inputs.

The OCP (:mod:`erva_ros.core.controllers.ocp`) is a collocation NLP in z = (states, inputs,
collocation states).  It is non-convex (bilinear u·v_gen, near bang-bang optima).
Each iteration, at the current point z:

1. *Condensing* (one compiled SX function).  A forward sweep over the intervals
   eliminates each interval's collocation states on the linearised equalities (one
   sparse LU of its 18 x 18 collocation Jacobian, kinematic rows first, no numerical
   pivoting: :func:`~erva_ros.core.controllers.linalg.lu_factor`): they follow the
   interval's start state and input, so the interval reduces to (x_i, v_i), with the
   transition matrix A_i and the Newton correction ζ_i of its defects; a backward
   sweep the multipliers.  The
   reduced Hessian Σ_i S_iᵀ (T_iᵀ H_i T_i) S_i and gradient follow (S_i = d(x_i, v_i)/du),
   with H_i either ``exact`` (the interval Lagrangian: cost plus multipliers times
   defects and transition) or ``gauss_newton``: the comfort residuals' Gauss-Newton
   term plus the *exact* Hessian of the economic term −α2·u·v_gen² (a Gauss-Newton
   model alone misfits it), the dynamics' curvature left out.  dz/du is never formed:
   the step is expanded from the A_i and K_i after the QP (O(N), :func:`step_function`).
2. *Convexification*: the N x N reduced Hessian's eigenvalues below a floor are raised
   to it (parallel Jacobi, :func:`~erva_ros.core.controllers.linalg.convexify`), so
   the QP is convex; along negative curvature its step goes to the box.
3. *Box QP* (DAQP, N variables, diagonally scaled: :func:`box_qp_function`) for du;
   the full step Δz = ζ + (dz/du)·du.
4. *Globalisation*: the candidate z + t·Δz is put back on the collocation equations
   (per interval, from that linear prediction, a Newton step and two chord steps with
   its factorisation: a simulation with the NLP's own integrator), and accepted by
   Armijo's rule on the ℓ1 merit f + ρ·‖g‖₁ of the very NLP that IPOPT solves, over
   t = 1, ½, ¼, ⅛; a step is evaluated only if the longer one failed (short-circuit
   conditionals).  After a full step that gained more than EXTRAPOLATION_RATIO times
   the QP's prediction, t = 2, 4 in turn while each lowers the merit further.
   Candidates judged by an RK4 rollout instead (the solver before these) are a
   different model: for bang-bang plans its quadrature of the cost was off by up to
   50 %, and its gradient disagreed with the NLP's.
5. *Stop* when an iteration is predicted to gain less than ``tol``·|f(start)| or no
   step decreases the merit, else after ``max_iter`` iterations.  Counts, never the
   wall clock, end a solve: offline results do not depend on the machine's load.

Starts: the warm start and the alternatives, each put on the collocation equations
(from each interval's start state held: :func:`start_function`); the best by its cost in
the NLP is iterated.  f and ‖g‖₁ of the current point travel with it, from where it was
evaluated (a start or the line search), so an iteration never evaluates the NLP twice.

The input box [u_min, u_max] is a parameter of the solver (after the OCP's p), not a
constant of its code: the bounds may change between two solves (live tuning,
docs/live.md) without a new compiled solver.

The whole solver is one CasADi Function with conditionals (no Python per iteration).
With ``codegen`` its two pieces are compiled to C as wholes, the starts and one
iteration (QP model, box QP, line search, stop test): the solver calls the iteration
``max_iter`` times, and it returns its input unchanged once done.  Compiled whole, no
matrix operation runs in CasADi's virtual machine, and the pieces do not depend on
``max_iter`` or ``tol``.  Each per-interval piece is one kernel called as a loop
(``mapaccum``), so the C code holds one copy of it (docs/nmpc.md).
"""

from functools import lru_cache

import casadi as ca
import numpy as np

from erva_ros.core.model.codegen import compile_for, load_or_build
from erva_ros.core.controllers.linalg import (convexify, lu_factor, lu_solve, SparseLU,
                                              symmetric)
from erva_ros.core.settings.controller import HESSIANS

#: Backtracking steps of the line search (a step is tried only if the longer one failed).
LINE_SEARCH_STEPS = (1.0, 0.5, 0.25, 0.125)
#: After an accepted full step that gained more than EXTRAPOLATION_RATIO times what the
#: QP predicted, these longer ones in turn while each lowers the merit further: the
#: model is cautious where the cost keeps falling towards the box.
EXTRAPOLATION_STEPS = (2.0, 4.0)
EXTRAPOLATION_RATIO = 1.2
#: Armijo constant: accept a step that gains this share of the predicted merit decrease.
ARMIJO = 1e-4
#: (Newton, chord) steps per interval that put a plan on the collocation equations: a
#: chord step reuses the Newton step's factorisation (~1/4 of a Newton step's arithmetic).
#: From the SQP's linear prediction, measured on seed 0's problems: defects ≤ 1e-8, the
#: cost within 2e-9 of more Newton steps' (one Newton step alone: defects up to 1e-2).
SOLVE_STEPS = (1, 2)
#: ℓ1 merit: ρ = RHO_FACTOR·max|multiplier| + RHO_MIN.
RHO_FACTOR, RHO_MIN = 2.0, 1e-6


def _packed(*mats):
    """Return the structural nonzeros of SX matrices as one column (a kernel's output)."""
    return ca.vertcat(*[e for m in mats for e in m.nonzeros()])


def _unpacked(vec, *mats):
    """Return matrices with the sparsity of ``mats`` from :func:`_packed`'s column ``vec``."""
    out, o = [], 0
    for m in mats:
        out.append(ca.SX(m.sparsity(), vec[o:o + m.nnz()]))
        o += m.nnz()
    return out


def _lu_packed(lu: SparseLU):
    """Return the non-constant entries of an LU's factors, as a column."""
    return ca.vertcat(*[e for row in lu.m for e in row if not e.is_constant()])


def _lu_unpacked(like: SparseLU, vec) -> SparseLU:
    """Return ``like``'s factors with its non-constant entries read from ``vec``."""
    it = iter(range(vec.numel()))
    return SparseLU(like.order, [[e if e.is_constant() else vec[next(it)] for e in row]
                                 for row in like.m])


@lru_cache(maxsize=32)
def _sweep_kernels(ocp, hessian: str):
    """Return the condensing's sweeps over the intervals (forward, backward), as loops.

    Each is one interval's work, compiled once and called N times (``mapaccum``), where
    unrolled over the intervals the condensing was 1.2-4 MB of straight-line code
    (more than the L2 cache), reloaded every iteration.

    ``forward`` (c_0, S_0, stages z_i, x_{i+1}, road w_i, h_i, e_i, α) -> (c_N, S_N,
    [K_i; A_i], dz0_i, d(x_i, v_i)/du, kept_i, ζ_i): per interval the Jacobians, the LU
    of its collocation Jacobian and the elimination of its collocation states,
    k_i = K_i·(x_i, v_i) + κ_i, its transition x_{i+1} = A_i·(x_i, v_i) + c_i and
    Newton correction ζ_i; S_i = d x_i/du; ``kept`` what the backward sweep needs.
    ``backward``, over the intervals in reverse, (ν, H, g, g_lin, ∇fᵀζ, max|λ|; z_i, w_i,
    h_i, α, K_i, ζ_i, kept_i, d(x_i, v_i)/du) accumulates the reduced Hessian's upper
    triangle Σ S_iᵀ(T_iᵀ·H_i·T_i)S_i, gradient and the multipliers ν_i.
    """
    nxa, nk, nb = ocp.nxa, ocp.nk, len(ocp.blocks)
    at = ocp.stage_slices(0)
    o = at.x.start
    col = ca.SX.sym('z_i', ocp.stage)
    xt, v, k = col[at.x.start - o:at.x.stop - o], col[at.v - o], col[at.k.start - o:]
    wv, h, al = ca.SX.sym('wv', ocp.degree + 1), ca.SX.sym('h'), ca.SX.sym('alpha', 2)
    mu, nu = ca.SX.sym('mu', nk), ca.SX.sym('nu', nxa)
    corr, x_next = ca.SX.sym('corr', nxa), ca.SX.sym('x_next', nxa)
    sens, unit = ca.SX.sym('sens', nxa, nb), ca.SX.sym('unit', 1, nb)
    y = ca.vertcat(xt, v, k)
    args = [xt, v, k, wv, h, al]
    g, phi, cost, res, weight, econ = ocp.interval(*args)
    once = {'never_inline': True}
    if hessian == 'exact':
        curv = ca.hessian(cost + ca.dot(mu, g) - ca.dot(nu, phi), y)[0]
        gn = []
    else:
        curv = ca.hessian(econ, y)[0]
        gn = [ca.jacobian(res, y), weight]
    ys = [ca.SX.sym('xt', nxa), ca.SX.sym('v'), ca.SX.sym('k', nk)]
    hess = ca.Function('interval_hess', ys + [wv, h, al, mu, nu],
                       [ca.substitute(curv, y, ca.vertcat(*ys))], once)
    jg, jphi, grad = ca.jacobian(g, y), ca.jacobian(phi, y), ca.gradient(cost, y)
    gx, gv, gk = jg[:, :nxa], jg[:, nxa], jg[:, nxa + 1:]
    lu = lu_factor(gk)          # collocation states: one sparse LU per interval
    kk = -lu_solve(lu, ca.horzcat(gx, gv, g + ca.mtimes(gx, corr)))
    t_i = ca.vertcat(ca.DM.eye(nxa + 1), kk[:, :nxa + 1])       # y_i = T_i·(x_i, v_i)
    zeta = ca.vertcat(corr, 0, kk[:, nxa + 1])
    a_i = ca.mtimes(jphi, t_i)
    corr_next = ca.mtimes(jphi, zeta) + phi - x_next
    s_i = ca.vertcat(sens, unit)                               # d(x_i, v_i)/du
    dz0 = ca.SX.zeros(ocp.stage)
    dz0[at.x.start - o:at.x.stop - o] = corr
    dz0[at.k.start - o:] = zeta[nxa + 1:]
    if ocp.with_acc:
        # the NLP's x_a(k) variable moves to the stage's new node acceleration
        dz0[at.acc - o] = corr_next[nxa - 1] + x_next[nxa - 1] - col[at.acc - o]
    kept_mats = [grad, gx, jphi] + gn
    forward = ca.Function(
        'interval_forward', [corr, sens, col, x_next, wv, h, unit, al],
        [corr_next, ca.mtimes(a_i, s_i), ca.vertcat(kk[:, :nxa + 1], a_i), dz0, s_i,
         ca.vertcat(_packed(*kept_mats), _lu_packed(lu)), zeta], once)

    kept = ca.SX.sym('kept', forward.size1_out(5))
    kk_in, zeta_in = ca.SX.sym('K', nk, nxa + 1), ca.SX.sym('zeta', nxa + 1 + nk)
    s_in = ca.SX.sym('s', nxa + 1, nb)
    grad_, gx_, jphi_, *gn_ = _unpacked(kept, *kept_mats)
    lu_ = _lu_unpacked(lu, kept[sum(m.nnz() for m in kept_mats):])
    t_in = ca.vertcat(ca.DM.eye(nxa + 1), kk_in)
    rhs = grad_[nxa + 1:] - ca.mtimes(jphi_[:, nxa + 1:].T, nu)
    mu_i = -lu_solve(lu_, rhs, transpose=True)          # collocation multipliers
    h_i = hess(*args, mu_i, nu)
    h_red = ca.mtimes([t_in.T, h_i, t_in])                # the interval on (x_i, v_i)
    g_red = ca.mtimes(t_in.T, grad_ + ca.mtimes(h_i, zeta_in))
    if hessian == 'gauss_newton':
        jres, wres = gn_
        jt = ca.mtimes(jres, t_in)
        h_red += 2 * ca.mtimes([jt.T, ca.diag(wres), jt])
        g_red += 2 * ca.mtimes(jt.T, wres * ca.mtimes(jres, zeta_in))
    hs = ca.mtimes(symmetric(h_red), s_in)
    upper = ca.SX.zeros(nb, nb)
    for j in range(nb):
        for i in range(j + 1):
            upper[i, j] = ca.dot(s_in[:, i], hs[:, j])
    hr, gr, gl = ca.SX.sym('hr', nb, nb), ca.SX.sym('gr', nb), ca.SX.sym('gl', nb)
    df0, lam = ca.SX.sym('df0'), ca.SX.sym('lam')
    backward = ca.Function(
        'interval_backward',
        [nu, hr, gr, gl, df0, lam, col, wv, h, al, kk_in, zeta_in, kept, s_in],
        [-(grad_[:nxa] + ca.mtimes(gx_.T, mu_i) - ca.mtimes(jphi_[:, :nxa].T, nu)),
         hr + upper, gr + ca.mtimes(s_in.T, g_red),
         gl + ca.mtimes(s_in.T, ca.mtimes(t_in.T, grad_)), df0 + ca.dot(grad_, zeta_in),
         ca.fmax(lam, ca.fmax(ca.mmax(ca.fabs(mu_i)), ca.mmax(ca.fabs(nu))))], once)
    return (forward.mapaccum('condensing_forward', nb, [0, 1], [0, 1]),
            backward.mapaccum('condensing_backward', nb, list(range(6)), list(range(6))))


@lru_cache(maxsize=None)
def _convexified(n: int, convex: bool) -> ca.Function:
    """Return (upper triangle of H) -> H convexified (or only made symmetric)."""
    hr = ca.MX.sym('h', n, n)
    out = ca.triu(hr) + ca.triu(hr, False).T
    return ca.Function('reduced_hessian', [hr], [convexify(out) if convex else out])


def qp_model_function(ocp, hessian: str = 'exact', convex: bool = True) -> ca.Function:
    """Return the condensed QP of the OCP at a point z (module doc, steps 1-2).

    (z, p) -> (H (convexified), g, g_lin, dz0, stages, [∇fᵀ dz0, ρ]): the QP
    min ½ duᵀ H du + gᵀ du; the full step Δz = dz0 + (dz/du)·du, expanded from
    ``stages`` by :func:`step_function`; g_lin = (dz/du)ᵀ∇f (the gradient without the
    curvature correction); ρ the ℓ1 merit's weight.

    Each interval's collocation states are eliminated first: on the linearised
    equalities they follow its start state and input, k_i = K_i·(x_i, v_i) + κ_i, so
    the interval reduces to (x_i, v_i), with the Hessian Tᵢᵀ·H_i·Tᵢ (T_i = [I; K_i])
    and the transition x_{i+1} = A_i·(x_i, v_i) + c_i.  Only these small matrices meet
    the N inputs; dz/du is never formed.  The intervals run as loops
    (:func:`_sweep_kernels`).
    """
    if hessian not in HESSIANS:
        raise ValueError(f'hessian {hessian!r} unknown; choose one of {", ".join(HESSIANS)}')
    nxa, nk, nb, nz = ocp.nxa, ocp.nk, len(ocp.blocks), ocp.nz
    forward, backward = _sweep_kernels(ocp, hessian)
    xt, v, k = ca.SX.sym('xt', nxa), ca.SX.sym('v'), ca.SX.sym('k', nk)
    wv, h, al = ca.SX.sym('wv', ocp.degree + 1), ca.SX.sym('h'), ca.SX.sym('alpha', 2)
    x_next = ca.SX.sym('x_next', nxa)
    # The prefix depends on nothing decided: only its defects are corrected.
    g_pre, phi_pre = ocp.prefix(xt, v, k, wv, h)
    dk = -lu_solve(lu_factor(ca.jacobian(g_pre, k)), g_pre)
    prefix = ca.Function('prefix_correction', [xt, v, k, wv, h, x_next],
                         [dk, ca.substitute(phi_pre, k, k + dk) - x_next])
    xb, wb = ca.SX.sym('x_end', nxa), ca.SX.sym('w_end')
    term = ocp.terminal(xb, wb, al)
    h_term, g_term = ca.hessian(term, xb)
    sens = ca.SX.sym('sens', nxa, nb)
    corr = ca.SX.sym('corr', nxa)
    terminal = ca.Function(
        'terminal_model', [xb, wb, al, sens, corr],
        [ca.triu(ca.mtimes([sens.T, h_term, sens])),
         ca.mtimes(sens.T, g_term + ca.mtimes(h_term, corr)), ca.mtimes(sens.T, g_term),
         ca.dot(g_term, corr), -g_term])

    z = ca.MX.sym('z', nz)
    p = ca.MX.sym('p', ocp.n_p)
    alpha = p[ocp.horizon + 1:ocp.horizon + 3]
    road, w_end, road_pre, h_pre, v_pre = ocp.road(p)
    o, o_end = ocp.offset, nz - nxa
    body = ca.reshape(z[o:o_end], ocp.stage, nb)
    x_next = ca.horzcat(body[:nxa, 1:], z[o_end:])
    if ocp.delayed:
        dk, corr = prefix(z[:nxa], v_pre, z[nxa:nxa + nk], road_pre, h_pre, z[nxa + nk:o + nxa])
        dz0_pre = ca.vertcat(ca.DM.zeros(nxa), dk)
    else:
        corr, dz0_pre = ca.DM.zeros(nxa), ca.DM.zeros(0)
    steps = ca.DM([[m * ocp.ts for m in ocp.blocks]])
    corr, sens, stages, dz0, s_all, kept, zeta = forward(
        corr, ca.DM.zeros(nxa, nb), body, x_next, road, steps, ca.reshape(ca.DM.eye(nb), 1, -1),
        ca.repmat(alpha, 1, nb))
    corr, sens = corr[:, -1], sens[:, -nb:]      # the state after the last interval
    hr, gr, g_lin, df0, nu = terminal(z[o_end:], w_end, alpha, sens, corr)

    def rev(m):
        """Return a horzcat of nb equal blocks with the blocks in reverse order."""
        w = m.size2() // nb
        return ca.horzcat(*[m[:, i * w:(i + 1) * w] for i in reversed(range(nb))])

    nu, hr, gr, g_lin, df0, lam = backward(
        nu, hr, gr, g_lin, df0, 0, rev(body), rev(road), rev(steps),
        ca.repmat(alpha, 1, nb), rev(stages[:nk, :]), rev(zeta), rev(kept), rev(s_all))
    nu, hr, gr, g_lin, df0, lam = (m[:, -w:] for m, w in zip(
        (nu, hr, gr, g_lin, df0, lam), (1, nb, 1, 1, 1, 1)))
    rho = RHO_FACTOR * lam + RHO_MIN
    dz0 = ca.vertcat(dz0_pre, ca.vec(dz0), corr)
    return ca.Function('qp_model', [z, p],
                       [_convexified(nb, convex)(hr), gr, g_lin, dz0, stages,
                        ca.vertcat(df0, rho)],
                       ['z', 'p'], ['h', 'g', 'g_lin', 'dz0', 'stages', 'merit'])


def _stage_column(ocp, x, v, acc, k):
    """Return one interval's part of z (its x_i, v_i, x_a(k) if any, K_i) in z's layout."""
    at = ocp.stage_slices(0)
    o = at.x.start
    col = ca.SX.zeros(ocp.stage)
    col[at.x.start - o:at.x.stop - o] = x
    col[at.v - o] = v
    if ocp.with_acc:
        col[at.acc - o] = acc
    col[at.k.start - o:] = k
    return col


def step_function(ocp) -> ca.Function:
    """Return (stages, dz0, du) -> Δz = dz0 + (dz/du)·du, from :func:`qp_model_function`.

    A forward sweep through the intervals' K_i and A_i: O(N), where the product with a
    dense dz/du would be O(N²); one interval compiled once, called N times.
    """
    nxa, nk, nb = ocp.nxa, ocp.nk, len(ocp.blocks)
    m, dx, du = ca.SX.sym('m', nk + nxa, nxa + 1), ca.SX.sym('dx', nxa), ca.SX.sym('du')
    d = ca.mtimes(m, ca.vertcat(dx, du))
    interval = ca.Function('expand_interval', [dx, m, du],
                           [d[nk:], _stage_column(ocp, dx, du, d[nk + nxa - 1], d[:nk])],
                           {'never_inline': True})
    sweep = interval.mapaccum('expand_sweep', nb, [0], [0])
    stages = ca.MX.sym('stages', nk + nxa, (nxa + 1) * nb)
    dz0, du = ca.MX.sym('dz0', ocp.nz), ca.MX.sym('du', nb)
    # x_0 (and the delay's prefix) is not decided
    dx_all, cols = sweep(ca.DM.zeros(nxa), stages, du.T)
    dz = ca.vertcat(ca.DM.zeros(ocp.offset), ca.vec(cols), dx_all[:, -1])
    return ca.Function('expand_step', [stages, dz0, du], [dz0 + dz],
                       ['stages', 'dz0', 'du'], ['dz'])


@lru_cache(maxsize=64)
def _collocation_solve(ocp, steps=SOLVE_STEPS) -> ca.Function:
    """Return (x_i, v_i, k guess, w_i, h) -> k_i on the interval's collocation equations.

    ``steps`` = (Newton, chord) steps from the guess, the chord steps with the last
    Newton step's factorisation.
    """
    nxa, nk = ocp.nxa, ocp.nk
    newton, chords = steps
    xt, v, k = ca.SX.sym('xt', nxa), ca.SX.sym('v'), ca.SX.sym('k', nk)
    wv, h = ca.SX.sym('wv', ocp.degree + 1), ca.SX.sym('h')
    g, _ = ocp.prefix(xt, v, k, wv, h)      # the same defects as every interval
    defects = ca.Function('defects', [xt, v, k, wv, h], [g])
    jac, k_on = ca.jacobian(g, k), k
    for n in range(newton):
        lu = lu_factor(jac if n == 0 else ca.substitute(jac, k, k_on))
        k_on = k_on - lu_solve(lu, defects(xt, v, k_on, wv, h))
    for _ in range(chords):                   # the last Newton step's Jacobian kept
        k_on = k_on - lu_solve(lu, defects(xt, v, k_on, wv, h))
    return ca.Function('collocation_solve', [xt, v, k, wv, h], [k_on], {'never_inline': True})


def _project(ocp, p, x, inputs, guesses, steps=SOLVE_STEPS):
    """Return the decision vector of ``inputs`` on the collocation equations, from x(t_k) (MX).

    Interval by interval (one interval compiled once, called N times): the ``steps`` =
    (Newton, chord) steps on the interval's collocation equations from its guess, then
    its end state starts the next interval.  A simulation with the NLP's own
    integrator, so a candidate's cost is the NLP's.  ``x`` is the scaled start state
    (with x_a(k-1) for the paper cost), ``inputs`` the scaled inputs (a row), and
    ``guesses`` (the delay prefix's, the intervals' as columns) the collocation states
    to start from, or None: from each interval's start state held.
    """
    nxa, nk, nb = ocp.nxa, ocp.nk, len(ocp.blocks)
    solve = _collocation_solve(ocp, steps)
    xt, v, k = ca.SX.sym('xt', nxa), ca.SX.sym('v'), ca.SX.sym('k', nk)
    wv, h, al = ca.SX.sym('wv', ocp.degree + 1), ca.SX.sym('h'), ca.SX.sym('alpha', 2)
    held = ca.repmat(xt[:ocp.nx], ocp.degree, 1)
    k_on = solve(xt, v, held if guesses is None else k, wv, h)
    x_next = ocp.interval(xt, v, k_on, wv, h, al)[1]
    interval = ca.Function('project_interval', [xt, v, k, wv, h],
                           [x_next, _stage_column(ocp, xt, v, x_next[nxa - 1], k_on)],
                           {'never_inline': True})
    sweep = interval.mapaccum('project_sweep', nb, [0], [0])
    road, _, road_pre, h_pre, v_pre = ocp.road(p)
    out = []                  # z: [the delay prefix], the intervals (each from its x_i), x_N
    if ocp.delayed:
        kp = solve(x, v_pre, ca.repmat(x[:ocp.nx], ocp.degree, 1) if guesses is None
                   else guesses[0], road_pre, h_pre)
        out = [x, kp]
        x = ocp.prefix(x, v_pre, kp, road_pre, h_pre)[1]
    k_guess = ca.DM.zeros(nk, nb) if guesses is None else guesses[1]
    steps_h = ca.DM([[m * ocp.ts for m in ocp.blocks]])
    xs, cols = sweep(x, inputs, k_guess, road, steps_h)
    return ca.vertcat(*out, ca.vec(cols), xs[:, -1])


@lru_cache(maxsize=32)
def merit_function(ocp) -> ca.Function:
    """Return (z, p) -> (f, ‖g‖₁): the NLP's cost and the ℓ1 norm of its equalities.

    ``ocp.nlp``'s sums (to rounding) on points on the equations (starts, line-search
    candidates), one interval compiled once and called N times.
    """
    nxa, nk, nb, nz = ocp.nxa, ocp.nk, len(ocp.blocks), ocp.nz
    at = ocp.stage_slices(0)
    o = at.x.start
    col, x_next = ca.SX.sym('z_i', ocp.stage), ca.SX.sym('x_next', nxa)
    wv, h, al = ca.SX.sym('wv', ocp.degree + 1), ca.SX.sym('h'), ca.SX.sym('alpha', 2)
    f_acc, g_acc = ca.SX.sym('f'), ca.SX.sym('g1')
    xt, v, k = col[at.x.start - o:at.x.stop - o], col[at.v - o], col[at.k.start - o:]
    acc = col[at.acc - o] if ocp.with_acc else None
    # (the paper cost's jerk term with the node acceleration: on the points judged here,
    # projections, the NLP's x_a(k) variable is that acceleration)
    defects, phi, cost = ocp.interval(xt, v, k, wv, h, al)[:3]
    gap = x_next - phi
    if ocp.with_acc:      # the NLP's x_a(k) variable and its equation
        gap = ca.vertcat(gap[:nxa - 1], x_next[nxa - 1] - acc, defects, acc - phi[nxa - 1])
    else:
        gap = ca.vertcat(gap, defects)
    interval = ca.Function('merit_interval', [f_acc, g_acc, col, x_next, wv, h, al],
                           [f_acc + cost, g_acc + ca.norm_1(gap)], {'never_inline': True})
    sweep = interval.mapaccum('merit_sweep', nb, [0, 1], [0, 1])
    z, p = ca.MX.sym('z', nz), ca.MX.sym('p', ocp.n_p)
    alpha = p[ocp.horizon + 1:ocp.horizon + 3]
    road, w_end, road_pre, h_pre, v_pre = ocp.road(p)
    o_end = nz - nxa
    body = ca.reshape(z[ocp.offset:o_end], ocp.stage, nb)
    g1 = 0
    if ocp.delayed:
        dfc, phi_k = ocp.prefix(z[:nxa], v_pre, z[nxa:nxa + nk], road_pre, h_pre)
        g1 = ca.norm_1(ca.vertcat(z[nxa + nk:ocp.offset + nxa] - phi_k, dfc))
    steps_h = ca.DM([[m * ocp.ts for m in ocp.blocks]])
    f, g1 = sweep(0, g1, body, ca.horzcat(body[:nxa, 1:], z[o_end:]), road, steps_h,
                  ca.repmat(alpha, 1, nb))
    f = f[-1] + ocp.terminal(z[o_end:], w_end, alpha)
    return ca.Function('merit', [z, p], [f, g1[-1]], ['z', 'p'], ['f', 'infeas'])


def projection_function(ocp, steps=SOLVE_STEPS) -> ca.Function:
    """Return (z, p) -> z on the collocation equations, for z's inputs.

    The steps start from z's collocation states (a good guess: the SQP's linear
    prediction); see :func:`_project`.
    """
    nxa, nk, nz, nb = ocp.nxa, ocp.nk, ocp.nz, len(ocp.blocks)
    z = ca.MX.sym('z', nz)
    p = ca.MX.sym('p', ocp.n_p)
    at = ocp.stage_slices(0)
    body = ca.reshape(z[ocp.offset:nz - nxa], ocp.stage, nb)
    inputs = body[at.v - at.x.start, :]
    guesses = (z[nxa:nxa + nk], body[at.k.start - at.x.start:, :])
    z_on = _project(ocp, p, z[:nxa], inputs, guesses, steps)
    return ca.Function('projection', [z, p], [z_on], ['z', 'p'], ['z_on'])


def start_function(ocp, steps=SOLVE_STEPS) -> ca.Function:
    """Return (x0, a_prev, u, p) -> (z, f, ‖g‖₁): the plan u (scaled) on the collocation equations.

    Each interval's solve starts from its start state held (no rollout needed: the
    collocation equations are linear but for the generator kinematics, so the
    ``steps`` reach them to rounding, ~1e-14, measured on the paper road).  f is the
    plan's cost in the NLP, what starts are compared by; ‖g‖₁ its defects.
    """
    x0, a_prev = ca.MX.sym('x0', ocp.nx), ca.MX.sym('a_prev')
    u, p = ca.MX.sym('u', len(ocp.blocks)), ca.MX.sym('p', ocp.n_p)
    x = x0 / ca.DM(ocp.x_scale)
    x = ca.vertcat(x, a_prev) if ocp.with_acc else x
    z = _project(ocp, p, x, u.T, None, steps)
    f, infeas = merit_function(ocp)(z, p)
    return ca.Function('plan_start', [x0, a_prev, u, p], [z, f, infeas],
                       ['x0', 'a_prev', 'u', 'p'], ['z', 'f', 'infeas'])


@lru_cache(maxsize=32)
def plan_value_function(ocp, codegen: str = 'off') -> ca.Function:
    """Return (x0, a_prev, u, p) -> (z, f, ‖g‖₁): a plan (scaled inputs) in the NLP, its cost.

    The real-time SQP's start evaluation (:func:`start_function`), compiled as
    ``codegen`` says: what its starts and IPOPT's solutions are compared by.
    """
    return compile_for(codegen, (start_function(ocp),), 'the NMPC solver')[0]


def box_qp_function(n: int) -> ca.Function:
    """Return (H, g, lo, hi) -> argmin ½ dᵀH d + gᵀd s.t. lo ≤ d ≤ hi, H positive definite.

    DAQP (a dual active-set method for small dense QPs, bundled with CasADi and
    generated to C with the solver): it solves the box QP to its KKT conditions,
    ~5 µs at n = 10 (qrqp, used before, took ~18 µs and left 2 of 500 recorded QPs
    with KKT residuals up to 0.5).  Diagonally scaled: the paper cost's Hessian spans
    1e6, scaled its condition number is ~1e3.
    """
    h, g = ca.MX.sym('h', n, n), ca.MX.sym('g', n)
    lo, hi = ca.MX.sym('lo', n), ca.MX.sym('hi', n)
    qp = ca.conic('box_qp_daqp', 'daqp', {'h': ca.Sparsity.dense(n, n), 'a': ca.Sparsity(0, n)},
                  {'error_on_fail': False})
    d = ca.diag(h)
    scale = 1 / ca.sqrt(ca.fmax(d, 1e-12 * ca.mmax(d) + 1e-300))
    ds = qp(h=h * ca.mtimes(scale, scale.T), g=g * scale, lbx=lo / scale, ubx=hi / scale)['x']
    return ca.Function('box_qp', [h, g, lo, hi], [ca.fmin(ca.fmax(scale * ds, lo), hi)],
                       ['h', 'g', 'lo', 'hi'], ['d'])


def _sqp_parts(ocp, n_alt: int, hessian: str):
    """Return (starts, step): the SQP's two pieces, each compiled whole with ``codegen``.

    ``starts`` (x0, a_prev, u_guess, u_alt, p) -> state = [z; f; ‖g‖₁; done; iterations]: the
    best start (module doc); p is the OCP's parameters and the input box
    (``OCP.with_box``).  ``step`` (done, p, f_ref, tol, state) -> state: one
    iteration (QP model, box QP, line search, stop test), or the state unchanged once
    ``done``.  Each is generated as one C function; the solver only calls ``step``
    ``max_iter`` times, so no model, QP or line-search operation runs in CasADi's
    virtual machine, and the compiled pieces do not depend on ``max_iter`` or ``tol``.
    """
    nb, nz = len(ocp.blocks), ocp.nz
    qp_model, expand, project, plan_start, merit = (
        qp_model_function(ocp, hessian), step_function(ocp), projection_function(ocp),
        start_function(ocp), merit_function(ocp))
    box_qp = box_qp_function(nb)
    u_idx = [int(i) for i in ocp.u_index]
    # The solver's parameters: the OCP's p and the input box (scaled), a parameter so that
    # the bounds may change between two solves without a new compiled solver.
    p = ca.MX.sym('p', ocp.n_pb)
    p_ocp, lo, hi = p[:ocp.n_p], p[ocp.n_p], p[ocp.n_p + 1]

    def candidate(zz, dz, t, rho):
        """Return z + t·Δz (inputs clipped into the box) on the equations: [z; f; ‖g‖₁], merit."""
        zc = zz + t * dz
        zc[u_idx] = ca.fmin(ca.fmax(zc[u_idx], lo), hi)
        zc = project(zc, p_ocp)        # from the linear prediction back onto the equalities
        f, infeas = merit(zc, p_ocp)
        return ca.vertcat(zc, f, infeas), f + rho * infeas

    # -- line search: step t is evaluated only if every longer step failed -----------
    z, dz, phi0, slope, rho, gain = (ca.MX.sym('z', nz), ca.MX.sym('dz', nz), ca.MX.sym('phi0'),
                                     ca.MX.sym('slope'), ca.MX.sym('rho'), ca.MX.sym('gain'))
    ls_in = [p, z, dz, phi0, slope, rho, gain]
    # After a full step that gained more than the QP predicted, longer ones while each
    # lowers the merit further.
    best, phi_best = ca.MX.sym('best', nz + 2), ca.MX.sym('phi_best')
    ext_in = [p, z, dz, rho, best, phi_best]
    extend = ca.Function('ls_keep', ext_in, [ca.vertcat(best, 1)])
    for n, t in reversed(list(enumerate(EXTRAPOLATION_STEPS))):
        cand, phic = candidate(z, dz, t, rho)
        out = ca.if_else(phic < phi_best, extend(p, z, dz, rho, cand, phic),
                         ca.vertcat(best, 1), True)
        extend = ca.Function(f'ls_extend_{n}', ext_in, [out])
    fail = ca.Function('ls_fail', ls_in, [ca.vertcat(z, phi0, 0, 0)])
    tail = fail
    for n, t in reversed(list(enumerate(LINE_SEARCH_STEPS))):
        cand, phic = candidate(z, dz, t, rho)
        ok = phic <= phi0 + ARMIJO * t * slope      # False for NaN: never a failed step
        if t == 1.0 and EXTRAPOLATION_STEPS:
            accept = ca.if_else(phi0 - phic > EXTRAPOLATION_RATIO * gain,
                                extend(p, z, dz, rho, cand, phic), ca.vertcat(cand, 1), True)
        else:
            accept = ca.vertcat(cand, 1)
        out = ca.if_else(ok, accept, tail(*ls_in), True)
        tail = ca.Function(f'line_search_{n}', ls_in, [out])
    line_search = tail

    # -- one iteration: state = [z; f; ‖g‖₁; done; iterations] ---------------------------
    # (f and ‖g‖₁ of z carried from where z was evaluated: the start or the line search)
    ns = nz + 4
    state = ca.MX.sym('state', ns)
    f_ref, tol = ca.MX.sym('f_ref'), ca.MX.sym('tol')
    z = state[:nz]
    h_red, g_red, g_lin, dz0, stages, mdata = qp_model(z, p_ocp)
    u = z[u_idx]
    du = box_qp(h_red, g_red, lo - u, hi - u)
    dz = expand(stages, dz0, du)
    df0, rho = mdata[0], mdata[1]
    f_cur, infeas = state[nz], state[nz + 1]
    # Directional derivative of the ℓ1 merit along a step that solves the linearised
    # equalities: ∇fᵀΔz − ρ‖g‖₁ (< 0 unless converged).
    slope = ca.fmin(df0 + ca.dot(g_lin, du) - rho * infeas, 0)
    gain = -(ca.dot(g_red, du) + 0.5 * ca.dot(du, ca.mtimes(h_red, du)))   # the QP's
    res = line_search(p, z, dz, f_cur + rho * infeas, slope, rho, gain)
    accepted = res[nz + 2]
    # Converged when the QP predicts less than tol·|f| to gain (f of the start).
    done = ca.logic_or(accepted == 0, gain <= tol * ca.fabs(f_ref))
    new = ca.vertcat(ca.if_else(accepted, res[:nz + 2], ca.vertcat(z, f_cur, infeas)), done,
                     state[ns - 1] + accepted)
    iterate = ca.Function('sqp_iteration', [p, f_ref, tol, state], [new])
    keep = ca.Function('sqp_done', [p, f_ref, tol, state], [state])
    switch = ca.Function.if_else('sqp_switch', keep, iterate)   # (done, ...) -> state
    done_in = ca.MX.sym('done')
    step = ca.Function('sqp_step', [done_in, p, f_ref, tol, state],
                       [switch(done_in, p, f_ref, tol, state)],
                       ['done', 'p', 'f_ref', 'tol', 'state'], ['state_next'])

    # -- starts ------------------------------------------------------------------------
    x0 = ca.MX.sym('x0', ocp.nx)
    a_prev = ca.MX.sym('a_prev')
    u_guess = ca.MX.sym('u_guess', nb)
    u_alt = ca.MX.sym('u_alt', nb, n_alt)

    # Start from the best, by its value in the very NLP solved, of the warm start and
    # the alternatives (columns of u_alt): the OCP is non-convex and a shifted plan can
    # sit in a poor basin.
    best = ca.vertcat(*plan_start(x0, a_prev, ca.fmin(ca.fmax(u_guess, lo), hi), p_ocp))
    for j in range(n_alt):
        alt = ca.vertcat(*plan_start(x0, a_prev, ca.fmin(ca.fmax(u_alt[:, j], lo), hi),
                                     p_ocp))
        best = ca.if_else(alt[nz] < best[nz], alt, best)      # [z; f; ‖g‖₁] together
    starts = ca.Function('sqp_starts', [x0, a_prev, u_guess, u_alt, p],
                         [ca.vertcat(best, 0, 0)],
                         ['x0', 'a_prev', 'u_guess', 'u_alt', 'p'], ['state'])
    return starts, step


@lru_cache(maxsize=32)
def build_rti(ocp, max_iter: int, tol: float = 1e-4, codegen: str = 'off',
              n_alt: int = 1, hessian: str = 'exact') -> ca.Function:
    """Return the real-time SQP as one Function (module doc).

    (x0, a_prev, u_guess, u_alt, p) -> (u, z, f, iterations): inputs scaled as in
    the OCP (v = u/U_SCALE), u_alt holds other starts (columns), p is the OCP's
    parameters followed by the input box (:meth:`~erva_ros.core.controllers.ocp.OCP.with_box`:
    the bounds may change between solves); the best start by its cost in the NLP is
    iterated until the step is below ``tol`` or ``max_iter`` iterations.
    """
    nb, nz = len(ocp.blocks), ocp.nz
    # Loaded without building when a process built this solver before (a node's start-up).
    starts, step = load_or_build(codegen, f'sqp|{ocp.key}|{n_alt}|{hessian}',
                                 lambda: _sqp_parts(ocp, n_alt, hessian), 'the NMPC solver')
    ns = starts.size1_out(0)                    # state = [z; f; ‖g‖₁; done; iterations]
    x0, a_prev, p = ca.MX.sym('x0', ocp.nx), ca.MX.sym('a_prev'), ca.MX.sym('p', ocp.n_pb)
    u_guess, u_alt = ca.MX.sym('u_guess', nb), ca.MX.sym('u_alt', nb, n_alt)
    st = starts(x0, a_prev, u_guess, u_alt, p)
    f_start = st[nz]
    for _ in range(max_iter):
        st = step(st[ns - 2], p, f_start, tol, st)
    z = st[:nz]
    rti = ca.Function('nmpc_rti', [x0, a_prev, u_guess, u_alt, p],
                      [z[[int(i) for i in ocp.u_index]], z, st[nz], st[ns - 1]],
                      ['x0', 'a_prev', 'u_guess', 'u_alt', 'p'],
                      ['u', 'z', 'f', 'iterations'])
    hi, lo = ocp.v_max, ocp.v_min
    rti(np.zeros(ocp.nx), 0.0, np.full(nb, hi), np.full((nb, n_alt), lo),
        ocp.with_box(np.zeros(ocp.n_p)))
    return rti


__all__ = ['EXTRAPOLATION_STEPS', 'LINE_SEARCH_STEPS', 'box_qp_function', 'build_rti',
           'plan_value_function', 'projection_function', 'qp_model_function', 'start_function',
           'step_function']
