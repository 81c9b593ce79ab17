"""The road ahead from the map, at the odometry position corrected by profile matching.

:class:`MapPreview` is the core of road_preview_node's ``source:=map`` (docs/road.md): per
sample t_k it takes the odometry distance and speed and the live road estimate ŵ_k (the
road estimator's, ``road/estimate``) and returns the preview w(t_k + j·Ts), j = 0..N, with
a variance per point:

1. **Alignment.**  The live estimates of the last ``window_m`` metres are matched with the
   map (:func:`~erva_ros.core.roadmap.profile.match`: cross-correlation, both detrended)
   every ``align_period`` samples, within ``search_m`` of the odometry position until a
   match is accepted (the first must be confirmed by the next window), then within
   ``track_m`` of the current offset.  A match of
   correlation ≥ ``min_correlation`` sets the offset δ (position = odometry + δ) and its
   uncertainty; a weaker one is refused (counted) and δ kept.
2. **Anchoring.**  The map holds the road's detail (each drive high-passed: the absolute
   height is not observable), the estimator has its own offset and drift.  So the preview
   is the live estimate plus the map's increments, plus the line through the live-minus-map
   residual over the window:  p_j = ŵ_k + h(x_j) − h(x_0) + b·(x_j − x_0),
   x_j = odometry + δ + v·j·Ts.
3. **Variance.**  var_j = var_map(x_j) + var_map(x_0) + σ_δ²·(h'(x_j)² + h'(x_0)²) + var(ŵ_k),
   σ_δ growing with the distance since the last accepted match (``drift_per_m``).
4. **Weighting** (``weighting='variance'``): each point's map increment is shrunk by
   S_j / (S_j + var_j), S_j the map's own mean squared increment over that distance
   (the conditional mean of the increment given a noisy reading of it): a point the map
   knows badly tends to the no-preview prediction.  ``'none'`` uses the map as it is.

Fallback: a point beyond the map's end, before its start or next to a gap node is the
no-preview prediction (ŵ_k held), counted in :class:`MapPreviewCounts`; so is every point
while the position is off the map.  The preview is always finite.
"""

from collections import deque
from dataclasses import dataclass, field
import math
from typing import Deque, Tuple

import numpy as np

from erva_ros.core.roadmap import MapError
from erva_ros.core.roadmap.profile import match
from erva_ros.core.roadmap.store import MapProfile

WEIGHTINGS = ('none', 'variance')
#: The first match needs the next window's offset within this (m).
CONFIRM_M = 0.3


@dataclass(frozen=True)
class MapPreviewSettings:
    """How the preview aligns and weights (SI units)."""

    window_m: float = 10.0           # live estimate matched over the last window_m metres
    search_m: float = 3.0            # ± around the odometry position, until a match
    track_m: float = 1.0             # ± around the current offset, once matched
    min_correlation: float = 0.85    # a weaker match is refused (another seed of the paper
    #                                  road correlates ~0.84: its sine is on every seed)
    max_unmatched_m: float = 20.0    # no match accepted for this far: no preview at all
    align_period: int = 5            # samples between matches
    prior_offset_std_m: float = 1.0  # σ_δ before the first match (the odometry's start error)
    drift_per_m: float = 0.01        # σ_δ grows this much per metre since the last match
    weighting: str = 'none'          # none | variance (see the module doc)
    slope: bool = True               # add the residual's line (step 2)

    def __post_init__(self):
        checks = (('window_m', self.window_m > 0), ('search_m', self.search_m > 0),
                  ('track_m', self.track_m > 0),
                  ('min_correlation', -1 <= self.min_correlation <= 1),
                  ('align_period', isinstance(self.align_period, int) and self.align_period >= 1),
                  ('prior_offset_std_m', self.prior_offset_std_m >= 0),
                  ('drift_per_m', self.drift_per_m >= 0),
                  ('max_unmatched_m', self.max_unmatched_m > 0))
        for name, ok in checks:
            if not ok:
                raise MapError(f'map preview: {name} = {getattr(self, name)!r} is out of range')
        if self.weighting not in WEIGHTINGS:
            raise MapError(f'map preview: weighting {self.weighting!r}; choose one of '
                           f'{", ".join(WEIGHTINGS)}')


@dataclass
class MapPreviewCounts:
    """What the preview did, summed over the samples (for /diagnostics and the summary)."""

    samples: int = 0
    points: int = 0
    fallback_points: int = 0         # points that got the no-preview prediction
    fallback_samples: int = 0        # samples with at least one such point
    beyond_end_points: int = 0
    before_start_points: int = 0
    gap_points: int = 0
    unmatched_points: int = 0        # points of unmatched_samples (below)
    alignments: int = 0              # matches accepted
    alignments_refused: int = 0      # matches below min_correlation or at the search edge
    unaligned_samples: int = 0       # samples before the first accepted match
    position_off_map_samples: int = 0  # samples whose own position is off the map (all
    #                                    their points fall back)
    unmatched_samples: int = 0       # samples max_unmatched_m after the last match (or the
    #                                  start) without one: all their points fall back


@dataclass
class PreviewResult:
    """One sample's preview."""

    heights: np.ndarray      # m, w(t_k + j·Ts), j = 0..N, in the estimator's frame
    variance: np.ndarray     # m² per point (inf: fallback point)
    position_m: float        # odometry + offset
    offset_m: float          # δ
    offset_std_m: float      # σ_δ
    correlation: float       # of the last match tried (nan: none yet)
    aligned: bool            # a match has been accepted
    fallback_points: int


@dataclass
class _Live:
    s: Deque[float] = field(default_factory=deque)
    w: Deque[float] = field(default_factory=deque)


class MapPreview:
    """The preview from a :class:`MapProfile` for a vehicle driving along it (module doc)."""

    def __init__(self, road_map: MapProfile, ts: float,
                 settings: MapPreviewSettings = MapPreviewSettings()):
        if road_map.n < 2 or not road_map.valid.any():
            raise MapError('the map is empty')
        self.map = road_map
        self.ts = float(ts)
        self.settings = settings
        self._h = np.where(road_map.valid, road_map.h, np.nan)
        self._slope = np.gradient(np.nan_to_num(self._h), road_map.grid_m)
        self._structure = self._structure_function()
        self.reset()

    def reset(self, offset_m: float = 0.0) -> None:
        """Forget the live history; start from odometry + ``offset_m``."""
        self.offset = float(offset_m)
        self.offset_std = self.settings.prior_offset_std_m
        self.aligned = False
        self.correlation = math.nan
        self._since = 0
        self._last_match_s = None
        self._start_s = None
        self._pending = None
        self._live = _Live()
        self.counts = MapPreviewCounts()

    def _structure_function(self) -> Tuple[np.ndarray, np.ndarray]:
        """Return (lag m, mean squared increment of the map's heights over the lag)."""
        h = self._h
        lags = np.arange(0, min(h.size - 1, int(round(40.0 / self.map.grid_m))) + 1)
        out = np.zeros(lags.size)
        for i, lag in enumerate(lags[1:], 1):
            d = h[lag:] - h[:-lag]
            d = d[np.isfinite(d)]
            out[i] = float(np.mean(d * d)) if d.size else 0.0
        return lags * self.map.grid_m, out

    # -- one sample ---------------------------------------------------------------------
    def step(self, s_odo: float, speed_mps: float, w_hat: float, var_w: float,
             points: int) -> PreviewResult:
        """Return the preview of ``points`` heights for the sample at odometry ``s_odo``."""
        st = self.settings
        c = self.counts
        c.samples += 1
        if self._start_s is None:
            self._start_s = float(s_odo)
        live = self._live
        live.s.append(float(s_odo))
        live.w.append(float(w_hat))
        while len(live.s) > 2 and live.s[-1] - live.s[1] >= st.window_m:
            live.s.popleft()
            live.w.popleft()
        self._since += 1
        if self._since >= st.align_period and live.s[-1] - live.s[0] >= 0.9 * st.window_m:
            self._align()
        if not self.aligned:
            c.unaligned_samples += 1
        if self._last_match_s is not None:
            drift = st.drift_per_m * abs(s_odo - self._last_match_s)
            sigma = math.hypot(self.offset_std, drift)
        else:
            sigma = self.offset_std
        x0 = s_odo + self.offset
        x = x0 + max(speed_mps, 0.0) * self.ts * np.arange(points)
        h, var, ok = self.map.sample(x)
        c.points += points
        on_map = bool(ok[0])
        since = s_odo - (self._start_s if self._last_match_s is None else self._last_match_s)
        unmatched = since > st.max_unmatched_m
        if unmatched:
            c.unmatched_samples += 1
        if not on_map or unmatched:
            ok[:] = False
        b = self._residual_slope() if st.slope and on_map else 0.0
        heights = np.full(points, float(w_hat))
        variance = np.full(points, math.inf)
        if ok[0]:
            inc = h - h[0]
            g = self._slope_at(x)
            v = var + var[0] + sigma ** 2 * (g ** 2 + g[0] ** 2) + max(var_w, 0.0)
            if st.weighting == 'variance':
                prior = np.interp(x - x0, *self._structure)
                with np.errstate(invalid='ignore', divide='ignore'):
                    gain = np.where(prior > 0, prior / (prior + v), 0.0)
                inc = inc * gain
            est = w_hat + inc + b * (x - x0)
            heights = np.where(ok, est, heights)
            variance = np.where(ok, v, variance)
            variance[0] = max(var_w, 0.0)
            heights[0] = w_hat
        bad = ~ok
        nbad = int(bad.sum())
        if nbad:
            # One reason per point: no recent match; else where the vehicle is, when that
            # is off the map (no anchor there); else where the point is.
            c.fallback_points += nbad
            c.fallback_samples += 1
            if unmatched:
                c.unmatched_points += nbad
            else:
                where = x
                if not on_map:
                    where = np.full(points, x0)
                    c.position_off_map_samples += 1
                c.beyond_end_points += int(np.sum(bad & (where > self.map.end_m)))
                c.before_start_points += int(np.sum(bad & (where < self.map.start_m)))
                c.gap_points += int(np.sum(bad & (where >= self.map.start_m)
                                           & (where <= self.map.end_m)))
        return PreviewResult(heights, variance, x0, self.offset, sigma, self.correlation,
                             self.aligned, nbad)

    def _slope_at(self, x: np.ndarray) -> np.ndarray:
        return np.interp(x, self.map.s, self._slope)

    def _residual_slope(self) -> float:
        """Return the slope of (live estimate − map) over the window (the map lacks it)."""
        s = np.fromiter(self._live.s, float)
        if s.size < 3 or s[-1] - s[0] <= 0:
            return 0.0
        h, _, ok = self.map.sample(s + self.offset)
        if ok.sum() < 3:
            return 0.0
        r = np.fromiter(self._live.w, float)[ok] - h[ok]
        return float(np.polyfit(s[ok], r, 1)[0])

    def _align(self) -> None:
        st = self.settings
        self._since = 0
        s = np.fromiter(self._live.s, float)
        w = np.fromiter(self._live.w, float)
        m = match(s, w, self.map.start_m, self.map.grid_m, self._h, self.offset,
                  st.track_m if self.aligned else st.search_m, self.map.grid_m)
        self.correlation = m.correlation
        good = m.correlation >= st.min_correlation and not m.at_edge
        if good and not self.aligned:
            # The first match must be confirmed by the next window (within CONFIRM_M):
            # one window of another road can correlate by chance, two in a row do not.
            pending, self._pending = self._pending, m.offset_m
            if pending is None:
                return                                  # waits for the next window
            good = abs(pending - m.offset_m) <= CONFIRM_M
        elif not good:
            self._pending = None
        if good:
            self.offset = m.offset_m
            self.offset_std = m.offset_std_m if math.isfinite(m.offset_std_m) else st.search_m
            self.aligned = True
            self._last_match_s = float(s[-1])
            self.counts.alignments += 1
        else:
            self.counts.alignments_refused += 1


def map_preview_source(preview: MapPreview):
    """Return ``preview`` as a preview source of the offline loop (vehicle.PreviewSource)."""
    def source(t, s_odo, v_odo, w_hat, var_w, n):
        return preview.step(s_odo, v_odo, w_hat, var_w, n).heights
    return source


__all__ = ['WEIGHTINGS', 'MapPreviewSettings', 'MapPreviewCounts', 'PreviewResult', 'MapPreview',
           'map_preview_source']
