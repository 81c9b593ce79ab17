"""The vehicle's own road in the live loop: the estimator's and the map preview's cores.

:class:`RoadEstimatorLoop` is state_estimator_node's core with ``road_at_tyre``
``estimated``: per ECU cycle the :class:`~erva_ros.core.model.road_estimator.RoadEKF` (the
quarter car *and* the road at the tyre from what the ECU measures), and the odometry
(distance = ∫ speed, with the configured error: :class:`~erva_ros.core.roadmap.vehicle.
Odometry`).  No road topic is read: each cycle is stamped with its instant k·Ts, where
an ECU samples (docs/hil.md §8; `erva run`'s simulated ECU on the road's samples, which
are there too).

:class:`MapPreviewLoop` is road_preview_node's core with ``source`` ``map``: per
``road/estimate`` the preview from the map
(:class:`~erva_ros.core.roadmap.preview.MapPreview`) at the odometry position corrected by
profile matching, stamped as the estimate, and its counts in the node's report.
"""

from collections import deque
import math
from typing import Any, Mapping, Optional, Tuple

import numpy as np

from erva_ros.core.contract import Measurements, RoadEstimate as EstimateMsg
from erva_ros.core.loop.estimator_loop import EstimatorLoop
from erva_ros.core.loop.validation import MessageRejected
from erva_ros.core.model.params import ParamError
from erva_ros.core.reports import EstimatorReport, RoadReport
from erva_ros.core.model.road_estimator import (road_noise, RoadEKF, RoadEstimate, RoadModel,
                                                RoadSensors)
from erva_ros.core.roadmap import MapError
from erva_ros.core.roadmap.location import parse_location
from erva_ros.core.roadmap.preview import MapPreview, MapPreviewSettings, PreviewResult
from erva_ros.core.roadmap.store import RoadMap
from erva_ros.core.roadmap.vehicle import Odometry, OdometryError
from erva_ros.core.wire import NS

_NAN = float('nan')


class RoadEstimatorLoop(EstimatorLoop):
    """The RoadEKF and the odometry over the ECU's cycles (module doc)."""

    def __init__(self, ekf: RoadEKF, ts: float, c_e0: float, max_gap_periods: int,
                 odometry: OdometryError, speed_mps: float, report: EstimatorReport):
        super().__init__(ekf, ts, c_e0, max_gap_periods, False, report)
        self.odometry_error = odometry
        self.odometry = Odometry(odometry, 0.0, ts)
        self.speed_mps = speed_mps
        self.distance_m = _NAN
        self.estimate: Optional[RoadEstimate] = None
        report.road_at_tyre = 'estimated'

    def has_grid(self) -> bool:
        """Return True: the grid is k·Ts (stamp)."""
        return True

    def road_at(self, stamp_ns: int) -> bool:
        """Return True: no road sample is awaited."""
        return True

    def stamp(self, stamp: int) -> int:
        """Return the instant a cycle received at ``stamp`` stands for: its k·Ts.

        A real ECU runs its cycles at k·Ts of the synchronised clock (docs/hil.md §8), and
        `erva run`'s simulated ECU on the road's samples, which are at k·Ts too: the grid
        of EstimatorLoop.stamp is that one.  So the state, the preview and the command
        carry the ECU's own instant, and the command's cycle number is the ECU's.
        """
        if self.grid_ns is None:
            self.grid_ns = 0
        return super().stamp(stamp)

    def step(self, stamp_ns: int, m: Measurements) -> np.ndarray:
        """Run the cycle ``m`` at ``stamp_ns`` (gaps predicted through); return x̂."""
        ekf: RoadEKF = self.ekf
        y = (m.sprung_accel, m.deflection, m.speed, m.force, _NAN)
        if any(math.isnan(v) for v in (m.c_e, m.c_e_mean, *y[:4])):
            self.report.incomplete += 1
        u_now, u_mean = m.c_e, m.c_e_mean
        if math.isnan(u_now):               # status frame lost: the last c_e held
            u_now = u_mean = self.u_now
        steps = 0 if self.last_ns is None else max(
            1, int(round((stamp_ns - self.last_ns) / self.ts_ns)))
        if steps > self.max_gap_periods:
            self.report.restarts += 1
        if steps == 0 or steps > self.max_gap_periods:
            ekf.reset()
            est = ekf.start(y, u_now)
        else:
            if steps > 1:
                self.report.gaps += 1
            for _ in range(steps - 1):     # over a gap: the last applied damping held
                ekf.cycle((_NAN,) * 5, self.u_now, self.u_now, self.u_now)
                self.odometry.step(self.speed_mps)
            est = ekf.cycle(y, u_mean, u_now, self.u_now)
        self.distance_m = self.odometry.step(self.speed_mps)[0]
        self.u_now = u_now
        self.estimate = est
        self.nis_sum += est.nis
        self.last_ns = stamp_ns
        self.report.updates += 1
        return est.x

    def distance_variance(self) -> float:
        """Return the odometry's variance at the last cycle under its error model (m²)."""
        e, s = self.odometry_error, max(self.distance_m, 0.0)
        n = s / max(self.speed_mps * self.ts, 1e-12)
        return e.bias_m ** 2 + (e.scale * s) ** 2 + n * (e.speed_noise_mps * self.ts) ** 2

    def road_message(self) -> Tuple[float, float, float, float]:
        """Return (distance, ŵ, var distance, var ŵ) of the last cycle (road/estimate)."""
        est = self.estimate
        return self.distance_m, est.w, self.distance_variance(), est.var_w

    def warm(self, encode) -> None:
        """Run a cycle on scratch copies, so the due one finds warm caches (EstimatorLoop)."""
        ekf = self.ekf
        z, p, k = ekf.z.copy(), ekf.P.copy(), ekf.k
        ekf.cycle((0.0, 0.0, 0.0, 0.0, _NAN), self.u_now, self.u_now, self.u_now)
        encode(self.last_ns or 0, ekf.x)
        ekf.z, ekf.P, ekf.k = z, p, k

    def fill(self) -> Tuple[float, ...]:
        """Bring the report's figures up to date; return the state estimate's std."""
        r, ekf = self.report, self.ekf
        saved = self.ekf
        nx = ekf.nx
        j = np.hstack([np.eye(nx), ekf._shift[:, None], np.zeros((nx, ekf.nz - nx - 1))])
        std = np.sqrt(np.maximum(np.diag(j @ ekf.P @ j.T), 0.0))
        self.ekf = _Std(ekf.model, std)       # the base fills its figures from ekf.std()
        try:
            super().fill()
        finally:
            self.ekf = saved
        r.road_estimates = r.updates
        r.distance_m = float(self.distance_m)
        if self.estimate is not None:
            r.road_std_m = math.sqrt(max(self.estimate.var_w, 0.0))
        return tuple(std)


class _Std:
    """What EstimatorLoop.fill asks of a filter: its model and std per state."""

    def __init__(self, model, std):
        self.model, self._std = model, std

    def std(self):
        return self._std


def road_estimator_loop(model, p: Mapping[str, Any], noise, report: EstimatorReport
                        ) -> RoadEstimatorLoop:
    """Return the RoadEstimatorLoop on ``model`` of state_estimator_node's parameters ``p``."""
    sensors = RoadSensors.of(noise)
    ekf = RoadEKF(model, p['ts'], road_noise(), RoadModel('random_walk', p['road_sigma_m']),
                  sensors, u_max=p['u_max'])
    odo = OdometryError(p['odometry_bias_m'], p['odometry_scale'],
                        p['odometry_speed_noise_mps'], p['odometry_seed'])
    return RoadEstimatorLoop(ekf, p['ts'], model.params.c_e0, p['max_gap_periods'], odo,
                             p['speed_mps'], report)


class MapPreviewLoop:
    """The preview from the map for each road estimate, and the report's counts (module doc)."""

    def __init__(self, p: Mapping[str, Any], report: RoadReport):
        if not p['map_file']:
            raise ParamError('source map needs map_file (a map of erva map build)')
        if parse_location(p['map_file']).server:    # never the network in the loop
            raise ParamError('map_file: a local map file; a server map is fetched into its '
                             'local cache first (erva map fetch, or erva run --preview '
                             'map:URI does it)')
        try:
            with RoadMap.open(p['map_file']) as road_map:
                profile = road_map.profile()
            settings = MapPreviewSettings(window_m=p['map_window_m'],
                                          search_m=p['map_search_m'],
                                          min_correlation=p['map_min_correlation'],
                                          weighting=p['map_weighting'])
            self.preview = MapPreview(profile, p['ts'], settings)
        except MapError as exc:
            raise ParamError(f'map_file: {exc}') from None
        self.ts_ns = int(round(p['ts'] * NS))
        self.points = p['preview_steps'] + 1
        self.nominal_speed = p['speed_mps']
        self.window = max(2, int(round(p['map_speed_window_s'] / p['ts'])) + 1)
        self.odometry: deque = deque(maxlen=self.window)
        self.last_ns: Optional[int] = None
        #: The longest runs of samples that fell back, were unmatched, and of refused
        #: alignments in a row: the worst instance of each, for the session's verdict.
        self.streaks = {name: Streak() for name in STREAKS}
        self.report = report
        report.source, report.map_file = 'map', p['map_file']

    def speed(self) -> float:
        """Return the odometry's slope over the window (the nominal speed before two)."""
        if len(self.odometry) < 2:
            return self.nominal_speed
        (t0, s0), (t1, s1) = self.odometry[0], self.odometry[-1]
        return (s1 - s0) / ((t1 - t0) / NS)

    def on_estimate(self, est: EstimateMsg) -> PreviewResult:
        """Return the preview for ``est`` (MessageRejected: not newer than the last)."""
        if self.last_ns is not None and est.stamp_ns <= self.last_ns:
            raise MessageRejected('road/estimate not newer than the last')
        self.last_ns = est.stamp_ns
        self.odometry.append((est.stamp_ns, est.distance_m))
        c = self.preview.counts
        unmatched, tries, refused = (c.unmatched_samples, c.alignments + c.alignments_refused,
                                     c.alignments_refused)
        res = self.preview.step(est.distance_m, self.speed(), est.height_m, est.var_w,
                                self.points)
        self.streaks['fallback'].mark(est.stamp_ns, res.fallback_points > 0)
        self.streaks['unmatched'].mark(est.stamp_ns, c.unmatched_samples > unmatched)
        if c.alignments + c.alignments_refused > tries:     # a match was tried
            self.streaks['refused'].mark(est.stamp_ns, c.alignments_refused > refused)
        self.fill()
        return res

    def fill(self) -> None:
        """Copy the preview's counts and alignment into the report."""
        c, r, pv = self.preview.counts, self.report, self.preview
        for name in ('samples', 'points', 'fallback_points', 'fallback_samples',
                     'beyond_end_points', 'before_start_points', 'gap_points',
                     'unmatched_points', 'alignments', 'alignments_refused',
                     'unaligned_samples'):
            setattr(r, f'map_{name}', getattr(c, name))
        r.map_offset_m, r.map_offset_std_m = float(pv.offset), float(pv.offset_std)
        r.map_correlation = float(pv.correlation)
        for name, streak in self.streaks.items():
            setattr(r, f'map_{name}_streak', streak.longest)
            setattr(r, f'map_{name}_streak_from_ns', streak.from_ns)
            setattr(r, f'map_{name}_streak_to_ns', streak.to_ns)


#: The map preview's streaks in RoadReport (``map_<name>_streak``, ``_from_ns``, ``_to_ns``).
STREAKS = ('fallback', 'unmatched', 'refused')


class Streak:
    """The longest run of marked events in a row, and its first and last stamp (ns)."""

    def __init__(self):
        self.longest = 0
        self.from_ns = self.to_ns = 0
        self._run = 0
        self._start = 0

    def mark(self, stamp_ns: int, hit: bool) -> None:
        """Take the next event at ``stamp_ns``: ``hit`` continues the run, else ends it."""
        if not hit:
            self._run = 0
            return
        if not self._run:
            self._start = stamp_ns
        self._run += 1
        if self._run > self.longest:
            self.longest, self.from_ns, self.to_ns = self._run, self._start, stamp_ns


__all__ = ['RoadEstimatorLoop', 'road_estimator_loop', 'MapPreviewLoop', 'STREAKS', 'Streak']
