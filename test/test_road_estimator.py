"""The road at the tyre estimated from the ECU's sensors: RTS against batch, the error bound."""

import math

import numpy as np
import pytest

from erva_ros.core.model.quarter_car import make_model
from erva_ros.core.model.params import paper_params, ParamError
from erva_ros.core.model.road_estimator import (ROAD_MEASUREMENTS, RoadEKF, RoadModel, RoadSensors,
                                                road_noise)
from erva_ros.core.roadmap.accuracy import accuracy

P = paper_params()
M = make_model(P)


def test_road_models_and_sensors():
    # ISO 8608: the increment's std over v·Ts follows the class (class C at 20 m/s: 4.5 mm).
    assert RoadModel.iso8608('C', 20.0, 0.02).sigma == pytest.approx(4.496e-3, rel=1e-3)
    assert RoadModel.iso8608('D').sigma == pytest.approx(2 * RoadModel.iso8608('C').sigma)
    with pytest.raises(ParamError, match="road model 'leaky'"):
        RoadModel('leaky')
    with pytest.raises(ParamError, match='sigma'):
        RoadModel(sigma=0.0)
    s = RoadSensors.of(road_noise())
    assert list(s.present()) == [True, True, True, True, False]
    # κ·σ_i with the DBC's 1 mA resolution: 120 N/A · sqrt(0.01² + 0.001²/12) A.
    assert s.generator_force == pytest.approx(120 * math.sqrt(1e-4 + 1e-6 / 12))
    assert not RoadSensors.of(road_noise(), current_a=None).present()[3]


def test_rts_equals_the_batch_posterior_on_the_linear_model():
    """The smoother is the batch (dense, least-squares) solution of the same linear problem.

    On the linear benchmark model with constant damping the EKF is a Kalman filter; the
    batch solution stacks every cycle's dynamics and measurements and solves them at once,
    so an error in the backward recursion (gain, covariance update, indexing) shows.
    """
    ekf = RoadEKF(make_model(P, 'benchmark'), keep_history=True, codegen='off')
    rng = np.random.default_rng(4)
    n, u = 12, 8000.0
    ys = []
    for k in range(n):
        y = np.array([0.3, 1e-3, 0.05, 3.0, np.nan]) * rng.standard_normal(5)
        if k == 5:
            y[1] = np.nan                        # a lost frame: a row left out
        ys.append(y)
    ekf.reset()
    z0, p0 = ekf.z.copy(), ekf.P.copy()
    ekf.start(ys[0], u)
    for k in range(1, n):
        ekf.cycle(ys[k], u, u)
    sm = ekf.smooth()
    nz, h = ekf.nz, ekf.history
    # Batch: the unknowns θ = [z_0, ε_0 .. ε_{n-2}] with z_{k+1} = A_k z_k + c_k + L_k ε_k
    # (Q_k = L_k L_kᵀ, singular: white accelerations), priors z_0 ~ N(z̄_0, P_0), ε ~ N(0, I);
    # every z_k is linear in θ, so one weighted least-squares solve gives the posterior.
    ls = []
    for k in range(n - 1):
        q = h.p_pred[k] - h.a[k] @ h.p_filt[k] @ h.a[k].T
        ev, vec = np.linalg.eigh(0.5 * (q + q.T))
        ls.append(vec * np.sqrt(np.clip(ev, 0.0, None)))
    dim = nz + nz * (n - 1)
    maps = [(np.hstack([np.eye(nz), np.zeros((nz, dim - nz))]), np.zeros(nz))]
    for k in range(n - 1):
        m, d = maps[-1]
        e = np.zeros((nz, dim))
        e[:, nz + k * nz:nz + (k + 1) * nz] = ls[k]
        c = h.z_pred[k] - h.a[k] @ h.z_filt[k]     # affine part: linear model
        maps.append((h.a[k] @ m + e, h.a[k] @ d + c))
    rows = [np.linalg.cholesky(np.linalg.inv(p0)).T @ maps[0][0],
            np.hstack([np.zeros((dim - nz, nz)), np.eye(dim - nz)])]
    rhs = [np.linalg.cholesky(np.linalg.inv(p0)).T @ z0, np.zeros(dim - nz)]
    for k in range(n):
        used = np.isfinite(ys[k]) & ekf.sensors.present()
        yh, hh = ekf._h(h.z_filt[k], u)
        off = yh - hh @ h.z_filt[k]
        wr = 1 / np.sqrt(ekf.sensors.r_diag()[used])
        m, d = maps[k]
        rows.append(wr[:, None] * (hh[used] @ m))
        rhs.append(wr * (ys[k][used] - off[used] - hh[used] @ d))
    theta, *_ = np.linalg.lstsq(np.vstack(rows), np.concatenate(rhs), rcond=None)
    zb = np.array([m @ theta + d for m, d in maps])
    w_batch = zb[:, nz - 1]
    # Agreement to ~1e-7 of the values: w's own variance is huge (σ = 1 m per cycle).
    assert np.allclose(sm.w, w_batch, rtol=0, atol=1e-6 * np.abs(w_batch).max())
    xb = zb[:, :nz - 1] + np.outer(w_batch, [1, 0, 1, 0])
    assert np.allclose(sm.x, xb, rtol=0, atol=1e-6 * np.abs(xb).max())


def test_cycles_without_measurements_and_bad_rows():
    ekf = RoadEKF(M)
    ekf.start([0.0, 0.0, 0.0, 0.0, np.nan], P.c_e0)
    est = ekf.cycle([np.nan] * 5, P.c_e0, P.c_e0)          # a lost cycle: predicted only
    assert est.rows == 0 and est.nis == 0.0 and np.all(np.isfinite(est.x))
    est = ekf.cycle([0.01, 1e-4, 0.0, 0.0, 5.0], P.c_e0, P.c_e0)
    assert est.rows == 4                                    # no wheel sensor: row 5 ignored
    assert est.var_w > 0 and est.var_w_abs > est.var_w
    with pytest.raises(ValueError, match=f'{len(ROAD_MEASUREMENTS)} rows'):
        ekf.cycle([0.0, 0.0, 0.0], P.c_e0, P.c_e0)


@pytest.mark.parametrize('road', ['paper', 'A', 'B', 'C', 'D'])
def test_road_error_at_the_shipped_sensor_noise_is_bounded(road):
    """The detail error stays below 0.4 mm on every road (docs/road.md: 0.15-0.25 mm).

    Seed 100 (nothing was tuned on it).  An estimator without the road as a state, or
    that misplaced it by one sample, would be off by about the road's own detail: 0.8 mm
    on the paper road, 2.3-19 mm on ISO A-D.
    """
    a = accuracy(P, road, 100, 'shipped', duration_s=6.0)
    assert a['smoother_detail'] < 4e-4, a
    assert a['filter_detail'] < 4e-4, a
    assert a['smoother_detail'] < 0.5 * a['road_detail'], a
    assert math.isfinite(a['filter_raw']) and a['predicted_std'] > 0


def test_the_period_is_predicted_as_the_ecu_applied_it():
    """A command latched 6 ms after the sample: two pieces, not the period's mean."""
    from erva_ros.core.model.plant import PlantSimulator
    from erva_ros.core.model.road_estimator import damping_profile
    ts, d = 0.02, 0.006
    u_prev, u_now = 20000.0, 0.0
    u_mean = (d * u_prev + (ts - d) * u_now) / ts
    assert damping_profile(u_mean, u_now, u_prev, ts) == pytest.approx((u_prev, u_now, d))
    assert damping_profile(u_mean, u_now, None, ts) == (u_mean, u_mean, 0.0)
    assert damping_profile(5000.0, 5000.0, 5000.0, ts) == (5000.0, 5000.0, 0.0)
    assert damping_profile(30000.0, 0.0, 20000.0, ts) == (30000.0, 30000.0, 0.0)  # no fit
    x0 = np.array([0.004, 0.05, 0.001, -0.3, 0.002, 0.4])
    plant = PlantSimulator(M, ts=ts, x0=x0)
    plant.step_delayed(u_prev, u_now, d, 0.0, 0.0)
    errors = []
    for prev in (u_prev, None):
        ekf = RoadEKF(M, codegen='off')
        ekf.reset(x0)
        ekf.cycle([np.nan] * 5, u_mean, u_now, prev)           # prediction only
        errors.append(np.abs(ekf.x - plant.x).max())
    # Two pieces: the plant to RK4's accuracy; the mean throughout: far off.
    assert errors[0] < 1e-6 < 1e-4 < errors[1], errors
