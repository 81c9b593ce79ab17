"""Closed-loop evaluation of the estimator (no ROS): the controller on estimated vs true state.

Two runs on the same road, same controller, same plant (``PlantSimulator``), same
metrics (:func:`erva_ros.core.metrics.comfort_power`):

* **full state** — the offline closed loop's semantics (``erva_ros.core.studies.closed_loop``): the
  controller sees x(t_k);
* **estimated** — the controller sees the EKF's x̂(t_k) built from the ECU's sensors
  only.  Per sample: the sensors are read at t_k while the previous command still
  acts (as the ECU samples before it latches a new duty), with the simulated ECU's
  noise (:class:`~erva_ros.core.hil.ecu_sim.SensorNoise`) and the DBC's quantisation; the
  EKF predicts with u_{k−1} and the road w_{k−1} → w_k, updates, and the controller
  computes u_k from x̂_k.

* **perturbed** (control experiment) — the controller sees the true state plus a tiny
  white perturbation (:data:`PERTURBATION`: 0.01 mm, 0.1 mm/s, 10-30 times smaller than
  the EKF's error).  A controller whose result moves a lot here is sensitive to *any*
  state error (a non-convex NMPC with a few SQP iterations lands in another local
  optimum), so its estimated-state difference cannot be blamed on the estimator.

The controller comes from :func:`erva_ros.core.controllers.make_controller` (passive,
skyhook, the NMPC with or without preview).  Reported: comfort (acceleration 2-norm
and RMS), average harvested power, their relative change, and the estimation error
RMS per state.
"""

from dataclasses import dataclass
from typing import Dict, Optional

import numpy as np

from erva_ros.core.model.estimator import EstimatorNoise, ExtendedKalmanFilter
from erva_ros.core.hil.ecu_sim import SensorNoise
from erva_ros.core.metrics import comfort_power
from erva_ros.core.model.quarter_car import QuarterCarModel
from erva_ros.core.model.plant import PlantSimulator

#: DBC resolution of the measured signals (config/erva_ecu.dbc): accel, deflection, speed.
QUANTUM = np.array([1e-3, 1e-5, 1e-3])
#: Std of the control experiment's state perturbation: positions (m), velocities (m/s).
PERTURBATION = (1e-5, 1e-4)


@dataclass
class RunResult:
    """One closed-loop run: metrics and the time series that made them."""

    metrics: Dict[str, float]
    sprung_accel: np.ndarray
    u: np.ndarray
    x: np.ndarray
    x_hat: Optional[np.ndarray] = None


def _run(model: QuarterCarModel, controller, road, duration_s: float, ts: float,
         estimator: Optional[ExtendedKalmanFilter], sensor: SensorNoise,
         perturb: Optional[np.ndarray] = None) -> RunResult:
    n = int(round(duration_s / ts))
    controller.reset()
    plant = PlantSimulator(model, ts)
    rng = np.random.default_rng(sensor.seed)
    sig = np.array([sensor.sprung_accel, sensor.deflection, sensor.speed])
    xs, xh, us, acc = [], [], [], []
    u_prev = controller.c_e0
    w_prev = road.height(0.0)
    for k in range(n):
        t_k = k * ts
        w_k = road.height(t_k)
        x_ctrl = plant.x
        if estimator is not None:
            if k > 0:
                estimator.predict(u_prev, w_prev, w_k)
            truth = np.asarray(model.measurements(plant.x, u_prev, w_k)).ravel()
            y = np.round((truth + sig * rng.standard_normal(3)) / QUANTUM) * QUANTUM
            estimator.update(y, u_prev, w_k)
            x_ctrl = estimator.x.copy()
            xh.append(x_ctrl)
        elif perturb is not None:
            x_ctrl = plant.x + perturb * rng.standard_normal(plant.x.size)
        preview = road.preview(t_k, controller.horizon, ts)
        u = controller.compute(x_ctrl, preview, t_k).damping_cmd
        s = plant.sample(u, w_k)
        xs.append(s.x)
        us.append(u)
        acc.append(s.sprung_accel)
        plant.step(u, w_k, road.height((k + 1) * ts))
        u_prev, w_prev = u, w_k
    metrics = comfort_power(acc, plant.harvested_j, n * ts)
    return RunResult(metrics, np.array(acc), np.array(us), np.array(xs),
                     np.array(xh) if estimator is not None else None)


def evaluate_estimator(model: QuarterCarModel, controller, road, duration_s: float,
                       ts: float = 0.02, noise: EstimatorNoise = EstimatorNoise(),
                       sensor: SensorNoise = SensorNoise(), u_max: Optional[float] = None,
                       x0_error: Optional[np.ndarray] = None) -> Dict:
    """Run ``controller`` with full state and with the EKF; return metrics and their ratios.

    ``x0_error`` starts the EKF away from the true initial state (default: at rest, as
    the plant).  Returns ``{'full': metrics, 'estimated': metrics, 'change_pct': {...},
    'perturbed': metrics, 'perturbed_change_pct': {...}, 'estimation_rms': {state: rms
    error}, 'state_rms': {state: rms of the true state}}``.
    """
    full = _run(model, controller, road, duration_s, ts, None, sensor)
    ekf = ExtendedKalmanFilter(model, ts, noise,
                               u_max=u_max if u_max is not None else controller.u_max)
    if x0_error is not None:
        ekf.reset(np.asarray(x0_error, dtype=float))
    est = _run(model, controller, road, duration_s, ts, ekf, sensor)
    sig = np.tile(PERTURBATION, ekf.nx // 2)
    perturbed = _run(model, controller, road, duration_s, ts, None, sensor, sig)
    names = ekf.model.state_names
    err = est.x_hat - est.x
    skip = min(len(err) // 4, int(round(0.5 / ts)))     # after the initial transient

    def change(run):
        return {k: 100.0 * (run.metrics[k] - full.metrics[k]) / full.metrics[k]
                for k in ('acc_2norm', 'acc_rms', 'power_w') if full.metrics[k]}

    return {
        'controller': controller.name,
        'road': getattr(road, 'name', ''),
        'duration_s': duration_s,
        'full': full.metrics,
        'estimated': est.metrics,
        'change_pct': change(est),
        'perturbed': perturbed.metrics,
        'perturbed_change_pct': change(perturbed),
        'estimation_rms': dict(zip(names, np.sqrt(np.mean(err[skip:] ** 2, axis=0)).tolist())),
        'state_rms': dict(zip(names, np.sqrt(np.mean(est.x[skip:] ** 2, axis=0)).tolist())),
        'noise': noise.as_dict(),
    }
