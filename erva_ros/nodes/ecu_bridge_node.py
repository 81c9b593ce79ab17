"""ecu_bridge_node: the NMPC's damping command onto the vehicle CAN bus, the ECU's sensors back.

A managed node around :class:`erva_ros.core.loop.bridge_loop.BridgeLoop`: ``damping_cmd``
→ clamped, converted to a PWM duty and sent at once in an E2E-protected frame naming its
cycle (with the loop's ``command_delay_s`` d > 0 the ECU applies it at t_k + d, and the
plan goes out with it; a command made for another d is refused and counted); a Ts/4
watchdog keeps the frames at Ts, follows the plan while a command is late and sends the
safe passive c_e0 (ERROR) after ``command_timeout_periods`` (a command already that old
on arrival is refused as stale).  ECU frames → ``ecu/*`` topics as they arrive, and each
whole cycle on ``ecu/measurements``.  Three reports: command link, CAN bus, ECU
heartbeat, with the bridge's latencies.  The command and the CAN reception each have
their own thread; a lost bus is reported and re-opened every ``bus_retry_s``.

Lifecycle (erva_ros/ros/loop_node.py): configure opens the bus; only while active does
the bridge take commands, send frames (the safe one too) and publish the ECU's frames.
Not active, it sends the ECU nothing: the ECU goes passive by its own rule (docs/hil.md
§8).  ``autostart`` (default true) configures and activates it at start-up.
"""

import sys

from geometry_msgs.msg import AccelStamped
from sensor_msgs.msg import JointState
from trajectory_msgs.msg import JointTrajectory

from erva_ros.core import topics
from erva_ros.core.hil import topics as hil_topics
from erva_ros.core.hil.bridge import BridgeCore
from erva_ros.core.loop.bridge_loop import BridgeLoop
from erva_ros.core.model.params import validate_erva
from erva_ros.core.settings.erva import ERVA_SPECS
from erva_ros.core.reports import BridgeBusReport, BridgeCommandReport, BridgeEcuReport
from erva_ros.ros.loop_node import LoopNode
from erva_ros.ros.rt_subscription import RealtimeSubscription
from erva_ros.ros.runtime import run_node

ECU_TOPICS = (hil_topics.ECU_DAMPING_APPLIED, hil_topics.ECU_SPRUNG_ACCEL,
              hil_topics.ECU_SUSPENSION, hil_topics.ECU_GENERATOR)


class EcuBridgeNode(LoopNode):
    """Forward damping commands to the ECU over CAN and publish its sensor frames."""

    NAME = 'ecu_bridge_node'
    REPORT = BridgeCommandReport

    bridge = cmd_sub = None

    def __init__(self):
        super().__init__()
        # A bus, DBC file or trace that cannot be used stops the node at start-up with one
        # line (as a value out of range), managed or not.
        BridgeCore.from_parameters(self.p, 0.0).close()
        # One name for its statuses in every state (the bag check looks for each name).
        self.report.node = f'{self.get_fully_qualified_name()}: command'
        self.report.hardware_id = self.p['bus']

    def configure(self) -> None:
        p = self.p
        params = validate_erva({k: p[k] for k in ERVA_SPECS})
        name = self.get_fully_qualified_name()
        self.reports = (self.report,
                        BridgeBusReport(node=f'{name}: can bus', hardware_id=p['bus']),
                        BridgeEcuReport(node=f'{name}: ecu', hardware_id=p['bus']))
        self.status.extra = list(self.reports[1:])
        self.pub_meas = self.publisher(JointState, hil_topics.ECU_MEASUREMENTS)
        pubs = {t: self.publisher(AccelStamped if t == hil_topics.ECU_SPRUNG_ACCEL
                                  else JointState, t) for t in ECU_TOPICS}
        self.bridge = BridgeLoop(p, params, lambda t, data: pubs[t].publish(data),
                                 self.pub_meas.publish, self.status.publish)
        # Its queue keeps as much as the NMPC's writer: after a stall or a link drop every
        # command is taken and counted (the old ones refused as stale).
        self.cmd_sub = RealtimeSubscription(self, JointTrajectory, topics.DAMPING_CMD,
                                            self.pub_meas.publisher.qos_profile,
                                            self._on_command, raw=True)
        self.status_timer()
        core, hw = self.bridge.core, self.bridge.hw
        if not core.open():
            self.get_logger().error(f'{p["bus"]}: {core.bus_error}; retrying every '
                                    f'{p["bus_retry_s"]:g} s')
        lo, hi = hw.c_e_range
        self.get_logger().info(
            f'bus {p["bus"]}, Ts = {p["ts"]:g} s, c_e in [{lo:.0f}, {hi:.0f}] Ns/m, safe c_e0 = '
            f'{params.c_e0:g} Ns/m (duty {hw.duty_from_c_e(params.c_e0):.3f}), timeout '
            f'{p["command_timeout_periods"]} periods, commands act at t_k + d = '
            f'{p["command_delay_s"]:g} s')

    # -- lifecycle ---------------------------------------------------------------------
    def activate(self) -> None:
        self.bridge.active = True
        self.bridge.start()           # (after the first activation's priority: inherited)
        if not self.cmd_sub.alive:
            self.cmd_sub.start()

    def deactivate(self) -> None:
        self.bridge.active = False

    def on_cleanup(self, state):
        self._close()
        return super().on_cleanup(state)

    def _close(self) -> None:
        try:
            if self.cmd_sub is not None:       # its thread ends before the bridge goes
                self.cmd_sub.destroy()
        finally:
            if self.bridge is not None:
                self.bridge.close()
            self.cmd_sub = self.bridge = None

    # -- ROS -> CAN --------------------------------------------------------------------
    def _on_command(self, data: bytes, info) -> None:
        why = self.bridge.take_command(data, info['received_timestamp'])
        if why is not None:
            self.reject(topics.DAMPING_CMD, why)

    # -- report ------------------------------------------------------------------------
    def refresh_report(self) -> None:
        for line in self.bridge.fill(self.reports):
            self.get_logger().error(line)

    def destroy_node(self):
        self._close()
        super().destroy_node()


def main(args=None):
    """Run ecu_bridge_node until shutdown."""
    # The CAN reader thread must not wait up to the default 5 ms for the GIL while the
    # executor thread runs a callback.
    sys.setswitchinterval(5e-4)
    return run_node(EcuBridgeNode, args)


if __name__ == '__main__':
    raise SystemExit(main())
