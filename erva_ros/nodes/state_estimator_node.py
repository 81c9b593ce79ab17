"""state_estimator_node: the NMPC's state ``/erva/state`` from the ECU's sensors (HIL mode).

A thin adapter around :class:`erva_ros.core.loop.estimator_loop.EstimatorLoop` (an EKF on
the shared model, paper eq. (11)): one ``ecu/measurements`` message per ECU cycle from
ecu_bridge_node, plus ``road/height`` (the road at the tyre, buffered and interpolated),
give one estimate on ``state``, stamped with the cycle's instant (on the road's grid with
``stamp_on_road_grid``, which `erva run --ecu virtual` sets).  A malformed message, an
absurd value or a NaN that is not a whole frame's is rejected and counted
(:func:`erva_ros.core.contract.decode_measurements`), never reaching the filter.

``ecu/measurements`` is on the loop's critical path: it is taken by its own thread
straight from its wait set (:class:`~erva_ros.ros.rt_subscription.RealtimeSubscription`,
subscriber node ``state_estimator_node_rt``), and 4 ms before the next cycle is due that
thread runs the cycle's computation once on scratch copies, so the real one finds the
CPU caches warm.  The ECU samples and sends at t_k as the road node publishes w(t_k),
which the prediction needs: a cycle whose road sample is not there yet waits for it up
to Ts/4 (``road_waits``; ``road_extrapolated`` if in vain); before the first road sample
there is no grid, and such a cycle is not published if the wait is in vain
(``before_road``).
"""

import threading
import time

from geometry_msgs.msg import PointStamped
from sensor_msgs.msg import JointState

from erva_ros.core import contract, topics
from erva_ros.core.estimator import ExtendedKalmanFilter
from erva_ros.core.hil import topics as hil_topics
from erva_ros.core.hil.settings import noise_of
from erva_ros.core.levels import OK, WARN
from erva_ros.core.loop.estimator_loop import EstimatorLoop, ROAD_WAIT_PERIODS
from erva_ros.core.params import ERVA_SPECS, validate_erva
from erva_ros.core.reports import EstimatorReport
from erva_ros.ros import qos as ros_qos
from erva_ros.ros.loop_node import LoopNode
from erva_ros.ros.rt_subscription import RealtimeSubscription
from erva_ros.ros.runtime import run_node

#: Cache warming runs this long before the next ECU cycle is due (s).
WARM_LEAD_S = 0.004


class StateEstimatorNode(LoopNode):
    """Estimate the quarter car's state from the ECU's measurements with an EKF."""

    NAME = 'state_estimator_node'
    REPORT = EstimatorReport

    def __init__(self):
        super().__init__(self.NAME)
        p = self.p
        self.kind = p['model']
        params = validate_erva({k: p[k] for k in ERVA_SPECS})
        ekf = ExtendedKalmanFilter(params, self.kind, p['ts'], noise_of(p), u_max=p['u_max'])
        self.report.hardware_id = f'ekf:{self.kind}'
        self.loop = EstimatorLoop(ekf, p['ts'], params.c_e0, p['max_gap_periods'],
                                  p['stamp_on_road_grid'], self.report)
        self.pub_state = self.publisher(JointState, topics.STATE)
        # The road (executor thread) and the measurements (their own thread) share the
        # filter's inputs and counters: one lock (re-entrant: a cycle may publish a status).
        self.lock = threading.RLock()
        self.road_arrived = threading.Condition(self.lock)
        self.report.level, self.report.message = WARN, 'waiting for ECU measurements'
        self._estimating = False
        self.meas_sub = RealtimeSubscription(self, JointState, hil_topics.ECU_MEASUREMENTS,
                                             ros_qos.control_qos(), self._on_measurements,
                                             idle=self._warm, raw=True)
        self.warm_after_s = max(p['ts'] - WARM_LEAD_S, 0.5 * p['ts'])
        self.subscribe(PointStamped, topics.ROAD_HEIGHT, self._on_road)
        self.status_timer()
        self.get_logger().info(
            f'EKF on the {self.kind} model, Ts = {p["ts"]:g} s, {ekf.substeps} RK4 '
            f'sub-steps (stable to c_e = {p["u_max"]:g} Ns/m), noise {noise_of(p)}')

    def started(self) -> None:
        self.meas_sub.start()

    def _on_road(self, data: bytes, rx_ns: int) -> None:
        with self.lock:
            try:
                road = contract.decode_road_height(data, strict=True)
            except contract.MessageRejected:
                self.report.rejected += 1
                return
            self.loop.add_road(road.stamp_ns, road.height_m)
            self.road_arrived.notify_all()

    def _on_measurements(self, data: bytes, info) -> None:
        t0 = time.perf_counter()
        with self.lock:
            try:
                m = contract.decode_measurements(data)
            except contract.MessageRejected:
                self.report.rejected += 1
                return
            loop = self.loop
            if not loop.has_grid() and not self._wait_for_road(loop.has_grid):
                # No grid yet: a state stamped off it would make the NMPC take the wrong
                # grid and refuse every later state.  Not published.
                self.report.before_road += 1
                return
            stamp = loop.stamp(m.stamp_ns)
            if not loop.is_new(stamp):
                return
            if loop.grid_ns is not None and not loop.road_at(stamp):
                self._wait_for_road(lambda: loop.road_at(stamp))
            x = loop.step(stamp, m)
            self.pub_state.publish(contract.encode_state(stamp, x, self.kind))
            if not self._estimating:
                self._estimating = True
                self.status.set(OK, 'estimating')
            loop.timings(info['received_timestamp'], time.time_ns(), stamp,
                         time.perf_counter() - t0)
            self.meas_sub.idle_at = time.monotonic() + self.warm_after_s

    def _wait_for_road(self, arrived) -> bool:
        """Wait (lock released) up to ROAD_WAIT_PERIODS until ``arrived()``; counted."""
        self.report.road_waits += 1
        return self.road_arrived.wait_for(arrived, ROAD_WAIT_PERIODS * self.loop.ts)

    def _warm(self) -> None:
        with self.lock:
            self.loop.warm(lambda stamp, x: contract.encode_state(stamp, x, self.kind))

    def refresh_report(self) -> None:
        # Only the snapshot holds the lock: a long run's percentiles never delay a cycle.
        with self.lock:
            self.loop.fill()
        r = self.report
        if r.no_road and r.level == OK:
            r.level, r.message = WARN, 'no road height received: assuming w = 0'
        if r.before_road and not r.updates:
            r.level, r.message = WARN, 'no road height yet: measurements off its grid not used'

    def destroy_node(self):
        try:
            self.meas_sub.destroy()
        finally:
            super().destroy_node()


def main(args=None):
    """Run state_estimator_node until shutdown."""
    return run_node(StateEstimatorNode, args)


if __name__ == '__main__':
    raise SystemExit(main())
