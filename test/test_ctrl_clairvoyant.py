"""The clairvoyant bound: never beaten by a causal controller on the same road."""

import numpy as np
import pytest

from erva_ros.core.studies.closed_loop import evaluation_objective, simulate_closed_loop
from erva_ros.core.controllers import ControllerSettings, make_controller
from erva_ros.core.controllers.clairvoyant import (clairvoyant_bound, plant_run, polish,
                                                   ReplayController)
from erva_ros.core.model.quarter_car import make_model
from erva_ros.core.model.params import paper_params
from erva_ros.core.road.profiles import make_road

P = paper_params()
M = make_model(P)
# Quality tests: no real-time budget, so a loaded CI machine cannot change results.
S = ControllerSettings(time_budget_s=10.0)
DURATION = 1.0   # 50 samples: every start of the bound and each causal run


@pytest.mark.parametrize('alpha', [(0.0, 1.0), (1.0, 0.0)])
def test_bound_is_never_beaten_by_a_causal_controller(alpha):
    # The causal runs are also starts of the bound, but a start is only ever counted
    # through IPOPT's local optimum evaluated in the plant: a controller that sees
    # more than the road (or a plant that differs) would show up here.
    road = make_road('paper', DURATION, seed=5)
    s = S.with_(alpha1=alpha[0], alpha2=alpha[1])
    runs = {name: simulate_closed_loop(M, make_controller(name, M, s), road, DURATION)
            for name in ('passive', 'skyhook', 'no_preview', 'preview', 'preview_long')}
    bound = clairvoyant_bound(M, road, DURATION, S.ts, alpha, S.u_min, S.u_max,
                              {k: r.u for k, r in runs.items() if k != 'passive'})
    for name, run in runs.items():
        assert bound.objective < evaluation_objective(run.metrics, alpha), name
    # The search and the polish only ever replace the best plan by a better one.
    assert bound.objective <= min(bound.starts.values())
    assert set(bound.starts) >= {'u_min', 'c_e0', 'u_max', 'preview'}
    assert np.all((bound.run.u >= S.u_min) & (bound.run.u <= S.u_max))
    # The polish optimises the plant's own discretisation: its prediction is the plant's.
    assert bound.agreement < 1e-9
    again = plant_run(M, bound.run.u, road.height(S.ts * np.arange(bound.run.u.size + 1)),
                      S.ts)
    assert evaluation_objective(again.metrics, alpha) == pytest.approx(bound.objective,
                                                                       rel=1e-12)


def test_replay_controller_reproduces_a_run():
    road = make_road('paper', 1.0, seed=1)
    run = simulate_closed_loop(M, make_controller('skyhook', M, S), road, 1.0)
    replay = ReplayController(run.u, S.ts, S.u_min, S.u_max, P.c_e0)
    again = simulate_closed_loop(M, replay, road, 1.0)
    np.testing.assert_array_equal(again.u, run.u)
    np.testing.assert_allclose(again.sprung_accel, run.sprung_accel, rtol=1e-12)
    assert again.harvested_j == pytest.approx(run.harvested_j, rel=1e-12)


def test_replay_on_the_closed_loop_equals_the_open_loop_plant_run():
    road = make_road('paper', 1.0, seed=3)
    u = np.where(np.arange(50) % 3 == 0, S.u_max, S.u_min)
    closed = simulate_closed_loop(M, ReplayController(u, S.ts, S.u_min, S.u_max, P.c_e0),
                                  road, 1.0)
    opened = plant_run(M, u, road.height(S.ts * np.arange(51)), S.ts)
    np.testing.assert_allclose(opened.sprung_accel, closed.sprung_accel, rtol=1e-12)
    for key in ('acc_2norm', 'acc_rms', 'power_w', 'acc_rms_continuous'):
        assert opened.metrics[key] == pytest.approx(closed.metrics[key], rel=1e-12), key


def test_polish_descends_to_the_box_minimum_and_never_increases():
    # A separable quadratic with its minimum outside the box in some coordinates:
    # the projected L-BFGS must end on the box-constrained minimiser.
    target = np.array([-1.0, 0.3, 2.5, 0.9, 1.7])

    def fg(u):
        return float(np.sum((u - target) ** 2)), 2 * (u - target)

    u, f, it = polish(fg, np.full(5, 1.0), 0.0, 2.0, max_iter=50)
    np.testing.assert_allclose(u, np.clip(target, 0.0, 2.0), atol=1e-8)
    assert f <= fg(np.full(5, 1.0))[0] and 1 <= it <= 50


def test_lbfgs_direction_skips_pairs_without_curvature_on_the_free_variables():
    # y·s > 0 over all variables (through a held one) but 0 on the free ones: once this
    # overflowed rho to 1e300 and the step to NaN, which stopped the bound's polish.
    import warnings
    from erva_ros.core.controllers.clairvoyant import lbfgs_direction
    free = np.array([True, True, False])
    pg = np.array([1.0, 2.0, 0.0])
    s_ = np.array([1.0, 1.0, 1.0])
    y_ = np.array([1.0, -1.0, 5.0])          # y·s = 5 > 0; on the free ones 0
    with warnings.catch_warnings():
        warnings.simplefilter('error')
        d, gamma = lbfgs_direction(pg, free, [(s_, y_)], 0.1)
    assert np.all(np.isfinite(d)) and gamma > 0 and d @ pg < 0 and d[2] == 0.0


def test_polish_stays_finite_when_variables_reach_the_box():
    # Curvature pairs positive over all variables need not be on the free ones: the
    # two-loop recursion must skip those (once it overflowed to a NaN step and stopped).
    import warnings
    from erva_ros.core.controllers.clairvoyant import polish
    rng = np.random.default_rng(0)
    m = rng.normal(size=(40, 40))
    a = m @ m.T + 0.1 * np.eye(40)
    b = 50.0 * rng.normal(size=40)

    def fg(u):
        return 0.5 * u @ a @ u - b @ u, a @ u - b

    with warnings.catch_warnings():
        warnings.simplefilter('error')          # an overflow or NaN fails the test
        u, f, _ = polish(fg, np.zeros(40), -1.0, 1.0, max_iter=300)
    assert np.all(np.isfinite(u)) and f < fg(np.zeros(40))[0]
    # First-order optimality on the box: no free variable has a gradient left.
    g = a @ u - b
    free = ~(((u <= -1.0) & (g > 0)) | ((u >= 1.0) & (g < 0)))
    assert np.max(np.abs(g[free])) < 1e-3 * np.max(np.abs(b))
