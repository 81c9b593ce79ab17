"""Lock-step mode: the live nodes over real DDS reproduce the offline closed loop (`erva sim`)."""

import time

import numpy as np

from erva_ros.closed_loop import simulate_closed_loop
from erva_ros.controllers import make_controller
from erva_ros.live.orchestrator import run_session, RunConfig
from erva_ros.live.scenario import build_preview_model, build_road
from erva_ros.params import load_erva_params


def test_lockstep_run_equals_the_offline_closed_loop(tmp_path):
    # The real NMPC with preview, a noisy preview and a non-default seed: every part of
    # the loop (road, preview error, controller warm start, plant) must line up.
    cfg = RunConfig(controller='preview', alpha1=1.0, alpha2=0.01, mode='lockstep', seed=4,
                    duration_s=1.0, session_dir=str(tmp_path),
                    live_overrides={'preview_noise': True, 'preview_snr_db': 15.0})
    t0 = time.monotonic()
    live = run_session(cfg)
    wall = time.monotonic() - t0
    assert live.exit_code == 0, live.summary['errors']
    s = live.session
    assert s.live['mode'] == 'lockstep' and s.live['preview_noise']

    params = load_erva_params()
    # The lock-step NMPC ignores the wall-clock budget (time is simulated); so does this run.
    ctrl = make_controller('preview', params, s.settings.with_(time_budget_s=10.0))
    off = simulate_closed_loop(params, ctrl, build_road(s.live), s.live['duration_s'],
                               preview_model=build_preview_model(s.live))
    tr = live.trajectory
    assert tr['x'].shape == off.x.shape == (50, 6)
    np.testing.assert_allclose(tr['t'], off.t, atol=1e-12)
    np.testing.assert_allclose(tr['w'], off.w, rtol=0, atol=1e-15)
    np.testing.assert_allclose(tr['x'], off.x, rtol=0, atol=1e-12)
    np.testing.assert_allclose(tr['u'], off.u, rtol=1e-9, atol=1e-6)
    np.testing.assert_allclose(tr['sprung_accel'], off.sprung_accel, rtol=0, atol=1e-9)
    m = live.summary['metrics']
    assert abs(m['acc_2norm'] - off.metrics['acc_2norm']) < 1e-9
    assert abs(m['power_w'] - off.metrics['power_w']) < 1e-7 * max(1.0, off.metrics['power_w'])
    # Nothing was skipped or timed out on the way.
    plant = live.summary['plant']
    assert plant['u_from_command'] == 50 and plant['lockstep_timeouts'] == 0
    assert live.summary['messages']['dropped_total'] == 0
    assert wall < 60
