"""The road map: heights and variances on a distance grid, fused over drives, in SQLite.

Schema (version :data:`SCHEMA_VERSION`; docs/road.md shows it with the fleet variant)::

    meta(key TEXT PRIMARY KEY, value TEXT NOT NULL)
        schema_version, route, grid_m, highpass_m, created_utc,
        residual_sum, residual_count  (the drives' normalised residuals, see below)
    nodes(i INTEGER PRIMARY KEY,       node i lies at i·grid_m along the route (m)
          info REAL NOT NULL,          Σ 1/v_d over the drives d (1/m²)
          info_height REAL NOT NULL,   Σ h_d/v_d (1/m)
          drives INTEGER NOT NULL)     how many drives saw the node
    drives(id INTEGER PRIMARY KEY AUTOINCREMENT, digest TEXT UNIQUE NOT NULL,
           source TEXT, vehicle TEXT, added_utc TEXT, first_node INTEGER,
           last_node INTEGER, offset_m REAL, scale REAL, origin_m REAL,
           correlation REAL, segments INTEGER, speed_mps REAL)
        a drive's odometry distance s is placed at s + offset_m + scale·(s − origin_m)

Fusion is by inverse variance, node by node: h = info_height / info, var = 1 / info.
Each drive adds to the two sums, so a new drive updates the map without the old drives
(incremental), the result does not depend on the order of the drives, and many writers
can add to one map (the fleet case: the same statements on a database server, docs).

Registration.  The first drive defines the map's distance axis.  Every later drive is
matched to the map before it is fused (:func:`register`): its detail, cut into segments,
is cross-correlated with the map's within ``search_m``; a line offset + scale·(s − s_0)
through the segments' offsets corrects its odometry (bias and scale error).  A drive that
matches nowhere (another route) is refused.

Variance scale.  The estimator's variances are those of the road relative to the car body
(erva_ros/core/road_estimator.py): right in ratio between drives, not in size.  When a
drive is added where the map has data, Σ (h_d − h_map)² / (v_d + v_map) over the overlap
is added to ``residual_sum`` (and the node count to ``residual_count``);
:attr:`MapProfile.variance_scale` is their ratio, and :meth:`MapProfile.var` is scaled by it.
"""

from dataclasses import dataclass
import contextlib
import datetime
import math
import os
import sqlite3
from typing import Dict, List

import numpy as np

from erva_ros.core.roadmap import MapError
from erva_ros.core.roadmap.drive import GridProfile
from erva_ros.core.roadmap.profile import highpass, match

SCHEMA_VERSION = 1
#: Registration: a segment must correlate at least this well to count, and at least
#: MIN_MATCHED of the segments must.  Two seeds of the paper road correlate ~0.84 (its
#: 1.7 Hz sine is the same on every seed); two drives of one route 0.99 and more.
MIN_CORRELATION = 0.9
MIN_MATCHED = 0.5
SCHEMA = """
CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE nodes (i INTEGER PRIMARY KEY, info REAL NOT NULL, info_height REAL NOT NULL,
                    drives INTEGER NOT NULL);
CREATE TABLE drives (id INTEGER PRIMARY KEY AUTOINCREMENT, digest TEXT UNIQUE NOT NULL,
                     source TEXT, vehicle TEXT, added_utc TEXT, first_node INTEGER,
                     last_node INTEGER, offset_m REAL, scale REAL, origin_m REAL,
                     correlation REAL, segments INTEGER, speed_mps REAL);
"""
#: How long a writer waits for another's lock before giving up (s).
LOCK_TIMEOUT_S = 2.0


@dataclass
class MapProfile:
    """The map in memory: per node i (first .. first + n − 1) the fused height and variance."""

    route: str
    grid_m: float
    highpass_m: float
    first: int
    info: np.ndarray         # Σ 1/v per node (0: no data: a gap)
    info_height: np.ndarray  # Σ h/v per node
    drives: np.ndarray       # drives per node
    residual_sum: float = 0.0
    residual_count: int = 0

    @property
    def n(self) -> int:
        return int(self.info.size)

    @property
    def valid(self) -> np.ndarray:
        return self.info > 0

    @property
    def s(self) -> np.ndarray:
        return (self.first + np.arange(self.n)) * self.grid_m

    @property
    def start_m(self) -> float:
        return self.first * self.grid_m

    @property
    def end_m(self) -> float:
        return (self.first + self.n - 1) * self.grid_m

    @property
    def h(self) -> np.ndarray:
        """Return the fused detail height per node (m; NaN in gaps)."""
        with np.errstate(invalid='ignore', divide='ignore'):
            return np.where(self.valid, self.info_height / self.info, np.nan)

    @property
    def variance_scale(self) -> float:
        """Return the factor the drives' residuals put on the estimator's variances (1: none)."""
        return self.residual_sum / self.residual_count if self.residual_count else 1.0

    @property
    def var(self) -> np.ndarray:
        """Return the fused variance per node times :attr:`variance_scale` (m²; inf: gap)."""
        with np.errstate(divide='ignore'):
            return np.where(self.valid, self.variance_scale / self.info, np.inf)

    def sample(self, s):
        """Return (height, variance, valid) at distances ``s`` (linear between nodes).

        Outside the map or next to a gap node: valid False, height NaN, variance inf.
        """
        s = np.asarray(s, dtype=float)
        pos = (s - self.start_m) / self.grid_m
        i0 = np.floor(pos).astype(int)
        frac = pos - i0
        inside = (i0 >= 0) & (i0 + 1 <= self.n - 1) | (np.abs(pos - (self.n - 1)) < 1e-9)
        i0 = np.clip(i0, 0, self.n - 1)
        i1 = np.clip(i0 + 1, 0, self.n - 1)
        valid = self.valid
        ok = inside & valid[i0] & valid[i1]
        h, v = self.h, self.var
        with np.errstate(invalid='ignore'):
            height = np.where(ok, h[i0] * (1 - frac) + h[i1] * frac, np.nan)
            var = np.where(ok, v[i0] * (1 - frac) + v[i1] * frac, np.inf)
        return height, var, ok

    def check_covers(self, route: str, start_m: float, end_m: float,
                     margin_m: float = 3.0) -> None:
        """Raise MapError (one line) unless the map is of ``route`` and covers the drive.

        What a session checks before it starts: the route name ('' on either side: not
        checked), the span [start_m − margin, end_m + margin] (odometry error and the
        preview horizon) inside the map, and no gap in it.
        """
        if route and self.route and route != self.route:
            raise MapError(f'the map is of route {self.route!r}, the session drives {route!r}')
        if not self.valid.any():
            raise MapError('the map is empty')
        lo, hi = start_m - margin_m, end_m + margin_m
        if lo < self.start_m or hi > self.end_m:
            raise MapError(f'the map covers {self.start_m:.1f}..{self.end_m:.1f} m, the '
                           f'session needs {lo:.1f}..{hi:.1f} m')
        inside = [(a, b) for a, b in self.gaps() if b >= lo and a <= hi]
        if inside:
            raise MapError(f'the map has a gap at {inside[0][0]:.1f}..{inside[0][1]:.1f} m, '
                           f'inside the {lo:.1f}..{hi:.1f} m the session needs')

    def gaps(self) -> List[tuple]:
        """Return the runs of nodes without data inside the map, as (start_m, end_m)."""
        out, i = [], 0
        valid = self.valid
        while i < self.n:
            if not valid[i]:
                j = i
                while j + 1 < self.n and not valid[j + 1]:
                    j += 1
                out.append(((self.first + i) * self.grid_m, (self.first + j) * self.grid_m))
                i = j + 1
            else:
                i += 1
        return out


@dataclass(frozen=True)
class Registration:
    """How a drive was placed on the map (identity for the first drive)."""

    offset_m: float
    scale: float
    origin_m: float
    correlation: float       # median over the segments used
    segments: int            # segments that matched (0: the first drive)


def register(profile: GridProfile, ref: MapProfile, search_m: float,
             segment_m: float = 20.0, refine_m: float = 0.5) -> Registration:
    """Return the offset and scale that put ``profile`` on the map ``ref`` (module doc).

    Two passes.  First the segments in driving order, each within ±``search_m`` of the
    line through the offsets found so far (a scale error moves the offset along the
    drive, beyond any fixed search); then every segment again within ±``refine_m`` of
    that line, and the line refitted.  MapError if too few segments match.
    """
    s, h = profile.s, profile.h
    origin = float(s[0])
    per = max(int(round(segment_m / profile.grid_m)), 8)
    segments = []
    for a in range(0, s.size - per // 2, per):
        seg = slice(a, min(a + per, s.size))
        ok = np.isfinite(h[seg])
        if ok.sum() >= per // 2:
            segments.append((s[seg][ok], h[seg][ok], float(np.mean(s[seg][ok])) - origin))

    def fit(mids, offs):
        if len(offs) >= 2 and np.ptp(mids) > 0:
            b, a0 = np.polyfit(mids, offs, 1)
            return float(a0), float(b)
        return (float(np.median(offs)), 0.0) if offs else (0.0, 0.0)

    result = None
    for refine in (False, True):
        line = result and (result.offset_m, result.scale)
        mids, offs, rhos = [], [], []
        for ss, hh, mid in segments:
            c = fit(mids, offs) if not refine else line
            m = match(ss, hh, ref.start_m, ref.grid_m, ref.h, c[0] + c[1] * mid,
                      refine_m if refine else search_m, ref.grid_m)
            if m.correlation >= MIN_CORRELATION and not m.at_edge:
                mids.append(mid)
                offs.append(m.offset_m)
                rhos.append(m.correlation)
        if len(offs) < max(1, MIN_MATCHED * len(segments)):
            if result is None:
                raise MapError(f'the drive matches the map nowhere ({len(offs)} of '
                               f'{len(segments)} {segment_m:g} m segments correlate >= '
                               f'{MIN_CORRELATION} within ±{search_m:g} m): another route, or '
                               'the map does not cover it')
            break
        a0, b = fit(mids, offs)
        result = Registration(a0, b, origin, float(np.median(rhos)), len(offs))
    return result


@dataclass(frozen=True)
class Comparison:
    """A map against a known road (:func:`compare`), errors in m."""

    offset_m: float          # where the map lies on the road (its first drive's odometry)
    scale: float
    correlation: float
    error_rms_m: float       # map − road detail, after placing the map on the road
    error_rms_unplaced_m: float  # the same at the map's own distances
    road_detail_rms_m: float
    predicted_std_m: float   # the map's own sqrt(mean variance)
    nodes: int               # nodes compared


def compare(profile: MapProfile, road_height, search_m: float = 3.0) -> Comparison:
    """Return how the map's detail matches the road ``road_height(s)`` (m along the route).

    The road gets the map's high-pass; the map is placed on it as a drive is on a map
    (:func:`register`), since the map's distances are its first drive's odometry.
    """
    if not profile.valid.any():
        raise MapError('the map is empty')
    margin = search_m + 4 * profile.highpass_m
    first = int(math.floor((profile.start_m - margin) / profile.grid_m))
    nodes = first + np.arange(int(round((profile.end_m - profile.start_m + 2 * margin)
                                        / profile.grid_m)) + 1)
    truth = highpass(np.asarray(road_height(nodes * profile.grid_m), dtype=float),
                     profile.grid_m, profile.highpass_m)
    ref = MapProfile('road', profile.grid_m, profile.highpass_m, first, np.ones(nodes.size),
                     truth, np.ones(nodes.size, dtype=int))
    own = GridProfile(profile.first, profile.h, np.where(profile.valid, 1 / np.maximum(
        profile.info, 1e-300), np.nan), profile.grid_m)
    reg = register(own, ref, search_m)
    placed = own.shifted(reg.offset_m, reg.scale, reg.origin_m)

    def err(g):
        t = np.interp(g.s, nodes * profile.grid_m, truth)
        ok = np.isfinite(g.h)
        return float(np.sqrt(np.mean((g.h[ok] - t[ok]) ** 2))), int(ok.sum())

    placed_err, n = err(placed)
    own_err, _ = err(own)
    ok = profile.valid
    return Comparison(reg.offset_m, reg.scale, reg.correlation, placed_err, own_err,
                      float(np.sqrt(np.mean(truth ** 2))),
                      float(np.sqrt(np.mean(profile.var[ok]))), n)


def _utc() -> str:
    return datetime.datetime.now(datetime.timezone.utc).isoformat(timespec='seconds')


class RoadMap:
    """A map file: open (or create) it, read it as a :class:`MapProfile`, add drives."""

    def __init__(self, path: str, conn: sqlite3.Connection, meta: Dict[str, str]):
        self.path = path
        self._conn = conn
        self.meta = meta

    # -- opening --------------------------------------------------------------------------
    @staticmethod
    def create(path: str, route: str, grid_m: float, highpass_m: float) -> 'RoadMap':
        """Create a new, empty map file at ``path`` (refuses an existing file)."""
        if os.path.exists(path):
            raise MapError(f'{path}: exists already')
        if not (math.isfinite(grid_m) and 0.01 <= grid_m <= 2.0):
            raise MapError(f'grid {grid_m!r} m: allowed [0.01, 2] m')
        try:
            conn = sqlite3.connect(path, timeout=LOCK_TIMEOUT_S, isolation_level=None)
            conn.executescript('BEGIN;' + SCHEMA + 'COMMIT;')
            meta = {'schema_version': str(SCHEMA_VERSION), 'route': route,
                    'grid_m': repr(float(grid_m)), 'highpass_m': repr(float(highpass_m)),
                    'created_utc': _utc(), 'residual_sum': '0.0', 'residual_count': '0'}
            conn.executemany('INSERT INTO meta VALUES (?, ?)', sorted(meta.items()))
        except sqlite3.Error as exc:
            raise MapError(f'{path}: cannot create the map ({exc})') from None
        return RoadMap(path, conn, meta)

    @staticmethod
    def open(path: str) -> 'RoadMap':
        """Open an existing map; a missing, foreign, corrupt or newer file is a MapError."""
        if not os.path.isfile(path):
            raise MapError(f'{path}: no such map file')
        try:
            conn = sqlite3.connect(f'file:{path}?mode=rw', uri=True, timeout=LOCK_TIMEOUT_S,
                                   isolation_level=None)
            rows = conn.execute('SELECT key, value FROM meta').fetchall()
            conn.execute('SELECT i, info, info_height, drives FROM nodes LIMIT 1').fetchall()
        except sqlite3.DatabaseError as exc:
            raise MapError(f'{path}: not a readable road map ({_why(exc)})') from None
        meta = dict(rows)
        version = meta.get('schema_version')
        if version != str(SCHEMA_VERSION):
            raise MapError(f'{path}: map schema version {version!r}, this erva_ros reads '
                           f'{SCHEMA_VERSION}')
        try:
            float(meta['grid_m']), float(meta['highpass_m'])
        except (KeyError, ValueError):
            raise MapError(f'{path}: damaged map (meta grid_m / highpass_m)') from None
        return RoadMap(path, conn, meta)

    def close(self) -> None:
        self._conn.close()

    def __enter__(self) -> 'RoadMap':
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # -- reading --------------------------------------------------------------------------
    @property
    def route(self) -> str:
        return self.meta.get('route', '')

    @property
    def grid_m(self) -> float:
        return float(self.meta['grid_m'])

    @property
    def highpass_m(self) -> float:
        return float(self.meta['highpass_m'])

    def profile(self) -> MapProfile:
        """Return the whole map in memory (one read)."""
        try:
            rows = self._conn.execute(
                'SELECT i, info, info_height, drives FROM nodes ORDER BY i').fetchall()
            meta = dict(self._conn.execute('SELECT key, value FROM meta').fetchall())
        except sqlite3.DatabaseError as exc:
            raise MapError(f'{self.path}: cannot read the map ({_why(exc)})') from None
        rs, rc = float(meta.get('residual_sum', 0)), int(meta.get('residual_count', 0))
        if not rows:
            return MapProfile(self.route, self.grid_m, self.highpass_m, 0, np.zeros(0),
                              np.zeros(0), np.zeros(0, dtype=int), rs, rc)
        a = np.array(rows, dtype=float)
        first, last = int(a[0, 0]), int(a[-1, 0])
        info, ih, dr = np.zeros(last - first + 1), np.zeros(last - first + 1), \
            np.zeros(last - first + 1, dtype=int)
        idx = a[:, 0].astype(int) - first
        info[idx], ih[idx], dr[idx] = a[:, 1], a[:, 2], a[:, 3].astype(int)
        return MapProfile(self.route, self.grid_m, self.highpass_m, first, info, ih, dr, rs, rc)

    def drives(self) -> List[Dict]:
        cur = self._conn.execute('SELECT * FROM drives ORDER BY id')
        names = [d[0] for d in cur.description]
        return [dict(zip(names, row)) for row in cur.fetchall()]

    # -- adding ---------------------------------------------------------------------------
    @contextlib.contextmanager
    def transaction(self):
        """Hold the map's write lock for a block: all of its adds commit, or none.

        The lock is taken first (another writer holds it: MapError after LOCK_TIMEOUT_S),
        so registration reads the map as it is then and concurrent writers never fuse
        against a map they did not see.
        """
        try:
            self._conn.execute('BEGIN IMMEDIATE')
        except sqlite3.OperationalError as exc:
            raise MapError(f'{self.path}: cannot write the map ({_why(exc)})') from None
        try:
            yield self
            self._conn.execute('COMMIT')
        except BaseException:
            self._conn.execute('ROLLBACK')
            raise
        finally:
            self.meta = dict(self._conn.execute('SELECT key, value FROM meta').fetchall())

    def add(self, profile: GridProfile, digest: str, source: str = '', vehicle: str = '',
            search_m: float = 3.0, speed_mps: float = math.nan) -> Registration:
        """Register ``profile`` on the map (unless it is the first) and fuse it, atomically."""
        with self.transaction():
            return self.add_locked(profile, digest, source, vehicle, search_m, speed_mps)

    def add_locked(self, profile: GridProfile, digest: str, source: str = '', vehicle: str = '',
                   search_m: float = 3.0, speed_mps: float = math.nan) -> Registration:
        """Do :meth:`add` inside a :meth:`transaction` the caller holds."""
        if not self._conn.in_transaction:
            raise RuntimeError('RoadMap.add_locked needs transaction()')
        if abs(profile.grid_m - self.grid_m) > 1e-12:
            raise MapError(f'drive on a {profile.grid_m:g} m grid, the map has {self.grid_m:g} m')
        if self._conn.execute('SELECT 1 FROM drives WHERE digest = ?', (digest,)).fetchone():
            raise MapError(f'{source or "drive"}: already in the map {self.path}')
        current = self.profile()
        if current.n and current.valid.any():
            reg = register(profile, current, search_m)
            placed = profile.shifted(reg.offset_m, reg.scale, reg.origin_m)
        else:
            reg, placed = Registration(0.0, 0.0, 0.0, 1.0, 0), profile
        self._fuse(placed, current)
        self._conn.execute(
            'INSERT INTO drives (digest, source, vehicle, added_utc, first_node, last_node, '
            'offset_m, scale, origin_m, correlation, segments, speed_mps) '
            'VALUES (?,?,?,?,?,?,?,?,?,?,?,?)',
            (digest, source, vehicle, _utc(), int(placed.first),
             int(placed.first + placed.h.size - 1), reg.offset_m, reg.scale, reg.origin_m,
             reg.correlation, reg.segments, speed_mps))
        return reg

    def _fuse(self, g: GridProfile, current: MapProfile) -> None:
        ok = np.isfinite(g.h) & np.isfinite(g.var) & (g.var > 0)
        nodes, h, v = g.nodes[ok], g.h[ok], g.var[ok]
        if current.n:
            mh, mv, mok = current.sample(nodes * g.grid_m)
            mv = mv / current.variance_scale           # back to the estimator's scale
            both = mok
            if both.any():
                r = float(np.sum((h[both] - mh[both]) ** 2 / (v[both] + mv[both])))
                meta = dict(self._conn.execute('SELECT key, value FROM meta').fetchall())
                self._conn.executemany('UPDATE meta SET value = ? WHERE key = ?', (
                    (repr(float(meta['residual_sum']) + r), 'residual_sum'),
                    (str(int(meta['residual_count']) + int(both.sum())), 'residual_count')))
        self._conn.executemany(
            'INSERT INTO nodes (i, info, info_height, drives) VALUES (?, ?, ?, 1) '
            'ON CONFLICT(i) DO UPDATE SET info = info + excluded.info, '
            'info_height = info_height + excluded.info_height, drives = drives + 1',
            [(int(i), float(1.0 / vi), float(hi / vi)) for i, hi, vi in zip(nodes, h, v)])


def _why(exc: Exception) -> str:
    text = str(exc).strip().splitlines()
    return text[0] if text else type(exc).__name__


__all__ = ['SCHEMA', 'SCHEMA_VERSION', 'MIN_CORRELATION', 'MIN_MATCHED', 'MapProfile',
           'Registration', 'RoadMap', 'register', 'Comparison', 'compare']
