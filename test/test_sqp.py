"""Real-time SQP (controllers/sqp.py) and the command delay modelled in the OCP."""

import casadi as ca
import numpy as np
import pytest

from erva_ros.core.studies.closed_loop import simulate_closed_loop
from erva_ros.core.controllers import ControllerSettings, make_controller
from erva_ros.core.controllers.linalg import (convexify, fill_reducing_order, JACOBI_SWEEPS,
                                              lu_factor, lu_solve)
from erva_ros.core.controllers.ocp import build_ocp, OCPSpec, stable_rollout_substep, U_SCALE
from erva_ros.core.controllers.sqp import (box_qp_function, plan_value_function,
                                           projection_function, qp_model_function,
                                           start_function, step_function)
from erva_ros.core.model.quarter_car import make_model
from erva_ros.core.model.params import paper_params
from erva_ros.core.model.plant import PlantSimulator
from erva_ros.core.road.profiles import make_road

P = paper_params()
S = ControllerSettings(time_budget_s=10.0)
MODEL = make_model(P)
X0 = np.array([1e-3, 1e-2, 5e-4, -2e-2, 2e-3, 3e-2])


def _ocp(cost='continuous', blocks=(1,) * 10, terminal=0.0, delayed=False):
    return build_ocp(MODEL, OCPSpec(S.ts, blocks, cost, S.u_min, S.u_max, terminal, 3,
                                    stable_rollout_substep(MODEL, S.u_max), delayed=delayed))


def _reference(ocp, z, p):
    """Exact reduced Hessian and gradient by dense linear algebra on the whole NLP."""
    zs, ps = ca.SX.sym('z', ocp.nz), ca.SX.sym('p', ocp.n_p)
    lam = ca.SX.sym('lam', ocp.nlp.size1_out(1))
    f, g = ocp.nlp(zs, ps)
    fn = ca.Function('ref', [zs, ps, lam], [g, ca.gradient(f, zs), ca.jacobian(g, zs),
                                            ca.hessian(f + ca.dot(lam, g), zs)[0]])
    g, grad, jac, _ = (np.asarray(ca.densify(v)) for v in fn(z, p, 0))
    g, grad = g.ravel(), grad.ravel()
    ui = ocp.u_index
    dep = np.array([i for i in range(ocp.nxa, ocp.nz) if i not in set(ui)])
    sens = -np.linalg.solve(jac[:, dep], np.column_stack([g, jac[:, ui]]))
    dz0 = np.zeros(ocp.nz)
    dz0[dep] = sens[:, 0]
    dz_du = np.zeros((ocp.nz, ui.size))
    dz_du[dep] = sens[:, 1:]
    dz_du[ui, np.arange(ui.size)] = 1.0
    lam = -np.linalg.solve(jac[:, dep].T, grad[dep])
    hess = np.asarray(ca.densify(fn(z, p, lam)[3]))
    return dz_du.T @ hess @ dz_du, dz_du.T @ (grad + hess @ dz0), dz0, dz_du


@pytest.mark.parametrize('cost,blocks,terminal,delayed', [
    ('continuous', (1,) * 10, 0.0, False), ('paper', (1,) * 10, 0.0, True),
    ('continuous', (1,) * 6 + (3,) * 2, 0.5, True)])
def test_condensing_is_the_exact_reduced_problem(cost, blocks, terminal, delayed):
    # The interval-by-interval sweeps give what dense linear algebra on the whole NLP
    # gives: the Newton step of the defects, dz/du and the exact reduced Hessian.
    ocp = _ocp(cost, blocks, terminal, delayed)
    exact = qp_model_function(ocp, 'exact', convex=False)
    expand = step_function(ocp)
    w = make_road('paper', 2.0, seed=1).preview(0.5, ocp.horizon, S.ts)
    rng = np.random.default_rng(3)
    for alpha in [(1.0, 0.0), (0.0, 1.0), (1.0, 0.01)]:
        p = ocp.params(w, alpha, 0.008, 12000.0)
        u = rng.uniform(0, 2, len(blocks))
        z = np.asarray(ocp.rollout(X0, 0.1, u, ocp.road_params(p))).ravel()
        h_ref, g_ref, dz0_ref, dz_du_ref = _reference(ocp, z, p)
        h, g, _, dz0, stages, _ = (np.asarray(v) for v in exact(z, p))
        # the step for du = e_j is dz0 plus dz/du's column j
        dz_du = np.column_stack([np.asarray(expand(stages, dz0, e)).ravel() - dz0.ravel()
                                 for e in np.eye(len(blocks))])
        scale = np.max(np.abs(h_ref))
        np.testing.assert_allclose(h, h_ref, atol=1e-10 * scale)
        np.testing.assert_allclose(g.ravel(), g_ref, atol=1e-10 * np.max(np.abs(g_ref)))
        np.testing.assert_allclose(dz0.ravel(), dz0_ref, atol=1e-12)
        np.testing.assert_allclose(dz_du, dz_du_ref, atol=1e-10)


@pytest.mark.parametrize('cost,blocks,delayed', [
    ('continuous', (1,) * 10, False), ('paper', (1,) * 4 + (3,) * 2, True)])
def test_stage_slices_tile_the_decision_vector(cost, blocks, delayed):
    # The one map of z's layout (the condensing, the step expansion and the projection
    # index z through it): after the delay prefix, each interval's x_i, v_i, x_a(k) and
    # K_i in turn, x_{i+1} the next interval's x, the last one ending z.
    ocp = _ocp(cost, blocks, delayed=delayed)
    owner = np.full(ocp.nz, -1)
    owner[:ocp.offset] = len(blocks)                 # the delay's prefix
    for i in range(len(blocks)):
        at = ocp.stage_slices(i)
        parts = [at.x, slice(at.v, at.v + 1), at.k]
        parts += [] if at.acc is None else [slice(at.acc, at.acc + 1)]
        for part in parts:
            assert np.all(owner[part] == -1)
            owner[part] = i
        nxt = ocp.stage_slices(i + 1).x if i + 1 < len(blocks) else slice(ocp.nz - ocp.nxa,
                                                                          ocp.nz)
        assert (at.x_next.start, at.x_next.stop) == (nxt.start, nxt.stop)
    assert (at.acc is not None) == (cost == 'paper')
    assert np.all(owner[:-ocp.nxa] >= 0) and np.all(owner[-ocp.nxa:] == -1)
    np.testing.assert_array_equal(ocp.u_index, [ocp.stage_slices(i).v
                                                for i in range(len(blocks))])


@pytest.mark.parametrize('u', [0.0, 2.0])
def test_sparse_lu_solves_the_collocation_jacobian_as_numpy_does(u):
    # The interval's 18 x 18 collocation Jacobian, factored in the fill-reducing order
    # without numerical pivoting, at both ends of the box (2 = u_max: the stiffest
    # dynamics, h·|λ| ≈ 26): the solutions of A·x = b and Aᵀ·x = b are numpy's
    # (pivoted LAPACK) to rounding, and the factors hold fewer entries than in the
    # natural order.
    ocp = _ocp()
    xt, v, k = ca.SX.sym('xt', ocp.nxa), ca.SX.sym('v'), ca.SX.sym('k', ocp.nk)
    wv, h = ca.SX.sym('wv', ocp.degree + 1), ca.SX.sym('h')
    gk = ca.jacobian(ocp.prefix(xt, v, k, wv, h)[0], k)
    b = ca.SX.sym('b', ocp.nk, 3)
    lu = lu_factor(gk)
    assert sorted(lu.order) == list(range(ocp.nk)) and lu.order != tuple(range(ocp.nk))
    fn = ca.Function('solve', [xt, v, k, wv, h, b],
                     [gk, lu_solve(lu, b), lu_solve(lu, b, transpose=True)])
    rng = np.random.default_rng(5)
    x0 = X0 / ocp.x_scale
    rhs = rng.normal(size=(ocp.nk, 3))
    a, x, xt_ = (np.asarray(ca.densify(o)) for o in fn(
        x0, u, np.tile(x0, ocp.degree) + rng.normal(0, 0.5, ocp.nk),
        rng.normal(0, 1e-2, ocp.degree + 1), S.ts, rhs))
    np.testing.assert_allclose(x, np.linalg.solve(a, rhs), rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(xt_, np.linalg.solve(a.T, rhs), rtol=1e-10, atol=1e-12)

    def fill(order):
        m = np.array(ca.DM(gk.sparsity(), 1))[np.ix_(order, order)] != 0
        for j in range(len(m)):             # symbolic elimination: the factors' pattern
            m[j + 1:, j + 1:] |= np.outer(m[j + 1:, j], m[j, j + 1:])
        return int(m.sum())

    assert fill(list(lu.order)) < 0.8 * fill(list(range(ocp.nk)))
    assert fill_reducing_order(np.eye(3)) == (0, 1, 2)


def test_box_qp_meets_its_kkt_conditions():
    # DAQP on box QPs like the SQP's (inputs at the bounds or inside, Hessian spectra
    # over 7 decades): the projected gradient vanishes.  qrqp, the solver before, left
    # ~9 % of these with projected gradients of order 1 (and 2 of 500 recorded QPs).
    n = 10
    qp = box_qp_function(n)
    rng = np.random.default_rng(0)
    worst = 0.0
    for _ in range(200):
        q, _ = np.linalg.qr(rng.normal(size=(n, n)))
        h = q @ np.diag(10.0 ** rng.uniform(-6, 1, n)) @ q.T
        g = rng.normal(size=n)
        u = rng.choice([0.0, 1.0, 2.0], n)
        lo, hi = -u, 2.0 - u
        d = np.asarray(qp(h, g, lo, hi)).ravel()
        assert np.all(d >= lo) and np.all(d <= hi)
        grad = h @ d + g
        free = (d > lo + 1e-9) & (d < hi - 1e-9)
        at_lo = d <= lo + 1e-9
        wrong = np.where(free, grad, np.where(at_lo, np.minimum(grad, 0), np.maximum(grad, 0)))
        worst = max(worst, np.max(np.abs(wrong)))
    assert worst < 1e-8


def test_the_compiled_box_qp_is_the_virtual_machines(tmp_path, monkeypatch):
    # Generated C calls DAQP: codegen compiles it against the casadi wheel's DAQP
    # (codegen.library_flags); the library gives the virtual machine's solutions.
    import shutil
    from erva_ros.core.model.codegen import compile_functions
    if not (shutil.which('cc') or shutil.which('gcc')):
        pytest.skip('no C compiler')
    monkeypatch.setenv('ERVA_CACHE_DIR', str(tmp_path))
    qp = box_qp_function(6)
    compiled, = compile_functions([qp])
    rng = np.random.default_rng(2)
    for _ in range(20):
        a = rng.normal(size=(6, 6))
        args = (a @ a.T + 1e-3 * np.eye(6), rng.normal(size=6), -rng.uniform(0, 1, 6),
                rng.uniform(0, 1, 6))
        np.testing.assert_allclose(np.asarray(compiled(*args)), np.asarray(qp(*args)),
                                   rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize('n', [10, 7])
def test_convexify_keeps_a_convex_hessian_and_floors_negative_curvature(n):
    # The eigenvectors kept, eigenvalues below 1e-6·max|λ| raised to it (numpy's
    # eigh as the reference); an odd size is padded inside and comes out whole.
    hs = ca.MX.sym('h', n, n)
    fn = ca.Function('cvx', [hs], [convexify(hs)])
    rng = np.random.default_rng(0)
    q, _ = np.linalg.qr(rng.normal(size=(n, n)))
    lam = np.array([5.0, 3.0, 2.0, 1.0, 0.5, 0.2, -0.1, -0.4, -2.0, 1e-3])[-n:]
    out = np.asarray(fn(q @ np.diag(lam) @ q.T))
    floor = 1e-6 * np.max(np.abs(lam))
    np.testing.assert_allclose(out, q @ np.diag(np.maximum(lam, floor)) @ q.T,
                               atol=1e-12 * np.max(np.abs(lam)))
    spd = q @ np.diag(np.abs(lam) + 0.1) @ q.T       # convex already: kept (5 sweeps)
    np.testing.assert_allclose(np.asarray(fn(spd)), spd, atol=1e-6 * np.max(np.abs(spd)))


def test_convexify_at_preview_longs_size_is_convex_and_close_to_the_exact_result():
    # preview_long's 20 x 20 reduced Hessian, JACOBI_SWEEPS parallel sweeps (one
    # compiled round in a loop): positive definite whatever the sweeps (V is a
    # product of rotations) and, on a spread indefinite spectrum like the recorded
    # problems', close to the exact V·max(Λ, floor)·Vᵀ.
    n = 20
    rng = np.random.default_rng(3)
    q, _ = np.linalg.qr(rng.normal(size=(n, n)))
    lam = rng.choice([-1.0, 1.0], n, p=[0.3, 0.7]) * 10.0 ** rng.uniform(-6, 0, n)
    h = q @ np.diag(lam) @ q.T
    exact = q @ np.diag(np.maximum(lam, 1e-6 * np.max(np.abs(lam)))) @ q.T
    hs = ca.MX.sym('h', n, n)
    for sweeps, close in ((JACOBI_SWEEPS, True), (1, False)):      # 3e-6 / 0.06 here
        out = np.asarray(ca.Function('cvx', [hs], [convexify(hs, sweeps)])(h))
        np.testing.assert_array_equal(out, out.T)
        assert np.min(np.linalg.eigvalsh(out)) > 0.0
        err = np.linalg.norm(out - exact) / np.linalg.norm(exact)
        assert (err < 1e-4) == close, (sweeps, err)


@pytest.mark.parametrize('delayed', [False, True])
def test_projection_puts_a_plan_on_the_collocation_equations(delayed):
    ocp = _ocp('paper', delayed=delayed)
    w = make_road('paper', 2.0, seed=2).preview(0.3, 10, S.ts)
    p = ocp.params(w, (1.0, 0.01), 0.006, 3000.0)
    u = np.random.default_rng(1).choice([0.0, 2.0], 10)     # bang-bang: far from linear
    z = np.asarray(ocp.rollout(X0, 0.2, u, ocp.road_params(p))).ravel()
    assert np.max(np.abs(np.asarray(ocp.nlp(z, p)[1]))) > 1e-6      # RK4 is not collocation
    zp = np.asarray(projection_function(ocp)(z, p)).ravel()
    assert np.max(np.abs(np.asarray(ocp.nlp(zp, p)[1]))) < 1e-10
    np.testing.assert_array_equal(zp[ocp.u_index], u)
    np.testing.assert_array_equal(zp[:ocp.nxa], z[:ocp.nxa])


@pytest.mark.parametrize('cost,blocks,delayed', [
    ('continuous', (1,) * 10, False), ('paper', (1,) * 10, True),
    ('continuous', (1,) * 6 + (4,) * 4, False)])
def test_a_start_needs_no_rollout(cost, blocks, delayed):
    # The SQP's starts: from each interval's start state held, its Newton and chord
    # steps reach the collocation equations as closely as from the RK4 rollout (the
    # guess the solver used before), for a bang-bang plan far from the held state's
    # motion, also over preview_long's 80 ms intervals.
    ocp = _ocp(cost, blocks, delayed=delayed)
    w = make_road('paper', 2.0, seed=2).preview(0.3, ocp.horizon, S.ts)
    p = ocp.params(w, (1.0, 0.01), 0.006, 3000.0)
    u = np.random.default_rng(1).choice([0.0, 2.0], len(blocks))
    z, f, infeas = (np.asarray(v).ravel() for v in start_function(ocp)(X0, 0.2, u, p))
    g = np.asarray(ocp.nlp(z, p)[1]).ravel()
    assert np.max(np.abs(g)) < 1e-10
    assert infeas[0] == pytest.approx(np.sum(np.abs(g)), rel=1e-12, abs=1e-15)   # to rounding
    rolled = np.asarray(projection_function(ocp)(
        np.asarray(ocp.rollout(X0, 0.2, u, ocp.road_params(p))).ravel(), p)).ravel()
    np.testing.assert_allclose(z, rolled, rtol=0, atol=1e-10)
    assert f[0] == pytest.approx(float(ocp.nlp(rolled, p)[0]), rel=1e-10)
    np.testing.assert_array_equal(z[ocp.u_index], u)


def test_the_delayed_ocp_predicts_the_delayed_plant():
    # Over [t_k, t_k + d] the acting command, then the plan on a grid shifted by d:
    # the OCP's nodes are the plant's states at t_k + d + j·Ts (step_delayed), with
    # the collocation model's accuracy (test_ctrl_nmpc) and not the 8 ms error of
    # planning as if the command acted at t_k.
    ocp = _ocp('continuous', delayed=True)
    d, u_acting = 0.008, 14000.0
    road = make_road('paper', 2.0, seed=2)
    t0 = 0.6
    plant = PlantSimulator(MODEL, S.ts)
    for k in range(int(t0 / S.ts)):
        plant.step(P.c_e0, road.height(k * S.ts), road.height((k + 1) * S.ts))
    x0 = plant.x.copy()
    u = np.random.default_rng(4).uniform(S.u_min, S.u_max, 10)
    w = road.preview(t0, 10, S.ts)
    p = ocp.params(w, (1.0, 0.0), d, u_acting)
    z = np.asarray(plan_value_function(ocp)(x0, 0.0, u / U_SCALE, p)[0]).ravel()
    nodes = ocp.nodes(z)
    truth, acting = [], u_acting
    probe = PlantSimulator(MODEL, S.ts, x0=x0)
    for k in range(10):
        w0, w1 = w[k], w[k + 1]
        half = PlantSimulator(MODEL, d, x0=probe.x)      # the state at t_k + d
        truth.append(half.step(acting, w0, w0 + (w1 - w0) * d / S.ts).copy())
        probe.step_delayed(acting, u[k], d, w0, w1)
        acting = u[k]
    truth = np.array(truth)
    scale = np.max(np.abs(truth), axis=0)
    err = np.max(np.abs(nodes[:10] - truth) / scale)
    assert err < 0.03
    # planning as if the command acted at t_k is an order of magnitude further off
    undelayed = _ocp('continuous')
    z0 = np.asarray(plan_value_function(undelayed)(
        x0, 0.0, u / U_SCALE, undelayed.params(w, (1.0, 0.0)))[0]).ravel()
    assert np.max(np.abs(undelayed.nodes(z0)[:10] - truth) / scale) > 5 * err


def test_the_delay_is_set_per_solve_without_rebuilding():
    c = make_controller('preview', MODEL, S.with_(cost='continuous', command_delay_s=0.008))
    solver = c._solver
    assert c.ocp.delayed and c.delay is None        # modelled, not predicted outside
    road = make_road('paper', 0.4, seed=0)
    first = simulate_closed_loop(MODEL, c, road, 0.4, actuation_delay_s=0.008)
    c.command_delay_s = 0.004
    second = simulate_closed_loop(MODEL, c, road, 0.4, actuation_delay_s=0.004)
    assert c._solver is solver and not np.allclose(first.u, second.u)
    assert set(first.status) == set(second.status) == {'ok'}
    with pytest.raises(ValueError, match='command delay'):
        c.command_delay_s = S.ts


def test_real_time_sqp_reaches_ipopt_on_a_hard_sample():
    # Converged (tolerance, not the iteration cap), the real-time SQP's plan is worth
    # what IPOPT finds from the same starts, within 0.5 %, on the continuous cost.
    road = make_road('paper', 1.0, seed=0)
    s = S.with_(cost='continuous', max_iter=30, sqp_tol=1e-7)
    c = make_controller('preview', MODEL, s)
    c.recorded_problems = []
    run = simulate_closed_loop(MODEL, c, road, 0.3)
    assert np.max(run.iterations) < 30
    gaps = [c.reference_gap(pr) for pr in c.recorded_problems[::3]]
    assert max(gaps) < 5e-3


def test_passive_tail_is_the_cost_beyond_the_horizon_under_c_e0():
    # Lyapunov quadratic forms = the integrals of a free response of the plant with the
    # passive damping (the model is nearly linear for millimetre deviations).
    from erva_ros.core.controllers.ocp import passive_tail
    q_acc, q_pow = (np.array(m) for m in passive_tail(MODEL, P.c_e0))
    x0 = np.array([2e-3, -1e-2, 5e-4, 3e-2, 1e-3, -2e-2])
    plant = PlantSimulator(MODEL, 0.02, x0=x0)
    # 30 s: the absorber mode (σ ≈ −0.28 1/s, energy ∝ e^{2σt}) has died out; 5 s leaves 6 %
    for _ in range(1500):
        plant.step(P.c_e0, 0.0, 0.0)
    assert plant.accel_sq_int == pytest.approx(x0 @ q_acc @ x0, rel=0.01)
    assert plant.harvested_j == pytest.approx(x0 @ q_pow @ x0, rel=0.01)
    # only the continuous cost gets it, and only when asked
    for cost, terminal, has_tail in [('continuous', 'passive', True),
                                     ('continuous', 'none', False), ('paper', 'passive', False)]:
        c = make_controller('preview', MODEL, S.with_(cost=cost, terminal_cost=terminal))
        value = float(c.ocp.terminal(np.r_[x0 / c.ocp.x_scale, [0.0] * c.ocp.with_acc], 0.0,
                                     [1.0, 0.0]))
        assert (value == pytest.approx(x0 @ q_acc @ x0 / S.ts)) if has_tail else value == 0.0


def test_longer_steps_after_a_full_step_save_iterations(monkeypatch):
    # The same recorded problems (a 0.6 s loop at (0, 1)) solved with and without the
    # line search's longer steps (EXTRAPOLATION_STEPS): with them, fewer iterations in
    # all and a final cost as low on average (relative, 1e-4).
    from erva_ros.core.controllers import sqp
    s = S.with_(cost='continuous', alpha1=0.0, alpha2=1.0, codegen='off')
    c = make_controller('preview', MODEL, s)
    c.recorded_problems = []
    simulate_closed_loop(MODEL, c, make_road('paper', 0.6, seed=1), 0.6)
    results = {}
    for name, steps in (('longer', sqp.EXTRAPOLATION_STEPS), ('without', ())):
        monkeypatch.setattr(sqp, 'EXTRAPOLATION_STEPS', steps)
        rti = sqp.build_rti(c.ocp, 9, s.sqp_tol, 'off', 3, 'exact')    # not cached: cap 9
        sqp.build_rti.cache_clear()
        out = [rti(pr.x, pr.a_prev, pr.u_guess, pr.u_alt, pr.p) for pr in c.recorded_problems]
        results[name] = (sum(int(o[3]) for o in out), np.array([float(o[2]) for o in out]))
    (it_longer, f_longer), (it_without, f_without) = results['longer'], results['without']
    assert it_longer < it_without
    assert np.mean((f_longer - f_without) / np.abs(f_without)) < 1e-4
