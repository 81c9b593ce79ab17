"""ROS 2 side of ``erva ecu-sim`` (simulation only): the road in, the ground truth out.

The simulated ECU itself speaks only CAN.  As a simulator of the *vehicle* it also
needs the road at the tyre and, for evaluation, it exposes what a real vehicle
cannot: the true outputs and state.  This node, spun between ECU cycles in the same
process (single-threaded), subscribes ``road/height`` and publishes

* ``sprung_accel`` and ``generator`` with the contract of erva_ros/core/topics.py (as
  plant_sim_node does), so `erva run` computes comfort and power on the truth;
* ``ecu_sim/state`` (the true state) and ``/diagnostics`` (ECU counters, the samples
  published, and ``finished: true`` when a run with a duration ends).

With the road from ROS, the ECU's cycles fall on the road's sample grid (see
:meth:`EcuSimRos.start_time_ns`) and the ground truth is stamped with exactly those
instants, as plant_sim_node stamps its samples.  With a road known ahead
(:class:`~erva_ros.core.hil.road_buffer.KnownRoad`, the session's road) the messages only
place the grid and are checked against it (``road_mismatches``); the ECU then never
waits for them.  The status also reports the ECU's share of the loop's latency:
``sample_to_can_ms`` (sample instant t_k → its sensor frames sent) and
``sample_to_applied_ms`` (t_k → the first command of the cycle applied), its mode
changes (``mode_changes``: ``cycle:MODE:c_e``) and, with a command delay d > 0, the
timing model's figures: late commands, t_k → command received, the actuation instant's
lateness (erva_ros/core/hil/ecu_sim.py).
"""

import time
from typing import Callable, Optional, Tuple

from erva_ros.core import contract, topics
from erva_ros.core.levels import ERROR, OK, WARN
from erva_ros.core.reports import EcuSimReport, report_status, Timing
from erva_ros.core.wire import NS
from erva_ros.ros import qos as ros_qos
from erva_ros.core.hil import topics as hil_topics
from erva_ros.core.hil.ecu_sim import EcuSample, EcuSimCore
from erva_ros.core.model.hardware import GeneratorHardware
from erva_ros.core.hil.latency import LatencyStats
from erva_ros.core.hil.road_buffer import KnownRoad, RoadBuffer


class EcuSimRos:
    """The ``ecu_sim`` node with its own context and executor."""

    def __init__(self, namespace: str, hardware: GeneratorHardware,
                 diagnostics_period_s: float = 0.5, known_road: Optional[KnownRoad] = None,
                 ts: float = 0.02, publisher_history_s: float = 10.0, session_id: str = ''):
        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.signals import SignalHandlerOptions
        from diagnostic_msgs.msg import DiagnosticArray
        from geometry_msgs.msg import AccelStamped, PointStamped
        from sensor_msgs.msg import JointState
        from erva_ros.ros.loop_node import CountedPublisher

        self.hw = hardware
        self.scheduling = 'off'            # set by `erva ecu-sim` (ros/realtime.py)
        self.context = rclpy.Context()
        # Signals stay with `erva ecu-sim`, which stops the ECU loop cleanly.
        rclpy.init(args=[], context=self.context, signal_handler_options=SignalHandlerOptions.NO)
        self.node = rclpy.create_node('ecu_sim', namespace=namespace, context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        qos = ros_qos.control_qos()
        self.road = RoadBuffer(max_extrapolation_s=0.02)
        self.known_road = known_road
        self.lag_can = LatencyStats()        # sample instant -> sensor frames sent
        self.lag_applied = LatencyStats()    # sample instant -> first command applied
        self.start_lag_s: Optional[float] = None
        self.node.create_subscription(PointStamped, topics.ROAD_HEIGHT, self._on_road, qos,
                                      raw=True)
        # Counted (erva run checks the bag against them), with the loop's history depth.
        counted = CountedPublisher
        pub_qos = ros_qos.publisher_qos(publisher_history_s, ts)
        self.pub_accel = counted(self.node.create_publisher(AccelStamped, topics.SPRUNG_ACCEL,
                                                            pub_qos))
        self.pub_gen = counted(self.node.create_publisher(JointState, topics.GENERATOR,
                                                          pub_qos))
        self.pub_state = counted(self.node.create_publisher(JointState, hil_topics.TRUE_STATE,
                                                            pub_qos))
        self.pub_diag = self.node.create_publisher(DiagnosticArray, topics.DIAGNOSTICS,
                                                   ros_qos.diagnostics_qos())
        self.diag_period = diagnostics_period_s
        self._last_diag = 0.0
        self.name = self.node.get_fully_qualified_name()
        self.report = EcuSimReport(node=self.name, hardware_id='ecu_sim', session=session_id)
        self.first_road_ns: Optional[int] = None
        self._grid: Optional[Tuple[int, int]] = None    # (t0, Ts) in ns
        self.published = 0

    def _on_road(self, data: bytes) -> None:
        try:
            road = contract.decode_road_height(data, strict=True)
        except contract.MessageRejected:
            return      # an absurd or malformed height: the ECU ignores it
        stamp, w = road.stamp_ns, road.height_m
        if self.first_road_ns is None:
            self.first_road_ns = stamp
            if self.known_road is not None:
                self.known_road.anchor(stamp, road.distance_m)
        if self.known_road is not None:
            self.known_road.check(stamp, w)
        self.road.add(stamp / NS, w)

    def road_height(self, t: float) -> float:
        """Return w(t) (m) at epoch time t: the known road, else the received samples."""
        if self.known_road is not None:
            return self.known_road.height(t)
        return self.road.height(t)

    def wait_for_road(self, timeout_s: float, stop: Callable[[], bool]) -> bool:
        """Spin until the first road sample arrived; False on timeout or stop."""
        end = time.monotonic() + timeout_s
        while len(self.road) == 0 and time.monotonic() < end and not stop():
            self.executor.spin_once(timeout_sec=0.05)
        return len(self.road) > 0

    def start_time_ns(self, ts: float) -> int:
        """Return the ECU's t0 (epoch ns): the newest instant of the road's sample grid.

        The road node publishes w(t_k) at t_k = t_first + k·Ts.  Cycles on the same
        grid make the state of t_k (estimated from this ECU's sensors) meet the preview
        of t_k in the NMPC, as with plant_sim_node.  Call after :meth:`wait_for_road`;
        then wait with :meth:`spin_for` (and :meth:`wait_road_sample`).
        """
        ts_ns = int(round(ts * NS))
        now = time.time_ns()
        t0 = now - (now - self.first_road_ns) % ts_ns
        self._grid = (t0, ts_ns)
        return t0

    def spin_for(self, seconds: float) -> None:
        """Serve ROS callbacks for ``seconds`` (the ECU loop's wait between cycles)."""
        end = time.monotonic() + seconds
        while True:
            left = end - time.monotonic()
            if left <= 0:
                return
            self.executor.spin_once(timeout_sec=left)

    def wait_road_sample(self, t: float) -> None:
        """Serve callbacks until the road sample of epoch time ``t`` arrived, at most Ts/4.

        For a road that arrives sample by sample (no road known ahead): the plant must
        be driven by the road the estimator sees rather than an extrapolation, so the
        sensor frames go out that much later.
        """
        ts = self._grid[1] * 1e-9
        end = time.monotonic() + ts / 4
        while self.road.latest[0] < t - ts / 2 and time.monotonic() < end:
            self.executor.spin_once(timeout_sec=max(0.0, end - time.monotonic()))

    def publish(self, core: EcuSimCore, s: EcuSample) -> None:
        """Publish the ground truth of one ECU cycle (stamp = ECU sample time)."""
        if self._grid is None:
            stamp = int(round((core.t0 + s.t) * NS))
        else:   # exactly on the grid (epoch seconds as a float are 0.2 us coarse)
            t0, ts_ns = self._grid
            stamp = t0 + int(round(s.t * NS / ts_ns)) * ts_ns
        self.pub_accel.publish(contract.encode_accel(stamp, s.sprung_accel))
        self.pub_gen.publish(contract.encode_generator(stamp, s.gen_position, s.v_gen, s.c_e))
        self.pub_state.publish(contract.encode_state(stamp, s.x, core.plant.model.joints))
        self.published += 1
        t_k = core.t0 + s.t
        if s.sent_at is not None:
            if self.start_lag_s is None:    # the first sample: how late the ECU started
                self.start_lag_s = s.sent_at - t_k
            self.lag_can.add(s.sent_at - t_k)
        if s.command_latched is not None:    # the command for the sample one Ts earlier
            self.lag_applied.add(s.command_latched - (t_k - core.cfg.period_s))
        now = time.monotonic()
        if now - self._last_diag >= self.diag_period:
            self._last_diag = now
            self._diag(core, s, finished=False)

    def publish_final(self, core: EcuSimCore, limit_s: float = 5.0) -> None:
        """Publish the last status with ``finished: true`` and wait until it is delivered.

        Every subscriber (the recorder) acknowledges what this process published before it
        exits, bounded by ``limit_s``: an exiting publisher takes the rest with it.
        """
        from rclpy.duration import Duration
        self._diag(core, None, finished=True)
        self.spin_for(0.1)
        end = time.monotonic() + limit_s
        for pub in (self.pub_accel.publisher, self.pub_gen.publisher,
                    self.pub_state.publisher, self.pub_diag):
            left = end - time.monotonic()
            if left <= 0 or not pub.wait_for_all_acked(Duration(nanoseconds=int(left * 1e9))):
                break

    def _diag(self, core: EcuSimCore, s, finished: bool) -> None:
        r = self.report
        counts = core.summary()
        for key, n in counts.items():
            if not key.startswith('rx_'):
                setattr(r, key, n)
        r.rx = {k[3:]: n for k, n in counts.items() if k.startswith('rx_')}
        r.finished = r.final = finished
        r.ecu_mode = core.mode.name
        r.harvested_j = core.plant.harvested_j
        r.acc_rms_continuous = core.plant.acc_rms_continuous()
        r.samples_published = self.published
        r.scheduling = self.scheduling
        r.mode_changes = core.mode_changes()
        pubs = (self.pub_accel, self.pub_gen, self.pub_state)
        r.published = {p.topic: p.count for p in pubs}
        r.subscribers = {p.topic: p.get_subscription_count() for p in pubs}
        r.status_seq += 1
        if self.start_lag_s is not None:
            r.start_lag_ms = round(self.start_lag_s * 1e3, 3)
        r.sample_to_can_ms = Timing.of(self.lag_can.summary())
        r.sample_to_applied_ms = Timing.of(self.lag_applied.summary())
        r.command_delay_ms = core.cfg.command_delay_s * 1e3
        r.first_late_cycle = -1 if core.first_late_cycle is None else core.first_late_cycle
        r.command_arrival_ms = Timing.of(core.arrival.summary())
        r.arrival_p999_ms = core.arrival.quantile(0.999) * 1e3
        r.cmd_jitter_ms = Timing.of(core.command_period.jitter.summary())
        r.actuation_jitter_ms = Timing.of(core.actuation.summary())
        if self.known_road is not None:
            r.road_checked = self.known_road.checked
            r.road_mismatches = self.known_road.mismatches
        r.level = ERROR if core.bus is None else (
            OK if core.mode.name == 'CONTROLLED' else WARN)
        r.message = core.bus_error or f'ECU {core.mode.name}'
        self.pub_diag.publish(contract.encode_diagnostics(
            self.node.get_clock().now().nanoseconds, [report_status(r)]))

    def shutdown(self) -> None:
        import rclpy
        self.executor.shutdown()
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)
