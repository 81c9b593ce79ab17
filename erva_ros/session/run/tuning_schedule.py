"""`erva run --set T:KEY=VALUE`: live parameter changes at sample times, through SetParameters.

What a user wants from a scheduled change: it acts from the sample at T (s after the
first), and it goes the way any other client's does -- the node's real
``set_parameters_atomically`` service, checked by the node, announced on
/parameter_events, recorded -- so a run with ``--set`` is a run with a change by hand,
only on time.

* Before anything starts (:func:`plan`), every change is parsed and checked in order as
  the node will check it (core/controllers/tuning.py): a bad one is one line, exit 2.
* Lock-step (:class:`ScheduledChanges`): nmpc_node holds the sample at T until a request
  came (``lockstep_hold_s``, the session params file has the first T); the session sends
  the request once it saw that sample's state -- published only after the command of
  the sample before -- with the next T as the new hold.  So the change acts from exactly
  the sample at T, as `erva sim --set` applies it: the same commands.
* Real time: the request goes out Ts/2 before the sample at T (wall clock, from the first
  state's stamp), so that it usually acts from that sample; the summary's segments say
  from which sample it did.

A refused change (the node's reason) or one without an answer is an error of the run.
"""

from dataclasses import dataclass, field
import time
from typing import Any, Dict, List, Optional, Sequence

from erva_ros.core.controllers.tuning import (Built, check_schedule, LIVE_KEYS, parse_change,
                                              parse_value, sample_of)
from erva_ros.core.loop.control_loop import NODE_LIVE_KEYS
from erva_ros.core.settings.schemas import spec_of
from erva_ros.core.model.params import ParamError

#: What `--set` may change: nmpc_node's live parameters but the hold itself.
RUN_KEYS = tuple(k for k in NODE_LIVE_KEYS if k != 'lockstep_hold_s')
#: Real time: a request due within this long (ns) is sent at its instant, the session's
#: loop (which polls every ~20 ms) waiting for it.
LOOKAHEAD_NS = 30_000_000


@dataclass
class Step:
    """The changes due at one sample, and what became of them."""

    k: int                              # the sample index
    t_s: float                          # its time after the first sample (k·Ts)
    changes: Dict[str, Any]
    sent_at: Optional[float] = None     # monotonic time the request went out
    future: Any = None
    accepted: Optional[bool] = None
    reason: str = ''
    request: Dict[str, Any] = field(default_factory=dict)


def _parse(key: str, text: str) -> Any:
    if key in LIVE_KEYS:
        return parse_value(key, text)
    spec = spec_of(key, 'nmpc_node')
    try:
        value = spec.python_type(text)
    except ValueError:
        raise ParamError(f'parameter {key!r} must be a {spec.kind} in {spec.describe()}, '
                         f'got {text!r}') from None
    return spec.check(key, value)


def plan(texts: Sequence[str], settings, c_e0: float, live: Dict[str, Any]) -> List[Step]:
    """Return the steps of ``--set`` options, checked in order (ParamError: one line)."""
    if not texts:
        return []
    for text in texts:
        if text.partition(':')[2].partition('=')[0].strip() == 'lockstep_hold_s':
            raise ParamError(f'--set {text!r}: lockstep_hold_s is the session\'s own (it '
                             'holds the sample of each --set in lock-step)')
    changes = [parse_change(t, RUN_KEYS, _parse) for t in texts]
    ts, duration = live['ts'], live['duration_s']
    for t, key, value in changes:
        if sample_of(t, ts) * ts >= duration:
            raise ParamError(f'--set {t:g}:{key}: the scenario ends at {duration:g} s '
                             '(--duration)')
    lockstep = live['mode'] == 'lockstep'
    check_schedule(Built.of(settings, c_e0), settings,
                   [c for c in changes if c[1] in LIVE_KEYS], lockstep)
    steps: Dict[int, Step] = {}
    for t, key, value in sorted(changes, key=lambda c: c[0]):
        k = sample_of(t, ts)
        steps.setdefault(k, Step(k, k * ts, {})).changes[key] = value
    return [steps[k] for k in sorted(steps)]


def first_hold_s(steps: Sequence[Step], live: Dict[str, Any]) -> float:
    """Return nmpc_node's ``lockstep_hold_s`` for a session: the first step's time (0: none)."""
    return steps[0].t_s if steps and live['mode'] == 'lockstep' else 0.0


class ScheduledChanges:
    """Send each step's request to ``node_name`` when its sample comes (see the module doc).

    ``client`` is a :class:`erva_ros.ros.param_client.RemoteParameters` of the node, its
    futures completed by the session's spin loop.
    """

    def __init__(self, steps: Sequence[Step], client, lockstep: bool, ts: float):
        self.steps = list(steps)
        self.client = client
        self.lockstep = lockstep
        self.ts_ns = int(round(ts * 1e9))
        self._next = 0

    def poll(self, first_stamp_ns: Optional[int], newest_state_ns: Optional[int]) -> None:
        """Send what is due, take what was answered (call it often while running)."""
        for step in self.steps[:self._next]:
            if step.accepted is None and step.future is not None and step.future.done():
                reason = _reason(step.future.result())
                step.accepted, step.reason = reason is None, reason or ''
        if self._next >= len(self.steps) or first_stamp_ns is None:
            return
        step = self.steps[self._next]
        due = first_stamp_ns + step.k * self.ts_ns
        if self.lockstep:
            if newest_state_ns is None or newest_state_ns < due or not self.client.ready():
                return
        else:
            # The session's loop comes by every ~20 ms: within reach, wait for the instant.
            left = due - self.ts_ns // 2 - time.time_ns()
            if left > LOOKAHEAD_NS or not self.client.ready():
                return
            if left > 0:
                time.sleep(left * 1e-9)
        step.request = dict(step.changes)
        if self.lockstep:          # the next hold, at once with this change
            after = self.steps[self._next + 1].t_s if self._next + 1 < len(self.steps) else 0.0
            step.request['lockstep_hold_s'] = after
        step.future = self.client.set(step.request)
        step.sent_at = time.monotonic()
        self._next += 1

    def errors(self, hold_timeouts: Optional[int] = 0) -> List[str]:
        """Return one line per change refused, unanswered or never sent, and per late hold.

        ``hold_timeouts``: lock-step samples nmpc_node solved without waiting any longer
        for their request (its report): those changes did not act from their sample.
        """
        out = []
        if hold_timeouts:
            out.append(f'{hold_timeouts} lock-step hold(s) of nmpc_node timed out: a --set '
                       'change acted later than its sample')
        for step in self.steps:
            what = ', '.join(f'{k}={v}' for k, v in step.changes.items())
            if step.accepted is False:
                out.append(f'--set {step.t_s:g}:{what} was refused: {step.reason}')
            elif step.sent_at is None:
                out.append(f'--set {step.t_s:g}:{what} was not sent (the run ended first)')
            elif step.accepted is None:
                out.append(f'--set {step.t_s:g}:{what}: no answer from nmpc_node')
        return out

    def results(self) -> List[Dict[str, Any]]:
        """Return each step's time, changes and outcome (the summary's ``tuning.set``)."""
        return [{'t_s': s.t_s, 'changes': dict(s.changes), 'accepted': s.accepted,
                 'reason': s.reason} for s in self.steps]


def _reason(response) -> Optional[str]:
    from erva_ros.ros.param_client import results_reason
    return results_reason(response.result)


__all__ = ['RUN_KEYS', 'LOOKAHEAD_NS', 'Step', 'plan', 'first_hold_s', 'ScheduledChanges']
