"""nmpc_node's core: solve each sample's job, count it, and say what the status should be.

The node feeds :class:`ControlLoop` the states, previews and timer ticks with its clock;
the :class:`~erva_ros.core.loop.sample_schedule.SampleScheduler` inside decides which
sample to solve when, :meth:`ControlLoop.solve` runs the controller and
:meth:`ControlLoop.published` counts what went out (late solves, deadline misses) and
returns the status the node should show.  Timings and counters go into the node's typed
report (:class:`~erva_ros.core.reports.NMPCReport`).  :meth:`ControlLoop.command` and
:meth:`ControlLoop.prediction` return the bytes of ``damping_cmd`` and of its companion
``prediction`` (core/loop/prediction.py), which the node publishes after the command.

Live tuning: :meth:`ControlLoop.stage` checks a parameter change the node accepted
(core/controllers/tuning.py for the controller's; ``state_timeout_periods`` for the
loop's) and stages it; it takes effect at the next sample boundary -- before the next
solve or safe command, never during one -- and the report says from which sample
(``parameter_set``, ``parameter_set_from_ns``, the ``live:`` values).  In lock-step
``lockstep_hold_s`` > 0 makes the sample at that time wait until a parameter request came
(`erva run --set`: the change then acts exactly from that sample, as in `erva sim --set`).
No ROS inside.
"""

from dataclasses import dataclass
import time
from typing import Any, Dict, Mapping, Optional, Tuple

import numpy as np

from erva_ros.core import contract
from erva_ros.core.controllers import make_controller
from erva_ros.core.controllers.settings import validate_settings
from erva_ros.core.controllers.tuning import LIVE_KEYS, LiveSettings, not_live, sample_of
from erva_ros.core.levels import ERROR, OK, WARN
from erva_ros.core.loop.prediction import PlanPredictor
from erva_ros.core.loop.validation import MessageRejected  # noqa: F401 (raised by on_*)
from erva_ros.core.loop.sample_schedule import Job, SampleScheduler
from erva_ros.core.timing import DurationStats, PeriodStats
from erva_ros.core.loop.validation import StampWindow
from erva_ros.core.model.params import validate_erva
from erva_ros.core.model.quarter_car import make_model
from erva_ros.core.settings.controller import NUMERIC_SPECS, SPECS
from erva_ros.core.settings.erva import ERVA_SPECS
from erva_ros.core.settings.loop import command_delay_ns
from erva_ros.core.settings.schemas import spec_of
from erva_ros.core.reports import format_value, NMPCReport, Timing
from erva_ros.core.wire import NS

#: How long (s) a deadline miss or fallback keeps the status at WARN.
WARN_HOLD_S = 1.0
#: Scheduler counters the report carries (core/loop/sample_schedule.py).
SCHEDULER_COUNTS = ('out_of_order', 'superseded_states', 'missed_samples', 'stale_previews',
                    'no_preview', 'state_timeouts')
#: The loop's own live parameters (besides the controller's, tuning.LIVE_KEYS).
LOOP_LIVE_KEYS = ('state_timeout_periods', 'lockstep_hold_s')
#: Every live parameter of nmpc_node.
NODE_LIVE_KEYS = LIVE_KEYS + LOOP_LIVE_KEYS
#: Wall time (s) a lock-step hold waits for its parameter request before it solves anyway
#: (counted ``hold_timeouts``): less than the plant's default lockstep_timeout_s (5 s).
HOLD_TIMEOUT_S = 2.0


@dataclass(frozen=True)
class Output:
    """A command to publish: its sample stamp and plan (plan[0] = c_e for t_k, Ns/m)."""

    stamp_ns: int
    plan: np.ndarray
    status: str            # the controller's: ok, late, fallback_plan, ..., or no_preview
    solve_s: float


def build_loop(p: Mapping[str, Any], window: StampWindow, report: NMPCReport) -> 'ControlLoop':
    """Return nmpc_node's loop from its parameters ``p`` (controller, model, predictor)."""
    settings = validate_settings({k: p[k] for k in SPECS})
    if p['mode'] == 'lockstep':    # simulated time: no wall-clock budget
        settings = settings.with_(time_budget_s=NUMERIC_SPECS['time_budget_s'].hi)
    model = make_model(validate_erva({k: p[k] for k in ERVA_SPECS}), p['model'])
    controller = make_controller(settings.controller, model, settings)
    loop = ControlLoop(controller, settings, p, window, report, model,
                       p['publish_prediction'])
    loop.hold_s = p['lockstep_hold_s']
    loop.warm_up(model.nx)
    loop.describe = (
        f'{controller.name} on the {p["model"]} model, {p["mode"]}, Ts = {settings.ts:g} '
        f's, d = {settings.command_delay_s:g} s, horizon {controller.horizon}, weights '
        f'({settings.alpha1:g}, {settings.alpha2:g}), budget {settings.time_budget_s:g} s'
        + (', publishing the prediction' if loop.predictor else ''))
    return loop


class ControlLoop:
    """Schedule, solve and count the NMPC's samples (see the module doc)."""

    def __init__(self, controller, settings, cfg: Mapping[str, Any], window: StampWindow,
                 report: NMPCReport, model, predict: bool = False):
        self.controller = controller
        self.ts = settings.ts
        self.ts_ns = int(round(settings.ts * NS))
        self.delay_ns = command_delay_ns(settings.command_delay_s)   # commands act at t_k + d
        #: The plan's trajectory on ``model`` after each command (None: not published).
        self.predictor = None if not predict else PlanPredictor(
            model, settings.ts, controller.horizon, settings.command_delay_s,
            controller.c_e0, settings.codegen)
        self.predict_time = DurationStats()
        self.lockstep = cfg['mode'] == 'lockstep'
        self.joints = model.joints          # the state's, as a state message names them
        self.describe = ''                  # what the node logs at start (build_loop)
        self.n_preview = controller.horizon + 1
        self.passive_plan = np.full(controller.horizon, controller.c_e0)
        self.sched = SampleScheduler(
            self.ts_ns, int(round(cfg['duration_s'] / self.ts)) + 1, self.n_preview,
            realtime=not self.lockstep, window=window,
            state_timeout_ns=int(round(cfg['state_timeout_periods'] * self.ts * NS)))
        self.timeout_periods = cfg['state_timeout_periods']
        self.report = report
        report.mode, report.controller = cfg['mode'], controller.name
        report.model, report.horizon = cfg['model'], controller.horizon
        report.time_budget_s = settings.time_budget_s
        self.solve_time = DurationStats()
        self.latency = DurationStats()      # sample time t_k -> command published
        self.rx_latency = DurationStats()   # state received -> command published
        self.cmd_period = PeriodStats(self.ts)
        self.tick_period = PeriodStats(self.ts)
        self.tick_phase = DurationStats()   # tick time after the sample grid t_k
        self._warn_until = 0.0
        self.outages_logged = 0
        #: Live tuning: the controller's settings in force and staged (tuning.LiveSettings),
        #: the loop's staged ones, and the lock-step hold.
        self.tuning = LiveSettings(controller, settings, controller.c_e0, self.lockstep)
        self._loop_staged = None            # {'state_timeout_periods': n} for the next sample
        self.hold_s = 0.0                   # lock-step: hold the sample at this time (0: never)
        self.requested = False              # a parameter request came since the last solve
        self._hold_passed: Optional[int] = None   # the hold's sample, once passed
        self._announce: Optional[str] = None
        self._fill_live()

    def warm_up(self, n_states: int) -> None:
        """Solve once at rest so the first real sample does not pay for first-call set-up."""
        self.controller.compute(np.zeros(n_states), np.zeros(self.n_preview), 0.0)
        self.controller.reset()

    def resume(self) -> None:
        """Start again after a deactivate (nothing to do before the first state)."""
        if self.sched.first_stamp is not None:
            self.sched.resume()
            self.controller.reset()                # its warm start is stale
            self.cmd_period.restart()

    # -- inputs (MessageRejected: a bad one never reaches a solve) ------------------------
    def on_state(self, data: bytes, now_ns: int) -> Tuple[int, Optional[Job]]:
        """Take a ``state`` message; return its stamp and the job to solve now, if any."""
        state = contract.decode_state(data, self.joints)
        return state.stamp_ns, self.sched.on_state(state.stamp_ns, state.x, now_ns)

    def on_preview(self, data: bytes, now_ns: int) -> Optional[Job]:
        """Take a ``road/preview`` message; return the job to solve now, if any."""
        preview = contract.decode_preview(data, self.ts_ns, self.n_preview)
        return self.sched.on_preview(preview.stamp_ns, preview.heights, now_ns)

    # -- live tuning -------------------------------------------------------------------
    def stage(self, changes: Mapping[str, Any]) -> None:
        """Check a parameter change and stage it for the next sample (ParamError: refused).

        All or nothing: a refused change stages nothing.  Any request that reaches this
        check, also one it refuses, releases a lock-step hold (the requester reports a
        refusal; `erva run --set` checks its changes before the run).
        """
        self.requested = True
        ctrl = {k: v for k, v in changes.items() if k in LIVE_KEYS}
        loop = {k: spec_of(k, 'nmpc_node').check(k, v) for k, v in changes.items()
                if k in LOOP_LIVE_KEYS}
        unknown = sorted(set(changes) - set(ctrl) - set(loop))
        if unknown:
            raise not_live(unknown[0], NODE_LIVE_KEYS)
        if ctrl:
            self.tuning.stage(ctrl)
        if 'state_timeout_periods' in loop:
            self._loop_staged = {'state_timeout_periods': loop['state_timeout_periods']}
        if 'lockstep_hold_s' in loop:          # when to hold: at once, not a setting
            self.hold_s = loop['lockstep_hold_s']

    def _hold_sample(self) -> Optional[int]:
        """Return the sample index ``lockstep_hold_s`` names (None: no hold, or passed)."""
        if not self.lockstep or self.hold_s <= 0:
            return None
        k = sample_of(self.hold_s, self.ts)
        return None if k == self._hold_passed else k

    def _index(self, stamp_ns: int) -> int:
        return (stamp_ns - self.sched.first_stamp) // self.ts_ns

    def holds(self, job: Job) -> bool:
        """Lock-step: return True if ``job`` waits for a parameter request (``lockstep_hold_s``).

        Once per hold: the first sample at or after its time, until a request came since
        the previous sample (also one that came before this sample arrived).
        """
        k = self._hold_sample()
        return k is not None and not self.requested and self._index(job.stamp_ns) >= k

    def give_up_hold(self) -> str:
        """Solve a held sample without its request (counted ``hold_timeouts``); say so."""
        self.requested = True
        self.report.hold_timeouts += 1
        return (f'no parameter request within {HOLD_TIMEOUT_S:g} s at t = {self.hold_s:g} s; '
                'solving on')

    def _boundary(self, stamp_ns: int) -> None:
        """Put staged changes in force: a sample boundary (before its solve or safe command)."""
        k = self._hold_sample()
        if k is not None and self._index(stamp_ns) >= k:
            self._hold_passed = k
        self.requested = False
        before = self._live_values()
        changed = self.tuning.apply()
        if self._loop_staged is not None:
            n = self._loop_staged['state_timeout_periods']
            self.timeout_periods = n
            self.sched.state_timeout_ns = int(round(n * self.ts * NS))
            self._loop_staged, changed = None, True
        if not changed:
            return
        after = self._live_values()
        r = self.report
        r.parameter_set += 1
        r.parameter_set_from_ns = stamp_ns
        self._fill_live()
        diff = ', '.join(f'{k} {after[k]} (was {before[k]})' for k in after
                         if after[k] != before[k]) or 'the same values'
        first = self.sched.first_stamp
        t = (stamp_ns - (stamp_ns if first is None else first)) * 1e-9
        self._announce = f'parameter set {r.parameter_set} from t = {t:.3f} s: {diff}'

    def announcement(self) -> Optional[str]:
        """Return (once) what a change that just took effect changed, for the log."""
        text, self._announce = self._announce, None
        return text

    def _live_values(self) -> Dict[str, Any]:
        return {**self.tuning.values(), 'state_timeout_periods': self.timeout_periods}

    def _fill_live(self) -> None:
        self.report.time_budget_s = self.tuning.settings.time_budget_s
        self.report.live = {k: format_value(v) for k, v in self._live_values().items()}

    # -- the sample's solve ------------------------------------------------------------
    def solve(self, job: Job) -> Output:
        """Run the controller on ``job`` (no preview: the passive plan).

        Changes staged before it take effect first (a sample boundary).
        """
        self._boundary(job.stamp_ns)
        if job.preview is None:
            return Output(job.stamp_ns, self.passive_plan, 'no_preview', 0.0)
        t = (job.stamp_ns // self.ts_ns) * self.ts if self.lockstep else job.stamp_ns * 1e-9
        res = self.controller.compute(job.x, job.preview, t)
        self.report.solves += 1
        return Output(job.stamp_ns, res.plan, res.status, res.solve_time_s)

    def command(self, stamp_ns: int, plan) -> bytes:
        """Return the ``damping_cmd`` of ``plan`` for ``stamp_ns`` (plan[j] at t_k + d + j·Ts)."""
        return contract.encode_command(stamp_ns, np.asarray(plan), self.ts_ns, self.delay_ns)

    def prediction(self, job: Job, out: Output) -> Optional[bytes]:
        """Return the ``prediction`` of a published command (None: none to publish).

        Every command is recorded (the damping it leaves acting); without a predictor or
        a preview (the road ahead unknown) nothing is predicted.
        """
        if self.predictor is None:
            return None
        if job.preview is None:
            self.predictor.commanded(out.stamp_ns, out.plan)
            return None
        t0 = time.perf_counter()
        p = self.predictor.sample(out.stamp_ns, job.x, out.plan, job.preview)
        data = contract.encode_prediction(out.stamp_ns, self.predictor.names, p.table(),
                                          self.ts_ns)
        self.predict_time.add(time.perf_counter() - t0)
        return data

    def published(self, out: Output, pub_ns: int, state_rx_ns: int
                  ) -> Optional[Tuple[int, str]]:
        """Count a command published at wall time ``pub_ns``; return the status to show.

        A late solve publishes its own plan (the freshest answer there is) and counts;
        in real time a command later than t_k + Ts is a deadline miss too.
        """
        r = self.report
        r.commands += 1
        self.solve_time.add(out.solve_s)
        missed = out.status == 'late'
        if not self.lockstep:
            self.cmd_period.mark(pub_ns * 1e-9)
            self.latency.add(max(0, pub_ns - out.stamp_ns) * 1e-9)
            self.rx_latency.add((pub_ns - state_rx_ns) * 1e-9)
            missed = missed or pub_ns - out.stamp_ns > self.ts_ns
        if out.status == 'late':
            r.late += 1
        if missed:
            r.deadline_misses += 1
        if missed or out.status != 'ok':
            self._warn_until = time.monotonic() + WARN_HOLD_S
            return WARN, f'last {out.status}' + (', deadline missed' if missed else '')
        if not self.sched.timed_out and time.monotonic() > self._warn_until:
            return OK, 'running'
        return None

    def safe(self, stamp_ns: int) -> Tuple[np.ndarray, str]:
        """Count a safe passive command for ``stamp_ns``; return its plan and ERROR text."""
        self._boundary(stamp_ns)
        self.report.safe_commands += 1
        if self.predictor is not None:
            self.predictor.commanded(stamp_ns, self.passive_plan)
        return self.passive_plan, (f'no state for more than {self.timeout_periods} periods: '
                                   'passive command')

    def new_outage(self) -> Optional[str]:
        """Return the text to log once per state outage (None: already logged)."""
        n = self.sched.count['state_timeouts']
        if n > self.outages_logged:
            self.outages_logged = n
            return (f'no state for {self.timeout_periods} periods: publishing the passive '
                    f'command {self.controller.c_e0:g} Ns/m')
        return None

    def tick(self, wall_ns: int) -> None:
        """Record a real-time tick at wall time ``wall_ns`` (its period and phase)."""
        self.tick_period.mark(wall_ns * 1e-9)
        self.tick_phase.add(((wall_ns - self.sched.first_stamp) % self.ts_ns) * 1e-9)

    def periodic_status(self) -> Optional[Tuple[int, str]]:
        """Return the status the period timer should restore (None: keep the current one)."""
        s = self.sched
        if (not s.timed_out and not s.finished and s.state is not None
                and time.monotonic() > self._warn_until):
            return OK, 'running'
        return None

    def fill(self) -> None:
        """Bring the report's counters and timings up to date."""
        r = self.report
        r.finished = self.sched.finished
        for key in SCHEDULER_COUNTS:
            setattr(r, key, self.sched.count[key])
        for key, n in self.controller.counters.items():
            setattr(r, f'controller_{key}', n)
        r.solve_ms = Timing.of(self.solve_time.summary())
        r.latency_ms = Timing.of(self.latency.summary())
        r.rx_latency_ms = Timing.of(self.rx_latency.summary())
        r.cmd_jitter_ms = Timing.of(self.cmd_period.jitter.summary())
        r.tick_jitter_ms = Timing.of(self.tick_period.jitter.summary())
        r.tick_phase_ms = Timing.of(self.tick_phase.summary())


__all__ = ['WARN_HOLD_S', 'SCHEDULER_COUNTS', 'LOOP_LIVE_KEYS', 'NODE_LIVE_KEYS',
           'HOLD_TIMEOUT_S', 'Output', 'build_loop', 'ControlLoop',
           'ERROR', 'MessageRejected']
