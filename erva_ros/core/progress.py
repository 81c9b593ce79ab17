"""Progress of a long command on stderr: one line per stage, with the elapsed time and an ETA.

Every command that runs longer than a few seconds (``erva table``, ``pareto``, ``fr``,
``delay-study``, ``bench``, ``replay --reevaluate``, ``bag soak``, a first-run compile)
reports each of its stages through one :class:`Progress`::

    erva table: seeds 3/10 (30 %), 4 min 12 s elapsed, ETA 9 min 48 s

On a terminal the stage's line is rewritten in place (at most every ``TTY_INTERVAL_S``)
and ends with a newline when the stage does.  Otherwise (a log file, CI) a plain line is
printed per tenth of the stage, not sooner than ``PLAIN_MIN_S`` after the previous one,
at least every ``PLAIN_INTERVAL_S``, and when it ends: a stage of seconds prints one
line.  ``enabled=False`` prints nothing: commands pass ``not args.json``, so the output
of ``--json`` carries no progress.  The ETA is the mean time per unit so far times the
units left (coarse when units finish in bursts, as parallel jobs do).  No ROS, no
third-party imports.
"""

import sys
import time
from typing import Callable, Optional, TextIO

#: A terminal line is rewritten at most this often (s); the last update always shows.
TTY_INTERVAL_S = 0.2
#: Without a terminal: a line per tenth of the stage, but not sooner than PLAIN_MIN_S
#: after the last one (a stage of seconds prints its final line only), and at least every
#: PLAIN_INTERVAL_S while it makes progress.
PLAIN_MIN_S = 5.0
PLAIN_INTERVAL_S = 60.0


def format_duration(seconds: float) -> str:
    """Return ``seconds`` as '42 s', '3 min 05 s' or '1 h 02 min'."""
    s = int(round(max(0.0, seconds)))
    if s < 60:
        return f'{s} s'
    if s < 3600:
        return f'{s // 60} min {s % 60:02d} s'
    return f'{s // 3600} h {(s % 3600) // 60:02d} min'


class Progress:
    """The progress of one stage (``label``) towards ``total`` units (see module doc).

    Call it as ``progress(done, total)`` (the callback the cores take), or use
    :meth:`advance`; :meth:`close` ends the stage's line.  ``progress(0)`` -- the work
    has started (a pool is up, a cluster connected) -- always shows, so a stage whose
    first unit takes minutes says so.  A stage with ``total`` None shows the elapsed time
    only; as a context manager it prints its start line at once.
    """

    def __init__(self, label: str, total: Optional[int] = None, enabled: bool = True,
                 stream: Optional[TextIO] = None,
                 clock: Callable[[], float] = time.monotonic):
        self.label = label
        self.total = total
        self.enabled = enabled
        self.stream = sys.stderr if stream is None else stream
        self.tty = bool(getattr(self.stream, 'isatty', lambda: False)())
        self.clock = clock
        self.started = clock()
        self.done = 0
        self.note = ''
        self.closed = False
        self._shown_at: Optional[float] = None
        self._shown_tenth = 0
        self._open_line = False

    # -- updates ---------------------------------------------------------------------
    def __call__(self, done: int, total: Optional[int] = None) -> None:
        """Set ``done`` units of ``total`` (callback form of :meth:`update`)."""
        self.update(done, total)

    def update(self, done: int, total: Optional[int] = None, note: str = '') -> None:
        """Set ``done`` (and ``total``, a ``note`` after the counts); show when due."""
        if total is not None:
            self.total = total
        self.done = done
        self.note = note
        if self.enabled and not self.closed:
            self._show(final=self.total is not None and done >= self.total)

    def advance(self, n: int = 1, note: str = '') -> None:
        """Count ``n`` more units done."""
        self.update(self.done + n, note=note)

    def close(self, note: str = '') -> None:
        """End the stage: its last line (with ``note``), then a newline on a terminal."""
        if self.closed:
            return
        if note:
            self.note = note
        shown_final = self._shown_at is not None and not self._open_line and self._finished()
        self.closed = True
        if self.enabled and (not shown_final or note):
            self._show(final=True)

    def __enter__(self) -> 'Progress':
        """Start the stage; one without a total says so at once."""
        if self.enabled and self.total is None:
            self._show(final=False, force=True)
        return self

    def __exit__(self, exc_type, *_) -> None:
        """End the stage; after an error, only end the open line (the error says why)."""
        if exc_type is None:
            self.close()
            return
        if self.enabled and self._open_line:
            self.stream.write('\n')
            self.stream.flush()
        self.closed = True

    # -- text ------------------------------------------------------------------------
    def _finished(self) -> bool:
        return self.total is not None and self.done >= self.total

    def line(self, now: Optional[float] = None) -> str:
        """Return the stage's line as it is now."""
        elapsed = (self.clock() if now is None else now) - self.started
        text = self.label
        if self.total:
            text += f' {self.done}/{self.total} ({100 * self.done // self.total} %)'
        if self.closed or self._finished():
            text += f', done in {format_duration(elapsed)}' if self._finished() or \
                self.total is None else f', stopped after {format_duration(elapsed)}'
        else:
            text += f', {format_duration(elapsed)} elapsed'
            if self.total and self.done > 0:
                eta = elapsed / self.done * (self.total - self.done)
                text += f', ETA {format_duration(eta)}'
        return text + (f'; {self.note}' if self.note else '')

    def _show(self, final: bool, force: bool = False) -> None:
        now = self.clock()
        if self.tty:
            if not final and self._shown_at is not None and \
                    now - self._shown_at < TTY_INTERVAL_S:
                return
            self.stream.write('\r' + self.line(now) + '\x1b[K' + ('\n' if final else ''))
            self._open_line = not final
        else:
            tenth = (10 * self.done // self.total) if self.total else -1
            since = now - (self.started if self._shown_at is None else self._shown_at)
            started = self._shown_at is None and self.done == 0
            due = (final or force or started or bool(self.note) or since >= PLAIN_INTERVAL_S
                   or (tenth != self._shown_tenth and since >= PLAIN_MIN_S))
            if not due:
                return
            self._shown_tenth = tenth
            self.stream.write(self.line(now) + '\n')
        self._shown_at = now
        self.stream.flush()


def stage(label: str, enabled: bool = True, stream: Optional[TextIO] = None) -> Progress:
    """Return a stage without a known total, for ``with``: its start and end lines."""
    return Progress(label, None, enabled, stream)


__all__ = ['Progress', 'stage', 'format_duration', 'TTY_INTERVAL_S', 'PLAIN_MIN_S',
           'PLAIN_INTERVAL_S']
