"""state_estimator_node's core: which instant an ECU cycle stands for, and the EKF's step.

The estimator gets one ``ecu/measurements`` message per ECU cycle (stamp: the CAN
receive time of its first frame; c_e applied and cycle mean, z̈_s, deflection, rotor
speed) and the road height at the tyre (``road/height``, buffered).  For each cycle
:class:`EstimatorLoop` predicts from t_{k-1} with the cycle-mean c_e and the road
w(t_{k-1}) → w(t_k), corrects with the measurements present (a lost frame's values are
NaN: that channel is left out, the cycle counted ``incomplete``; a lost status frame
holds the last applied c_e) in one compiled call
(:meth:`erva_ros.core.model.estimator.ExtendedKalmanFilter.cycle`), and counts gaps, restarts
and repeats in the node's report.

On the road grid (``stamp_on_road_grid``, what `erva run --ecu virtual` sets), a cycle's
stamp is the road's sample instant t_k at most 3Ts/4 before (Ts/4 after) its receive
time (:meth:`EstimatorLoop.stamp`): the simulated ECU samples on that grid and sends at
once, and the NMPC pairs each state with the road preview of the same t_k.  No ROS
inside: the node waits for the road sample of a cycle (Ts/4 at most) and publishes.
"""

import math
from typing import Optional, Tuple

import numpy as np

from erva_ros.core.contract import Measurements
from erva_ros.core.model.estimator import ExtendedKalmanFilter
from erva_ros.core.hil.latency import LatencyStats
from erva_ros.core.hil.road_buffer import RoadBuffer
from erva_ros.core.reports import EstimatorReport, Timing
from erva_ros.core.wire import NS

#: On the road grid, how long a cycle waits for its road sample w(t_k) (periods).
ROAD_WAIT_PERIODS = 0.25


class EstimatorLoop:
    """The EKF over the ECU's cycles, with the road grid and the report (module doc)."""

    def __init__(self, ekf: ExtendedKalmanFilter, ts: float, c_e0: float,
                 max_gap_periods: int, on_road_grid: bool, report: EstimatorReport):
        self.ekf = ekf
        self.ts = ts
        self.ts_ns = int(round(ts * NS))
        self.max_gap_periods = max_gap_periods
        self.on_road_grid = on_road_grid
        self.grid_ns: Optional[int] = None  # a road sample instant: the grid's phase
        self.road = RoadBuffer(max_extrapolation_s=ts)
        self.last_ns: Optional[int] = None  # stamp of the last published estimate
        self.u_now = c_e0                   # damping applied at the last stamp (Ns/m)
        self.nis_sum = 0.0
        self.report = report
        self.latency = LatencyStats()       # ecu/measurements received -> state published
        self.compute = LatencyStats()       # time spent in that callback
        self.lag_meas = LatencyStats()      # sample instant -> ecu/measurements received
        self.lag_state = LatencyStats()     # sample instant -> state published

    # -- the road ------------------------------------------------------------------------
    def add_road(self, stamp_ns: int, w: float) -> None:
        """Keep a road height w(t) stamped ``stamp_ns`` (the first one places the grid)."""
        if self.on_road_grid and self.grid_ns is None:
            self.grid_ns = stamp_ns
        self.road.add(stamp_ns / NS, w)

    def has_grid(self) -> bool:
        """Return True once the road's grid is known (or not needed)."""
        return not self.on_road_grid or self.grid_ns is not None

    def road_at(self, stamp_ns: int) -> bool:
        """Return True once the road sample of ``stamp_ns`` (or a later one) arrived."""
        latest = self.road.latest
        return latest is not None and latest[0] >= stamp_ns / NS - 1e-6

    # -- a cycle -------------------------------------------------------------------------
    def stamp(self, stamp: int) -> int:
        """Return the instant (ns) an ECU message received at ``stamp`` (ns) stands for.

        On the road grid: the road sample instant in the window [−Ts/4, 3Ts/4) around the
        CAN receive time.  The ECU samples on that grid and sends at once, so its frames
        arrive a fraction of a millisecond after the instant; the quarter period before
        it keeps the pairing right when the ECU gateway's clock is a little behind the
        road's host (docs/hil.md).  The first cycle comes when the ECU has just started
        on the first road sample, on a busy machine up to a period late: the instant
        before it, but not before the first road sample.
        """
        if self.grid_ns is None:
            return stamp
        if self.last_ns is None:
            return max(stamp - (stamp - self.grid_ns) % self.ts_ns, self.grid_ns)
        return stamp - ((stamp - self.grid_ns + self.ts_ns // 4) % self.ts_ns
                        - self.ts_ns // 4)

    def is_new(self, stamp_ns: int) -> bool:
        """Return True if a cycle stamped ``stamp_ns`` is after the last one (else counted)."""
        if self.last_ns is not None and stamp_ns <= self.last_ns:
            self.report.late_or_repeated += 1
            return False
        return True

    def step(self, stamp_ns: int, m: Measurements) -> np.ndarray:
        """Predict to ``stamp_ns`` and correct with the cycle ``m``; return the estimate x."""
        y = (m.c_e, m.c_e_mean, *m.sensors)
        if any(math.isnan(v) for v in y):   # a CAN frame of the cycle was lost
            self.report.incomplete += 1
        u_now, u_mean = m.c_e, m.c_e_mean
        if math.isnan(u_now):               # status frame lost: the last c_e held
            u_now = u_mean = self.u_now
        self.nis_sum += self._predict_correct(stamp_ns, u_now, u_mean, m.sensors)
        self.last_ns = stamp_ns
        self.report.updates += 1
        return self.ekf.x

    def _predict_correct(self, stamp_ns: int, u_now: float, u_mean: float, y) -> float:
        """Predict from the last estimate to ``stamp_ns`` and correct with y; return NIS."""
        t1 = stamp_ns / NS
        if len(self.road) == 0:
            self.report.no_road += 1
        elif self.road.latest[0] < t1 - 1e-6:   # w(t_k) not here yet: extrapolated
            self.report.road_extrapolated += 1
        w1 = self.road.height(t1)
        steps = 0 if self.last_ns is None else max(
            1, int(round((stamp_ns - self.last_ns) / self.ts_ns)))
        if steps == 1:                      # every cycle: one compiled call
            _, nis = self.ekf.cycle(y, u_mean, u_now, self.road.height(self.last_ns / NS), w1)
            self.u_now = u_now
            return nis
        if steps == 0 or steps > self.max_gap_periods:
            if steps:
                self.report.restarts += 1
            self.ekf.reset()
        else:
            self.report.gaps += 1
            t0 = self.last_ns / NS
            for i in range(steps):          # over a gap: the last applied damping held
                self.ekf.predict(u_mean if i == steps - 1 else self.u_now,
                                 self.road.height(t0 + i * self.ts),
                                 self.road.height(t0 + (i + 1) * self.ts))
        self.u_now = u_now
        return self.ekf.update(y, u_now, w1).nis

    def warm(self, encode) -> None:
        """Run a cycle's computation on scratch copies, so the due one finds warm caches.

        After ~Ts asleep, with the other processes of the loop on the same cores, the
        code and data are out of the CPU caches: the cycle then costs several times its
        warm time (the compiled EKF cycle 0.4 ms instead of 0.1 ms).
        """
        ekf = self.ekf
        x, p, k = ekf.x, ekf.P, ekf.k
        ekf.cycle((0.0, 0.0, 0.0), self.u_now, self.u_now, 0.0, 0.0)
        encode(self.last_ns or 0, ekf.x)
        ekf.x, ekf.P, ekf.k = x, p, k

    def timings(self, rx_ns: int, done_ns: int, stamp_ns: int, compute_s: float) -> None:
        """Record a cycle's latencies (receive -> published; on the grid: from t_k)."""
        self.latency.add((done_ns - rx_ns) * 1e-9)
        self.compute.add(compute_s)
        if self.grid_ns is not None:        # stamps are sample instants: the loop's chain
            self.lag_meas.add((rx_ns - stamp_ns) * 1e-9)
            self.lag_state.add((done_ns - stamp_ns) * 1e-9)

    def fill(self) -> Tuple[float, ...]:
        """Bring the report's figures up to date; return the estimate's std per state."""
        r = self.report
        r.nis_mean = self.nis_sum / max(r.updates, 1)
        std = self.ekf.std()
        r.std = {name: float(s) for name, s in zip(self.ekf.model.state_names, std)}
        r.latency_ms = Timing.of(self.latency.summary())
        r.compute_ms = Timing.of(self.compute.summary())
        r.sample_to_measurements_ms = Timing.of(self.lag_meas.summary())
        r.sample_to_state_ms = Timing.of(self.lag_state.summary())
        return tuple(std)


__all__ = ['ROAD_WAIT_PERIODS', 'EstimatorLoop']
