"""Timing helpers of the live nodes: grid alignment and bounded statistics of durations."""

import math
from typing import Dict, Optional

import numpy as np

from erva_ros.core.metrics import percentiles_ms


def next_grid_delay_ns(now_ns: int, ref_ns: int, period_ns: int, offset_ns: int = 0) -> int:
    """Return the time from ``now_ns`` to the next instant ref + offset + m·period (ns, > 0)."""
    phase = (now_ns - ref_ns - offset_ns) % period_ns
    return period_ns - phase


#: Durations kept raw (exact percentiles) up to this many (40 s at 50 Hz); beyond, the
#: percentiles come from the histogram of all of them.
EXACT_SAMPLES = 2_000
#: The histogram: log-spaced bins of 0.2 % relative width from 1 ns to 1000 s.
HIST_LO_S, HIST_HI_S, HIST_REL = 1e-9, 1e3, 0.002
_LOG_LO = math.log(HIST_LO_S)
_LOG_STEP = math.log1p(HIST_REL)
_NBINS = int(math.ceil((math.log(HIST_HI_S) - _LOG_LO) / _LOG_STEP)) + 1


class DurationStats:
    """Durations in seconds (solve times, latencies, jitter) of a whole session, in fixed memory.

    :meth:`summary` gives p50 / p99 / max in milliseconds and the sample count
    (erva_ros.core.metrics.percentiles_ms), so nodes, `erva run` and reports agree.  The
    count and the max are exact.  Up to ``exact`` samples (:data:`EXACT_SAMPLES`) the
    percentiles are exact too; beyond, each is the centre of the histogram bin holding
    its rank: bins 0.2 % wide, so within 0.1 % of a sample at that rank (values from
    1 ns to 1000 s; shorter ones count as 0, longer ones in the last bin).

    All memory is taken, and written, at construction (~0.13 MB): a node's resident
    size does not grow with the session.  Keeping every sample, as before, grew nmpc_node
    by ~190 bytes per sample (six of these, 32 bytes per Python float in a deque).
    Summarising the histogram costs the same at any length: sorting an hour of
    samples (200,000) took 12 ms, with the GIL held, every 0.5 s.
    """

    def __init__(self, exact: int = EXACT_SAMPLES):
        # np.full writes every element: np.zeros would map pages lazily, resident only
        # as values arrive -- slow growth again.
        self._raw = np.full(int(exact), np.nan)
        self._hist = np.full(_NBINS, 0, dtype=np.int64)
        self._count = 0
        self._max = -math.inf

    @staticmethod
    def _bin(seconds: float) -> int:
        if not seconds > HIST_LO_S:
            return 0
        return min(int((math.log(seconds) - _LOG_LO) / _LOG_STEP), _NBINS - 1)

    def add(self, seconds: float) -> None:
        """Add one duration (s)."""
        seconds = float(seconds)
        if self._count < self._raw.size:
            self._raw[self._count] = seconds
        self._hist[self._bin(seconds)] += 1
        self._count += 1
        if seconds > self._max:
            self._max = seconds

    def __len__(self) -> int:
        return self._count

    def quantile(self, q: float) -> float:
        """Return a quantile, e.g. 0.999 (s; NaN without samples), as :meth:`summary` does."""
        if not self._count:
            return math.nan
        if self._count <= self._raw.size:
            return float(np.percentile(self._raw[:self._count], 100 * q))
        k = int(np.searchsorted(np.cumsum(self._hist), q * self._count))  # bin of that rank
        centre = math.exp(_LOG_LO + (k + 0.5) * _LOG_STEP) if k else 0.0
        return min(centre, self._max)

    def summary(self) -> Dict[str, float]:
        """Return {'p50', 'p99', 'max' (ms), 'samples'}."""
        if self._count <= self._raw.size:
            return percentiles_ms(self._raw[:self._count])
        return {'p50': self.quantile(0.5) * 1e3, 'p99': self.quantile(0.99) * 1e3,
                'max': self._max * 1e3, 'samples': self._count}


class PeriodStats:
    """Jitter |Δt − Ts| of consecutive event times (s), e.g. command publications."""

    def __init__(self, period_s: float, exact: int = EXACT_SAMPLES):
        self.period_s = float(period_s)
        self.jitter = DurationStats(exact)
        self._last: Optional[float] = None

    def mark(self, t_s: float) -> None:
        """Record an event at time ``t_s`` (s)."""
        if self._last is not None:
            self.jitter.add(abs((t_s - self._last) - self.period_s))
        self._last = t_s

    def restart(self) -> None:
        """Forget the previous event (after a deliberate pause, so it is not counted)."""
        self._last = None


class SampleGrid:
    """The samples t_k = start + k·Ts, k = 0..n−1, of a real-time time master's timer.

    A firing takes the newest instant of the grid that has passed, so a sample is stamped
    with when it was taken, never later; a timer that fell behind by whole periods skips
    samples (counted in ``skipped``).  The last sample is never skipped: the run ends
    with it (the plant steps to t_{n−1} only on its height), so a firing past the end
    takes it, late.
    """

    def __init__(self, period_ns: int, n_samples: int):
        self.period_ns, self.n_samples = int(period_ns), int(n_samples)
        self.start_ns: Optional[int] = None
        self.last_k = -1
        self.skipped = 0

    def due(self, now_ns: int) -> Optional[int]:
        """Return the sample to publish at ``now_ns`` (None: none due); the first call starts."""
        if self.start_ns is None:
            self.start_ns = int(now_ns)
        k = min((now_ns - self.start_ns) // self.period_ns, self.n_samples - 1)
        if k <= self.last_k:
            return None
        self.skipped += k - self.last_k - 1
        self.last_k = k
        return k

    def stamp_ns(self, k: int) -> int:
        """Return t_k (ns)."""
        return self.start_ns + k * self.period_ns

    @property
    def done(self) -> bool:
        """Return True once the last sample was taken."""
        return self.last_k >= self.n_samples - 1


__all__ = ['next_grid_delay_ns', 'DurationStats', 'PeriodStats', 'SampleGrid']
