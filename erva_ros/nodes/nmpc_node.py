"""nmpc_node: the damping controller at 1/Ts (paper §III.A), publishing each command with its plan.

A thin adapter around :func:`erva_ros.core.controllers.make_controller` (parameter
``controller``: preview, no_preview, preview_long, skyhook, passive; settings from
config/nmpc.yaml).  For the newest state x(t_k) and the preview stamped t_k it calls
``Controller.compute`` and publishes ``damping_cmd``: points[0] = u_k, points[j] =
the planned u_{k+j} (Ns/m), header.stamp = t_k, so the plant can fall back to the
plan if a later command is late.

Modes:

* ``realtime``: a wall-clock timer at 1/Ts, phase-aligned to the state stamps (it
  ticks at t_k + m·Ts).  Each tick takes the newest state and preview; if the state
  of this period has not arrived yet, the tick arms the node and the state is
  solved the moment it arrives (with its preview, which the road node publishes
  just after the height), so the state-to-command latency is the solve time plus
  message transport; at most one such early solve per tick keeps the rate at 1/Ts
  even if states come faster (the scheduling is
  :class:`erva_ros.core.loop.sample_schedule.SampleScheduler`, ROS-free).  A solve over
  ``time_budget_s`` still publishes its own plan -- the freshest answer there is --
  counted ``late`` and as a deadline miss, as is a command published later than
  t_k + Ts; a failed or non-finite solve publishes the controller's fallback
  (shifted plan, then passive).  After ``state_timeout_periods`` periods without a state, each tick
  publishes the safe passive command c_e0 (stamped with the sample time it is for,
  on the grid of the last state) and the status is ERROR until states return.
* ``lockstep``: solves each state as soon as the preview with the same stamp is
  there; the wall-clock budget is disabled (time is simulated) so the run is
  deterministic.

After the scenario's last sample (``duration_s``, by the state stamps *and* the node's
own clock) it stops and reports ``finished``, so the end of the road is not mistaken
for a lost plant.

Incoming states and previews are validated (erva_ros.core.loop.validation): a non-finite
or absurd value, or a stamp outside ``[now - max_stamp_age_s, now + max_stamp_lead_s]``
of the node's clock or off the sample grid, is rejected, counted and logged at a
limited rate, and never reaches the controller.  Timings and counters are published
on ``/diagnostics``.
"""

import time

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from sensor_msgs.msg import JointState
from trajectory_msgs.msg import JointTrajectory

from erva_ros.core import topics
from erva_ros.ros import qos as ros_qos
from erva_ros.core.controllers import make_controller
from erva_ros.core.controllers.settings import NUMERIC_SPECS
from erva_ros.ros import diagnostics as diag
from erva_ros.ros.msgs import damping_msg, parse_preview, parse_state, s_to_ns
from erva_ros.ros.parameters import (declare_controller_settings, declare_erva_params,
                                     declare_live, loop_priority, stamp_window)
from erva_ros.ros.runtime import run_node
from erva_ros.core.loop.sample_schedule import Job, SampleScheduler
from erva_ros.core.loop.timing import DurationStats, next_grid_delay_ns, PeriodStats
from erva_ros.core.loop.validation import MessageRejected, Rejections
from erva_ros.core.model import STATE_NAMES

LIVE_PARAMETERS = ('mode', 'model', 'duration_s', 'state_timeout_periods',
                   'diagnostics_period_s', 'reject_log_period_s', 'max_stamp_lead_s',
                   'max_stamp_age_s', 'publisher_history_s', 'realtime_priority')
#: How long (s) a deadline miss or fallback keeps the status at WARN.
WARN_HOLD_S = 1.0


class NMPCNode(Node):
    """Compute the damping command of each sample and publish it with its plan."""

    def __init__(self):
        super().__init__('nmpc_node')
        params = declare_erva_params(self)
        settings = declare_controller_settings(self)
        cfg = declare_live(self, LIVE_PARAMETERS)
        self.realtime_priority = loop_priority(cfg)    # applied by run_node once started
        self.cfg = cfg
        self.kind = cfg['model']
        self.lockstep = cfg['mode'] == 'lockstep'
        if self.lockstep:
            settings = settings.with_(time_budget_s=NUMERIC_SPECS['time_budget_s'].hi)
        self.settings = settings
        self.ts = settings.ts
        self.ts_ns = s_to_ns(settings.ts)
        self.controller = make_controller(settings.controller, params, settings, self.kind)
        self.n_preview = self.controller.horizon + 1
        self.passive_plan = np.full(self.controller.horizon, self.controller.c_e0)
        self._warm_up()

        self.sched = SampleScheduler(
            self.ts_ns, int(round(cfg['duration_s'] / self.ts)) + 1, self.n_preview,
            realtime=not self.lockstep, window=stamp_window(cfg, self.ts, self.lockstep),
            state_timeout_ns=s_to_ns(cfg['state_timeout_periods'] * self.ts))
        self.state_rx_ns = 0         # wall time the state being solved arrived
        self._warn_until = 0.0
        self._outages_logged = 0
        self._tick_timer = None
        self._align_timer = None
        self.count = {'commands': 0, 'solves': 0, 'late': 0, 'deadline_misses': 0,
                      'safe_commands': 0}
        self.solve = DurationStats()
        self.latency = DurationStats()      # sample time t_k -> command published
        self.rx_latency = DurationStats()   # state received -> command published
        self.cmd_period = PeriodStats(self.ts)
        self.tick_period = PeriodStats(self.ts)
        self.tick_phase = DurationStats()   # tick time after the sample grid t_k
        self.rejections = Rejections(self.get_logger().warning, time.monotonic,
                                     cfg['reject_log_period_s'])
        self.steady = Clock(clock_type=ClockType.STEADY_TIME)

        qos = ros_qos.control_qos()
        self.pub_cmd = diag.CountedPublisher(self.create_publisher(
            JointTrajectory, topics.DAMPING_CMD,
            ros_qos.publisher_qos(cfg['publisher_history_s'], self.ts)))
        self.pub_diag = self.create_publisher(DiagnosticArray, topics.DIAGNOSTICS,
                                              ros_qos.diagnostics_qos())
        self.status = diag.StatusReporter(
            self.get_fully_qualified_name(), f'controller:{self.controller.name}',
            self.pub_diag.publish, lambda: self.get_clock().now().nanoseconds,
            self._diag_values, publishers=[self.pub_cmd])
        # Subscribed last: a subscriber seen by the road node means the controller is built.
        self.create_subscription(JointTrajectory, topics.ROAD_PREVIEW, self._on_preview, qos)
        self.create_subscription(JointState, topics.STATE, self._on_state, qos)
        self.create_timer(cfg['diagnostics_period_s'], self._on_diag_timer, clock=self.steady)
        self.status.set(diag.OK, 'waiting for the first state')
        self.get_logger().info(
            f'{self.controller.name} on the {self.kind} model, {cfg["mode"]}, Ts = '
            f'{self.ts:g} s, horizon {self.controller.horizon}, weights '
            f'({settings.alpha1:g}, {settings.alpha2:g}), budget {settings.time_budget_s:g} s')

    def _warm_up(self) -> None:
        """Solve once at rest so the first real sample does not pay for first-call set-up."""
        self.controller.compute(np.zeros(len(STATE_NAMES[self.kind])),
                                np.zeros(self.n_preview), 0.0)
        self.controller.reset()

    def _now(self) -> int:
        """Return the node's clock (ns): wall time, or simulated time in lock-step."""
        return self.get_clock().now().nanoseconds

    # -- inputs ------------------------------------------------------------------------
    def _on_state(self, msg: JointState) -> None:
        rx_ns = time.time_ns()
        if self.sched.finished:
            return
        was_timed_out = self.sched.timed_out
        try:
            stamp, x = parse_state(msg, self.kind)
            job = self.sched.on_state(stamp, x, self._now())
        except MessageRejected as exc:
            self.rejections.reject(topics.STATE, str(exc))
            return
        self.state_rx_ns = rx_ns
        if was_timed_out:
            self.cmd_period.restart()
            self.get_logger().info('states are back: controller running again')
        if not self.lockstep and self._tick_timer is None and self._align_timer is None:
            self._align(stamp)
        if job is not None:
            self._run(job)
        elif self.sched.finished:       # the last sample came late, its safe command stands
            self._finish()

    def _on_preview(self, msg: JointTrajectory) -> None:
        try:
            stamp, heights = parse_preview(msg, self.ts_ns, self.n_preview)
            job = self.sched.on_preview(stamp, heights, self._now())
        except MessageRejected as exc:
            self.rejections.reject(topics.ROAD_PREVIEW, str(exc))
            return
        if job is not None:
            self._run(job)

    # -- realtime scheduling -----------------------------------------------------------
    def _align(self, stamp: int) -> None:
        """Start the 1/Ts tick timer in phase with the state stamps (ticks at t_k + m·Ts)."""
        delay = next_grid_delay_ns(time.time_ns(), stamp, self.ts_ns)
        self._align_timer = self.create_timer(delay * 1e-9, self._start_ticks)

    def _start_ticks(self) -> None:
        """Run at the first grid instant: start the periodic timer and act as its tick."""
        self._align_timer.cancel()
        self.destroy_timer(self._align_timer)
        self._tick_timer = self.create_timer(self.ts, self._on_tick)
        self.sched.armed = True   # the timer's first tick is a period away: the next state is due

    def _on_tick(self) -> None:
        now_ns = time.time_ns()
        self.tick_period.mark(now_ns * 1e-9)
        self.tick_phase.add(((now_ns - self.sched.first_stamp) % self.ts_ns) * 1e-9)
        job, safe = self.sched.on_tick(self._now())
        if job is not None:
            self._run(job)
        if safe is not None:
            self._publish_safe(safe)

    def _publish_safe(self, stamp: int) -> None:
        """Publish the passive command c_e0 (and its plan) with ERROR: no state is coming."""
        if self.sched.count['state_timeouts'] > self._outages_logged:
            self._outages_logged = self.sched.count['state_timeouts']
            self.get_logger().error(f'no state for {self.cfg["state_timeout_periods"]} '
                                    f'periods: publishing the passive command '
                                    f'{self.controller.c_e0:g} Ns/m')
        self.pub_cmd.publish(damping_msg(stamp, self.passive_plan, self.ts_ns))
        self.count['safe_commands'] += 1
        self.status.set(diag.ERROR, f'no state for more than '
                        f'{self.cfg["state_timeout_periods"]} periods: passive command')

    # -- solving -----------------------------------------------------------------------
    def _run(self, job: Job) -> None:
        """Solve one sample and publish its command with the plan."""
        stamp = job.stamp_ns
        if job.preview is None:
            plan, status, solve_s = self.passive_plan, 'no_preview', 0.0
        else:
            t = (stamp // self.ts_ns) * self.ts if self.lockstep else stamp * 1e-9
            res = self.controller.compute(job.x, job.preview, t)
            plan, status, solve_s = res.plan, res.status, res.solve_time_s
            self.count['solves'] += 1
        self.pub_cmd.publish(damping_msg(stamp, plan, self.ts_ns))
        pub_ns = time.time_ns()
        self.count['commands'] += 1
        self.solve.add(solve_s)
        # A late solve publishes its own plan (the freshest answer there is) and counts.
        missed = status == 'late'
        if not self.lockstep:
            self.cmd_period.mark(pub_ns * 1e-9)
            self.latency.add(max(0, pub_ns - stamp) * 1e-9)
            self.rx_latency.add((pub_ns - self.state_rx_ns) * 1e-9)
            missed = missed or pub_ns - stamp > self.ts_ns
        if status == 'late':
            self.count['late'] += 1
        if missed:
            self.count['deadline_misses'] += 1
        if missed or status != 'ok':
            self._warn_until = time.monotonic() + WARN_HOLD_S
            why = f'last {status}' + (', deadline missed' if missed else '')
            self.status.set(diag.WARN, why)
        elif not self.sched.timed_out and time.monotonic() > self._warn_until:
            self.status.set(diag.OK, 'running')
        if self.sched.finished:
            self._finish()
        self.status.after_sample()

    def _finish(self) -> None:
        """Stop after the scenario's last sample (duration_s): no timeout at the road's end."""
        if self._tick_timer is not None:
            self._tick_timer.cancel()
        self.status.set(diag.OK, f'finished: {self.count["commands"]} commands')
        self.status.publish()

    # -- diagnostics -------------------------------------------------------------------
    def _on_diag_timer(self) -> None:
        if (not self.sched.timed_out and not self.sched.finished
                and self.sched.state is not None and time.monotonic() > self._warn_until):
            self.status.set(diag.OK, 'running')
        self.status.on_timer(2 * self.ts)

    def _diag_values(self):
        vals = {'mode': self.cfg['mode'], 'controller': self.controller.name,
                'finished': self.sched.finished,
                'model': self.kind, 'horizon': self.controller.horizon,
                'time_budget_s': self.settings.time_budget_s,
                'scheduling': getattr(self, 'scheduling', 'off')}
        vals.update(self.count)
        vals.update(self.sched.count)
        vals.update(diag.flatten('solve_ms', self.solve.summary()))
        vals.update(diag.flatten('latency_ms', self.latency.summary()))
        vals.update(diag.flatten('rx_latency_ms', self.rx_latency.summary()))
        vals.update(diag.flatten('cmd_jitter_ms', self.cmd_period.jitter.summary()))
        vals.update(diag.flatten('tick_jitter_ms', self.tick_period.jitter.summary()))
        vals.update(diag.flatten('tick_phase_ms', self.tick_phase.summary()))
        vals.update({f'controller_{k}': v for k, v in self.controller.counters.items()})
        vals['rejected_state'] = self.rejections.counts.get(topics.STATE, 0)
        vals['rejected_preview'] = self.rejections.counts.get(topics.ROAD_PREVIEW, 0)
        return vals


def main(args=None) -> int:
    """Run nmpc_node until shutdown."""
    return run_node('nmpc_node', NMPCNode, args)


if __name__ == '__main__':
    import sys
    sys.exit(main())
