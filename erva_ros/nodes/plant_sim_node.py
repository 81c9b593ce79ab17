"""plant_sim_node: the ERVA quarter car (or the linear benchmark) simulated live.

A thin adapter around :class:`erva_ros.core.plant.PlantSimulator` (paper eq. (11), or
eq. (15) with ``model: benchmark``).  The plant moves along the road: each road
height w(t_{k+1}) from road_preview_node advances it one period Ts from t_k with
the damping u_k held (0.5 ms RK4 sub-steps, road linear in the step), then it
publishes the state at t_{k+1} and the chassis acceleration and generator outputs
at t_k (they depend on u_k).  u_k is chosen by
:class:`~erva_ros.core.loop.command_hold.CommandHold`: the command stamped t_k, else
the newest command's plan, else passive c_e0, each counted and reported.

Modes (parameter ``mode``):

* ``realtime``: the road node's 50 Hz wall-clock samples set the pace; u_k is
  decided when w(t_{k+1}) arrives, so a command later than that is late.
* ``lockstep``: this node publishes ``/clock``.  After the state at t_k it waits
  for the command stamped t_k (or ``lockstep_timeout_s`` of wall time), then
  publishes /clock t_{k+1}; the road node answers with w(t_{k+1}) and the loop
  repeats -- deterministic, and equal to the offline closed loop (`erva sim`).

Topics (erva_ros/core/topics.py): publishes state, sprung_accel, generator,
/diagnostics (and /clock); subscribes road/height and damping_cmd.  Being where the
commands are used, it also measures the loop as it sees it (realtime): state
published -> its command received (loop_latency_ms) and the command period jitter.
"""

import time

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import AccelStamped, PointStamped
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rosgraph_msgs.msg import Clock as ClockMsg
from sensor_msgs.msg import JointState
from trajectory_msgs.msg import JointTrajectory

from erva_ros.core import topics
from erva_ros.ros import qos as ros_qos
from erva_ros.ros import diagnostics as diag
from erva_ros.core.loop.command_hold import CommandHold
from erva_ros.ros.msgs import (accel_msg, clock_msg, generator_msg, parse_damping,
                               parse_road_height, s_to_ns, state_msg)
from erva_ros.ros.parameters import (declare_erva_params, declare_live, loop_priority,
                                     stamp_window)
from erva_ros.ros.runtime import run_node
from erva_ros.ros.time_master import readers_ready, Settling
from erva_ros.core.loop.timing import DurationStats, PeriodStats
from erva_ros.core.loop.validation import MessageRejected, Rejections
from erva_ros.core.plant import PlantSimulator

LIVE_PARAMETERS = ('mode', 'model', 'ts', 'duration_s', 'command_timeout_s',
                   'lockstep_timeout_s', 'wait_for_subscribers', 'wait_for_reader',
                   'start_delay_s', 'diagnostics_period_s', 'reject_log_period_s',
                   'max_stamp_lead_s', 'max_stamp_age_s', 'publisher_history_s',
                   'realtime_priority')


class PlantSimNode(Node):
    """Simulate the quarter car one control period per road sample."""

    def __init__(self):
        super().__init__('plant_sim_node')
        self.params = declare_erva_params(self)
        cfg = declare_live(self, LIVE_PARAMETERS)
        self.realtime_priority = loop_priority(cfg)    # applied by run_node once started
        self.cfg = cfg
        self.kind = cfg['model']
        self.lockstep = cfg['mode'] == 'lockstep'
        self.ts_ns = s_to_ns(cfg['ts'])
        self.n_steps = int(round(cfg['duration_s'] / cfg['ts']))
        self.plant = PlantSimulator(self.params, self.kind, cfg['ts'])
        self.hold = CommandHold(self.ts_ns, self.params.c_e0, s_to_ns(cfg['command_timeout_s']))
        # A road height or command stamped far from this node's clock is foreign or corrupt:
        # one from the future would otherwise make the plant integrate up to it, or hold
        # back every real command as "older".
        self.window = stamp_window(cfg, cfg['ts'], self.lockstep)
        self.steady = Clock(clock_type=ClockType.STEADY_TIME)

        self.k = None            # index of the current sample (state x_k published)
        self.t_ns = None         # stamp of sample k (ns)
        self.w_k = 0.0           # road height at t_k (m)
        self.u_k = None          # damping decided for [t_k, t_k + Ts) (Ns/m)
        self.sample = None       # plant outputs at t_k with u_k
        self.finished = False
        self.started = False
        self._settling = Settling(cfg['start_delay_s'])
        self._asked_since = 0.0   # when the loop was last asked to answer (/clock, state)
        self._last_height = time.monotonic()
        self.count = {'states': 0, 'clock': 0, 'late_commands': 0, 'road_gaps': 0,
                      'lockstep_timeouts': 0}
        self.rejections = Rejections(self.get_logger().warning, time.monotonic,
                                     cfg['reject_log_period_s'])
        self.road_latency = DurationStats()   # road sample time -> height received
        self.step_time = DurationStats()      # height received -> state published
        self.loop_latency = DurationStats()   # state published -> its command received
        self.cmd_period = PeriodStats(cfg['ts'])   # command arrivals |Δt - Ts|
        self._state_pub_ns = 0

        qos = ros_qos.control_qos()
        pub_qos = ros_qos.publisher_qos(cfg['publisher_history_s'], cfg['ts'])
        counted = diag.CountedPublisher
        self.pub_state = counted(self.create_publisher(JointState, topics.STATE, pub_qos))
        self.pub_accel = counted(self.create_publisher(AccelStamped, topics.SPRUNG_ACCEL,
                                                       pub_qos))
        self.pub_gen = counted(self.create_publisher(JointState, topics.GENERATOR, pub_qos))
        self.pub_diag = self.create_publisher(DiagnosticArray, topics.DIAGNOSTICS,
                                              ros_qos.diagnostics_qos())
        self.pub_clock = (counted(self.create_publisher(ClockMsg, topics.CLOCK, pub_qos))
                          if self.lockstep else None)
        self.status = diag.StatusReporter(
            self.get_fully_qualified_name(), f'plant:{self.kind}', self.pub_diag.publish,
            lambda: self.get_clock().now().nanoseconds, self._diag_values,
            publishers=[self.pub_state, self.pub_accel, self.pub_gen]
            + ([self.pub_clock] if self.pub_clock else []))
        self.sub_cmd = self.create_subscription(JointTrajectory, topics.DAMPING_CMD,
                                                self._on_command, qos)
        self.sub_height = self.create_subscription(PointStamped, topics.ROAD_HEIGHT,
                                                   self._on_height, qos)
        self.create_timer(cfg['diagnostics_period_s'], self._on_diag_timer, clock=self.steady)
        if self.lockstep:
            # Wall-clock timer: sim time stands still while the plant waits.
            self.create_timer(0.05, self._on_lockstep_timer, clock=self.steady)
        self.status.set(diag.OK, 'waiting for the road' if not self.lockstep
                        else 'waiting for the nodes before publishing /clock')
        self.get_logger().info(
            f'{self.kind} plant, {cfg["mode"]}, Ts = {cfg["ts"]:g} s, '
            f'{self.n_steps} steps ({cfg["duration_s"]:g} s)')

    # -- road samples drive the plant ---------------------------------------------------
    def _on_height(self, msg: PointStamped) -> None:
        rx_ns = time.time_ns()
        try:
            stamp, _, w = parse_road_height(msg)
            self.window.check('road height', stamp, self.get_clock().now().nanoseconds)
        except MessageRejected as exc:
            self.rejections.reject(topics.ROAD_HEIGHT, str(exc))
            return
        self._last_height = time.monotonic()
        if self.finished:
            return
        if not self.lockstep:
            self.road_latency.add((rx_ns - stamp) * 1e-9)
        if self.k is None:
            self.k, self.t_ns, self.w_k = 0, stamp, w
            self._publish_state()
            self.status.set(diag.OK, 'running')
            return
        steps, rest = divmod(stamp - self.t_ns, self.ts_ns)
        if steps <= 0 or rest != 0:
            why = 'not after' if steps <= 0 else 'off the Ts grid of'
            self.rejections.reject(topics.ROAD_HEIGHT, f'stamp {stamp} ns is {why} the '
                                   f'current sample {self.t_ns} ns')
            return
        if steps > 1:
            self.count['road_gaps'] += 1
        w0 = self.w_k
        for i in range(1, steps + 1):  # a skipped road sample: road linear across the gap
            self._advance(w0 + (w - w0) * i / steps)
            if self.finished:
                break
        self.step_time.add((time.time_ns() - rx_ns) * 1e-9)
        self.status.after_sample()

    def _advance(self, w_next: float) -> None:
        """Step the plant from t_k to t_{k+1}; publish x_{k+1} and the outputs at t_k."""
        if self.u_k is None:
            self._decide()
        t_k, u_k, sample = self.t_ns, self.u_k, self.sample
        self.plant.step(u_k, self.w_k, w_next)
        self.k += 1
        self.t_ns += self.ts_ns
        self.w_k, self.u_k, self.sample = w_next, None, None
        self._publish_state()
        self.pub_accel.publish(accel_msg(t_k, sample.sprung_accel))
        position, v_gen, _ = self.plant.generator(sample.x, u_k)
        self.pub_gen.publish(generator_msg(t_k, position, v_gen, u_k))
        if self.k >= self.n_steps:
            self.finished = True
            self.status.set(diag.OK, f'finished: {self.k} steps, '
                            f'{self.plant.harvested_j:.4g} J harvested')
            self.status.publish()

    def _decide(self) -> None:
        """Fix u_k for [t_k, t_k + Ts) from the command, its plan or passive c_e0."""
        self.u_k, source = self.hold.select(self.t_ns)
        self.sample = self.plant.sample(self.u_k, self.w_k)
        if source == 'command':
            self.status.set(diag.OK, 'running')
        elif source == 'plan':
            self.status.set(diag.WARN, 'command late: applying the previous plan')
        elif self.hold.stamp_ns is None:
            self.status.set(diag.WARN, 'no command yet: passive damping c_e0')
        else:
            self.status.set(diag.ERROR, 'no command and plan used up: passive damping c_e0')

    def _publish_state(self) -> None:
        self.pub_state.publish(state_msg(self.t_ns, self.plant.x, self.kind))
        self._state_pub_ns = time.time_ns()
        self.count['states'] += 1
        self._asked_since = time.monotonic()

    # -- commands ----------------------------------------------------------------------
    def _on_command(self, msg: JointTrajectory) -> None:
        rx_ns = time.time_ns()
        try:
            stamp, plan = parse_damping(msg, self.ts_ns)
            self.window.check('command', stamp, self.get_clock().now().nanoseconds)
        except MessageRejected as exc:
            self.rejections.reject(topics.DAMPING_CMD, str(exc))
            return
        if not self.lockstep and stamp == self.t_ns:
            # The loop as the plant sees it: its state out -> the command for it back.
            self.loop_latency.add((rx_ns - self._state_pub_ns) * 1e-9)
            self.cmd_period.mark(rx_ns * 1e-9)
        if self.t_ns is not None and stamp < self.t_ns:
            self.count['late_commands'] += 1  # its sample is already integrated
        self.hold.update(stamp, plan)
        if (self.lockstep and self.k is not None and not self.finished
                and self.u_k is None and stamp == self.t_ns):
            self._decide()
            self._tick_clock()

    # -- lock-step ---------------------------------------------------------------------
    def _tick_clock(self) -> None:
        """Publish /clock for the next sample (lock-step): the road node answers with w."""
        nxt = 0 if self.t_ns is None else self.t_ns + self.ts_ns
        self.pub_clock.publish(clock_msg(nxt))
        self.count['clock'] += 1
        self._asked_since = time.monotonic()

    def _on_lockstep_timer(self) -> None:
        if not self.started:
            if self._graph_ready():
                self.started = True
                self.status.set(diag.OK, 'running')
                self._tick_clock()
            return
        timeout = self.cfg['lockstep_timeout_s']
        if time.monotonic() - self._asked_since <= timeout:
            return
        if self.k is None:
            # /clock is volatile: a first tick out before the road node's reader matched
            # is gone for good, and the loop would wait forever.  Once more, counted.
            self.get_logger().warning(f'no road height for t = 0 within {timeout:g} s; '
                                      '/clock again')
        elif not self.finished and self.u_k is None:
            self.get_logger().warning(f'no command for t = {self.t_ns * 1e-9:.3f} s within '
                                      f'{timeout:g} s; stepping on')
            self._decide()
        else:
            return
        self.count['lockstep_timeouts'] += 1
        self._tick_clock()

    def _graph_ready(self) -> bool:
        """Return True once the loop's topics are matched and have settled (lock-step start)."""
        ready = (readers_ready(self, (self.pub_state,), self.cfg)
                 and self.sub_height.get_publisher_count() >= 1
                 and self.sub_cmd.get_publisher_count() >= 1)
        return self._settling.held(ready, time.monotonic())

    # -- diagnostics -------------------------------------------------------------------
    def _on_diag_timer(self) -> None:
        stalled = (self.k is not None and not self.finished and not self.lockstep
                   and time.monotonic() - self._last_height > 5 * self.cfg['ts'])
        if stalled:
            self.status.set(diag.WARN, 'no road height: plant stopped')
        self.status.on_timer(2 * self.cfg['ts'])

    def _diag_values(self):
        vals = {'mode': self.cfg['mode'], 'model': self.kind, 'steps': self.k or 0,
                'steps_total': self.n_steps, 'finished': self.finished,
                'sim_time_s': 0.0 if self.k is None else self.k * self.cfg['ts'],
                'harvested_j': self.plant.harvested_j,
                'acc_rms_continuous': self.plant.acc_rms_continuous(),
                'scheduling': getattr(self, 'scheduling', 'off')}
        vals.update({f'u_from_{s}': n for s, n in self.hold.counts.items()})
        vals.update(self.count)
        vals.update(diag.flatten('road_latency_ms', self.road_latency.summary()))
        vals.update(diag.flatten('step_ms', self.step_time.summary()))
        vals.update(diag.flatten('loop_latency_ms', self.loop_latency.summary()))
        vals.update(diag.flatten('cmd_jitter_ms', self.cmd_period.jitter.summary()))
        vals['out_of_order_commands'] = self.hold.out_of_order
        vals['rejected_road_height'] = self.rejections.counts.get(topics.ROAD_HEIGHT, 0)
        vals['rejected_damping_cmd'] = self.rejections.counts.get(topics.DAMPING_CMD, 0)
        return vals


def main(args=None) -> int:
    """Run plant_sim_node until shutdown."""
    return run_node('plant_sim_node', PlantSimNode, args)


if __name__ == '__main__':
    import sys
    sys.exit(main())
