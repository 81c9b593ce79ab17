"""Road height at the tyre from time-stamped samples (``/erva/road/height``), for any time t.

The simulated ECU and the estimator both need w(t) between and slightly after the
road samples they received (the road node and the ECU run on unsynchronised 50 Hz
clocks).  Between samples w is linear; after the newest sample it is extrapolated
linearly for at most ``max_extrapolation_s`` (default one period), then held, so a
stalled road source never produces a runaway height.
"""

from collections import deque
from typing import Deque, Optional, Tuple


class RoadBuffer:
    """The last ``size`` road samples (t in s, w in m), interpolated on request."""

    def __init__(self, size: int = 256, max_extrapolation_s: float = 0.02):
        self._s: Deque[Tuple[float, float]] = deque(maxlen=size)
        self.max_extrapolation_s = float(max_extrapolation_s)
        self.rejected = 0

    def __len__(self) -> int:
        return len(self._s)

    def add(self, t: float, w: float) -> bool:
        """Append a sample; an out-of-order or repeated time is rejected (False)."""
        if self._s and t <= self._s[-1][0]:
            self.rejected += 1
            return False
        self._s.append((float(t), float(w)))
        return True

    @property
    def latest(self) -> Optional[Tuple[float, float]]:
        return self._s[-1] if self._s else None

    def height(self, t: float, default: float = 0.0) -> float:
        """Return w(t) (m); ``default`` before the first sample arrived."""
        s = self._s
        if not s:
            return default
        if t >= s[-1][0]:
            if len(s) < 2:
                return s[-1][1]
            (t0, w0), (t1, w1) = s[-2], s[-1]
            ahead = min(t - t1, self.max_extrapolation_s)
            return w1 + (w1 - w0) / (t1 - t0) * ahead
        if t <= s[0][0]:
            return s[0][1]
        # Newest samples are asked for most: search from the end.
        for i in range(len(s) - 1, 0, -1):
            t0, w0 = s[i - 1]
            if t0 <= t:
                t1, w1 = s[i]
                return w0 + (w1 - w0) * (t - t0) / (t1 - t0)
        return s[0][1]
