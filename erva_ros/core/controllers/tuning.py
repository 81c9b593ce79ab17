"""Live tuning: which controller settings may change while a controller runs, and the check.

A controls engineer changes weights and limits between runs and during them, as
ros2_control's controllers allow.  These settings (:data:`LIVE_KEYS`) take effect at the
next sample, without a new solver:

==============  ===========================================================================
alpha1, alpha2  the OCP's weights: parameters of the compiled solver (ocp.py, ``p``)
u_min, u_max    the input box: a parameter of the compiled real-time SQP (sqp.py); it must
                keep the passive damping c_e0 the controller was built with inside (the
                passive fallback, and the NMPC's terminal cost, are built on it)
use_preview     preview / preview_long: plan on the road preview, or predict the road as
                ``road_prediction`` says (no_preview's law: the same OCP, the road is its
                parameter); road_prediction too (hold or zero)
fallback        after a failed solve: the previous plan shifted, then c_e0; or c_e0 at once
time_budget_s   the real-time SQP's budget (what counts a solve late)
==============  ===========================================================================

Every other setting shapes the compiled solver (horizon, cost, collocation, iterations
are unrolled into it ...) or the loop's grid (ts, command_delay_s): docs/live.md says
why for each.  :func:`retuned` returns the settings after a change, checked as at
start-up (:func:`~erva_ros.core.controllers.settings.validate_settings`) and against the
running controller: a refused change raises one :class:`ParamError` line naming the key,
the value and the reason, and changes nothing.  :func:`parse_change` reads the
``T:key=value`` of `erva run --set` and `erva sim --set`; :class:`Schedule` applies such
changes at their sample in the offline loop.
"""

from dataclasses import asdict, dataclass
from typing import Any, Dict, List, Mapping, Optional, Sequence, Tuple

from erva_ros.core.controllers.settings import ControllerSettings, validate_settings
from erva_ros.core.settings.controller import NUMERIC_SPECS, SPECS
from erva_ros.core.model.params import ParamError
from erva_ros.core.settings.schemas import read_only_reason, SCHEMAS
from erva_ros.core.settings.specs import Flag, Integer, unknown_parameters

#: The controller settings that may change while it runs (module doc): their specs say so.
LIVE_KEYS = tuple(key for key, spec in SPECS.items() if spec.live)
#: The NMPC controllers (the weights, the preview switch and the budget are theirs).
NMPC_NAMES = ('no_preview', 'preview', 'preview_long')


@dataclass(frozen=True)
class Built:
    """What a running controller was built with, which its live settings must respect."""

    controller: str     # its law (make_controller's name)
    c_e0: float         # Ns/m, its passive damping (c_e0 clipped into the start's box)
    u_max: float        # Ns/m, the start's u_max (the IPOPT reference's rollout is sized for it)

    @classmethod
    def of(cls, settings: ControllerSettings, c_e0: float) -> 'Built':
        """Return what a controller built from ``settings`` and the device's ``c_e0`` has."""
        return cls(settings.controller, min(max(c_e0, settings.u_min), settings.u_max),
                   settings.u_max)


def not_live(key: str, live: Sequence[str]) -> ParamError:
    """Return the error of a change of ``key``, which is not one of ``live``: why not."""
    known = {k for schema in SCHEMAS.values() for k in schema.specs()}
    if key not in known:
        return unknown_parameters([key], known)
    return ParamError(f'parameter {key!r} is read-only while the controller runs: '
                      f'{read_only_reason(key)} (live: {", ".join(live)})')


def retuned(built: Built, settings: ControllerSettings, changes: Mapping[str, Any],
            lockstep: bool = False) -> ControllerSettings:
    """Return ``settings`` with ``changes`` applied, checked for the running controller.

    Raises :class:`ParamError` (one line, nothing changed) for a key that cannot change
    live, a value out of its range, a combination start-up would refuse (u_min < u_max,
    a nonzero weight), a box without the controller's passive damping, or a setting the
    controller does not have (the weights of skyhook, the preview of no_preview, the
    budget of the IPOPT reference or in lock-step, where time is simulated).
    """
    fixed = sorted(set(changes) - set(LIVE_KEYS))
    if fixed:
        raise not_live(fixed[0], LIVE_KEYS)
    name = built.controller
    solver = settings.solver if name in NMPC_NAMES else None
    for key, value in changes.items():
        SPECS[key].check(key, value)
        unchanged = value == getattr(settings, key)
        if unchanged:
            continue
        if key in ('alpha1', 'alpha2', 'use_preview', 'road_prediction', 'time_budget_s') \
                and name not in NMPC_NAMES:
            raise ParamError(f'parameter {key!r}: controller {name} has no '
                             f'{"weights" if key.startswith("alpha") else key} '
                             '(an NMPC setting)')
        if key == 'use_preview' and name == 'no_preview':
            raise ParamError('parameter \'use_preview\': controller no_preview never uses the '
                             'preview; start with controller preview to switch it live')
        if key == 'time_budget_s' and (lockstep or solver == 'ipopt'):
            why = ('lock-step has no wall-clock budget (time is simulated)' if lockstep
                   else 'the IPOPT reference has no budget')
            raise ParamError(f'parameter \'time_budget_s\': {why}')
    new = validate_settings(dict(asdict(settings), **changes))
    c_e0 = built.c_e0
    if not new.u_min <= c_e0 <= new.u_max:
        raise ParamError(f'parameters \'u_min\', \'u_max\' = [{new.u_min:g}, {new.u_max:g}] '
                         f'Ns/m must keep the passive damping c_e0 = {c_e0:g} Ns/m inside '
                         '(the fallback, and the NMPC\'s terminal cost, are built on it); '
                         'restart with that box to leave it out')
    if solver == 'ipopt' and new.u_max > built.u_max:
        raise ParamError(f'parameter \'u_max\' = {new.u_max:g}: the IPOPT reference\'s start '
                         f'rollout is stable up to the u_max it was built with '
                         f'({built.u_max:g} Ns/m); restart with the larger box')
    return new


class LiveSettings:
    """The settings a running controller uses, and a change staged for its next sample.

    :meth:`stage` checks a change (:func:`retuned`; a refused one raises and stages
    nothing) over what is in force or already staged; :meth:`apply`, at a sample
    boundary (before the sample's solve), hands the staged settings to the controller
    (:meth:`Controller.retune`).  nmpc_node stages what its parameter callback accepted;
    `erva sim --set` stages its schedule's changes at their samples: one path for both.
    """

    def __init__(self, controller, settings: ControllerSettings, c_e0: float,
                 lockstep: bool = False):
        self.controller = controller
        self.settings = settings
        self.built = Built.of(settings, c_e0)
        self.lockstep = lockstep
        self.staged: Optional[ControllerSettings] = None
        #: Sets of changes applied so far (0: the start's settings).
        self.applied = 0

    def stage(self, changes: Mapping[str, Any]) -> ControllerSettings:
        """Check ``changes`` and stage them for the next sample; return the staged settings."""
        self.staged = retuned(self.built, self.staged or self.settings, changes, self.lockstep)
        return self.staged

    def apply(self) -> bool:
        """At a sample boundary: put the staged settings in force; True if there were any."""
        if self.staged is None:
            return False
        self.settings, self.staged = self.staged, None
        self.controller.retune(self.settings)
        self.applied += 1
        return True

    def values(self) -> Dict[str, Any]:
        """Return the live settings in force, by name."""
        return {key: getattr(self.settings, key) for key in LIVE_KEYS}


def parse_value(key: str, text: str) -> Any:
    """Return the value of a live setting ``key`` written as text (``0.5``, ``true``, ``plan``)."""
    spec = SPECS.get(key)
    if spec is None or key not in LIVE_KEYS:
        raise not_live(key, LIVE_KEYS)
    if isinstance(spec, Flag):
        if text.lower() not in ('true', 'false'):
            raise ParamError(f'parameter {key!r} must be true or false, got {text!r}')
        return text.lower() == 'true'
    if key in NUMERIC_SPECS:
        try:
            value = (int if isinstance(spec, Integer) else float)(text)
        except ValueError:
            raise ParamError(f'parameter {key!r} must be a {spec.kind} in {spec.describe()}, '
                             f'got {text!r}') from None
        return spec.check(key, value)
    return spec.check(key, text)


def parse_change(text: str, keys: Sequence[str] = LIVE_KEYS,
                 parse=parse_value) -> Tuple[float, str, Any]:
    """Return (T, key, value) of ``T:key=value`` (T in s from the first sample, > 0).

    ``keys``: the names allowed; ``parse(key, text)`` converts the value.
    """
    head, sep, assignment = text.partition(':')
    key, eq, value = assignment.partition('=')
    try:
        t = float(head)
    except ValueError:
        t = -1.0
    if not sep or not eq or not key:
        raise ParamError(f'--set {text!r}: write T:key=value, e.g. 1.0:alpha1=0.5 (T in s '
                         'from the first sample)')
    if not 0 < t < float('inf'):
        raise ParamError(f'--set {text!r}: T must be a time in s after the first sample '
                         '(> 0; the start\'s values are the options\')')
    key = key.strip()
    if key not in keys:
        raise ParamError(f'--set {text!r}: {not_live(key, keys)}')
    return t, key, parse(key, value.strip())


def sample_of(t: float, ts: float) -> int:
    """Return the first sample k with k·Ts >= ``t`` (to a millionth of Ts)."""
    k = int(t / ts)
    return k if k * ts >= t - 1e-6 * ts else k + 1


class Schedule:
    """Changes of live settings at given samples: ``(T, key, value)``, in time order.

    :meth:`due` returns the changes for sample k (all with ``sample_of(T) <= k`` not yet
    given), one dict per sample: what `erva sim --set` applies before solving sample k,
    as nmpc_node does with `erva run --set` in lock-step.
    """

    def __init__(self, changes: Sequence[Tuple[float, str, Any]], ts: float):
        self.ts = ts
        self.pending: List[Tuple[int, str, Any]] = sorted(
            ((sample_of(t, ts), key, value) for t, key, value in changes),
            key=lambda c: c[0])

    def due(self, k: int) -> Optional[Dict[str, Any]]:
        """Return the changes due at sample ``k`` (None: none), in the order given."""
        out: Dict[str, Any] = {}
        while self.pending and self.pending[0][0] <= k:
            _, key, value = self.pending.pop(0)
            out[key] = value
        return out or None

    def samples(self) -> List[int]:
        """Return the samples at which changes are due (each once, in order)."""
        return sorted({k for k, _, _ in self.pending})


def grouped(changes: Sequence[Tuple[float, str, Any]], ts: float
            ) -> List[Tuple[int, Dict[str, Any]]]:
    """Return the changes grouped by their sample: [(k, {key: value})], in order."""
    schedule = Schedule(changes, ts)
    return [(k, schedule.due(k)) for k in schedule.samples()]


class ScheduledTuning:
    """`erva sim --set`: a schedule's changes staged and applied before their samples.

    :meth:`before_sample` is the offline loop's sample boundary
    (``simulate_closed_loop(before_sample=...)``); :attr:`sets` lists (first sample,
    values in force) for the segments.
    """

    def __init__(self, controller, settings: ControllerSettings, c_e0: float,
                 changes: Sequence[Tuple[float, str, Any]]):
        self.live = LiveSettings(controller, settings, c_e0)
        self.schedule = Schedule(changes, settings.ts)
        self.sets: List[Tuple[int, Dict[str, Any]]] = [(0, self.live.values())]

    def before_sample(self, k: int) -> None:
        """Apply the changes due at sample ``k`` (checked beforehand: check_schedule)."""
        due = self.schedule.due(k)
        if due:
            self.live.stage(due)
            self.live.apply()
            self.sets.append((k, self.live.values()))


def check_schedule(built: Built, settings: ControllerSettings,
                   changes: Sequence[Tuple[float, str, Any]], lockstep: bool = False
                   ) -> List[ControllerSettings]:
    """Check a whole schedule in order before anything runs; return the settings per step.

    A change that would be refused at its sample (u_min above the u_max in force then...)
    is refused here, with the time it was for.
    """
    out = []
    for k, step in grouped(changes, settings.ts):
        try:
            settings = retuned(built, settings, step, lockstep)
        except ParamError as exc:
            raise ParamError(f'--set at {k * settings.ts:g} s: {exc}') from None
        out.append(settings)
    return out


__all__ = ['LIVE_KEYS', 'NMPC_NAMES', 'Built', 'not_live', 'retuned', 'LiveSettings',
           'parse_value', 'parse_change', 'sample_of', 'Schedule', 'ScheduledTuning', 'grouped',
           'check_schedule']
