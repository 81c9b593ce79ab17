"""A node's status on ``/diagnostics``, as diagnostic_updater publishes it, without ROS.

Each node owns one :class:`StatusReporter` around its typed report
(:mod:`erva_ros.core.reports`): it publishes the report about every diagnostics period
and at once whenever the level or message changes, so an ERROR is visible within one
message latency rather than at the next period.

While the control loop runs, the periodic status (percentiles over thousands of
samples) is built in the slack right after the node's work for a sample, never between
a sample's arrival and its result: the period timer only marks it due
(:meth:`StatusReporter.on_timer`) and the node calls :meth:`StatusReporter.after_sample`.
When no samples flow, the timer publishes.
"""

import time
from typing import Callable, List, Sequence

from erva_ros.core.contract import encode_diagnostics
from erva_ros.core.levels import OK
from erva_ros.core.reports import NodeReport, report_status


class StatusReporter:
    """Publish a node's report periodically and immediately on a level or message change.

    ``publish`` takes the DiagnosticArray's bytes, ``now_ns`` is the node clock,
    ``refresh`` brings the report's figures up to date before each publication (timings,
    counters kept elsewhere).  Every status carries ``status_seq`` (1, 2, ...) and, for
    each of ``publishers`` (objects with ``topic``, ``count`` and
    ``get_subscription_count()``), what it published and the readers it matched.
    """

    def __init__(self, report: NodeReport, publish: Callable[[bytes], None],
                 now_ns: Callable[[], int], refresh: Callable[[], None] = lambda: None,
                 publishers: Sequence = ()):
        self.report = report
        #: Further reports published in the same array, after the node's own (the
        #: bridge's CAN bus and ECU link), with its status_seq.
        self.extra: List[NodeReport] = []
        self._publish = publish
        self._now_ns = now_ns
        self._refresh = refresh
        self.publishers: List = list(publishers)
        report.level, report.message = OK, 'starting'
        self._due = False
        self._last_sample = -1e9

    @property
    def level(self) -> int:
        """Return the current level."""
        return self.report.level

    @property
    def message(self) -> str:
        """Return the current message."""
        return self.report.message

    def set(self, level: int, message: str) -> None:
        """Change the status; publish at once if the level or message changed."""
        if (level, message) != (self.report.level, self.report.message):
            self.report.level, self.report.message = level, message
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

    def publish(self, final: bool = False) -> None:
        """Publish the current report with fresh figures (``final``: the node is stopping)."""
        r = self.report
        r.published = {p.topic: p.count for p in self.publishers}
        r.subscribers = {p.topic: p.get_subscription_count() for p in self.publishers}
        self._refresh()
        r.status_seq += 1
        r.final = final
        for x in self.extra:    # (the process's scheduling is the node's own report's)
            x.session, x.status_seq, x.final, x.scheduling = r.session, r.status_seq, final, ''

        self._publish(encode_diagnostics(self._now_ns(),
                                         [report_status(x) for x in [r, *self.extra]]))
        self._due = False


__all__ = ['StatusReporter']
