"""Road height at the tyre from time-stamped samples (``/erva/road/height``), for any time t.

The simulated ECU and the estimator both need w(t) between and slightly after the
road samples they received (the road node and the ECU run on unsynchronised 50 Hz
clocks).  Between samples w is linear; after the newest sample it is extrapolated
linearly for at most ``max_extrapolation_s`` (default one period), then held, so a
stalled road source never produces a runaway height.  :class:`KnownRoad` is the road
a simulated vehicle knows ahead (the session's), placed on the messages' sample grid.
"""

from collections import deque
import math
from typing import Callable, Deque, Dict, Optional, Tuple


#: A time within this fraction of a period of a sample instant is that instant.
GRID_SNAP = 1e-4


class RoadBuffer:
    """The last ``size`` road samples (t in s, w in m), interpolated on request."""

    def __init__(self, size: int = 256, max_extrapolation_s: float = 0.02):
        self._s: Deque[Tuple[float, float]] = deque(maxlen=size)
        self.max_extrapolation_s = float(max_extrapolation_s)
        self.rejected = 0

    def __len__(self) -> int:
        return len(self._s)

    def add(self, t: float, w: float) -> bool:
        """Append a sample; a non-finite, out-of-order or repeated one is rejected (False)."""
        if not (math.isfinite(t) and math.isfinite(w)) or self._s and t <= self._s[-1][0]:
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


class KnownRoad:
    """A road known ahead (the session's), on the sample grid of the road node's messages.

    The road node publishes w(t_k) = ``height_at(k·Ts)`` at t_k = t_first + k·Ts with
    the distance travelled speed·k·Ts.  The simulated vehicle drives over the same road:
    :meth:`anchor` places the grid with the first message, :meth:`height` then gives w at
    any epoch time without waiting for the messages (linear between the samples, as the
    estimator and plant_sim_node see it), and :meth:`check` counts the received samples
    that differ from it (a different road or a shifted grid: ``mismatches``).
    """

    def __init__(self, height_at: Callable[[float], float], speed_mps: float, ts: float):
        self._height_at = height_at
        self.speed_mps = float(speed_mps)
        self.ts = float(ts)
        self.ts_ns = int(round(ts * 1e9))
        self.origin_ns: Optional[int] = None     # epoch ns of sample 0
        self.checked = 0
        self.mismatches = 0
        self._cache: Dict[int, float] = {}

    def sample(self, k: int) -> float:
        """Return w(t_k) (m), exactly as the road node computes it."""
        k = max(int(k), 0)
        w = self._cache.get(k)
        if w is None:
            if len(self._cache) > 4096:
                self._cache.clear()
            w = self._cache[k] = float(self._height_at(k * self.ts))
        return w

    def anchor(self, stamp_ns: int, distance_m: float) -> None:
        """Place the grid: the message stamped ``stamp_ns`` is sample distance / (speed·Ts)."""
        k = int(round(distance_m / (self.speed_mps * self.ts))) if self.speed_mps > 0 else 0
        self.origin_ns = int(stamp_ns) - k * self.ts_ns

    def _origin(self) -> int:
        if self.origin_ns is None:
            raise RuntimeError('KnownRoad: anchor() places the sample grid first')
        return self.origin_ns

    def check(self, stamp_ns: int, w: float) -> bool:
        """Return True if a received sample agrees with this road (else count a mismatch)."""
        k, rest = divmod(int(stamp_ns) - self._origin(), self.ts_ns)
        self.checked += 1
        ok = rest == 0 and abs(self.sample(k) - w) <= 1e-9
        self.mismatches += not ok
        return ok

    def height(self, t: float) -> float:
        """Return w(t) (m) at epoch time t (s); needs :meth:`anchor` first."""
        x = (t * 1e9 - self._origin()) / self.ts_ns
        k = math.floor(x)
        frac = x - k
        # On the grid: within 2 us of it at Ts = 20 ms (epoch seconds as floats are
        # 0.24 us coarse, and sums of them a few ulps off), the exact sample.
        if frac < GRID_SNAP or frac > 1 - GRID_SNAP:
            return self.sample(int(round(x)))
        w0, w1 = self.sample(k), self.sample(k + 1)
        return w0 + (w1 - w0) * frac
