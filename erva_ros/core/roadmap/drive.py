"""A recorded drive and its road estimate on the map's distance grid.

:class:`DriveRecord` is what a drive leaves behind (a HIL bag, or the offline vehicle loop):
per ECU cycle its stamp, the odometry distance, the measured rows
(:data:`~erva_ros.core.model.road_estimator.ROAD_MEASUREMENTS`) and the damping the ECU reported.
:func:`estimate_drive` runs the road estimator over it and smooths (RTS);
:func:`grid_profile` puts the smoothed road on the map's grid: the detail
(:func:`~erva_ros.core.roadmap.profile.highpass`) and its variance per node.
"""

from dataclasses import dataclass
import hashlib
import math
from typing import Optional

import numpy as np

from erva_ros.core.model.quarter_car import QuarterCarModel
from erva_ros.core.model.road_estimator import ROAD_MEASUREMENTS, RoadEKF
from erva_ros.core.roadmap import MapError
from erva_ros.core.roadmap.profile import highpass

#: Drives are cut where the odometry jumps further than this between cycles (m): a node is
#: never interpolated across a hole in the recording.
MAX_STEP_M = 2.0


@dataclass
class DriveRecord:
    """One drive: per ECU cycle (rows in time order, one per Ts; NaN rows: missing cycles)."""

    t: np.ndarray            # s, cycle stamps
    distance: np.ndarray     # m along the route, from odometry
    y: np.ndarray            # (n, 5) ROAD_MEASUREMENTS, NaN = not measured
    u_now: np.ndarray        # Ns/m applied at the sample
    u_mean: np.ndarray       # Ns/m, mean over the cycle that ended at the sample
    source: str = ''         # where it came from (bag path, "offline drive 3")
    route: str = ''          # route name ('' unknown)
    speed_mps: float = math.nan

    def __post_init__(self):
        n = len(self.t)
        if n < 2:
            raise MapError(f'drive {self.source or "?"}: {n} ECU cycles, need at least 2')
        if self.y.shape != (n, len(ROAD_MEASUREMENTS)):
            raise MapError(f'drive {self.source}: measurements of shape {self.y.shape}, '
                           f'expected ({n}, {len(ROAD_MEASUREMENTS)})')
        for name in ('distance', 'u_now', 'u_mean'):
            if len(getattr(self, name)) != n:
                raise MapError(f'drive {self.source}: {name} has {len(getattr(self, name))} '
                               f'values for {n} cycles')

    def digest(self) -> str:
        """Return a fingerprint of the data (the map refuses the same drive twice)."""
        h = hashlib.sha256()
        for a in (self.t, self.distance, self.y, self.u_now, self.u_mean):
            h.update(np.ascontiguousarray(a, dtype=float).tobytes())
        return h.hexdigest()[:32]


@dataclass
class DriveEstimate:
    """The smoothed road of a drive, per cycle."""

    distance: np.ndarray     # m
    w: np.ndarray            # m (offset and drift unobservable)
    var_w: np.ndarray        # m², relative to the body (RoadEstimate.var_w)
    w_filtered: np.ndarray   # m, the causal estimate


def estimate_drive(record: DriveRecord, model: QuarterCarModel, ts: float = 0.02,
                   estimator: Optional[RoadEKF] = None) -> DriveEstimate:
    """Return the RTS-smoothed road estimate of ``record`` (the default RoadEKF on ``model``)."""
    ekf = estimator or RoadEKF(model, ts, keep_history=True)
    if not ekf.keep_history:
        raise ValueError('estimate_drive needs a RoadEKF with keep_history=True')
    ekf.reset()
    u_now = _held(record.u_now, model.params.c_e0)
    u_mean = np.where(np.isfinite(record.u_mean), record.u_mean, u_now)
    ekf.start(record.y[0], u_now[0])
    for k in range(1, len(record.t)):
        ekf.cycle(record.y[k], u_mean[k], u_now[k], u_now[k - 1])
    sm = ekf.smooth()
    return DriveEstimate(np.asarray(record.distance, dtype=float), sm.w, sm.var_w,
                         sm.w_filtered)


def _held(u: np.ndarray, first: float) -> np.ndarray:
    """Return u with each NaN (a lost status frame) replaced by the last value before it."""
    out = np.array(u, dtype=float)
    last = first
    for i, v in enumerate(out):
        if math.isfinite(v):
            last = v
        else:
            out[i] = last
    return out


@dataclass
class GridProfile:
    """A drive's road detail on the map grid: node i is at i·grid_m along the route."""

    first: int               # index of the first node
    h: np.ndarray            # m, detail height per node (NaN: no data at that node)
    var: np.ndarray          # m² per node
    grid_m: float

    @property
    def nodes(self) -> np.ndarray:
        return self.first + np.arange(self.h.size)

    @property
    def s(self) -> np.ndarray:
        return self.nodes * self.grid_m

    def shifted(self, offset_m: float, scale: float = 0.0, origin_m: float = 0.0
                ) -> 'GridProfile':
        """Return the profile with its positions s mapped to s + offset + scale·(s − origin)."""
        s = self.s
        ok = np.isfinite(self.h)
        target = s + offset_m + scale * (s - origin_m)
        return _on_grid(target[ok], self.h[ok], self.var[ok], self.grid_m)


def _on_grid(s: np.ndarray, h: np.ndarray, var: np.ndarray, grid_m: float) -> GridProfile:
    """Interpolate samples (s increasing) to the grid nodes between them; holes stay NaN."""
    order = np.argsort(s, kind='stable')
    s, h, var = s[order], h[order], var[order]
    first = int(math.ceil(s[0] / grid_m - 1e-9))
    last = int(math.floor(s[-1] / grid_m + 1e-9))
    if last < first:
        raise MapError('drive shorter than one grid step of the map')
    nodes = np.arange(first, last + 1) * grid_m
    hn = np.interp(nodes, s, h)
    vn = np.interp(nodes, s, var)
    j = np.clip(np.searchsorted(s, nodes), 1, s.size - 1)
    hole = (s[j] - s[j - 1]) > MAX_STEP_M
    hn[hole] = np.nan
    return GridProfile(first, hn, vn, grid_m)


def grid_profile(est: DriveEstimate, grid_m: float, highpass_m: float,
                 skip_s: float = 1.0, ts: float = 0.02) -> GridProfile:
    """Return the drive's detail on the map grid, without its first ``skip_s`` (filter start).

    The smoothed height is put on the grid, high-passed there, and its variance
    interpolated.  Cycles at standstill (the distance not increasing by more than 1 mm)
    add nothing: only the first at each position is kept.  Reversing is an error.
    """
    skip = min(int(round(skip_s / ts)), max(len(est.w) - 2, 0))
    s, w, v = est.distance[skip:], est.w[skip:], est.var_w[skip:]
    ok = np.isfinite(s) & np.isfinite(w) & np.isfinite(v)
    s, w, v = s[ok], w[ok], v[ok]
    if s.size and np.any(np.diff(s) < -1e-3):
        raise MapError('drive: the odometry distance decreases (forward driving only)')
    keep = np.ones(s.size, dtype=bool)
    keep[1:] = s[1:] > np.maximum.accumulate(s)[:-1] + 1e-3
    s, w, v = s[keep], w[keep], v[keep]
    if s.size < 2:
        raise MapError('drive: the vehicle did not move')
    g = _on_grid(s, w, v, grid_m)
    g.h = highpass(g.h, grid_m, highpass_m)
    return g


__all__ = ['DriveRecord', 'DriveEstimate', 'GridProfile', 'estimate_drive', 'grid_profile',
           'MAX_STEP_M']
