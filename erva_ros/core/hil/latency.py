"""Latency statistics of the HIL nodes, without the start-up transient."""

from erva_ros.core.timing import DurationStats, EXACT_SAMPLES

#: Samples ignored after start-up (DDS discovery, first-call allocations): 0.5 s at 50 Hz.
WARMUP_SAMPLES = 25


class LatencyStats(DurationStats):
    """A :class:`~erva_ros.core.timing.DurationStats` ignoring ``warmup`` first samples."""

    def __init__(self, warmup: int = WARMUP_SAMPLES, exact: int = EXACT_SAMPLES):
        super().__init__(exact)
        self._skip = int(warmup)

    def add(self, seconds: float) -> None:
        """Add one duration (s), unless still warming up."""
        if self._skip > 0:
            self._skip -= 1
            return
        super().add(seconds)
