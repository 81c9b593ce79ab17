"""Actuation delay (plant), its compensation (controllers) and the continuous comfort measure."""

import numpy as np
import pytest

from erva_ros.core.studies.closed_loop import simulate_closed_loop
from erva_ros.core.controllers import ControllerSettings, make_controller
from erva_ros.core.controllers.delay import DelayCompensation
from erva_ros.core.controllers.skyhook import SkyhookController
from erva_ros.core.model.quarter_car import make_model
from erva_ros.core.model.params import paper_params
from erva_ros.core.model.plant import PlantSimulator
from erva_ros.core.road.profiles import make_road

P = paper_params()
M = make_model(P)
S = ControllerSettings(time_budget_s=10.0)
TS, D = 0.02, 0.008


def test_the_controller_plans_from_the_state_when_its_command_acts():
    """Compensated, the law sees exactly the plant's state at t_k + d."""
    seen = []

    class Recording(SkyhookController):
        def _compute(self, x, preview, t):
            seen.append((x.copy(), preview.copy(), t))
            return super()._compute(x, preview, t)

    ctrl = Recording(10, TS, 0.0, 20000.0, P.c_e0)
    ctrl.predict_delay(M, D)
    road = make_road('paper', 1.0, seed=1)
    plant = PlantSimulator(M, ts=TS, x0=np.array([0.01, -0.1, 0.002, 0.2, 0.003, -0.3]))
    acting = P.c_e0
    for k in range(5):
        t_k = k * TS
        res = ctrl.compute(plant.x, road.preview(t_k, 10, TS), t_k)
        # the true state at t_k + d: the plant over d with the acting command
        probe = PlantSimulator(M, ts=D, x0=plant.x)
        w_d = road.height(t_k) + (road.height(t_k + TS) - road.height(t_k)) * D / TS
        x_true = probe.step(acting, road.height(t_k), w_d)
        x_seen, preview_seen, t_seen = seen[-1]
        np.testing.assert_allclose(x_seen, x_true, rtol=1e-12, atol=1e-15)
        assert t_seen == pytest.approx(t_k + D)
        grid = t_k + D + TS * np.arange(10)        # the preview moved by d (last held)
        np.testing.assert_allclose(preview_seen[:10], np.interp(
            grid, t_k + TS * np.arange(11), road.preview(t_k, 10, TS)), atol=1e-15)
        assert preview_seen[10] == road.preview(t_k, 10, TS)[10]
        plant.step_delayed(acting, res.damping_cmd, D, road.height(t_k),
                           road.height(t_k + TS))
        acting = res.damping_cmd


def test_delay_compensation_rejects_a_delay_outside_the_period():
    model = M
    for bad in (0.0, -0.001, TS, 0.05):
        with pytest.raises(ValueError, match='command delay'):
            DelayCompensation(model, TS, bad)
    with pytest.raises(Exception, match='command_delay_s'):
        S.with_(command_delay_s=0.02)


def test_a_constant_command_does_not_care_about_the_delay():
    road = make_road('paper', 1.0, seed=0)
    now = simulate_closed_loop(M, make_controller('passive', M, S), road, 1.0)
    late = simulate_closed_loop(M, make_controller('passive', M, S), road, 1.0,
                                actuation_delay_s=D)
    np.testing.assert_allclose(late.x, now.x, rtol=1e-9, atol=1e-14)
    assert late.harvested_j == pytest.approx(now.harvested_j, rel=1e-9)


def test_a_delay_changes_a_switching_law_and_vanishes_continuously():
    road = make_road('paper', 1.0, seed=0)
    runs = {d: simulate_closed_loop(M, make_controller('skyhook', M, S), road, 1.0,
                                    actuation_delay_s=d) for d in (0.0, 1e-7, D)}
    assert not np.allclose(runs[D].u, runs[0.0].u)
    np.testing.assert_allclose(runs[1e-7].x, runs[0.0].x, rtol=1e-4, atol=1e-7)
    with pytest.raises(ValueError, match='actuation delay'):
        simulate_closed_loop(M, make_controller('skyhook', M, S), road, 1.0,
                             actuation_delay_s=TS)


def test_continuous_comfort_integral_matches_a_fine_quadrature():
    """∫ z̈_s² dt of the plant's step against the trapezoid rule on a 50 µs grid."""
    model = M
    x0 = np.array([0.01, -0.1, 0.002, 0.2, 0.003, -0.3])
    plant = PlantSimulator(M, ts=TS, x0=x0)
    u, w0, w1 = 15000.0, 0.001, 0.0015
    plant.step(u, w0, w1)
    n = 400
    w = w0 + (w1 - w0) * np.arange(n + 1) / n
    xs = model.simulate(x0, np.full(n, u), w, TS / n, substeps=1)
    acc, _ = model.outputs_along(xs, u, w)
    reference = np.trapezoid(np.asarray(acc).ravel() ** 2, dx=TS / n)
    assert plant.accel_sq_int == pytest.approx(reference, rel=1e-4)
    assert plant.accel_sq_int > 0


def test_the_continuous_rms_is_reported_and_equals_the_sampled_one_for_passive():
    road = make_road('paper', 2.0, seed=0)
    m = simulate_closed_loop(M, make_controller('passive', M, S), road, 2.0).metrics
    # constant damping: no switching, the samples represent the whole signal
    assert m['acc_rms_continuous'] == pytest.approx(m['acc_rms'], rel=0.02)


def test_erva_sim_reports_the_delay_options(erva):
    run = erva('sim', '--duration', '0.4', '--controller', 'skyhook', '--actuation-delay',
               '0.008', '--command-delay', '0.008', '--json')
    assert run.returncode == 0, run.stderr
    import json
    out = json.loads(run.stdout)
    assert out['actuation_delay_s'] == 0.008 and out['command_delay_s'] == 0.008
    assert out['acc_rms_continuous'] > 0
    bad = erva('sim', '--duration', '0.4', '--actuation-delay', '0.02')
    assert bad.returncode == 2 and 'actuation delay' in bad.stderr
    bad = erva('sim', '--duration', '0.4', '--command-delay', '0.03')
    assert bad.returncode == 2 and "'command_delay_s'" in bad.stderr


def test_a_diverging_prediction_falls_back_instead_of_reaching_the_law():
    ctrl = make_controller('skyhook', M, S.with_(command_delay_s=D))
    x_absurd = np.array([1e300, 1e300, -1e300, 1e300, 1e300, -1e300])
    res = ctrl.compute(x_absurd, np.zeros(11), 0.0)
    assert res.status == 'fallback_passive' and 'delay compensation' in res.reason
    assert ctrl.counters['failures'] == 1 and res.damping_cmd == P.c_e0


def test_delay_study_prints_every_variant_and_rejects_a_bad_delay(erva):
    run = erva('delay-study', '--seeds', '2', '--duration', '0.4', '--controller', 'preview',
               '--json')
    assert run.returncode == 0, run.stderr
    import json
    out = json.loads(run.stdout)
    assert sorted(out['seeds']) == ['0', '1'] and out['delay_s'] == 0.008
    for seed in out['seeds'].values():
        assert set(seed) == {'no_delay', 'delayed', 'predicted', 'modelled'}
        assert all(v['acc_rms_continuous'] > 0 and v['fallbacks'] == 0 for v in seed.values())
    # the command acting 8 ms late changes the run; modelling it changes it again
    s0 = out['seeds']['0']
    assert len({s0[v]['acc_rms_continuous'] for v in s0}) == 4
    bad = erva('delay-study', '--seeds', '1', '--delay', '0.02')
    assert bad.returncode == 2 and 'must be below ts' in bad.stderr.strip().splitlines()[-1]
