"""How well the road estimator rebuilds the road at the tyre (``erva map accuracy``, docs/road.md).

Per road and seed: a drive with the ECU's sensors (:class:`~erva_ros.core.roadmap.vehicle.
EcuSensors`, the shipped noise) and a switching damping (4 / 18 kNs/m every 7 samples, as
a controller switches), the road estimator over it (filter, causal) and its RTS smoothing.
Errors against the true road, after the first second (the filter's start):

* ``raw``: RMS of ŵ − w with its mean removed.  Dominated by what is not observable: the
  estimate's slow drift (the offset and vertical velocity of the car's frame).
* ``detail``: RMS of the same error high-passed as the map high-passes a drive
  (:func:`~erva_ros.core.roadmap.profile.highpass`, σ = 6 m of road): what the preview
  and the map use.

Estimator variants (:data:`VARIANTS`), to choose the road model and the sensors by measuring.
"""

from dataclasses import dataclass
from typing import Dict, Optional

import numpy as np

from erva_ros.core.controllers.base import Controller
from erva_ros.core.model.estimator import EstimatorNoise
from erva_ros.core.model.quarter_car import make_model, QuarterCarModel
from erva_ros.core.model.params import ERVAParams
from erva_ros.core.model.road_estimator import RoadEKF, RoadModel, RoadSensors, road_noise
from erva_ros.core.roadmap import MapError
from erva_ros.core.roadmap.profile import HIGHPASS_M, highpass
from erva_ros.core.road.profiles import make_road

#: Roads of the table: (kind, ISO class).
ROADS = {'paper': ('paper', None), 'A': ('iso8608', 'A'), 'B': ('iso8608', 'B'),
         'C': ('iso8608', 'C'), 'D': ('iso8608', 'D')}
#: Std of the unsprung accelerometer of the "wheel" variant (m/s²): a MEMS part at the hub.
WHEEL_ACCEL = 0.05


@dataclass(frozen=True)
class EstimatorVariant:
    """Road model and sensors of one row of the table."""

    road_model: str = 'unknown_input'    # unknown_input | iso_matched | integrated
    current: bool = True                 # the generator current (force) row
    wheel: bool = False                  # an unsprung accelerometer
    known_road_noise: bool = False       # the known-road EKF's process noise (0.1/1/0.1)


VARIANTS = {
    'shipped': EstimatorVariant(),
    'iso_matched': EstimatorVariant(road_model='iso_matched'),
    'integrated': EstimatorVariant(road_model='integrated'),
    'no_current': EstimatorVariant(current=False),
    'wheel_accel': EstimatorVariant(wheel=True),
    'known_road_noise': EstimatorVariant(known_road_noise=True),
}


def _estimator(quarter_car: QuarterCarModel, variant: EstimatorVariant,
               road_class: Optional[str], speed: float, ts: float) -> RoadEKF:
    noise = EstimatorNoise() if variant.known_road_noise else road_noise()
    if variant.road_model == 'iso_matched':
        model = RoadModel.iso8608(road_class or 'A', speed, ts)
    elif variant.road_model == 'integrated':
        model = RoadModel('integrated', 0.05)
    else:
        model = RoadModel()
    sensors = RoadSensors.of(noise, current_a=0.01 if variant.current else None,
                             unsprung_accel=WHEEL_ACCEL if variant.wheel else None)
    return RoadEKF(quarter_car, ts=ts, noise=noise, road=model, sensors=sensors,
                   keep_history=True)


def accuracy(params: ERVAParams, road: str, seed: int, variant: str = 'shipped',
             duration_s: float = 8.0, speed_mps: float = 20.0, ts: float = 0.02) -> Dict:
    """Return the estimation errors (m) of one drive on ``road`` (a key of :data:`ROADS`)."""
    from erva_ros.core.roadmap.vehicle import EcuSensors, simulate_vehicle

    if road not in ROADS:
        raise MapError(f'road {road!r}; choose one of {", ".join(ROADS)}')
    if variant not in VARIANTS:
        raise MapError(f'estimator variant {variant!r}; choose one of {", ".join(VARIANTS)}')
    kind, cls = ROADS[road]
    opts = {'road_class': cls} if cls else {}
    r = make_road(kind, duration_s, seed=seed, speed_mps=speed_mps, **opts)
    v = VARIANTS[variant]

    class Switching(Controller):
        name = 'switching'

        def _compute(self, x, preview, t):
            k = int(round(t / self.ts))
            return np.full(self.horizon, 18000.0 if (k // 7) % 2 else 4000.0), 0

    ctrl = Switching(1, ts, 0.0, 22800.0, params.c_e0)
    model = make_model(params)
    ekf = _estimator(model, v, cls, speed_mps, ts)
    sensors = EcuSensors(unsprung_accel=WHEEL_ACCEL if v.wheel else None)
    run = simulate_vehicle(model, ctrl, r, duration_s, sensors=sensors,
                           sensor_seed=seed + 31, preview=lambda *a: np.zeros(2))
    ekf.reset()
    ekf.start(run.y[0], run.u_now[0])
    for k in range(1, run.t.size):
        ekf.cycle(run.y[k], run.u_mean[k], run.u_now[k], run.u_now[k - 1])
    sm = ekf.smooth()
    skip = int(round(1.0 / ts))
    dx = speed_mps * ts
    out = {}
    for name, w_hat in (('filter', sm.w_filtered), ('smoother', sm.w)):
        e = (w_hat - run.w)[skip:]
        out[f'{name}_raw'] = float(np.std(e))
        out[f'{name}_detail'] = float(np.sqrt(np.mean(highpass(e, dx, HIGHPASS_M) ** 2)))
    w = run.w[skip:]
    out['road_raw'] = float(np.std(w))
    out['road_detail'] = float(np.sqrt(np.mean(highpass(w, dx, HIGHPASS_M) ** 2)))
    out['predicted_std'] = float(np.sqrt(np.mean(sm.var_w[skip:])))
    return out


__all__ = ['ROADS', 'VARIANTS', 'EstimatorVariant', 'WHEEL_ACCEL', 'accuracy']
