"""plant_sim_node: the ERVA quarter car (or the linear benchmark) simulated live.

A thin adapter around :class:`erva_ros.core.loop.plant_loop.PlantLoop` (paper eq. (11)
or (15) on the shared model): each ``road/height`` sample steps it one period; it
publishes ``state`` at t_{k+1} and ``sprung_accel`` and ``generator`` at t_k.
``realtime``: the road's wall-clock samples set the pace (and the node measures the
loop as it sees it: state out -> command back, the command period jitter).
``lockstep``: it publishes ``/clock`` and waits for each sample's command (at most
``lockstep_timeout_s`` of wall time): deterministic, and equal to `erva sim`.  Each
command acts at its sample + ``command_delay_s`` (and must say so: the contract).
"""

import time

from geometry_msgs.msg import AccelStamped, PointStamped
from rosgraph_msgs.msg import Clock as ClockMsg
from sensor_msgs.msg import JointState
from trajectory_msgs.msg import JointTrajectory

from erva_ros.core import contract, topics
from erva_ros.core.levels import OK, WARN
from erva_ros.core.loop.plant_loop import PlantLoop
from erva_ros.core.loop.validation import MessageRejected
from erva_ros.core.model.quarter_car import make_model
from erva_ros.core.model.params import validate_erva
from erva_ros.core.settings.erva import ERVA_SPECS
from erva_ros.core.reports import PlantReport
from erva_ros.ros.loop_node import LoopNode
from erva_ros.ros.runtime import run_node
from erva_ros.ros.time_master import readers_ready, Settling


class PlantSimNode(LoopNode):
    """Simulate the quarter car one control period per road sample."""

    NAME = 'plant_sim_node'
    REPORT = PlantReport

    def configure(self) -> None:
        p = self.p
        model = make_model(validate_erva({k: p[k] for k in ERVA_SPECS}), p['model'])
        self.loop = PlantLoop(model, p, self.report)
        self.report.hardware_id = f'plant:{model.kind}'
        self.lockstep = self.loop.lockstep
        # A road height or command stamped far from this node's clock is foreign or corrupt:
        # one from the future would otherwise make the plant integrate up to it, or hold
        # back every real command as "older".
        self.window = self.stamp_window(self.lockstep)
        self.started_clock = False
        self._settling = Settling(p['start_delay_s'])
        self._asked_since = 0.0   # when the loop was last asked to answer (/clock, state)
        self._last_height = time.monotonic()
        self._state_pub_ns = 0
        self.pub_state = self.publisher(JointState, topics.STATE)
        self.pub_accel = self.publisher(AccelStamped, topics.SPRUNG_ACCEL)
        self.pub_gen = self.publisher(JointState, topics.GENERATOR)
        self.pub_clock = self.publisher(ClockMsg, topics.CLOCK) if self.lockstep else None
        self.sub_cmd = self.subscribe(JointTrajectory, topics.DAMPING_CMD, self._on_command)
        self.sub_height = self.subscribe(PointStamped, topics.ROAD_HEIGHT, self._on_height)
        self.status_timer(2 * p['ts'])
        if self.lockstep:   # wall-clock timer: sim time stands still while the plant waits
            self.timer(0.05, self._on_lockstep_timer, clock=self.steady)
        self.get_logger().info(f'{model.kind} plant, {p["mode"]}, Ts = {p["ts"]:g} s, '
                               f'd = {p["command_delay_s"]:g} s, {self.loop.n_steps} steps '
                               f'({p["duration_s"]:g} s)')

    def activate(self) -> None:
        if self.loop.k is None:
            self.status.set(OK, 'waiting for the nodes before publishing /clock'
                            if self.lockstep else 'waiting for the road')

    def _on_height(self, data: bytes, rx_ns: int) -> None:
        try:
            road = contract.decode_road_height(data, strict=True)
            self.window.check('road height', road.stamp_ns, self.now_ns())
            if self.loop.finished:
                return
            first = self.loop.k is None
            steps = self.loop.on_height(road.stamp_ns, road.height_m)
        except MessageRejected as exc:
            self.reject(topics.ROAD_HEIGHT, str(exc))
            return
        self._last_height = time.monotonic()
        if not self.lockstep:
            self.loop.road_latency.add((rx_ns - road.stamp_ns) * 1e-9)
        if first:
            self._publish_state(self.loop.t_ns, self.loop.plant.x)
            self.status.set(OK, 'running')
            return
        for s in steps:
            if s.decision is not None:
                self.status.set(*s.decision)
            self._publish_state(s.t_k + self.loop.ts_ns, s.x_next)
            self.pub_accel.publish(contract.encode_accel(s.t_k, s.sprung_accel))
            self.pub_gen.publish(contract.encode_generator(s.t_k, *s.generator, s.u_at_t_k))
        if self.loop.finished:
            self.status.set(OK, f'finished: {self.loop.k} steps, '
                            f'{self.loop.plant.harvested_j:.4g} J harvested')
            self.status.publish()
        self.loop.step_time.add((time.time_ns() - rx_ns) * 1e-9)
        self.status.after_sample()

    def _publish_state(self, stamp_ns: int, x) -> None:
        self.pub_state.publish(contract.encode_state(stamp_ns, x, self.loop.model.joints))
        self._state_pub_ns = time.time_ns()
        self.report.states += 1
        self._asked_since = time.monotonic()

    def _decide(self) -> None:
        self.status.set(*self.loop.decide())

    def _on_command(self, data: bytes, rx_ns: int) -> None:
        try:
            cmd = contract.decode_command(data, self.loop.ts_ns)
            self.window.check('command', cmd.stamp_ns, self.now_ns())
            contract.check_command_delay(cmd, self.loop.delay_ns)
        except MessageRejected as exc:
            self.reject(topics.DAMPING_CMD, str(exc))
            return
        if not self.lockstep and cmd.stamp_ns == self.loop.t_ns:
            # The loop as the plant sees it: its state out -> the command for it back.
            self.loop.loop_latency.add((rx_ns - self._state_pub_ns) * 1e-9)
            self.loop.cmd_period.mark(rx_ns * 1e-9)
        if self.loop.on_command(cmd.stamp_ns, cmd.plan, rx_ns):
            self._decide()
            self._tick_clock()

    # -- lock-step ---------------------------------------------------------------------
    def _tick_clock(self) -> None:
        """Publish /clock for the next sample (lock-step): the road node answers with w."""
        t = self.loop.t_ns
        self.pub_clock.publish(contract.encode_clock(0 if t is None else t + self.loop.ts_ns))
        self.report.clock += 1
        self._asked_since = time.monotonic()

    def _on_lockstep_timer(self) -> None:
        loop = self.loop
        if not self.started_clock:
            ready = (readers_ready(self, (self.pub_state,), self.p)
                     and self.sub_height.get_publisher_count() >= 1
                     and self.sub_cmd.get_publisher_count() >= 1)
            if self._settling.held(ready, time.monotonic()):
                self.started_clock = True
                self.status.set(OK, 'running')
                self._tick_clock()
            return
        timeout = self.p['lockstep_timeout_s']
        if time.monotonic() - self._asked_since <= timeout:
            return
        if loop.k is None:
            # /clock is volatile: a first tick out before the road node's reader matched
            # is gone for good, and the loop would wait forever.  Once more, counted.
            self.get_logger().warning(f'no road height for t = 0 within {timeout:g} s; '
                                      '/clock again')
        elif not loop.finished and loop.u_k is None:
            self.get_logger().warning(f'no command for t = {loop.t_ns * 1e-9:.3f} s within '
                                      f'{timeout:g} s; stepping on')
            self._decide()
        else:
            return
        self.report.lockstep_timeouts += 1
        self._tick_clock()

    def on_status_timer(self, busy_window_s: float) -> None:
        if (self.loop.k is not None and not self.loop.finished and not self.lockstep
                and time.monotonic() - self._last_height > 5 * self.p['ts']):
            self.status.set(WARN, 'no road height: plant stopped')
        super().on_status_timer(busy_window_s)

    def refresh_report(self) -> None:
        self.loop.fill()
        self.report.rejected_road_height = self.rejected(topics.ROAD_HEIGHT)
        self.report.rejected_damping_cmd = self.rejected(topics.DAMPING_CMD)


def main(args=None) -> int:
    """Run plant_sim_node until shutdown."""
    return run_node(PlantSimNode, args)


if __name__ == '__main__':
    import sys
    sys.exit(main())
