"""Timing helpers of the live nodes: grid alignment and bounded statistics of durations."""

from collections import deque
from typing import Dict, Optional

from erva_ros.metrics import percentiles_ms


def next_grid_delay_ns(now_ns: int, ref_ns: int, period_ns: int, offset_ns: int = 0) -> int:
    """Return the time from ``now_ns`` to the next instant ref + offset + m·period (ns, > 0)."""
    phase = (now_ns - ref_ns - offset_ns) % period_ns
    return period_ns - phase


class DurationStats:
    """Durations in seconds (solve times, latencies, jitter), the newest ``maxlen`` kept.

    :meth:`summary` gives p50 / p99 / max in milliseconds and the sample count
    (erva_ros.metrics.percentiles_ms), so nodes, `erva run` and reports agree.
    """

    def __init__(self, maxlen: int = 200_000):
        self._samples = deque(maxlen=maxlen)

    def add(self, seconds: float) -> None:
        """Add one duration (s)."""
        self._samples.append(float(seconds))

    def __len__(self) -> int:
        return len(self._samples)

    def summary(self) -> Dict[str, float]:
        """Return {'p50', 'p99', 'max' (ms), 'samples'}."""
        return percentiles_ms(list(self._samples))


class PeriodStats:
    """Jitter |Δt − Ts| of consecutive event times (s), e.g. command publications."""

    def __init__(self, period_s: float, maxlen: int = 200_000):
        self.period_s = float(period_s)
        self.jitter = DurationStats(maxlen)
        self._last: Optional[float] = None

    def mark(self, t_s: float) -> None:
        """Record an event at time ``t_s`` (s)."""
        if self._last is not None:
            self.jitter.add(abs((t_s - self._last) - self.period_s))
        self._last = t_s

    def restart(self) -> None:
        """Forget the previous event (after a deliberate pause, so it is not counted)."""
        self._last = None


__all__ = ['next_grid_delay_ns', 'DurationStats', 'PeriodStats']
