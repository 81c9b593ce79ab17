"""nmpc_node: the damping controller at 1/Ts (paper §III.A), publishing each command with its plan.

A thin adapter around the controller of :func:`erva_ros.core.controllers.make_controller`
(``controller``: preview, no_preview, preview_long, skyhook, passive) and
:class:`erva_ros.core.loop.control_loop.ControlLoop` (which sample to solve when, what
counts as late, the safe command without states).  For the state x(t_k) and the preview
stamped t_k it publishes ``damping_cmd``: points[0] = u_k, points[j] = the planned
u_{k+j} (Ns/m), stamped t_k; u_{k+j} acts at t_{k+j} + d (``command_delay_s``, which
the OCP models).  Then, with ``publish_prediction``, ``prediction``: the states, z̈_s
and power the plan predicts at t_k + j·Ts (core/loop/prediction.py).  ``realtime``: a
1/Ts wall-clock timer in phase with the state stamps; ``lockstep``: each state solved
once its preview is there, no budget.  Inputs are validated (core/contract.py).

Live parameters (`erva param set`; announced on /parameter_events): the weights, the box,
the preview switch, the fallbacks (core/controllers/tuning.py); checked and staged by the
core, they act from the next sample, the status with the new set going out at once.  In
lock-step the sample at ``lockstep_hold_s`` waits for a parameter request (`erva run --set`).
"""

import time

from sensor_msgs.msg import JointState
from trajectory_msgs.msg import JointTrajectory

from erva_ros.core import topics
from erva_ros.core.levels import ERROR, OK, WARN
from erva_ros.core.controllers.settings import validate_settings
from erva_ros.core.settings.controller import SPECS
from erva_ros.core.loop.control_loop import build_loop, HOLD_TIMEOUT_S, MessageRejected, Output
from erva_ros.core.loop.sample_schedule import Job
from erva_ros.core.timing import next_grid_delay_ns
from erva_ros.core.reports import NMPCReport
from erva_ros.ros.loop_node import LoopNode
from erva_ros.ros.runtime import run_node


class NMPCNode(LoopNode):
    """Compute the damping command of each sample and publish it with its plan."""

    NAME = 'nmpc_node'
    REPORT = NMPCReport

    def configure(self) -> None:
        self.lockstep = self.p['mode'] == 'lockstep'
        self.loop = build_loop(self.p, self.stamp_window(self.lockstep), self.report)
        self.report.hardware_id = f'controller:{self.loop.controller.name}'
        self.state_rx_ns = 0         # wall time the state being solved arrived
        self._tick_timer = self._align_timer = None
        self._held = None            # lock-step: (job, since) waiting for a parameter request
        self._resume = self.create_guard_condition(self._resume_held)
        self._built.append((self.destroy_guard_condition, self._resume))
        self.pub_cmd = self.publisher(JointTrajectory, topics.DAMPING_CMD)
        if self.loop.predictor is not None:
            self.pub_prediction = self.publisher(JointTrajectory, topics.PREDICTION)
        # Subscribed last: a subscriber seen by the road node means the controller is built.
        self.subscribe(JointTrajectory, topics.ROAD_PREVIEW, self._on_preview)
        self.subscribe(JointState, topics.STATE, self._on_state)
        self.status_timer(2 * self.loop.ts)
        self.get_logger().info(self.loop.describe)

    # -- lifecycle ---------------------------------------------------------------------
    def activate(self) -> None:
        self.loop.resume()
        self.status.set(OK, 'waiting for the first state')

    def deactivate(self) -> None:
        self.status.set(WARN, 'inactive: no command is published')

    # -- inputs ------------------------------------------------------------------------
    def _on_state(self, data: bytes, rx_ns: int) -> None:
        sched = self.loop.sched
        if sched.finished:
            return
        was_timed_out = sched.timed_out
        try:
            stamp_ns, job = self.loop.on_state(data, self.now_ns())
        except MessageRejected as exc:
            self.reject(topics.STATE, str(exc))
            return
        self.state_rx_ns = rx_ns
        if was_timed_out:
            self.loop.cmd_period.restart()
            self.get_logger().info('states are back: controller running again')
        if not self.lockstep and self._tick_timer is None and self._align_timer is None:
            # The 1/Ts tick timer in phase with the state stamps (ticks at t_k + m·Ts).
            delay = next_grid_delay_ns(time.time_ns(), stamp_ns, self.loop.ts_ns)
            self._align_timer = self.create_timer(delay * 1e-9, self._start_ticks)
        if job is not None:
            self._run(job)
        elif sched.finished:       # the last sample came late, its safe command stands
            self._finish()

    def _on_preview(self, data: bytes, rx_ns: int) -> None:
        try:
            job = self.loop.on_preview(data, self.now_ns())
        except MessageRejected as exc:
            self.reject(topics.ROAD_PREVIEW, str(exc))
            return
        if job is not None:
            self._run(job)

    # -- realtime scheduling -----------------------------------------------------------
    def _start_ticks(self) -> None:
        """Run at the first grid instant: start the periodic timer and act as its tick."""
        self._align_timer.cancel()
        self.destroy_timer(self._align_timer)
        self._tick_timer = self.timer(self.loop.ts, self._on_tick)
        self.loop.sched.armed = True   # the first tick is a period away: the next state is due

    def _on_tick(self) -> None:
        self.loop.tick(time.time_ns())
        job, safe = self.loop.sched.on_tick(self.now_ns())
        if job is not None:
            self._run(job)
        if safe is not None:
            outage = self.loop.new_outage()
            if outage:
                self.get_logger().error(outage)
            plan, text = self.loop.safe(safe)
            self.pub_cmd.publish(self.loop.command(safe, plan))
            self._announce()
            self.status.set(ERROR, text)

    # -- live parameters ---------------------------------------------------------------
    def on_parameters(self, values) -> None:
        if self.configured:       # checked and staged for the next sample (or ParamError)
            self.loop.stage(values)
        else:                     # configure builds with them: the same checks as then
            validate_settings({**{k: self.p[k] for k in SPECS},
                               **{k: v for k, v in values.items() if k in SPECS}})

    def parameters_set(self, names) -> None:
        if self._held is not None:       # a lock-step hold ends with the request
            self._resume.trigger()

    def _announce(self) -> None:
        """Say from when a new parameter set acts (its first command is out): log, status."""
        text = self.loop.announcement()
        if text:
            self.get_logger().info(text)
            self.status.publish()

    def _resume_held(self) -> None:
        if self._held is not None:
            job, self._held = self._held[0], None
            self._run(job)

    # -- solving -----------------------------------------------------------------------
    def _run(self, job: Job) -> None:
        """Solve one sample, publish its command with the plan, then its prediction."""
        if self.loop.holds(job):
            self._held = (job, time.monotonic())
            self.status.set(OK, f'lock-step: the sample at t = {self.loop.hold_s:g} s waits '
                            'for a parameter request')
            return
        out: Output = self.loop.solve(job)
        self.pub_cmd.publish(self.loop.command(out.stamp_ns, out.plan))
        self._announce()
        change = self.loop.published(out, time.time_ns(), self.state_rx_ns)
        if change is not None:
            self.status.set(*change)
        prediction = self.loop.prediction(job, out)     # off the command's path
        if prediction is not None:
            self.pub_prediction.publish(prediction)
        if self.loop.sched.finished:
            self._finish()
        self.status.after_sample()

    def _finish(self) -> None:
        """Stop after the scenario's last sample (duration_s): no timeout at the road's end."""
        if self._tick_timer is not None:
            self._tick_timer.cancel()
        self.status.set(OK, f'finished: {self.report.commands} commands')
        self.status.publish()

    # -- report ------------------------------------------------------------------------
    def on_status_timer(self, busy_window_s: float) -> None:
        if self._held is not None and time.monotonic() - self._held[1] > HOLD_TIMEOUT_S:
            self.get_logger().warning(self.loop.give_up_hold())
            self._resume_held()
        change = self.loop.periodic_status()
        if change is not None:
            self.status.set(*change)
        super().on_status_timer(busy_window_s)

    def refresh_report(self) -> None:
        self.loop.fill()
        self.report.rejected_state = self.rejected(topics.STATE)
        self.report.rejected_preview = self.rejected(topics.ROAD_PREVIEW)


def main(args=None) -> int:
    """Run nmpc_node until shutdown."""
    return run_node(NMPCNode, args)


if __name__ == '__main__':
    import sys
    sys.exit(main())
