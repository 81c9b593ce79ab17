"""Validation of incoming messages: non-finite or absurd values never reach a controller or plant.

Every value a node receives is checked against :data:`LIMITS` before it is used.
A message that fails is dropped whole (no partial use), counted per topic, and
logged at most once per ``log_period_s`` per topic with the number suppressed since,
so a flood of bad messages cannot flood the log or slow the control loop.

The limits are *absurdity* bounds: values no quarter car on a road can produce
(a suspension state of a metre, a road step of a metre, a negative damping).  They
catch unit errors, corrupted or uninitialised messages and test injections; they are
not operating limits (the controller's input box [u_min, u_max] is).
"""

import math
from typing import Callable, Dict, Iterable, Optional

from erva_ros.core.settings.erva import ERVA_SPECS
from erva_ros.core.settings.specs import Number

#: Absurdity bounds of incoming values (SI units).
LIMITS: Dict[str, Number] = {
    'position': Number(-1.0, 1.0, 'm', 'displacement z_s, z_us, z_d (strut travel is ~0.2 m)'),
    'velocity': Number(-20.0, 20.0, 'm/s', 'velocity of z_s, z_us, z_d'),
    'road_height': Number(-1.0, 1.0, 'm', 'road height at the tyre'),
    'distance': Number(-1e9, 1e9, 'm', 'distance travelled'),
    'damping': Number(0.0, ERVA_SPECS['c_e0'].hi, 'Ns/m', 'electrical damping c_e'),
}


class MessageRejected(ValueError):
    """An incoming message is malformed or holds a non-finite or absurd value."""


def check_values(what: str, values: Iterable[float], limit: str) -> None:
    """Raise :class:`MessageRejected` unless every value is finite and inside LIMITS[limit]."""
    spec = LIMITS[limit]
    for i, v in enumerate(values):
        if not math.isfinite(v):
            raise MessageRejected(f'{what}[{i}] = {v} is not finite')
        if not spec.lo <= v <= spec.hi:
            raise MessageRejected(f'{what}[{i}] = {v:g} {spec.unit} is absurd '
                                  f'(allowed {spec.describe()})')


class StampWindow:
    """Reject stamps outside a window around the receiving node's own clock.

    A sample stamp is the instant the sample was taken, so in a working loop it lies
    slightly in the past of every node's clock.  A stamp from the far future (a foreign
    or corrupt message) would otherwise become "the newest" and block every real one
    behind it, or end a scenario early; one from long ago is useless to a controller.
    ``max_lead_ns`` allows clock skew between hosts and the NMPC's safe commands, which
    are stamped for the sample they stand in for (at most one period ahead);
    ``max_age_ns`` bounds how stale an input may be.
    """

    def __init__(self, max_lead_ns: int, max_age_ns: int):
        self.max_lead_ns = int(max_lead_ns)
        self.max_age_ns = int(max_age_ns)

    def check(self, what: str, stamp_ns: int, now_ns: int) -> None:
        """Raise :class:`MessageRejected` if ``stamp_ns`` is outside the window of ``now_ns``."""
        lead = stamp_ns - now_ns
        if lead > self.max_lead_ns:
            raise MessageRejected(f'{what} stamp is {lead * 1e-9:.3f} s in the future of this '
                                  f'node\'s clock (allowed {self.max_lead_ns * 1e-9:g} s; '
                                  f'clocks not synchronised?)')
        if -lead > self.max_age_ns:
            raise MessageRejected(f'{what} stamp is {-lead * 1e-9:.3f} s old '
                                  f'(allowed {self.max_age_ns * 1e-9:g} s)')


class Rejections:
    """Count rejected messages per topic and log them at a limited rate.

    ``log`` is called with one line, at most once per ``log_period_s`` per topic; the
    line says how many rejections of that topic were not logged since the last one.
    ``clock`` returns the current time in seconds (monotonic).
    """

    def __init__(self, log: Callable[[str], None], clock: Callable[[], float],
                 log_period_s: float = 1.0):
        self._log = log
        self._clock = clock
        self.log_period_s = float(log_period_s)
        self.counts: Dict[str, int] = {}
        self._last_log: Dict[str, float] = {}
        self._suppressed: Dict[str, int] = {}

    def reject(self, topic: str, reason: str) -> None:
        """Count one rejected message on ``topic``; log it unless logged too recently."""
        self.counts[topic] = self.counts.get(topic, 0) + 1
        now = self._clock()
        last: Optional[float] = self._last_log.get(topic)
        if last is not None and now - last < self.log_period_s:
            self._suppressed[topic] = self._suppressed.get(topic, 0) + 1
            return
        skipped = self._suppressed.pop(topic, 0)
        more = f'; {skipped} more not logged' if skipped else ''
        self._last_log[topic] = now
        self._log(f'rejected message on {topic}: {reason} '
                  f'({self.counts[topic]} rejected so far{more})')

    @property
    def total(self) -> int:
        """Return the number of rejected messages on all topics."""
        return sum(self.counts.values())


__all__ = ['LIMITS', 'MessageRejected', 'check_values', 'Rejections', 'StampWindow']
