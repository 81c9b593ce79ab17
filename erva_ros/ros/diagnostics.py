"""Node status on ``/diagnostics`` (diagnostic_msgs/DiagnosticArray), as diagnostic_updater does.

Each node owns one :class:`StatusReporter`: it publishes the node's status (level,
one-line message, counters and timings as key/value strings) about every
diagnostics period and at once whenever the level or message changes, so an ERROR
is visible within one message latency rather than at the next period.

While the control loop runs, the periodic status (percentiles over thousands of
samples) is built in the slack right after the node's work for a sample, never
between a sample's arrival and its result: the period timer only marks it due
(:meth:`StatusReporter.on_timer`) and the node calls
:meth:`StatusReporter.after_sample`.  When no samples flow, the timer publishes.
"""

import math
import time
from typing import Any, Callable, Dict, Optional, Sequence, Tuple

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

from erva_ros.core.levels import ERROR, LEVEL_NAMES, OK, STALE, WARN
from erva_ros.ros.msgs import ns_to_time


def format_value(value: Any) -> str:
    """Return ``value`` as diagnostic text (floats with 9 significant digits)."""
    if isinstance(value, bool):
        return 'true' if value else 'false'
    if isinstance(value, float):
        return f'{value:.9g}' if math.isfinite(value) else str(value)
    return str(value)


def status_msg(name: str, level: int, message: str, values: Dict[str, Any],
               hardware_id: str = '') -> DiagnosticStatus:
    """Return a DiagnosticStatus with ``values`` as key/value strings (:func:`format_value`)."""
    return DiagnosticStatus(level=bytes([level]), name=name, message=message,
                            hardware_id=hardware_id,
                            values=[KeyValue(key=k, value=format_value(v))
                                    for k, v in values.items()])


def array_msg(stamp_ns: int, statuses: Sequence[DiagnosticStatus]) -> DiagnosticArray:
    """Return a DiagnosticArray of ``statuses`` stamped ``stamp_ns``."""
    arr = DiagnosticArray(status=list(statuses))
    arr.header.stamp = ns_to_time(stamp_ns)
    return arr


def parse_status(status: DiagnosticStatus) -> Tuple[str, int, str, Dict[str, str]]:
    """Return (name, level, message, values) of a DiagnosticStatus."""
    level = status.level
    level = level[0] if isinstance(level, (bytes, bytearray)) else int(level)
    return status.name, int(level), status.message, {kv.key: kv.value for kv in status.values}


def value_float(text: Optional[str]) -> float:
    """Return a diagnostic value (a string, or None when absent) as a float; NaN if none."""
    try:
        return float(text)
    except (TypeError, ValueError):
        return math.nan


def value_int(text: Optional[str]) -> Optional[int]:
    """Return a diagnostic counter as an int; None when absent or not a number."""
    value = value_float(text)
    return int(value) if math.isfinite(value) else None


def flatten(prefix: str, stats: Dict[str, Any]) -> Dict[str, Any]:
    """Return ``{prefix_key: value}`` for a stats dict (e.g. solve_ms_p99)."""
    return {f'{prefix}_{k}': v for k, v in stats.items()}


class CountedPublisher:
    """A publisher that counts what it published, for the session's loss accounting.

    ``erva run`` compares, per topic, what every node says it published with what the
    recorder and the bag hold; the node's status carries ``published:<topic>`` and the
    subscriptions its writer has matched, ``subscribers:<topic>`` (the start gate).
    """

    def __init__(self, publisher):
        self.publisher = publisher
        self.topic = publisher.topic_name
        self.count = 0

    def publish(self, msg) -> None:
        """Publish ``msg`` (a message or its CDR bytes) and count it."""
        self.publisher.publish(msg)
        self.count += 1

    def get_subscription_count(self) -> int:
        """Return the subscriptions this writer has matched."""
        return self.publisher.get_subscription_count()


def publisher_values(publishers: Sequence[CountedPublisher]) -> Dict[str, int]:
    """Return ``published:<topic>`` and ``subscribers:<topic>`` of each counted publisher."""
    out: Dict[str, int] = {}
    for pub in publishers:
        out[f'published:{pub.topic}'] = pub.count
        out[f'subscribers:{pub.topic}'] = pub.get_subscription_count()
    return out


class StatusReporter:
    """Publish a node's status periodically and immediately on a level or message change.

    ``values`` is called at every publication and returns the current counters and
    timings; ``publish`` is the /diagnostics publisher's publish method, ``now_ns``
    the node clock.  Every status also carries ``status_seq`` (1, 2, ... per node: a
    recording can show that none is missing) and, for each of ``publishers``
    (:class:`CountedPublisher`), ``published:<topic>`` and ``subscribers:<topic>``.
    """

    def __init__(self, name: str, hardware_id: str, publish: Callable[[DiagnosticArray], None],
                 now_ns: Callable[[], int], values: Callable[[], Dict[str, Any]],
                 publishers: Sequence['CountedPublisher'] = ()):
        self.name = name
        self.hardware_id = hardware_id
        self._publish = publish
        self._now_ns = now_ns
        self._values = values
        self.publishers = list(publishers)
        self.level = OK
        self.message = 'starting'
        self.published = 0
        self._due = False
        self._last_sample = -1e9

    def set(self, level: int, message: str) -> None:
        """Change the status; publish at once if the level or message changed."""
        if (level, message) != (self.level, self.message):
            self.level, self.message = level, message
            self.publish()

    def on_timer(self, busy_window_s: float) -> None:
        """Period timer: publish now if idle (or overdue), else mark due for after_sample."""
        idle = time.monotonic() - self._last_sample > busy_window_s
        if idle or self._due:
            self.publish()
        else:
            self._due = True

    def after_sample(self) -> None:
        """Call after the node finished a sample's work: publish if the period is due."""
        self._last_sample = time.monotonic()
        if self._due:
            self.publish()

    def publish(self) -> None:
        """Publish the current status with fresh values."""
        values = dict(self._values())
        values['status_seq'] = self.published + 1
        values.update(publisher_values(self.publishers))
        self._publish(array_msg(self._now_ns(), [status_msg(self.name, self.level, self.message,
                                                            values, self.hardware_id)]))
        self.published += 1
        self._due = False


__all__ = ['OK', 'WARN', 'ERROR', 'STALE', 'LEVEL_NAMES', 'format_value', 'status_msg',
           'array_msg', 'parse_status', 'value_float', 'value_int', 'flatten', 'CountedPublisher',
           'publisher_values', 'StatusReporter']
