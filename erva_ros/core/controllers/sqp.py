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
2. *Convexification*: the N x N reduced Hessian's eigenvalues are mirrored, |λ|, and
   floored (Jacobi, compiled), so the QP is convex and its step a descent direction
   where F is concave.
3. *Box QP* (DAQP, N variables, diagonally scaled: :func:`box_qp_function`) for du;
   the full step Δz = ζ + (dz/du)·du.
4. *Globalisation*: the candidate z + t·Δz is put back on the collocation equations
   (per interval, from that linear prediction, a Newton step and two chord steps with
   its factorisation: a simulation with the NLP's own integrator), and accepted by
   Armijo's rule on the ℓ1 merit f + ρ·‖g‖₁ of the very NLP that IPOPT solves, over
   t = 1, ½, ¼, ⅛; a step is evaluated only if the longer one failed (short-circuit
   conditionals).  Candidates judged by an RK4 rollout instead (the solver this one
   replaces) are a different model: for bang-bang plans its quadrature of the cost was
   off by up to 50 %, and its gradient disagreed with the NLP's, so steps were
   rejected or misjudged.
5. *Stop* when an iteration is predicted to gain less than ``tol``·|f(start)| or no
   step decreases the merit, else after ``max_iter`` iterations.  Counts, never the
   wall clock, end a solve: offline results do not depend on the machine's load.

Starts: the warm start and the alternatives, each put on the collocation equations
(from each interval's start state held: :func:`start_function`); the best by its cost in
the NLP is iterated.  f and ‖g‖₁ of the current point travel with it, from where it was
evaluated (a start or the line search), so an iteration never evaluates the NLP twice.

The whole solver is one CasADi Function with conditionals (no Python per iteration).
With ``codegen`` its two pieces are compiled to C as wholes, the starts and one
iteration (QP model, box QP, line search, stop test): the solver calls the iteration
``max_iter`` times, and it returns its input unchanged once done.  Compiled whole, no
matrix operation runs in CasADi's virtual machine, and the pieces do not depend on
``max_iter`` or ``tol`` (docs/nmpc.md measures both changes).
"""

from functools import lru_cache

import casadi as ca
import numpy as np

from erva_ros.core.codegen import compile_for
from erva_ros.core.controllers.linalg import convexify, lu_factor, lu_solve, symmetric
from erva_ros.core.controllers.settings import HESSIANS

#: Backtracking steps of the line search (a step is tried only if the longer one failed).
LINE_SEARCH_STEPS = (1.0, 0.5, 0.25, 0.125)
#: After an accepted full step, these longer ones in turn while each lowers the merit
#: further: the SQP's model is cautious where the cost keeps falling towards the box.
EXTRAPOLATION_STEPS = ()
#: Armijo constant: accept a step that gains this share of the predicted merit decrease.
ARMIJO = 1e-4
#: (Newton, chord) steps per interval that put a plan on the collocation equations: a
#: chord step reuses the Newton step's factorisation (~1/4 of a Newton step's arithmetic).
#: From the SQP's linear prediction, measured on seed 0's problems: defects ≤ 1e-8, the
#: cost within 2e-9 of more Newton steps' (one Newton step alone: defects up to 1e-2).
SOLVE_STEPS = (1, 2)
#: ℓ1 merit: ρ = RHO_FACTOR·max|multiplier| + RHO_MIN.
RHO_FACTOR, RHO_MIN = 2.0, 1e-6


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
    the N inputs; dz/du is never formed.
    """
    if hessian not in HESSIANS:
        raise ValueError(f'hessian {hessian!r} unknown; choose one of {", ".join(HESSIANS)}')
    nxa, nk, nb, nz = ocp.nxa, ocp.nk, len(ocp.blocks), ocp.nz
    xt, v, k = ca.SX.sym('xt', nxa), ca.SX.sym('v'), ca.SX.sym('k', nk)
    wv, h, al = ca.SX.sym('wv', ocp.degree + 1), ca.SX.sym('h'), ca.SX.sym('alpha', 2)
    mu, nu = ca.SX.sym('mu', nk), ca.SX.sym('nu', nxa)
    y = ca.vertcat(xt, v, k)
    g, phi, cost, res, weight, econ = ocp.interval(xt, v, k, wv, h, al)
    inline = {'never_inline': True}    # one compiled copy, called per interval
    if hessian == 'exact':
        curv = ca.hessian(cost + ca.dot(mu, g) - ca.dot(nu, phi), y)[0]
        gn = []                   # no residual Jacobian: a called Function computes all
    else:
        curv = ca.hessian(econ, y)[0]
        gn = [ca.jacobian(res, y), weight]
    jac = ca.Function('interval_jac', [xt, v, k, wv, h, al],
                      [g, phi, ca.jacobian(g, y), ca.jacobian(phi, y), ca.gradient(cost, y)]
                      + gn, inline)
    hess = ca.Function('interval_hess', [xt, v, k, wv, h, al, mu, nu], [curv], inline)
    g_pre, phi_pre = ocp.prefix(xt, v, k, wv, h)
    jac_pre = ca.Function('prefix_jac', [xt, v, k, wv, h],
                          [g_pre, phi_pre, ca.jacobian(g_pre, k), ca.jacobian(phi_pre, k)],
                          inline)
    xb, wb = ca.SX.sym('x_end', nxa), ca.SX.sym('w_end')
    term = ocp.terminal(xb, wb, al)
    h_term, g_term = ca.hessian(term, xb)
    terminal = ca.Function('terminal_derivs', [xb, wb, al], [term, g_term, h_term])

    z = ca.SX.sym('z', nz)
    p = ca.SX.sym('p', ocp.n_p)
    alpha = p[ocp.horizon + 1:ocp.horizon + 3]
    road, w_end, road_pre, h_pre, v_pre = ocp.road(p)
    dz0 = ca.SX.zeros(nz)
    sens = ca.SX.zeros(nxa, nb)          # d x_i / du on the linearised equalities
    corr = ca.SX.zeros(nxa)              # Newton correction of x_i (closes the defects)
    lam_max = 0
    if ocp.delayed:
        # The prefix depends on nothing decided: only its defects are corrected.
        gp, php, gk, phk = jac_pre(z[:nxa], v_pre, z[nxa:nxa + nk], road_pre, h_pre)
        dk = -lu_solve(lu_factor(gk), gp)
        dz0[nxa:nxa + nk] = dk
        x_next = z[nxa + nk:ocp.offset + nxa]
        corr = ca.mtimes(phk, dk) + php - x_next
    sweep, stages = [], []
    for i, m in enumerate(ocp.blocks):
        at = ocp.stage_slices(i)
        xi, vi, ki = z[at.x], z[at.v], z[at.k]
        args = (xi, vi, ki, road[:, i], m * ocp.ts, alpha)
        gi, phii, jg, jphi, grad, *gn_terms = jac(*args)
        gx, gv, gk = jg[:, :nxa], jg[:, nxa], jg[:, nxa + 1:]
        lu = lu_factor(gk)          # collocation states: one sparse LU per interval
        kk = -lu_solve(lu, ca.horzcat(gx, gv, gi + ca.mtimes(gx, corr)))
        t_i = ca.vertcat(ca.DM.eye(nxa + 1), kk[:, :nxa + 1])     # y_i = T_i·(x_i, v_i)
        a_i = ca.mtimes(jphi, t_i)                                 # x_{i+1} = A_i·(x_i, v_i)
        unit = ca.DM.zeros(1, nb)
        unit[i] = 1.0
        s_i = ca.vertcat(sens, unit)                               # d(x_i, v_i)/du
        zeta = ca.vertcat(corr, 0, kk[:, nxa + 1])
        x_next = z[at.x_next]
        sens = ca.mtimes(a_i, s_i)
        corr = ca.mtimes(jphi, zeta) + phii - x_next
        stages.append(ca.vertcat(kk[:, :nxa + 1], a_i))
        dz0[at.x] = zeta[:nxa]
        dz0[at.k] = zeta[nxa + 1:]
        if ocp.with_acc:
            # the NLP's x_a(k) variable moves to the stage's new node acceleration
            dz0[at.acc] = corr[nxa - 1] + x_next[nxa - 1] - z[at.acc]
        sweep.append((args, s_i, t_i, zeta, grad, gx, jphi, lu, gn_terms))
    o_end = nz - nxa
    dz0[o_end:] = corr
    _, t_grad, t_hess = terminal(z[o_end:], w_end, alpha)
    hr = ca.mtimes([sens.T, t_hess, sens])
    gr = ca.mtimes(sens.T, t_grad + ca.mtimes(t_hess, corr))
    g_lin = ca.mtimes(sens.T, t_grad)
    df0 = ca.dot(t_grad, corr)
    nu_next = -t_grad                    # multiplier of x_{i+1} = phi_i
    for args, s_i, t_i, zeta, grad, gx, jphi, lu, gn_terms in reversed(sweep):
        jphi_x, jphi_k = jphi[:, :nxa], jphi[:, nxa + 1:]
        rhs = grad[nxa + 1:] - ca.mtimes(jphi_k.T, nu_next)
        mu_i = -lu_solve(lu, rhs, transpose=True)          # collocation multipliers
        h_i = hess(*args, mu_i, nu_next)
        h_red = ca.mtimes([t_i.T, h_i, t_i])                # the interval on (x_i, v_i)
        g_red = ca.mtimes(t_i.T, grad + ca.mtimes(h_i, zeta))
        if hessian == 'gauss_newton':
            jres, wres = gn_terms
            jt = ca.mtimes(jres, t_i)
            h_red += 2 * ca.mtimes([jt.T, ca.diag(wres), jt])
            g_red += 2 * ca.mtimes(jt.T, wres * ca.mtimes(jres, zeta))
        h_red = symmetric(h_red)
        hr += ca.mtimes([s_i.T, h_red, s_i])
        gr += ca.mtimes(s_i.T, g_red)
        g_lin += ca.mtimes(s_i.T, ca.mtimes(t_i.T, grad))
        df0 += ca.dot(grad, zeta)
        lam_max = ca.fmax(lam_max, ca.fmax(ca.mmax(ca.fabs(mu_i)), ca.mmax(ca.fabs(nu_next))))
        nu_next = -(grad[:nxa] + ca.mtimes(gx.T, mu_i) - ca.mtimes(jphi_x.T, nu_next))
    rho = RHO_FACTOR * lam_max + RHO_MIN
    merit = ca.vertcat(df0, rho)
    hr = symmetric(hr)
    return ca.Function('qp_model', [z, p],
                       [convexify(hr) if convex else hr, gr, g_lin, dz0, ca.horzcat(*stages),
                        merit],
                       ['z', 'p'], ['h', 'g', 'g_lin', 'dz0', 'stages', 'merit'])


def step_function(ocp) -> ca.Function:
    """Return (stages, dz0, du) -> Δz = dz0 + (dz/du)·du, from :func:`qp_model_function`.

    A forward sweep through the intervals' K_i and A_i: O(N), where the product with a
    dense dz/du would be O(N²).
    """
    nxa, nk, nb, nz = ocp.nxa, ocp.nk, len(ocp.blocks), ocp.nz
    stages = ca.SX.sym('stages', nk + nxa, (nxa + 1) * nb)
    dz0, du = ca.SX.sym('dz0', nz), ca.SX.sym('du', nb)
    dz = ca.SX.zeros(nz)
    dx = ca.SX.zeros(nxa)               # x_0 (and the delay's prefix) is not decided
    for i in range(nb):
        at = ocp.stage_slices(i)
        m_i = stages[:, i * (nxa + 1):(i + 1) * (nxa + 1)]
        d = ca.mtimes(m_i, ca.vertcat(dx, du[i]))
        dz[at.x] = dx
        dz[at.v] = du[i]
        dz[at.k] = d[:nk]
        dx = d[nk:]
        if ocp.with_acc:
            dz[at.acc] = dx[nxa - 1]
    dz[nz - nxa:] = dx
    return ca.Function('expand_step', [stages, dz0, du], [dz0 + dz],
                       ['stages', 'dz0', 'du'], ['dz'])


def _project(ocp, p, x, inputs, guess, steps=SOLVE_STEPS):
    """Return the decision vector of ``inputs`` on the collocation equations, from x(t_k).

    Interval by interval: from ``guess(i, x_i)`` (i = -1: the delay's prefix), the
    ``steps`` = (Newton, chord) steps on the interval's collocation equations, then its
    end state starts the next interval.  A simulation with the NLP's own integrator,
    so a candidate's cost is the NLP's.  ``x`` is the scaled start state (with
    x_a(k-1) for the paper cost), ``inputs`` the scaled inputs of the intervals.
    """
    nxa, nk = ocp.nxa, ocp.nk
    newton, chords = steps
    xt, v, k = ca.SX.sym('xt', nxa), ca.SX.sym('v'), ca.SX.sym('k', nk)
    wv, h, al = ca.SX.sym('wv', ocp.degree + 1), ca.SX.sym('h'), ca.SX.sym('alpha', 2)
    g, phi = ocp.prefix(xt, v, k, wv, h)      # the same defects as every interval
    defects = ca.Function('defects', [xt, v, k, wv, h], [g])
    jac, k_on = ca.jacobian(g, k), k
    for n in range(newton):
        lu = lu_factor(jac if n == 0 else ca.substitute(jac, k, k_on))
        k_on = k_on - lu_solve(lu, defects(xt, v, k_on, wv, h))
    for _ in range(chords):                   # the last Newton step's Jacobian kept
        k_on = k_on - lu_solve(lu, defects(xt, v, k_on, wv, h))
    solve = ca.Function('collocation_solve', [xt, v, k, wv, h], [k_on], {'never_inline': True})
    end = ca.Function('interval_end', [xt, v, k, wv, h], [ocp.interval(xt, v, k, wv, h, al)[1]])
    end_pre = ca.Function('prefix_end', [xt, v, k, wv, h], [phi])
    road, _, road_pre, h_pre, v_pre = ocp.road(p)
    out = [x]
    if ocp.delayed:
        kp = solve(x, v_pre, guess(-1, x), road_pre, h_pre)
        x = end_pre(x, v_pre, kp, road_pre, h_pre)
        out += [kp, x]
    for i, m in enumerate(ocp.blocks):
        ki = solve(x, inputs[i], guess(i, x), road[:, i], m * ocp.ts)
        x_next = end(x, inputs[i], ki, road[:, i], m * ocp.ts)
        out += [inputs[i]] + ([x_next[nxa - 1]] if ocp.with_acc else []) + [ki, x_next]
        x = x_next
    return ca.vertcat(*out)


def projection_function(ocp, steps=SOLVE_STEPS) -> ca.Function:
    """Return (z, p) -> z on the collocation equations, for z's inputs (compiled SX).

    The steps start from z's collocation states (a good guess: the SQP's linear
    prediction); see :func:`_project`.
    """
    nxa, nk, nz = ocp.nxa, ocp.nk, ocp.nz
    z = ca.SX.sym('z', nz)
    p = ca.SX.sym('p', ocp.n_p)
    at = [ocp.stage_slices(i) for i in range(len(ocp.blocks))]

    def guess(i, _x):
        return z[nxa:nxa + nk] if i < 0 else z[at[i].k]

    z_on = _project(ocp, p, z[:nxa], [z[a.v] for a in at], guess, steps)
    return ca.Function('projection', [z, p], [z_on], ['z', 'p'], ['z_on'])


def start_function(ocp, steps=SOLVE_STEPS) -> ca.Function:
    """Return (x0, a_prev, u, p) -> (z, f, ‖g‖₁): the plan u (scaled) on the collocation equations.

    Each interval's solve starts from its start state held (no rollout needed: the
    collocation equations are linear but for the generator kinematics, so the
    ``steps`` reach them to rounding, ~1e-14, measured on the paper road).  f is the
    plan's cost in the NLP, what starts are compared by; ‖g‖₁ its defects.
    """
    x0, a_prev = ca.SX.sym('x0', ocp.nx), ca.SX.sym('a_prev')
    u, p = ca.SX.sym('u', len(ocp.blocks)), ca.SX.sym('p', ocp.n_p)
    x = x0 / ca.DM(ocp.x_scale)
    x = ca.vertcat(x, a_prev) if ocp.with_acc else x

    def guess(_i, xi):
        return ca.repmat(xi[:ocp.nx], ocp.degree, 1)

    z = _project(ocp, p, x, [u[i] for i in range(len(ocp.blocks))], guess, steps)
    f, g = ocp.nlp(z, p)
    return ca.Function('plan_start', [x0, a_prev, u, p], [z, f, ca.norm_1(g)],
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
    best start (module doc).  ``step`` (done, p, f_ref, tol, state) -> state: one
    iteration (QP model, box QP, line search, stop test), or the state unchanged once
    ``done``.  Each is generated as one C function; the solver only calls ``step``
    ``max_iter`` times, so no model, QP or line-search operation runs in CasADi's
    virtual machine, and the compiled pieces do not depend on ``max_iter`` or ``tol``.
    """
    nb, nz = len(ocp.blocks), ocp.nz
    qp_model, expand, project, plan_start, nlp = (
        qp_model_function(ocp, hessian), step_function(ocp), projection_function(ocp),
        start_function(ocp), ocp.nlp)
    box_qp = box_qp_function(nb)
    lo, hi = ocp.v_min, ocp.v_max
    u_idx = [int(i) for i in ocp.u_index]
    p = ca.MX.sym('p', ocp.n_p)

    def candidate(zz, dz, t, rho):
        """Return z + t·Δz (inputs clipped into the box) on the equations: [z; f; ‖g‖₁], merit."""
        zc = zz + t * dz
        zc[u_idx] = ca.fmin(ca.fmax(zc[u_idx], lo), hi)
        zc = project(zc, p)        # from the linear prediction back onto the equalities
        f, g = nlp(zc, p)
        infeas = ca.norm_1(g)
        return ca.vertcat(zc, f, infeas), f + rho * infeas

    # -- line search: step t is evaluated only if every longer step failed -----------
    z, dz, phi0, slope, rho = (ca.MX.sym('z', nz), ca.MX.sym('dz', nz), ca.MX.sym('phi0'),
                               ca.MX.sym('slope'), ca.MX.sym('rho'))
    ls_in = [p, z, dz, phi0, slope, rho]
    # After an accepted full step, longer ones while each lowers the merit further.
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
        accept = (extend(p, z, dz, rho, cand, phic) if t == 1.0
                  else ca.vertcat(cand, 1))
        out = ca.if_else(ok, accept, tail(*ls_in), True)
        tail = ca.Function(f'line_search_{n}', ls_in, [out])
    line_search = tail

    # -- one iteration: state = [z; f; ‖g‖₁; done; iterations] ---------------------------
    # (f and ‖g‖₁ of z carried from where z was evaluated: the start or the line search)
    ns = nz + 4
    state = ca.MX.sym('state', ns)
    f_ref, tol = ca.MX.sym('f_ref'), ca.MX.sym('tol')
    z = state[:nz]
    h_red, g_red, g_lin, dz0, stages, mdata = qp_model(z, p)
    u = z[u_idx]
    du = box_qp(h_red, g_red, lo - u, hi - u)
    dz = expand(stages, dz0, du)
    df0, rho = mdata[0], mdata[1]
    f_cur, infeas = state[nz], state[nz + 1]
    # Directional derivative of the ℓ1 merit along a step that solves the linearised
    # equalities: ∇fᵀΔz − ρ‖g‖₁ (< 0 unless converged).
    slope = ca.fmin(df0 + ca.dot(g_lin, du) - rho * infeas, 0)
    res = line_search(p, z, dz, f_cur + rho * infeas, slope, rho)
    accepted = res[nz + 2]
    # Converged when the QP predicts less than tol·|f| to gain (f of the start).
    gain = -(ca.dot(g_red, du) + 0.5 * ca.dot(du, ca.mtimes(h_red, du)))
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
    best = ca.vertcat(*plan_start(x0, a_prev, ca.fmin(ca.fmax(u_guess, lo), hi), p))
    for j in range(n_alt):
        alt = ca.vertcat(*plan_start(x0, a_prev, ca.fmin(ca.fmax(u_alt[:, j], lo), hi), p))
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
    the OCP (v = u/U_SCALE), u_alt holds other starts (columns); the best start by
    its cost in the NLP is iterated until the step is below ``tol`` or
    ``max_iter`` iterations.
    """
    nb, nz = len(ocp.blocks), ocp.nz
    starts, step = compile_for(codegen, _sqp_parts(ocp, n_alt, hessian), 'the NMPC solver')
    ns = starts.size1_out(0)                    # state = [z; f; ‖g‖₁; done; iterations]
    x0, a_prev, p = ca.MX.sym('x0', ocp.nx), ca.MX.sym('a_prev'), ca.MX.sym('p', ocp.n_p)
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
    rti(np.zeros(ocp.nx), 0.0, np.full(nb, hi), np.full((nb, n_alt), lo), np.zeros(ocp.n_p))
    return rti


__all__ = ['EXTRAPOLATION_STEPS', 'LINE_SEARCH_STEPS', 'box_qp_function', 'build_rti',
           'plan_value_function', 'projection_function', 'qp_model_function', 'start_function',
           'step_function']
