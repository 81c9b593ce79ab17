"""state_estimator_node: the NMPC's state ``/erva/state`` from the ECU's sensors (HIL mode).

A thin adapter around :class:`erva_ros.core.loop.estimator_loop.EstimatorLoop` (an EKF on
the shared model, paper eq. (11)): one ``ecu/measurements`` message per ECU cycle from
ecu_bridge_node and, with ``road_at_tyre`` ``truth``, ``road/height`` (buffered,
interpolated) give one estimate on ``state`` stamped with the cycle's instant (on the
road's grid with ``stamp_on_road_grid``).  With ``estimated`` (docs/road.md) no road is
read: the RoadEKF estimates it (:mod:`erva_ros.core.loop.road_loop`), each cycle stamped with
its instant k·Ts (the real-ECU contract, docs/hil.md §8), and ``road/estimate`` carries
ŵ(t_k) and the odometry distance.
A malformed or absurd message is rejected and counted, never reaching the filter.

``ecu/measurements`` is taken by its own thread straight from its wait set
(:class:`~erva_ros.ros.rt_subscription.RealtimeSubscription`), which 4 ms before the next
cycle runs the cycle's computation on scratch copies (warm caches).  On the road grid a
cycle whose road sample is not there yet waits for it up to Ts/4 (``road_waits``).
A managed node (:class:`~erva_ros.ros.loop_node.LoopNode`): configure builds the filter.
"""

import threading
import time

from geometry_msgs.msg import PointStamped, PoseWithCovarianceStamped
from sensor_msgs.msg import JointState

from erva_ros.core import contract, topics
from erva_ros.core.model.estimator import ExtendedKalmanFilter
from erva_ros.core.hil import topics as hil_topics
from erva_ros.core.hil.settings import noise_of
from erva_ros.core.levels import OK, WARN
from erva_ros.core.loop.estimator_loop import EstimatorLoop, ROAD_WAIT_PERIODS
from erva_ros.core.model.quarter_car import make_model
from erva_ros.core.model.params import validate_erva
from erva_ros.core.settings.erva import ERVA_SPECS
from erva_ros.core.reports import EstimatorReport
from erva_ros.core.loop.road_loop import road_estimator_loop
from erva_ros.ros import qos as ros_qos
from erva_ros.ros.loop_node import LoopNode
from erva_ros.ros.rt_subscription import RealtimeSubscription
from erva_ros.ros.runtime import run_node

#: Cache warming runs this long before the next ECU cycle is due (s).
WARM_LEAD_S = 0.004


class StateEstimatorNode(LoopNode):
    """Estimate the quarter car's state (and with road_at_tyre estimated the road) with an EKF."""

    NAME = 'state_estimator_node'
    REPORT = EstimatorReport
    meas_sub = None

    def configure(self) -> None:
        p = self.p
        self.model = make_model(validate_erva({k: p[k] for k in ERVA_SPECS}), p['model'])
        self.estimated = p['road_at_tyre'] == 'estimated'
        if self.estimated:          # the road is a state: no road topic is read
            self.loop = road_estimator_loop(self.model, p, noise_of(p), self.report)
            self.pub_road = self.publisher(PoseWithCovarianceStamped, topics.ROAD_ESTIMATE)
        else:
            ekf = ExtendedKalmanFilter(self.model, p['ts'], noise_of(p), u_max=p['u_max'])
            self.loop = EstimatorLoop(ekf, p['ts'], self.model.params.c_e0,
                                      p['max_gap_periods'],
                                      p['stamp_on_road_grid'], self.report)
            self.subscribe(PointStamped, topics.ROAD_HEIGHT, self._on_road)
        self.report.hardware_id = (f'{"road_ekf" if self.estimated else "ekf"}:'
                                   f'{self.model.kind}')
        self.pub_state = self.publisher(JointState, topics.STATE)
        # The road (executor thread) and the measurements (their own thread) share the
        # filter's inputs and counters: one lock (re-entrant: a cycle may publish a status).
        self.lock = threading.RLock()
        self.road_arrived = threading.Condition(self.lock)
        self._estimating = False
        self.meas_sub = RealtimeSubscription(self, JointState, hil_topics.ECU_MEASUREMENTS,
                                             ros_qos.control_qos(), self._on_measurements,
                                             idle=self._warm, raw=True)
        self._built.append((self._drop_meas_sub, self.meas_sub))
        self.warm_after_s = max(p['ts'] - WARM_LEAD_S, 0.5 * p['ts'])
        self.status_timer()
        self.get_logger().info(
            f'{type(self.loop.ekf).__name__} on the {self.model.kind} model, road at the tyre '
            f'{p["road_at_tyre"]}, Ts = {p["ts"]:g} s, noise {noise_of(p)}')

    def activate(self) -> None:
        if not self.meas_sub.alive:
            self.meas_sub.start()
        self.status.set(WARN, 'waiting for ECU measurements')

    def deactivate(self) -> None:
        self.status.set(WARN, 'inactive: no state is published')

    def _drop_meas_sub(self, sub) -> None:
        self.meas_sub = None
        sub.destroy()

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
        if not self.active:
            return
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
            self.pub_state.publish(contract.encode_state(stamp, x, self.model.joints))
            if self.estimated:
                self.pub_road.publish(contract.encode_road_estimate(stamp,
                                                                    *loop.road_message()))
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
            self.loop.warm(lambda stamp, x: contract.encode_state(stamp, x, self.model.joints))

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
            if self.meas_sub is not None:
                self.meas_sub.destroy()
        finally:
            super().destroy_node()


def main(args=None):
    """Run state_estimator_node until shutdown."""
    return run_node(StateEstimatorNode, args)


if __name__ == '__main__':
    raise SystemExit(main())
