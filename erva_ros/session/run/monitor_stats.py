"""What the session monitor keeps of a session's data: streaming figures in fixed memory.

`erva run`'s monitor (:class:`erva_ros.session.run.observations.Observations`) decodes each
data message as it arrives and folds the session's own ones in here
(:class:`SessionStreams`); the summary (:mod:`erva_ros.session.run.monitor_figures`) and the
verdict (:mod:`erva_ros.session.run.verdict`) read the figures.  Nothing grows with the
session's length:

* sums, counts and extremes: comfort of the first ``n_steps`` accelerations, the span of
  the state arrivals, commands received and for samples, the verdict's worst instances
  (:class:`Worst`, :class:`Gaps`);
* latencies and the monitor's period jitter as :class:`~erva_ros.core.timing.DurationStats`
  (exact to 2,000 samples, within 0.1 % beyond);
* what belongs to one sample across topics is paired by stamp in a bounded window of the
  recent samples (:data:`WINDOW`): a command with the state of its stamp (also when the
  state comes later), an estimate with the ECU's true state of its sample, the nearest
  stamp in the estimator's own stamping window (:class:`PairedError`);
* the sampled trajectory in preallocated columns, up to ``cap`` samples
  (:data:`TRAJECTORY_CAP`): beyond, it is the session's first part.
"""

import math
from collections import OrderedDict, deque
from typing import Any, Dict, Optional

import numpy as np

from erva_ros.core.timing import DurationStats, PeriodStats
from erva_ros.core.reports import Timing

#: Recent samples kept per topic to pair a sample's messages across topics: ~20 s at
#: 50 Hz, far more than topics drift apart in the monitor's queues (depth 1000 each).
WINDOW = 1024
#: Commands kept waiting for the state of their stamp beyond WINDOW: then not for a sample.
MAX_PENDING = WINDOW
#: Samples of the trajectory kept by default: one hour at 50 Hz (~16 MB).
TRAJECTORY_CAP = 180_000
#: Width of the trajectory's state column (the benchmark model's state has 4).
STATE_WIDTH = 6


class Recent(OrderedDict):
    """The newest ``size`` entries by insertion (stamps come in order): older ones go."""

    def __init__(self, size: int = WINDOW):
        super().__init__()
        self.size = size

    def put(self, key, value) -> None:
        """Add ``key``, forgetting the oldest entry beyond ``size``."""
        self[key] = value
        if len(self) > self.size:
            self.popitem(last=False)


def paired(recent: Recent, stamp: int, lo_ns: int, hi_ns: int, look: int = 8):
    """Return (key, entry) of a recent key k with ``lo_ns <= stamp - k < hi_ns`` (None).

    The window is one period wide, so at most one sample of a grid lies in it.
    """
    for i, key in enumerate(reversed(recent)):
        if lo_ns <= stamp - key < hi_ns:
            return key, recent[key]
        if i >= look:
            break
    return None


class Worst:
    """The largest value (s) of a series and when it was (ns): the first of equal ones.

    Only values over ``over_s`` count (``count``): e.g. pauses over a threshold.
    """

    def __init__(self, over_s: float = -math.inf):
        self.over_s = over_s
        self.count = 0
        self.value_s = math.nan
        self.at_ns = 0

    def add(self, value_s: float, at_ns: int) -> None:
        """Take one value (s) at ``at_ns``."""
        if not value_s > self.over_s:
            return
        self.count += 1
        if self.count == 1 or value_s > self.value_s or (value_s == self.value_s
                                                         and at_ns < self.at_ns):
            self.value_s, self.at_ns = value_s, at_ns


class Gaps(Worst):
    """The gaps between consecutive instants (ns, in order); each at its earlier instant."""

    def __init__(self, over_s: float = -math.inf):
        super().__init__(over_s)
        self.last_ns: Optional[int] = None

    def mark(self, t_ns: int) -> None:
        """Take the next instant."""
        if self.last_ns is not None:
            self.add((t_ns - self.last_ns) * 1e-9, self.last_ns)
        self.last_ns = t_ns


class Span:
    """Count, first and last (smallest and largest) of a series of instants (ns)."""

    def __init__(self):
        self.count = 0
        self.first: Optional[int] = None
        self.last: Optional[int] = None

    def add(self, t_ns: int) -> None:
        """Take one instant."""
        self.count += 1
        self.first = t_ns if self.first is None else min(self.first, t_ns)
        self.last = t_ns if self.last is None else max(self.last, t_ns)


class SumSquares:
    """The sum of squares of the first ``limit`` values (None: all), compensated (Neumaier)."""

    def __init__(self, limit: Optional[int] = None):
        self.limit = limit
        self.count = 0
        self._sum = 0.0
        self._c = 0.0

    def add(self, value: float) -> None:
        """Take one value (ignored beyond ``limit``)."""
        if self.limit is not None and self.count >= self.limit:
            return
        self.count += 1
        term = value * value
        total = self._sum + term
        if abs(self._sum) >= abs(term):
            self._c += (self._sum - total) + term
        else:
            self._c += (term - total) + self._sum
        self._sum = total

    @property
    def total(self) -> float:
        """Return the sum."""
        return self._sum + self._c


class PairedError:
    """Estimates against the truth of their sample: sums of error² and truth², by coordinate.

    The coordinates are the state's and :data:`DERIVED` (the suspension deflection and its
    rate), which stay observable when the road is estimated (docs/road.md).  The first
    ``warmup`` pairs are left out (the filter starts from rest).  ``offset_ns`` is the
    estimate's stamp minus the truth's (None before a pair; 0 when both are on the
    samples' grid, else a constant part of a period), ``offset_spread_ns`` its largest
    minus smallest value over the pairs (0 when every pair agrees).
    """

    def __init__(self, warmup: int):
        self.warmup = warmup
        self.pairs = 0
        self.err2: Optional[np.ndarray] = None
        self.true2: Optional[np.ndarray] = None
        self.offset_ns: Optional[int] = None
        self._offsets = (0, 0)          # smallest, largest

    def add(self, estimate: np.ndarray, truth: np.ndarray, offset_ns: int = 0) -> None:
        """Take one pair (pairs come in stamp order: both topics do)."""
        self.pairs += 1
        if self.offset_ns is None:
            self.offset_ns, self._offsets = offset_ns, (offset_ns, offset_ns)
        else:
            lo, hi = self._offsets
            self._offsets = (min(lo, offset_ns), max(hi, offset_ns))
        if self.pairs <= self.warmup:
            return
        err, truth = with_derived(estimate - truth), with_derived(truth)
        if self.err2 is None:
            self.err2, self.true2 = err ** 2, truth ** 2
        else:
            self.err2 = self.err2 + err ** 2
            self.true2 = self.true2 + truth ** 2

    @property
    def matched(self) -> int:
        """Return the pairs counted (after the warm-up)."""
        return max(0, self.pairs - self.warmup)

    @property
    def offset_spread_ns(self) -> int:
        """Return the largest minus the smallest stamp offset of the pairs."""
        return self._offsets[1] - self._offsets[0]


#: Coordinates added to a state's in the estimation error: (name, i, j) for x_i − x_j.
DERIVED = (('z_s - z_us', 0, 2), ('zdot_s - zdot_us', 1, 3))


def with_derived(x: np.ndarray) -> np.ndarray:
    """Return the state x followed by its :data:`DERIVED` coordinates."""
    return np.concatenate([x, [x[i] - x[j] for _, i, j in DERIVED]])


class Commands:
    """The commands received, those for a sample the monitor saw the state of, and their timing.

    A command is for a sample when a state of its stamp arrived (a command of an outage's
    sample whose state comes later counts too).  The timing of those, in their order of
    arrival: rate, sample -> command and state -> command latencies, period jitter, the
    latest one (:attr:`late`); and the pauses between all commands over ``pause_s``.
    """

    def __init__(self, ts: float, pause_s: float):
        self.received = 0
        self.for_samples = 0
        self.first_rx_s: Optional[float] = None
        self.last_rx_s: Optional[float] = None
        self.sample_to_command = DurationStats()
        self.state_to_command = DurationStats()
        self.jitter = PeriodStats(ts)
        self.late = Worst()                 # sample -> command (s), at the sample's stamp
        self.pauses = Gaps(pause_s)         # between arrivals of all commands
        self.pending: deque = deque()       # (stamp, rx) waiting for their state

    def for_sample(self, stamp: int, rx: int, state_rx: int) -> None:
        """Count a command of a sample whose state arrived at ``state_rx``."""
        self.for_samples += 1
        rx_s = float(rx) * 1e-9
        if self.first_rx_s is None:
            self.first_rx_s = rx_s
        self.last_rx_s = rx_s
        self.jitter.mark(rx_s)
        self.sample_to_command.add((rx - stamp) * 1e-9)
        self.state_to_command.add((rx - state_rx) * 1e-9)
        self.late.add((rx - stamp) * 1e-9, stamp)


class Trajectory:
    """The sampled trajectory, one row per sample (an acceleration's stamp), up to ``cap`` rows.

    Preallocated and written through at construction: the resident size does not grow.
    """

    def __init__(self, cap: int):
        self.cap = int(cap)
        self.rows = 0
        self.stamp = np.full(self.cap, 0, dtype=np.int64)
        self.x = np.full((self.cap, STATE_WIDTH), np.nan)
        self.u = np.full(self.cap, np.nan)
        self.w = np.full(self.cap, np.nan)
        self.sprung_accel = np.full(self.cap, np.nan)
        self.power = np.full(self.cap, np.nan)


class SessionStreams:
    """The session's data messages folded as they arrive (see the module doc).

    Each topic's messages come in stamp order, each stamp once (the caller drops the
    others as foreign); commands may repeat a stamp.  ``ts`` is the loop's period,
    ``n_steps`` the samples the comfort counts (None: all), ``pause_s`` the command
    pause the verdict reports, ``cap`` the trajectory's rows and ``warmup`` the
    estimate/truth pairs left out of the estimation error.
    """

    def __init__(self, ts: float, n_steps: Optional[int] = None, pause_s: float = math.inf,
                 cap: int = TRAJECTORY_CAP, warmup: int = 0):
        self.ts = float(ts)
        self.n_steps = n_steps
        self.state_rx = Span()          # arrivals of the states
        self.state_stamp = Span()       # their stamps
        self.state_gaps = Gaps()        # between state arrivals
        self.road_gaps = Gaps()         # between road-height stamps
        self.accel = SumSquares(n_steps)
        self.accels = 0
        self.commands = Commands(ts, pause_s)
        self.error = PairedError(warmup)
        # An estimate stamped s is of the ECU's sample t with s - t in [-Ts/4, 3Ts/4): the
        # window in which the estimator places a cycle received at s on its grid
        # (EstimatorLoop.stamp).  With the ECU on that grid s = t; an ECU off it (its
        # clock not the estimator's) puts its samples a constant part of a period away.
        ts_ns = int(round(self.ts * 1e9))
        self._pair_ns = (-(ts_ns // 4), ts_ns - ts_ns // 4)
        self.state_size: Optional[int] = None
        self.trajectory = Trajectory(cap if n_steps is None else min(cap, n_steps))
        self._states = Recent()         # stamp -> (rx, x)
        self._truth = Recent()          # stamp -> x
        self._heights = Recent()        # stamp -> height
        self._power = Recent()          # stamp -> power
        self._u = Recent()              # stamp -> the first command's plan[0]
        self._rows = Recent()           # stamp -> trajectory row

    # -- input -----------------------------------------------------------------------------
    def _row(self, stamp: int) -> Optional[int]:
        return self._rows.get(stamp)

    def add_state(self, stamp: int, rx: int, x: np.ndarray) -> None:
        """Take a state of sample ``stamp`` received at ``rx`` (ns)."""
        if self.state_size is None:
            self.state_size = len(x)
        self.state_rx.add(rx)
        self.state_stamp.add(stamp)
        self.state_gaps.mark(rx)
        self._states.put(stamp, (rx, x))
        row = self._row(stamp)
        if row is not None:
            self.trajectory.x[row, :len(x)] = x
        hit = paired(self._truth, stamp, *self._pair_ns)
        if hit is not None:
            self.error.add(x, hit[1], stamp - hit[0])
        self._resolve()

    def add_truth(self, stamp: int, x: np.ndarray) -> None:
        """Take the ECU's true state of sample ``stamp`` (HIL)."""
        self._truth.put(stamp, x)
        lo, hi = self._pair_ns
        hit = paired(self._states, stamp, -hi + 1, -lo + 1)    # stamp - s in (-hi, -lo]
        if hit is not None:
            self.error.add(hit[1][1], x, hit[0] - stamp)

    def add_accel(self, stamp: int, value: float) -> None:
        """Take the sprung-mass acceleration of sample ``stamp``: a row of the trajectory."""
        self.accels += 1
        self.accel.add(value)
        tr = self.trajectory
        row = tr.rows
        if row >= tr.cap:
            return
        tr.rows += 1
        self._rows.put(stamp, row)
        tr.stamp[row], tr.sprung_accel[row] = stamp, value
        state = self._states.get(stamp)
        if state is not None:
            tr.x[row, :len(state[1])] = state[1]
        tr.u[row] = self._u.get(stamp, np.nan)
        tr.w[row] = self._heights.get(stamp, np.nan)
        tr.power[row] = self._power.get(stamp, np.nan)

    def add_height(self, stamp: int, height: float) -> None:
        """Take the road height of sample ``stamp``."""
        self.road_gaps.mark(stamp)
        self._heights.put(stamp, height)
        row = self._row(stamp)
        if row is not None:
            self.trajectory.w[row] = height

    def add_power(self, stamp: int, power: float) -> None:
        """Take the harvested power of sample ``stamp``."""
        self._power.put(stamp, power)
        row = self._row(stamp)
        if row is not None:
            self.trajectory.power[row] = power

    def add_command(self, stamp: int, rx: int, u: float) -> None:
        """Take a command of sample ``stamp`` received at ``rx``; its plan[0] is ``u``."""
        c = self.commands
        c.received += 1
        c.pauses.mark(rx)
        if stamp not in self._u:        # the trajectory's u: the sample's first command
            self._u.put(stamp, u)
            row = self._row(stamp)
            if row is not None and math.isnan(self.trajectory.u[row]):
                self.trajectory.u[row] = u
        c.pending.append((stamp, rx))
        self._resolve()

    def _resolve(self, final: bool = False) -> None:
        """Count the waiting commands, in their order, whose state arrived or never will.

        A state of a stamp not newer than the newest state's is not coming (states come
        in order); ``final``: the session is over, none is coming.
        """
        c = self.commands
        newest = self.state_stamp.last
        while c.pending:
            stamp, rx = c.pending[0]
            state = self._states.get(stamp)
            if state is not None:
                c.for_sample(stamp, rx, state[0])
            elif not (final or len(c.pending) > MAX_PENDING
                      or (newest is not None and stamp <= newest)):
                return
            c.pending.popleft()

    def settle(self) -> None:
        """Count every waiting command (before a summary): no state is coming for it."""
        self._resolve(final=True)

    # -- output ----------------------------------------------------------------------------
    def comfort_sum_squares(self, n_steps: int) -> Optional[float]:
        """Return Σ a² of the first ``n_steps`` accelerations from the streaming sum.

        None if the sum counted a different number of them (``n_steps`` of the
        construction differs); the trajectory's column then has them, if within ``cap``.
        """
        n = min(self.accels, n_steps)
        return self.accel.total if self.accel.count == n else None

    def first_accels(self, n: int) -> Optional[np.ndarray]:
        """Return the first ``n`` accelerations (None: beyond the trajectory's rows)."""
        tr = self.trajectory
        return tr.sprung_accel[:n].copy() if n <= tr.rows else None

    def sampled(self, n_steps: Optional[int] = None) -> Dict[str, Any]:
        """Return the trajectory's first ``n_steps`` rows (t from the first state's stamp)."""
        tr = self.trajectory
        n = tr.rows if n_steps is None else min(tr.rows, n_steps)
        t0 = 0 if self.state_stamp.first is None else self.state_stamp.first
        return {'t': (tr.stamp[:n] - t0) * 1e-9,
                'x': tr.x[:n, :self.state_size or STATE_WIDTH].copy(),
                'u': tr.u[:n].copy(), 'w': tr.w[:n].copy(),
                'sprung_accel': tr.sprung_accel[:n].copy(), 'power': tr.power[:n].copy()}


def stats(timing: Optional[Timing]) -> Dict[str, Any]:
    """Return p50/p99/max (ms, NaN if unknown) and samples (None if unknown) of a Timing."""
    if timing is None:
        return {'p50': float('nan'), 'p99': float('nan'), 'max': float('nan'),
                'samples': None}
    return timing.as_dict()


__all__ = ['stats', 'WINDOW', 'MAX_PENDING', 'TRAJECTORY_CAP', 'Recent', 'Worst', 'Gaps', 'Span',
           'SumSquares', 'paired', 'PairedError', 'DERIVED', 'with_derived', 'Commands',
           'Trajectory', 'SessionStreams']
