"""The offline vehicle loop: ECU sensors, odometry, the road estimator, a preview source, the NMPC.

What a vehicle has, simulated without ROS or CAN, for the map study (docs/road.md):

* a route (:class:`Route`): the road as a function of distance, driven at any speed;
* the ECU's sensors (:class:`EcuSensors`): the rows of
  :data:`erva_ros.core.model.road_estimator.ROAD_MEASUREMENTS` with the simulated ECU's noise
  (config/hil.yaml) and the DBC's resolution, sampled at t_k while the previous command
  still acts (the ECU samples before the new duty latches);
* odometry (:class:`Odometry`): distance = ∫ measured speed, with an error model;
* the loop (:func:`simulate_vehicle`): per sample t_k the sensors, the estimator
  (:class:`~erva_ros.core.model.road_estimator.RoadEKF`, or the true state), the preview source
  (the true road, or :class:`~erva_ros.core.roadmap.preview.MapPreview`), the controller,
  and the plant (:class:`~erva_ros.core.model.plant.PlantSimulator`), with the command acting
  ``delay_s`` after its sample as in the HIL loop.

Comfort and power are measured after ``warmup_s`` (the plant starts at rest on the route):
the continuous RMS of z̈_s and the harvested energy that the plant integrates, and the
sampled z̈_s (paper's 2-norm).
"""

from dataclasses import dataclass, field
import math
from typing import Callable, Dict, Optional, Tuple

import numpy as np

from erva_ros.core.hil.ecu_sim import SensorNoise
from erva_ros.core.model.hardware import GeneratorHardware
from erva_ros.core.model.quarter_car import QuarterCarModel
from erva_ros.core.model.plant import PlantSimulator
from erva_ros.core.model.road_estimator import QUANTA, RoadEKF
from erva_ros.core.roadmap import MapError
from erva_ros.core.roadmap.drive import DriveRecord
from erva_ros.core.road.profiles import Road

#: DBC resolution of an unsprung-mass accelerometer, were one fitted (m/s²).
UNSPRUNG_QUANTUM = 1e-2


@dataclass(frozen=True)
class Route:
    """A road as a function of distance: heights (m) on the grid ``x`` (m, increasing)."""

    name: str
    x: np.ndarray
    h: np.ndarray

    @staticmethod
    def of(road: Road) -> 'Route':
        """Return the route a time road describes at its own speed (x = speed·t)."""
        return Route(road.name, road.times * road.speed_mps, road.heights)

    @property
    def length_m(self) -> float:
        return float(self.x[-1])

    def height(self, s):
        return np.interp(s, self.x, self.h)

    def drive(self, speed_mps: float, start_m: float = 0.0) -> Road:
        """Return the road at the tyre (a time road, t = 0 at ``start_m``) at ``speed_mps``."""
        if not speed_mps > 0:
            raise MapError(f'speed {speed_mps!r} m/s must be > 0')
        keep = self.x >= start_m
        return Road(f'{self.name} from {start_m:g} m at {speed_mps:g} m/s',
                    (self.x[keep] - start_m) / speed_mps, self.h[keep], speed_mps)


@dataclass(frozen=True)
class EcuSensors:
    """The ECU's sensors: noise (config/hil.yaml), DBC resolution, an optional wheel sensor."""

    noise: SensorNoise = SensorNoise()
    hardware: GeneratorHardware = GeneratorHardware()
    unsprung_accel: Optional[float] = None   # std (m/s²) of an unsprung accelerometer; None: none

    def sampler(self, model, seed: int) -> Callable[[np.ndarray, float, float], np.ndarray]:
        """Return y(x, u, w): one cycle's rows, noisy and quantised (seeded)."""
        rng = np.random.default_rng(seed)
        n, hw = self.noise, self.hardware
        q = np.array([QUANTA['sprung_accel'], QUANTA['deflection'], QUANTA['generator_speed']])
        sig = np.array([n.sprung_accel, n.deflection, n.speed])
        kappa = hw.kappa_n_per_a
        wheel = self.unsprung_accel

        def sample(x, u, w):
            base = np.asarray(model.measurements(x, u, w)).ravel()
            v_gen = float(model.generator_velocity(x))
            noisy = np.round((base + sig * rng.standard_normal(3)) / q) * q
            current = hw.current(u, v_gen) + n.current * rng.standard_normal()
            force = kappa * round(current / QUANTA['current']) * QUANTA['current']
            if wheel is None:
                zus = math.nan
            else:
                zus = float(np.asarray(model.ode(x, u, w)).ravel()[3])
                zus = round((zus + wheel * rng.standard_normal()) / UNSPRUNG_QUANTUM) \
                    * UNSPRUNG_QUANTUM
            return np.array([noisy[0], noisy[1], noisy[2], force, zus])
        return sample


@dataclass(frozen=True)
class OdometryError:
    """Distance = ∫ measured speed: a start bias, a scale error and white speed noise."""

    bias_m: float = 0.0          # position error at the start (m)
    scale: float = 0.0           # relative speed error (0.005: reads 0.5 % fast)
    speed_noise_mps: float = 0.0  # std of white noise on each speed sample (m/s)
    seed: int = 0

    @staticmethod
    def level(error_m: float, seed: int, route_m: float = 100.0) -> 'OdometryError':
        """Return the study's error of size ``error_m``: bias ±e, scale ±e per ``route_m``, noise.

        Signs from ``seed``; speed noise 0.05 m/s (a wheel-speed signal) when e > 0.
        """
        if error_m == 0:
            return OdometryError(seed=seed)
        rng = np.random.default_rng([seed, 7717])
        sb, ss = rng.choice([-1.0, 1.0], size=2)
        return OdometryError(sb * error_m, ss * error_m / route_m, 0.05, seed)


class Odometry:
    """Odometry along a route at constant true speed: s(t_k) and the measured speed."""

    def __init__(self, error: OdometryError, start_m: float, ts: float):
        self.error = error
        self.ts = float(ts)
        self.s = start_m + error.bias_m
        self._rng = np.random.default_rng([error.seed, 4243])
        self._first = True

    def step(self, speed_mps: float) -> Tuple[float, float]:
        """Return (distance at t_k, measured speed at t_k); advance to t_k+1."""
        e = self.error
        v = speed_mps * (1 + e.scale) + e.speed_noise_mps * self._rng.standard_normal()
        s = self.s
        self.s += v * self.ts
        return s, v


#: A preview source: (t_k, odometry distance, measured speed, ŵ_k, var(ŵ_k), points) ->
#: heights w(t_k + j·Ts), j = 0..points-1 (m), in the estimator's frame.
PreviewSource = Callable[[float, float, float, float, float, int], np.ndarray]


def oracle_preview(road: Road, ts: float, anchored: bool) -> PreviewSource:
    """Return the true road ahead; ``anchored``: its increments added to the estimate ŵ_k."""
    def source(t, s_odo, v_odo, w_hat, var_w, n):
        p = road.preview(t, n - 1, ts)
        return w_hat + (p - p[0]) if anchored else p
    return source


@dataclass
class VehicleRun:
    """One drive of :func:`simulate_vehicle`: per-sample series and the metrics."""

    t: np.ndarray                # s
    s_true: np.ndarray           # m along the route
    s_odo: np.ndarray            # m, the odometry
    w: np.ndarray                # m, true road at the tyre
    w_hat: np.ndarray            # m, the estimate (the truth without an estimator)
    x: np.ndarray                # (n, nx) true state
    u: np.ndarray                # Ns/m, command computed at t_k
    y: np.ndarray                # (n, 5) the ECU's measurements
    u_now: np.ndarray            # Ns/m applied when the sensors were sampled
    u_mean: np.ndarray           # Ns/m, mean over the cycle that ended at t_k
    metrics: Dict[str, float] = field(default_factory=dict)

    def record(self, source: str, route: str, speed_mps: float) -> DriveRecord:
        """Return what a recorder of this drive would have: measurements and odometry."""
        return DriveRecord(self.t.copy(), self.s_odo.copy(), self.y.copy(), self.u_now.copy(),
                           self.u_mean.copy(), source, route, speed_mps)


def simulate_vehicle(model: QuarterCarModel, controller, road: Road, duration_s: float, *,
                     start_m: float = 0.0, estimator: Optional[RoadEKF] = None,
                     preview: Optional[PreviewSource] = None,
                     odometry: OdometryError = OdometryError(),
                     sensors: EcuSensors = EcuSensors(), sensor_seed: int = 0,
                     delay_s: float = 0.0, warmup_s: float = 0.0) -> VehicleRun:
    """Drive ``road`` (t = 0 at route distance ``start_m``) with ``controller`` on ``model``.

    See the module doc.

    ``estimator`` None: the controller gets the true state; ``preview`` None: the true road
    ahead (anchored on ŵ_k with an estimator).  The plant starts at rest on the road's
    height at t = 0.
    """
    ts = controller.ts
    n = int(round((warmup_s + duration_s) / ts))
    n_warm = int(round(warmup_s / ts))
    if not 0.0 <= delay_s < ts:
        raise ValueError(f'delay must be in [0, Ts = {ts:g} s), got {delay_s:g} s')
    controller.reset()
    w0 = float(road.height(0.0))
    plant = PlantSimulator(model, ts)
    x0 = plant.model.zero_state()
    x0[0] = x0[2] = w0
    plant.reset(x0)
    sample_y = sensors.sampler(plant.model, sensor_seed)
    odo = Odometry(odometry, start_m, ts)
    # The true road ahead, in the estimator's frame when there is one (its offset is not
    # observable: a true height next to an estimated state would be a false tyre force).
    source = preview or oracle_preview(road, ts, anchored=estimator is not None)
    points = controller.horizon + 1
    if estimator is not None:
        estimator.reset()
    nx = plant.model.nx
    out = {k: np.empty(n) for k in ('t', 's', 's_odo', 'w', 'w_hat', 'u', 'u_now', 'u_mean',
                                    'acc')}
    xs, ys = np.empty((n, nx)), np.empty((n, 5))
    acting, previous = controller.c_e0, controller.c_e0     # u_{k-1}, u_{k-2}
    energy0 = accel0 = 0.0
    for k in range(n):
        if k == n_warm:
            energy0, accel0 = plant.harvested_j, plant.accel_sq_int
        t_k = k * ts
        w_k = float(road.height(t_k))
        u_mean = (delay_s * previous + (ts - delay_s) * acting) / ts
        y = sample_y(plant.x, acting, w_k)
        if estimator is None:
            x_ctrl, w_hat, var_w = plant.x, w_k, 0.0
        else:
            est = (estimator.start(y, acting) if k == 0
                   else estimator.cycle(y, u_mean, acting, previous))
            x_ctrl, w_hat, var_w = est.x, est.w, est.var_w
        s_odo, v_odo = odo.step(road.speed_mps)
        p = source(t_k, s_odo, v_odo, w_hat, var_w, points)
        u = controller.compute(x_ctrl, p, t_k).damping_cmd
        s = plant.sample(acting if delay_s else u, w_k)
        for key, v in (('t', t_k), ('s', start_m + road.speed_mps * t_k), ('s_odo', s_odo),
                       ('w', w_k), ('w_hat', w_hat), ('u', u), ('u_now', acting),
                       ('u_mean', u_mean), ('acc', s.sprung_accel)):
            out[key][k] = v
        xs[k], ys[k] = s.x, y
        w1 = float(road.height(t_k + ts))
        if delay_s:
            plant.step_delayed(acting, u, delay_s, w_k, w1)
        else:
            plant.step(u, w_k, w1)
        previous, acting = acting, u
    span = (n - n_warm) * ts
    acc = out['acc'][n_warm:]
    metrics = {'acc_rms_continuous': math.sqrt((plant.accel_sq_int - accel0) / span),
               'power_w': (plant.harvested_j - energy0) / span,
               'acc_2norm': float(np.sqrt(np.sum(acc ** 2))),
               'acc_rms': float(np.sqrt(np.mean(acc ** 2)))}
    metrics.update({f'ctrl_{k}': v for k, v in controller.counters.items()})
    return VehicleRun(out['t'], out['s'], out['s_odo'], out['w'], out['w_hat'], xs, out['u'],
                      ys, out['u_now'], out['u_mean'], metrics)


__all__ = ['Route', 'EcuSensors', 'OdometryError', 'Odometry', 'PreviewSource',
           'oracle_preview', 'VehicleRun', 'simulate_vehicle', 'UNSPRUNG_QUANTUM']
