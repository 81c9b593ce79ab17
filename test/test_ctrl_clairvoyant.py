"""The clairvoyant bound: never beaten by a causal controller on the same road."""

import numpy as np
import pytest

from erva_ros.closed_loop import evaluation_objective, simulate_closed_loop
from erva_ros.controllers import ControllerSettings, make_controller
from erva_ros.controllers.clairvoyant import clairvoyant_bound, ReplayController
from erva_ros.params import paper_params
from erva_ros.roads import make_road

P = paper_params()
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
    runs = {name: simulate_closed_loop(P, make_controller(name, P, s), road, DURATION)
            for name in ('passive', 'skyhook', 'no_preview', 'preview', 'preview_long')}
    bound = clairvoyant_bound(P, road, DURATION, S.ts, alpha, S.u_min, S.u_max,
                              {k: r.u for k, r in runs.items() if k != 'passive'})
    for name, run in runs.items():
        assert bound.objective < evaluation_objective(run.metrics, alpha), name
    assert bound.objective == min(bound.starts.values())
    assert set(bound.starts) >= {'u_min', 'c_e0', 'u_max', 'preview'}
    assert np.all((bound.run.u >= S.u_min) & (bound.run.u <= S.u_max))


def test_replay_controller_reproduces_a_run():
    road = make_road('paper', 1.0, seed=1)
    run = simulate_closed_loop(P, make_controller('skyhook', P, S), road, 1.0)
    replay = ReplayController(run.u, S.ts, S.u_min, S.u_max, P.c_e0)
    again = simulate_closed_loop(P, replay, road, 1.0)
    np.testing.assert_array_equal(again.u, run.u)
    np.testing.assert_allclose(again.sprung_accel, run.sprung_accel, rtol=1e-12)
    assert again.harvested_j == pytest.approx(run.harvested_j, rel=1e-12)
