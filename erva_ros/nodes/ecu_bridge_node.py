"""ecu_bridge_node: the NMPC's damping command onto the vehicle CAN bus, the ECU's sensors back.

A thin adapter around :class:`erva_ros.core.hil.bridge.BridgeCore`: ``damping_cmd`` →
clamped, converted to a PWM duty and sent at once in an E2E-protected frame naming its
cycle (with the loop's ``command_delay_s`` d > 0 the ECU applies it at t_k + d, and the
plan goes out with it; a command made for another d is refused and counted); a Ts/4
watchdog keeps the frames at Ts, follows the plan while a command is late and sends the
safe passive c_e0 (ERROR) after ``command_timeout_periods`` (a command already that old
on arrival is refused as stale).  ECU frames → ``ecu/*`` topics as they arrive, and each
whole cycle on ``ecu/measurements`` (:class:`erva_ros.core.hil.messages.EcuMessages`).
Three reports: command link, CAN bus, ECU heartbeat, with the bridge's latencies.  The
command and the CAN reception each have their own thread; a lost bus is reported and
re-opened every ``bus_retry_s``, never ending the node.
"""

import sys
import threading
import time

from geometry_msgs.msg import AccelStamped
from sensor_msgs.msg import JointState
from trajectory_msgs.msg import JointTrajectory

from erva_ros.core import contract, topics
from erva_ros.core.hil import topics as hil_topics
from erva_ros.core.hil.bridge import BridgeCore, EcuCycle, SensorFrame
from erva_ros.core.hil.latency import LatencyStats
from erva_ros.core.hil.messages import EcuMessages
from erva_ros.core.levels import ERROR
from erva_ros.core.params import ERVA_SPECS, validate_erva
from erva_ros.core.reports import (BridgeBusReport, BridgeCommandReport, BridgeEcuReport,
                                   Timing)
from erva_ros.ros.loop_node import LoopNode
from erva_ros.ros.rt_subscription import RealtimeSubscription
from erva_ros.ros.runtime import run_node

#: Commands beyond this magnitude (Ns/m) are absurd (a unit error), not just out of range:
#: refused; those in it are clamped to the generator's range (counted).
ABSURD_C_E = 1e6


class EcuBridgeNode(LoopNode):
    """Forward damping commands to the ECU over CAN and publish its sensor frames."""

    NAME = 'ecu_bridge_node'
    REPORT = BridgeCommandReport

    def __init__(self):
        super().__init__(self.NAME)
        p = self.p
        self.params = validate_erva({k: p[k] for k in ERVA_SPECS})
        self.core = BridgeCore.from_parameters(p, self.params.c_e0)
        self.hw, ts = self.core.hw, p['ts']
        self.delay_ns = int(round(p['command_delay_s'] * 1e9))
        name = self.report.node
        self.report.node, self.report.hardware_id = f'{name}: command', p['bus']
        self.reports = (self.report,
                        BridgeBusReport(node=f'{name}: can bus', hardware_id=p['bus']),
                        BridgeEcuReport(node=f'{name}: ecu', hardware_id=p['bus']))
        self.status.extra = list(self.reports[1:])
        # Added latency (DDS / kernel receive time -> done) and, inside it, the node's own
        # processing (callback entry -> done): the rest is waiting to be scheduled.
        self.lat = {k: LatencyStats() for k in ('ros_to_can', 'sample_to_can',
                                                'ros_to_can_proc', 'can_to_ros',
                                                'can_to_ros_proc')}
        self.pub_meas = self.publisher(JointState, hil_topics.ECU_MEASUREMENTS)
        self.pubs = {t: self.publisher(AccelStamped if t == hil_topics.ECU_SPRUNG_ACCEL
                                       else JointState, t)
                     for t in (hil_topics.ECU_DAMPING_APPLIED, hil_topics.ECU_SPRUNG_ACCEL,
                               hil_topics.ECU_SUSPENSION, hil_topics.ECU_GENERATOR)}
        self.messages = EcuMessages(self.hw, self.params.l)
        # Its queue keeps as much as the NMPC's writer: after a stall or a link drop every
        # command is taken and counted (the old ones refused as stale).
        self.cmd_sub = RealtimeSubscription(self, JointTrajectory, topics.DAMPING_CMD,
                                            self.pub_meas.publisher.qos_profile,
                                            self._on_command, raw=True)
        self.status_timer()
        self._last_state = self._last_levels = None
        if not self.core.open():
            self.get_logger().error(f'{p["bus"]}: {self.core.bus_error}; retrying every '
                                    f'{p["bus_retry_s"]:g} s')
        self._stop = threading.Event()
        self._reader = threading.Thread(target=self._can_loop, name='can', daemon=True)
        lo, hi = self.hw.c_e_range
        self.get_logger().info(
            f'bus {p["bus"]}, Ts = {ts:g} s, c_e in [{lo:.0f}, {hi:.0f}] Ns/m, safe c_e0 = '
            f'{self.params.c_e0:g} Ns/m (duty {self.hw.duty_from_c_e(self.params.c_e0):.3f}), '
            f'timeout {p["command_timeout_periods"]} periods, commands act at t_k + d = '
            f'{p["command_delay_s"]:g} s')

    def started(self) -> None:
        self._reader.start()
        self.cmd_sub.start()

    # -- ROS -> CAN --------------------------------------------------------------------
    def _on_command(self, data: bytes, info) -> None:
        t0 = time.perf_counter()
        try:
            cmd = contract.decode_command(data)
            if not all(abs(v) <= ABSURD_C_E for v in cmd.plan):   # also NaN
                raise contract.MessageRejected('absurd c_e')
        except contract.MessageRejected:
            self.report.messages_rejected += 1
            self.core.watchdog.reject()
            return
        try:   # the ECU applies it at t_k + d: the d the OCP planned with must be ours
            contract.check_command_delay(cmd, self.delay_ns)
        except contract.MessageRejected as exc:
            self.core.watchdog.reject(wrong_delay=True)
            self.reject(topics.DAMPING_CMD, str(exc))
            return
        rx = info['received_timestamp']
        # The stamp is the sample the command was computed for (synchronised clocks
        # across hosts, docs/hil.md): a command delivered late is refused, not applied;
        # its cycle (CMD_CYCLE) tells the ECU when it acts.
        result = self.core.submit(cmd.plan, offsets=cmd.offsets_s,
                                  age_s=(rx - cmd.stamp_ns) * 1e-9, stamp_ns=cmd.stamp_ns)
        if result in ('sent', 'clamped'):
            done = time.time_ns()
            self.lat['ros_to_can'].add((done - rx) * 1e-9)
            self.lat['sample_to_can'].add((done - cmd.stamp_ns) * 1e-9)
            self.lat['ros_to_can_proc'].add(time.perf_counter() - t0)

    def _tick(self) -> None:
        self.core.tick()
        cyc = self.core.expire()                # a cycle that lost a frame: publish it
        if cyc is not None:
            self._publish_cycle(cyc)
        # An ERROR (or its end) is published at once, not at the next period.
        state = (self.core.command_state, self.core.bus_up, self.core.ecu_silent())
        if state != self._last_state:
            self._last_state = state
            self.status.publish()

    # -- CAN -> ROS --------------------------------------------------------------------
    def _can_loop(self) -> None:
        """CAN thread: publish each ECU frame as it arrives; run the watchdog every Ts/4."""
        period, next_tick = self.p['ts'] / 4, time.monotonic()
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
        for topic, data in self.messages.frame(f):
            self.pubs[topic].publish(data)
        if done is not None:                    # the cycle this frame completed: last
            self._publish_cycle(done)
        self.lat['can_to_ros'].add(time.time() - f.rx_time)
        self.lat['can_to_ros_proc'].add(time.perf_counter() - t0)

    def _publish_cycle(self, cyc: EcuCycle) -> None:
        """Publish one ECU cycle on ``ecu/measurements`` (NaN: that frame was lost)."""
        self.pub_meas.publish(self.messages.cycle(cyc))

    # -- report ------------------------------------------------------------------------
    def refresh_report(self) -> None:
        cmd, _, ecu = self.core.diagnostics(reports=self.reports)
        t = {k: Timing.of(v.summary()) for k, v in self.lat.items()}
        cmd.ros_to_can_ms, cmd.sample_to_can_ms = t['ros_to_can'], t['sample_to_can']
        cmd.ros_to_can_proc_ms = t['ros_to_can_proc']
        ecu.can_to_ros_ms, ecu.can_to_ros_proc_ms = t['can_to_ros'], t['can_to_ros_proc']
        levels = [(r.level, r.message.split(':')[0]) for r in self.reports]
        if levels != self._last_levels:
            for r in self.reports:
                if r.level >= ERROR:
                    self.get_logger().error(f'{r.node}: {r.message}')
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
    """Run ecu_bridge_node until shutdown."""
    # The CAN reader thread must not wait up to the default 5 ms for the GIL while the
    # executor thread runs a callback.
    sys.setswitchinterval(5e-4)
    return run_node(EcuBridgeNode, args)


if __name__ == '__main__':
    raise SystemExit(main())
