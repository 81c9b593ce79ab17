"""EKF on the shared CasADi model: same discretisation, exact Jacobians, convergence, loop."""

import numpy as np
import pytest

from erva_ros.core.controllers import ControllerSettings, make_controller
from erva_ros.core.model.estimator import EstimatorNoise, ExtendedKalmanFilter, validate_noise
from erva_ros.core.hil.ecu_sim import SensorNoise
from erva_ros.core.hil.evaluation import evaluate_estimator, QUANTUM
from erva_ros.core.model.quarter_car import make_model
from erva_ros.core.model.params import paper_params, ParamError
from erva_ros.core.model.plant import PlantSimulator
from erva_ros.core.road.profiles import make_road

P = paper_params()
M = make_model(P)
X = np.array([0.004, 0.05, 0.001, -0.08, 0.002, 0.03])


@pytest.fixture(scope='module')
def ekf():
    return ExtendedKalmanFilter(M)


def test_prediction_is_the_shared_model_and_its_exact_jacobian(ekf):
    # The EKF's step is QuarterCarModel.rk4_step itself, stable up to the hardware's c_e.
    step = M.rk4_step(ekf.ts, ekf.substeps)
    xn, a = ekf._pred(X, 15000.0, 1e-3, 1.2e-3)
    assert np.allclose(np.asarray(xn).ravel(), np.asarray(step(X, 15000.0, 1e-3, 1.2e-3)).ravel(),
                       rtol=0, atol=1e-15)
    assert ekf.substeps >= 8        # h·|λ| <= 1.39 at 22.8 kNs/m (stiff: docs/model.md)
    fd = np.empty((6, 6))
    for i in range(6):
        d = np.zeros(6)
        d[i] = 1e-7
        fd[:, i] = (np.asarray(step(X + d, 15000.0, 1e-3, 1.2e-3)).ravel()
                    - np.asarray(step(X - d, 15000.0, 1e-3, 1.2e-3)).ravel()) / 2e-7
    assert np.allclose(np.asarray(a), fd, rtol=1e-5, atol=1e-7)
    # Outputs: the model's sprung acceleration, the deflection, the rotor speed v_gen / l.
    model = M
    y = ekf._meas(X, 15000.0, 1e-3)[0]
    assert np.allclose(np.asarray(y).ravel(), [float(model.sprung_accel(X, 15000.0, 1e-3)),
                                               X[0] - X[2],
                                               float(model.generator_velocity(X)) / P.l])


def test_sequential_rows_equal_the_batch_update():
    a, b = ExtendedKalmanFilter(M), ExtendedKalmanFilter(M)
    y = np.array([0.5, 0.004, 0.2])
    for e in (a, b):
        e.reset(X)
        e.predict(12000.0, 1e-3, 1.2e-3)
    res = a.update(y, 12000.0, 1.2e-3)
    b.linearize_output(12000.0, 1.2e-3)
    nis = sum(b.correct(i, y[i])[1] for i in (2, 0, 1))          # any order
    assert np.allclose(a.x, b.x, atol=1e-14) and np.allclose(a.P, b.P, atol=1e-14)
    assert nis == pytest.approx(res.nis)
    # A missing row (lost CAN frame) is a NaN: only the others are used.
    c = ExtendedKalmanFilter(M)
    c.reset(X)
    r = c.update([np.nan, 0.004, np.nan], 12000.0, 0.0)
    assert list(r.used) == [False, True, False] and r.innovation.shape == (1,)


def test_one_call_cycle_equals_predict_then_update(ekf):
    # The node's per-cycle path (one compiled call), with rows missing (NaN) too.
    a, b = ExtendedKalmanFilter(M), ekf
    for y in ([0.5, 0.004, 0.2], [np.nan, 0.004, 0.2], [np.nan] * 3):
        a.reset(X)
        b.reset(X)
        a.predict(12000.0, 1e-3, 1.2e-3)
        res = a.update(y, 13000.0, 1.2e-3)
        x, nis = b.cycle(y, 12000.0, 13000.0, 1e-3, 1.2e-3)
        assert np.allclose(x, a.x, rtol=0, atol=1e-12) and np.allclose(b.P, a.P, atol=1e-14)
        assert nis == pytest.approx(res.nis, rel=1e-9, abs=1e-15) and b.k == a.k


def test_converges_from_a_wrong_initial_state_with_consistent_innovations():
    road = make_road('paper', 5.0, seed=3)
    plant = PlantSimulator(M, ts=0.02)
    ekf = ExtendedKalmanFilter(M, noise=EstimatorNoise())
    ekf.reset(np.array([0.008, -0.05, 0.004, 0.05, -0.006, 0.05]))   # plant starts at rest
    sensor = SensorNoise()
    rng = np.random.default_rng(1)
    sig = np.array([sensor.sprung_accel, sensor.deflection, sensor.speed])
    errors, nis = [], []
    for k in range(250):
        t = 0.02 * k
        u = 18000.0 if (k // 20) % 2 else 4000.0        # a switching damping, known to it
        w0, w1 = road.height(t), road.height(t + 0.02)
        plant.step(u, w0, w1)
        truth = np.array([plant.sample(u, w1).sprung_accel, plant.x[0] - plant.x[2],
                          float(plant.model.generator_velocity(plant.x)) / P.l])
        y = np.round((truth + sig * rng.standard_normal(3)) / QUANTUM) * QUANTUM
        ekf.predict(u, w0, w1)
        nis.append(ekf.update(y, u, w1).nis)
        errors.append(np.abs(ekf.x - plant.x))
    errors = np.array(errors)
    start = np.abs(np.array([0.008, -0.05, 0.004, 0.05, -0.006, 0.05]))
    late = np.sqrt(np.mean(errors[150:] ** 2, axis=0))     # the last 2 s
    assert np.all(late < 0.1 * start), late / start
    # The noise model fits: mean NIS near its 3 degrees of freedom.
    assert 1.0 < np.mean(nis[50:]) < 6.0


def test_noise_parameters_are_validated():
    with pytest.raises(ParamError, match="'r_speed' = 0"):
        validate_noise({'r_speed': 0.0})
    assert validate_noise({'q_accel_s': 0.3}).q_accel_s == 0.3


def test_skyhook_on_estimated_state_stays_within_margins():
    """Comfort and power within ±10 % of the same law on the true state, on every seed."""
    controller = make_controller('skyhook', M, ControllerSettings())
    for seed in range(3):
        r = evaluate_estimator(M, controller, make_road('paper', 4.0, seed=seed), 4.0,
                               sensor=SensorNoise(seed=seed))
        assert abs(r['change_pct']['acc_2norm']) < 10.0, r
        assert abs(r['change_pct']['power_w']) < 10.0, r
        rel = {k: r['estimation_rms'][k] / r['state_rms'][k] for k in r['state_rms']}
        assert max(rel.values()) < 0.3, rel


@pytest.mark.slow
def test_nmpc_on_estimated_state_stays_within_margins_on_average():
    """NMPC (preview, α = (1, 0)): mean comfort over seeds within ±15 % of the full state.

    Per seed the NMPC's result moves by up to ±30 % even when the true state is only
    perturbed by 0.1 mm/s (the 'perturbed' control run): its non-convex problem, solved
    with a few SQP iterations, lands in different local optima.  So the margin is on the
    mean over seeds, and the estimated-state run is compared with that sensitivity.
    """
    settings = ControllerSettings().with_(alpha1=1.0, alpha2=0.0, time_budget_s=10.0)
    controller = make_controller('preview', M, settings)
    runs = [evaluate_estimator(M, controller, make_road('paper', 4.0, seed=seed), 4.0,
                               sensor=SensorNoise(seed=seed)) for seed in range(3)]
    acc = np.mean([r['change_pct']['acc_2norm'] for r in runs])
    assert abs(acc) < 15.0, [r['change_pct'] for r in runs]
    for r in runs:
        assert r['estimated']['acc_2norm'] < 1.5 * r['full']['acc_2norm']
