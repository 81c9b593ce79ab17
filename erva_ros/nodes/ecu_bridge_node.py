"""ecu_bridge_node: the NMPC's damping command onto the vehicle CAN bus, the ECU's sensors back.

A thin rclpy adapter around :class:`erva_ros.core.hil.bridge.BridgeCore` (no ROS inside):

* ``damping_cmd`` (JointTrajectory, joint c_e) → clamped to the generator's range,
  converted to a PWM duty (c_e = κ²/R, erva_ros/core/hil/hardware.py) and sent at once in
  an E2E-protected ERVA_CMD frame; a 4·Ts watchdog timer keeps the frames at Ts,
  follows the NMPC's plan while a command is late, and sends the safe passive c_e0
  with an ERROR diagnostic once no fresh command came for ``command_timeout_periods``.
  The watchdog and the CAN reception share one thread; ``damping_cmd`` is taken by a
  second one straight from its wait set (:class:`RealtimeSubscription`, subscriber
  node ``ecu_bridge_node_rt``); the executor only serves the periodic diagnostics.
* ECU frames (reader thread, E2E-checked) → ``ecu/damping_applied``,
  ``ecu/sprung_accel``, ``ecu/suspension``, ``ecu/generator`` (erva_ros/core/hil/topics.py),
  each published as soon as its frame arrived, all stamped with the CAN receive time
  of the ECU cycle's first frame; and the whole cycle once more in one message,
  ``ecu/measurements`` (the estimator's input: one callback per cycle), published
  when its last frame arrived, right after that frame's own topic (the estimator it
  wakes then does not compete with the bridge for the CPU).  A cycle that lost
  a frame is published with NaN for that frame's values when the next cycle's first
  frame arrives or Ts/2 after its first frame (the watchdog's Ts/4 check), whichever
  comes first.
* ``/diagnostics``: command link, CAN bus (E2E counters, losses, reconnects) and ECU
  heartbeat, with the bridge's added latency (p50/p99/max in ms) and, on the command
  link, ``sample_to_can_ms``: the command's sample instant (its stamp) → frame sent.
* A ``damping_cmd`` whose stamp is older than ``command_timeout_periods`` when it
  arrives is refused (``commands_stale``): e.g. commands DDS queued while a link between
  hosts was down must not be applied as fresh (clocks synchronised, docs/hil.md).

Bus loss never ends the node: it is reported and the bus re-opened every ``bus_retry_s``.
"""

import gc
import itertools
import sys
import threading
import time

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import AccelStamped
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from sensor_msgs.msg import JointState
from trajectory_msgs.msg import JointTrajectory

from erva_ros.core import topics
from erva_ros.ros import qos as ros_qos
from erva_ros.core.hil import topics as hil_topics
from erva_ros.core.hil.bridge import BridgeConfig, BridgeCore, EcuCycle, SensorFrame
from erva_ros.core.hil.codec import EcuCodec, Kind
from erva_ros.core.hil.latency import LatencyStats
from erva_ros.core.hil.settings import BRIDGE_DEFAULTS, BRIDGE_SPECS, hardware_of, TS_SPEC
from erva_ros.core.hil.transport import open_bus, parse_spec
from erva_ros.ros import diagnostics as diag
from erva_ros.ros.cdr import (CdrError, decode_joint_trajectory, encode_accel_stamped,
                              JointStateEncoder)
from erva_ros.ros.parameters import (declare, declare_all, declare_erva_params, declare_live,
                                     LIVE_DEFAULTS, loop_priority)
from erva_ros.ros.rt_subscription import RealtimeSubscription
from erva_ros.ros.runtime import run_node
from erva_ros.core.params import ParamError

#: Commands beyond this magnitude (Ns/m) are absurd (a unit error), not just out of range.
ABSURD_C_E = 1e6


def parse_command(data: bytes):
    """Return (stamp ns, plan Ns/m, time offsets s) of a serialized ``damping_cmd``.

    (None, None, None) for malformed CDR, other joints, no points, a point without
    exactly one position, or an absurd value (beyond :data:`ABSURD_C_E`, NaN, infinite).
    """
    try:
        stamp, names, points = decode_joint_trajectory(data)
    except CdrError:
        return None, None, None
    if names != [topics.DAMPING_JOINT] or not points:
        return None, None, None
    plan, offsets = [], []
    for positions, (sec, nsec) in points:
        if len(positions) != 1 or not abs(positions[0]) <= ABSURD_C_E:   # also NaN
            return None, None, None
        plan.append(positions[0])
        offsets.append((sec * 1_000_000_000 + nsec) * 1e-9)
    return stamp, plan, offsets


class EcuBridgeNode(Node):
    """Forward damping commands to the ECU over CAN and publish its sensor frames."""

    def __init__(self):
        super().__init__('ecu_bridge_node')
        self.params = declare_erva_params(self)
        self.ts = declare(self, 'ts', TS_SPEC, LIVE_DEFAULTS['ts'])
        # SCHED_FIFO once started (run_node, live/realtime.py): the node is on the loop.
        live = declare_live(self, ('realtime_priority', 'publisher_history_s'))
        self.realtime_priority = loop_priority(live)
        cfg = declare_all(self, BRIDGE_SPECS, BRIDGE_DEFAULTS)
        try:
            parse_spec(cfg['bus'])
            codec = EcuCodec(cfg['dbc_file'] or None)
        except (ValueError, FileNotFoundError) as exc:
            raise ParamError(str(exc)) from None
        self.hw = hardware_of(cfg)
        self.cfg = cfg
        self.core = BridgeCore(
            codec, self.hw,
            BridgeConfig(period_s=self.ts,
                         command_timeout_s=cfg['command_timeout_periods'] * self.ts,
                         sensor_timeout_s=cfg['sensor_timeout_periods'] * self.ts,
                         c_e_safe=self.params.c_e0, bus_retry_s=cfg['bus_retry_s'],
                         max_delta_counter=cfg['max_delta_counter']),
            lambda: open_bus(cfg['bus']))
        # Added latency (DDS / kernel receive time -> done) and, inside it, the node's own
        # processing (callback entry -> done): the rest is waiting to be scheduled.
        self.lat_cmd = LatencyStats()       # damping_cmd received -> CAN frame sent
        self.lag_cmd = LatencyStats()       # the command's sample instant -> frame sent
        self.proc_cmd = LatencyStats()
        self.lat_sensor = LatencyStats()    # CAN frame received -> its topic published
        self.proc_sensor = LatencyStats()
        self.rejected_msgs = 0

        # Counted (erva run checks the bag against them), with a history that lets a
        # stalled recorder catch up (publisher_history_s of the loop, at the ECU's rate).
        counted = diag.CountedPublisher
        pub_qos = ros_qos.publisher_qos(live['publisher_history_s'], self.ts)
        self.pub_accel = counted(self.create_publisher(AccelStamped,
                                                       hil_topics.ECU_SPRUNG_ACCEL, pub_qos))
        self.pub_susp = counted(self.create_publisher(JointState, hil_topics.ECU_SUSPENSION,
                                                      pub_qos))
        self.pub_gen = counted(self.create_publisher(JointState, hil_topics.ECU_GENERATOR,
                                                     pub_qos))
        self.pub_applied = counted(self.create_publisher(
            JointState, hil_topics.ECU_DAMPING_APPLIED, pub_qos))
        self.pub_meas = counted(self.create_publisher(JointState, hil_topics.ECU_MEASUREMENTS,
                                                      pub_qos))
        self.counted_publishers = [self.pub_meas, self.pub_applied, self.pub_accel,
                                   self.pub_susp, self.pub_gen]
        self._status_seq = itertools.count(1)   # next() is atomic: two threads publish
        self.pub_diag = self.create_publisher(DiagnosticArray, topics.DIAGNOSTICS,
                                              ros_qos.diagnostics_qos())
        self.enc_applied = JointStateEncoder(hil_topics.APPLIED_JOINTS)
        self.enc_susp = JointStateEncoder((hil_topics.SUSPENSION_JOINT,))
        self.enc_gen = JointStateEncoder((topics.GENERATOR_JOINT,))
        self.enc_meas = JointStateEncoder(hil_topics.MEASUREMENT_NAMES)
        # The command is on the loop's critical path: taken by its own thread, not the
        # executor (erva_ros/ros/rt_subscription.py; ~0.5 ms less per command).  Its queue
        # keeps as much as the NMPC's writer (publisher_history_s): after a stall of the
        # bridge or a link drop every command is taken and counted -- the old ones refused
        # as stale -- instead of a keep-last 10 dropping them unseen.
        self.cmd_sub = RealtimeSubscription(self, JointTrajectory, topics.DAMPING_CMD,
                                            pub_qos, self._on_command, raw=True)
        steady = Clock(clock_type=ClockType.STEADY_TIME)
        # The Ts/4 watchdog runs in the CAN thread (below), not as an rclpy timer: the
        # executor then wakes only for commands, and never holds the GIL while a CAN
        # frame waits to be published.
        self.create_timer(cfg['diagnostics_period_s'], self._publish_diagnostics, clock=steady)
        self._last_levels = None
        self._last_state = None

        if not self.core.open():
            self.get_logger().error(f'{cfg["bus"]}: {self.core.bus_error}; retrying every '
                                    f'{cfg["bus_retry_s"]:g} s')
        self._stop = threading.Event()
        self._reader = threading.Thread(target=self._can_loop, name='can', daemon=True)
        self._reader.start()
        self.cmd_sub.start()
        # Start-up objects (CasADi functions, messages, rclpy) are never garbage: keep the
        # collector from scanning them, so a collection cannot stall a cycle for ms.
        gc.freeze()
        lo, hi = self.hw.c_e_range
        self.get_logger().info(
            f'bus {cfg["bus"]}, Ts = {self.ts:g} s, c_e in [{lo:.0f}, {hi:.0f}] Ns/m, '
            f'safe c_e0 = {self.params.c_e0:g} Ns/m (duty '
            f'{self.hw.duty_from_c_e(self.params.c_e0):.3f}), timeout '
            f'{cfg["command_timeout_periods"]} periods')

    # -- ROS -> CAN --------------------------------------------------------------------
    def _on_command(self, data: bytes, info) -> None:
        t0 = time.perf_counter()
        stamp, plan, offsets = parse_command(data)
        if plan is None:
            self.rejected_msgs += 1
            self.core.watchdog.reject()
            return
        # The stamp is the sample the command was computed for (synchronised clocks
        # across hosts, docs/hil.md): a command delivered late, e.g. queued by DDS
        # while a link was down, is refused rather than applied as fresh.
        result = self.core.submit(plan, offsets=offsets,
                                  age_s=(info['received_timestamp'] - stamp) * 1e-9)
        if result in ('sent', 'clamped'):
            done = time.time_ns()
            self.lat_cmd.add((done - info['received_timestamp']) * 1e-9)
            self.lag_cmd.add((done - stamp) * 1e-9)
            self.proc_cmd.add(time.perf_counter() - t0)

    def _tick(self) -> None:
        self.core.tick()
        cyc = self.core.expire()                # a cycle that lost a frame: publish it
        if cyc is not None:
            self._publish_cycle(cyc)
        # An ERROR (or its end) is published at once, not at the next period.
        state = (self.core.command_state, self.core.bus_up, self.core.ecu_silent())
        if state != self._last_state:
            self._last_state = state
            self._publish_diagnostics()

    # -- CAN -> ROS --------------------------------------------------------------------
    def _can_loop(self) -> None:
        """CAN thread: publish each ECU frame as it arrives; run the watchdog every Ts/4."""
        period = self.ts / 4
        next_tick = time.monotonic()
        while not self._stop.is_set():
            now = time.monotonic()
            if now >= next_tick:
                self._tick()
                next_tick = max(next_tick + period, now)
                continue
            f = self.core.receive(timeout=next_tick - now)
            if f is not None:
                self._publish_frame(f)

    def _publish_frame(self, f: SensorFrame) -> None:
        """Publish one ECU frame at once, stamped with its ECU cycle's stamp."""
        t0 = time.perf_counter()
        done = None
        for cyc in f.cycles:                    # an older, incomplete cycle: first
            if cyc.stamp == f.stamp:
                done = cyc
            else:
                self._publish_cycle(cyc)
        stamp = int(round(f.stamp * 1e9))
        p = f.payload
        # Serialized here (erva_ros/ros/cdr.py): a fraction of rclpy's conversion cost.
        if f.kind is Kind.STATUS:
            self.pub_applied.publish(self.enc_applied.encode(
                stamp, (float(p.c_e_applied), float(p.c_e_mean))))
        elif f.kind is Kind.CHASSIS:
            self.pub_accel.publish(encode_accel_stamped(stamp, (0.0, 0.0,
                                                                float(p.sprung_accel))))
            self.pub_susp.publish(self.enc_susp.encode(stamp, (float(p.deflection),)))
        else:
            # The contract's generator topic is in stroke terms: v_gen = l·phi'.
            self.pub_gen.publish(self.enc_gen.encode(
                stamp, (), (float(p.speed * self.params.l),),
                (float(self.hw.force_from_current(p.current)),)))
        if done is not None:                    # the cycle this frame completed: last
            self._publish_cycle(done)
        self.lat_sensor.add(time.time() - f.rx_time)
        self.proc_sensor.add(time.perf_counter() - t0)

    def _publish_cycle(self, cyc: EcuCycle) -> None:
        """Publish one ECU cycle on ``ecu/measurements`` (NaN: that frame was lost)."""
        nan = float('nan')
        st = cyc.payloads.get(Kind.STATUS)
        ch = cyc.payloads.get(Kind.CHASSIS)
        gen = cyc.payloads.get(Kind.GENERATOR)
        values = ([float(st.c_e_applied), float(st.c_e_mean)] if st else [nan, nan]) + (
            [float(ch.sprung_accel), float(ch.deflection)] if ch else [nan, nan]) + (
            [float(gen.speed), float(self.hw.force_from_current(gen.current))]
            if gen else [nan, nan])
        self.pub_meas.publish(self.enc_meas.encode(int(round(cyc.stamp * 1e9)), values))

    # -- diagnostics -------------------------------------------------------------------
    def publish_status(self) -> None:
        """Publish the statuses now (the final counts, on shutdown: runtime.run_node)."""
        self._publish_diagnostics()

    def _publish_diagnostics(self) -> None:
        statuses = self.core.diagnostics(prefix=self.get_fully_qualified_name())
        lat = {}
        for name, stats in (('ros_to_can_ms', self.lat_cmd), ('can_to_ros_ms', self.lat_sensor),
                            ('ros_to_can_proc_ms', self.proc_cmd),
                            ('can_to_ros_proc_ms', self.proc_sensor),
                            ('sample_to_can_ms', self.lag_cmd)):
            lat.update(diag.flatten(name, stats.summary()))
        statuses[0].values.update({k: diag.format_value(v) for k, v in lat.items()
                                   if k.startswith(('ros_to_can', 'sample_to_can'))})
        statuses[0].values['messages_rejected'] = str(self.rejected_msgs)
        statuses[0].values['scheduling'] = getattr(self, 'scheduling', 'off')
        statuses[0].values.update({k: str(v) for k, v in
                                   diag.publisher_values(self.counted_publishers).items()})
        seq = str(next(self._status_seq))
        for s in statuses:
            s.values['status_seq'] = seq
        statuses[2].values.update({k: diag.format_value(v) for k, v in lat.items()
                                   if k.startswith('can_to_ros')})
        self.pub_diag.publish(diag.array_msg(self.get_clock().now().nanoseconds, [
            diag.status_msg(s.name, s.level, s.message, s.values, self.cfg['bus'])
            for s in statuses]))
        levels = [(s.level, s.message.split(':')[0]) for s in statuses]
        if levels != self._last_levels:
            for s in statuses:
                if s.level >= diag.ERROR:
                    self.get_logger().error(f'{s.name}: {s.message}')
            self._last_levels = levels

    def destroy_node(self):
        self._stop.set()
        try:
            self.cmd_sub.destroy()
        finally:
            if self._reader.is_alive():
                self._reader.join(timeout=1.0)
            self.core.close()
            super().destroy_node()


def main(args=None):
    # The CAN reader thread must not wait up to the default 5 ms for the GIL while the
    # executor thread runs a callback.
    sys.setswitchinterval(5e-4)
    return run_node('ecu_bridge_node', EcuBridgeNode, args)


if __name__ == '__main__':
    raise SystemExit(main())
