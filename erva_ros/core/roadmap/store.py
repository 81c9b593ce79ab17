"""The road map: heights and variances on a distance grid, fused over drives.

The map lives in an SQLite file or on a PostgreSQL server (:mod:`.location`, the two
databases: :mod:`.backends`); this module is the same for both.  Schema (version
:data:`~erva_ros.core.roadmap.backends.SCHEMA_VERSION`; docs/road.md)::

    meta(key TEXT PRIMARY KEY, value TEXT NOT NULL)
        schema_version, route, grid_m, highpass_m, created_utc
    nodes(i INTEGER PRIMARY KEY,       node i lies at i·grid_m along the route (m)
          info REAL NOT NULL,          Σ 1/v_d over the drives d (1/m²)
          info_height REAL NOT NULL,   Σ h_d/v_d (1/m)
          drives INTEGER NOT NULL)     how many drives saw the node
    drives(id INTEGER PRIMARY KEY AUTOINCREMENT, digest TEXT UNIQUE NOT NULL,
           source TEXT, vehicle TEXT, added_utc TEXT, first_node INTEGER,
           last_node INTEGER, offset_m REAL, scale REAL, origin_m REAL,
           correlation REAL, segments INTEGER, speed_mps REAL,
           residual_sum REAL, residual_count INTEGER, added_by TEXT)
        a drive's odometry distance s is placed at s + offset_m + scale·(s − origin_m)

Fusion is by inverse variance, node by node: h = info_height / info, var = 1 / info.
Each drive adds to the two sums, so a new drive updates the map without the old drives
(incremental), the sums do not depend on the order of the drives, and many writers can
add to one map at once (:meth:`RoadMap.add_drives`).

Registration.  The first drive defines the map's distance axis.  Every later drive is
matched to the map before it is fused (:func:`register`): its detail, cut into segments,
is cross-correlated with the map's within ``search_m``; a line offset + scale·(s − s_0)
through the segments' offsets corrects its odometry (bias and scale error).  A drive that
matches nowhere (another route) is refused.  Registration reads only the drive's section
of the map (:meth:`DriveItem.span`).

Variance scale.  The estimator's variances are those of the road relative to the car body
(erva_ros/core/model/road_estimator.py): right in ratio between drives, not in size.  When a
drive is added where the map has data, Σ (h_d − h_map)² / (v_d + v_map) over the overlap
is stored with the drive (``residual_sum``, and the node count ``residual_count``; a
version-1 file kept the totals in meta);
:attr:`MapProfile.variance_scale` is their ratio over all drives, and :meth:`MapProfile.var`
is scaled by it.
"""

from dataclasses import dataclass
import contextlib
import datetime
import math
import os
import sqlite3
import tempfile
import time
from typing import Dict, List, Optional, Sequence, Tuple, Union

import numpy as np

from erva_ros.core.roadmap import MapError
from erva_ros.core.roadmap.backends import connect, Db, finite_or_none, SCHEMA_VERSION, SqliteDb
from erva_ros.core.roadmap.drive import GridProfile
from erva_ros.core.roadmap.location import MapLocation, parse_location
from erva_ros.core.roadmap.profile import highpass, match

#: Registration: a segment must correlate at least this well to count, and at least
#: MIN_MATCHED of the segments must.  Two seeds of the paper road correlate ~0.84 (its
#: 1.7 Hz sine is the same on every seed); two drives of one route 0.99 and more.
MIN_CORRELATION = 0.9
MIN_MATCHED = 0.5
#: How long a writer waits for another's write lock before giving up (s).  The lock is
#: held for a transaction's sums (ms per drive), not for the registration.
LOCK_TIMEOUT_S = 10.0
#: A writer whose section another writer changed since its snapshot starts its add again
#: (registration without the lock) this many times, then registers under the lock.
OPTIMISTIC_TRIES = 3


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


def _location(location: Union[str, MapLocation]) -> MapLocation:
    return location if isinstance(location, MapLocation) else parse_location(location)


@dataclass(frozen=True)
class DriveItem:
    """A drive to add: its profile on the map grid and what the drives table records."""

    profile: GridProfile
    digest: str
    source: str = ''
    vehicle: str = ''
    route: str = ''              # the drive's route ('' unknown: not checked)
    speed_mps: float = math.nan
    search_m: float = 3.0        # registration: odometry error searched, ± m

    def span(self) -> Tuple[int, int]:
        """Return the nodes registration may read: the drive's ± what it may be moved."""
        g = self.profile
        length_m = g.h.size * g.grid_m
        margin = int(math.ceil((2 * self.search_m + 0.02 * length_m + 20.0) / g.grid_m))
        return g.first - margin, g.first + g.h.size - 1 + margin


class RoadMap:
    """A map (a file or a server, :mod:`~erva_ros.core.roadmap.location`): read it, add drives.

    Adding is safe with many writers at once (the fleet case, docs/fleet.md):
    :meth:`add_drives` registers each drive against a consistent snapshot of its section
    without holding any lock, then takes the map's write lock, re-registers only if a
    drive that overlaps the section was added since the snapshot, and adds the sums.  So
    the result is always that of adding the drives one after another in the order they
    committed, and the write lock is held for the sums, not for the registration.
    """

    def __init__(self, db: Db, meta: Dict[str, str]):
        self.db = db
        self.meta = meta

    @property
    def location(self) -> MapLocation:
        return self.db.location

    @property
    def path(self) -> str:
        """Return the map's location as it may be shown (a path, or a URI without secret)."""
        return self.db.name

    # -- opening --------------------------------------------------------------------------
    @staticmethod
    def create(location, route: str, grid_m: float, highpass_m: float) -> 'RoadMap':
        """Create a new, empty map at ``location`` (refuses an existing one)."""
        loc = _location(location)
        if not (math.isfinite(grid_m) and 0.01 <= grid_m <= 2.0):
            raise MapError(f'grid {grid_m!r} m: allowed [0.01, 2] m')
        meta = {'schema_version': str(SCHEMA_VERSION), 'route': route,
                'grid_m': repr(float(grid_m)), 'highpass_m': repr(float(highpass_m)),
                'created_utc': _utc()}
        if not loc.server:
            if loc.target != ':memory:' and os.path.exists(loc.target):
                raise MapError(f'{loc.display}: exists already')
            db = SqliteDb(loc, LOCK_TIMEOUT_S, create=True)
            try:
                db.create_schema(meta)
            except sqlite3.Error as exc:
                db.close()
                raise MapError(f'{loc.display}: cannot create the map ({_why(exc)})') from None
            return RoadMap(db, meta)
        road_map, created = RoadMap._open_or_create_server(loc, meta)
        if not created:
            road_map.close()
            raise MapError(f'{loc.display}: exists already')
        return road_map

    @staticmethod
    def _open_or_create_server(loc: MapLocation, meta: Dict[str, str]):
        db = connect(loc, LOCK_TIMEOUT_S)
        try:
            if db.schema_exists():             # the common case: no lock to open a map
                db.close()
                return RoadMap.open(loc), False
            db.begin_write(LOCK_TIMEOUT_S)     # two creators: one creates, one waits
            created = not db.schema_exists()
            if created:
                db.create_schema(meta)
            db.commit()
        except BaseException as exc:
            db.rollback()
            db.close()
            err = db.map_error(exc, 'cannot create the map')
            if err:
                raise err from None
            raise
        if created:
            return RoadMap(db, dict(meta)), True
        db.close()
        return RoadMap.open(loc), False

    @staticmethod
    def open_or_create(location, route: str, grid_m: float, highpass_m: float):
        """Return (the map, created): the map at a server ``location``, created if missing.

        Two vehicles creating one map at once: one creates it, the other waits for the
        write lock and opens it (SQLite files: :func:`add_to_map`).
        """
        loc = _location(location)
        if not loc.server:
            raise ValueError('open_or_create is for server maps; files: add_to_map')
        if not (math.isfinite(grid_m) and 0.01 <= grid_m <= 2.0):
            raise MapError(f'grid {grid_m!r} m: allowed [0.01, 2] m')
        meta = {'schema_version': str(SCHEMA_VERSION), 'route': route,
                'grid_m': repr(float(grid_m)), 'highpass_m': repr(float(highpass_m)),
                'created_utc': _utc()}
        return RoadMap._open_or_create_server(loc, meta)

    @staticmethod
    def exists(location) -> bool:
        """Return whether a map is at ``location`` (a server must be reachable: else MapError)."""
        loc = _location(location)
        if not loc.server:
            return os.path.exists(loc.target)
        db = connect(loc, LOCK_TIMEOUT_S)
        try:
            return db.schema_exists()
        finally:
            db.close()

    @staticmethod
    def open(location) -> 'RoadMap':
        """Open an existing map; a missing, foreign, corrupt or newer one is a MapError."""
        loc = _location(location)
        name = loc.display
        if not loc.server and not os.path.isfile(loc.target):
            raise MapError(f'{name}: no such map file')
        db = connect(loc, LOCK_TIMEOUT_S)
        try:
            if db.kind == 'postgresql' and not db.schema_exists():
                raise MapError(f'{name}: no road map on this server (erva map build or '
                               'erva map migrate makes one)')
            rows = db.execute('SELECT key, value FROM meta')
            db.execute('SELECT i, info, info_height, drives FROM nodes LIMIT 1')
        except MapError:
            db.close()
            raise
        except Exception as exc:
            db.close()
            if isinstance(exc, sqlite3.DatabaseError):
                raise MapError(f'{name}: not a readable road map ({_why(exc)})') from None
            err = db.map_error(exc, 'cannot read the map')
            if err:
                raise err from None
            raise
        meta = dict(rows)
        version = meta.get('schema_version')
        if version not in (str(SCHEMA_VERSION), '1' if db.kind == 'sqlite' else None):
            db.close()
            raise MapError(f'{name}: map schema version {version!r}, this erva_ros reads '
                           f'{SCHEMA_VERSION} (and 1): a newer erva_ros wrote it')
        try:
            float(meta['grid_m']), float(meta['highpass_m'])
        except (KeyError, ValueError):
            db.close()
            raise MapError(f'{name}: damaged map (meta grid_m / highpass_m)') from None
        return RoadMap(db, meta)

    def close(self) -> None:
        self.db.close()

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

    @property
    def version(self) -> int:
        return int(self.meta.get('schema_version', SCHEMA_VERSION))

    @contextlib.contextmanager
    def snapshot(self):
        """Read the map as one consistent snapshot within the block (nested: the outer one)."""
        if self.db.in_tx:
            yield self
            return
        try:
            self.db.begin_read()
            yield self
            self.db.commit()
        except BaseException as exc:
            if self.db.in_tx:
                self.db.rollback()
            self._raise(exc, 'cannot read the map')

    def _raise(self, exc: BaseException, doing: str):
        """Re-raise ``exc``, a database error as its one-line MapError."""
        err = None if isinstance(exc, MapError) else self.db.map_error(exc, doing)
        if err is not None:
            raise err from None
        raise exc

    def profile(self, start_m: Optional[float] = None, end_m: Optional[float] = None
                ) -> MapProfile:
        """Return the map in memory, or its section [start_m, end_m] (one snapshot)."""
        lo = -2 ** 62 if start_m is None else int(math.floor(start_m / self.grid_m))
        hi = 2 ** 62 if end_m is None else int(math.ceil(end_m / self.grid_m))
        with self.snapshot():
            meta = dict(self.db.execute('SELECT key, value FROM meta'))
            p = self._section(lo, hi)
            rs, rc = float(meta.get('residual_sum', 0)), int(meta.get('residual_count', 0))
            if self.version >= 2:
                s, c = self.db.execute('SELECT SUM(residual_sum), SUM(residual_count) '
                                       'FROM drives')[0]
                rs, rc = rs + float(s or 0.0), rc + int(c or 0)
        p.residual_sum, p.residual_count = rs, rc
        return p

    def _section(self, lo: int, hi: int) -> MapProfile:
        """Return nodes lo..hi at the estimator's variance (scale 1), inside a transaction."""
        rows = self.db.execute('SELECT i, info, info_height, drives FROM nodes '
                               'WHERE i >= ? AND i <= ? ORDER BY i', (lo, hi))
        if not rows:
            return MapProfile(self.route, self.grid_m, self.highpass_m, 0, np.zeros(0),
                              np.zeros(0), np.zeros(0, dtype=int))
        a = np.array(rows, dtype=float)
        first, last = int(rows[0][0]), int(rows[-1][0])
        info, ih, dr = np.zeros(last - first + 1), np.zeros(last - first + 1), \
            np.zeros(last - first + 1, dtype=int)
        idx = a[:, 0].astype(np.int64) - first
        info[idx], ih[idx], dr[idx] = a[:, 1], a[:, 2], a[:, 3].astype(int)
        return MapProfile(self.route, self.grid_m, self.highpass_m, first, info, ih, dr)

    def drives(self) -> List[Dict]:
        with self.snapshot():
            names, rows = self.db.columns('SELECT * FROM drives ORDER BY id')
        return [dict(zip(names, row)) for row in rows]

    def has_drive(self, digest: str) -> bool:
        with self.snapshot():
            return bool(self.db.execute('SELECT 1 FROM drives WHERE digest = ?', (digest,)))

    # -- adding ---------------------------------------------------------------------------
    def add(self, profile: GridProfile, digest: str, source: str = '', vehicle: str = '',
            search_m: float = 3.0, speed_mps: float = math.nan) -> Registration:
        """Register ``profile`` on the map (unless it is the first) and fuse it, atomically."""
        return self.add_drives([DriveItem(profile, digest, source, vehicle, '', speed_mps,
                                          search_m)])[0]

    def add_drives(self, items: Sequence[DriveItem], timing: Optional[Dict] = None
                   ) -> List[Registration]:
        """Add ``items`` in one transaction (all or none); writers may run at once (class doc).

        ``timing`` (a dict) gets the stages' wall times in s -- ``read`` (the snapshot),
        ``register`` (without a lock), ``write`` (waiting for the lock, the sums, the
        commit), ``again`` (drives registered again under the lock) and ``retries`` (adds
        started again because another writer changed the section meanwhile).
        """
        clock = time.perf_counter
        times = {'read': 0.0, 'register': 0.0, 'write': 0.0, 'again': 0, 'retries': 0}
        for it in items:
            if abs(it.profile.grid_m - self.grid_m) > 1e-12:
                raise MapError(f'drive on a {it.profile.grid_m:g} m grid, the map has '
                               f'{self.grid_m:g} m')
            self._check_route(it)
        if self.version < SCHEMA_VERSION:
            try:
                self.db.upgrade(str(self.version))
            except Exception as exc:
                self._raise(exc, 'cannot upgrade the map')
            self.meta['schema_version'] = str(SCHEMA_VERSION)
        for attempt in range(OPTIMISTIC_TRIES + 1):
            t0 = clock()
            with self.snapshot():                      # 1. what the map is now
                snap_id = int(self.db.execute('SELECT MAX(id) FROM drives')[0][0] or 0)
                empty = not self.db.execute('SELECT 1 FROM nodes LIMIT 1')
                refs = []
                for it in items:
                    self._check_new(it)
                    refs.append(None if empty else self._section(*it.span()))
            t1 = clock()
            regs = []                                  # 2. registered without a lock
            for it, ref in zip(items, refs):
                try:
                    regs.append(self._register(it, ref))
                except MapError:
                    regs.append(None)                  # again under the lock: it may match then
            t2 = clock()
            times['read'] += t1 - t0
            times['register'] += t2 - t1
            try:                                       # 3. the sums, under the write lock
                self.db.begin_write(LOCK_TIMEOUT_S)
            except Exception as exc:
                self._raise(exc, 'cannot write the map')
            try:
                out = self._add_locked(items, refs, regs, snap_id, empty,
                                       attempt < OPTIMISTIC_TRIES, times)
                if out is None:                        # another writer was first: again
                    self.db.rollback()
                    times['retries'] += 1
                    times['write'] += clock() - t2
                    continue
                self.db.commit()
            except BaseException as exc:
                self.db.rollback()
                self._raise(exc, 'cannot add to the map')
            times['write'] += clock() - t2
            break
        if timing is not None:
            timing.update(times)
        self.meta = dict(self.db.execute('SELECT key, value FROM meta'))
        return out

    def _add_locked(self, items, refs, regs, snap_id: int, empty: bool, may_retry: bool,
                    times: Dict) -> Optional[List[Registration]]:
        """Fuse ``items`` under the write lock; None if a retry is better (add_drives).

        A drive is registered again (here, under the lock) when the map in its section
        changed since the snapshot: another writer's drive there (then, while
        ``may_retry``, the whole add starts again without the lock instead), or an
        earlier drive of this same transaction.
        """
        own: List[int] = []
        out = []
        for it, ref, reg in zip(items, refs, regs):
            self._check_new(it)
            lo, hi = it.span()
            mine = ' AND id NOT IN (' + ', '.join(map(str, own)) + ')' if own else ''
            where = '' if empty else ' AND first_node <= ? AND last_node >= ?'
            others = bool(self.db.execute(f'SELECT 1 FROM drives WHERE id > ?{mine}{where} '
                                          'LIMIT 1', (snap_id,) + (() if empty else (hi, lo))))
            if others and may_retry:
                return None
            ours = bool(own) and bool(self.db.execute(
                f'SELECT 1 FROM drives WHERE id IN ({", ".join(map(str, own))}) AND '
                'first_node <= ? AND last_node >= ? LIMIT 1', (hi, lo)))
            if others or ours or reg is None or (empty and own):
                now_empty = not self.db.execute('SELECT 1 FROM nodes LIMIT 1')
                ref = None if now_empty else self._section(lo, hi)
                reg = self._register(it, ref)
                times['again'] += 1
            own.append(self._fuse(it, reg, ref))
            out.append(reg)
        return out

    def drop_if_empty(self) -> bool:
        """Remove a server map that has no drive (a failed first build); return if removed."""
        try:
            self.db.begin_write(LOCK_TIMEOUT_S)
            gone = not self.db.execute('SELECT 1 FROM drives LIMIT 1')
            if gone:
                self.db.drop_schema()
            self.db.commit()
            return gone
        except Exception as exc:
            self.db.rollback()
            self._raise(exc, 'cannot remove the empty map')

    def _check_route(self, it: DriveItem) -> None:
        if it.route and self.route and it.route != self.route:
            raise MapError(f'{it.source or "drive"}: drive on route {it.route!r}, the map is '
                           f'of route {self.route!r}')

    def _check_new(self, it: DriveItem) -> None:
        if self.db.execute('SELECT 1 FROM drives WHERE digest = ?', (it.digest,)):
            raise MapError(f'{it.source or "drive"}: already in the map {self.path}')

    @staticmethod
    def _register(it: DriveItem, ref: Optional[MapProfile]) -> Registration:
        if ref is None:
            return Registration(0.0, 0.0, 0.0, 1.0, 0)      # the first drive: the axis
        if not ref.valid.any():
            raise MapError(f'the drive matches the map nowhere (the map has no data within '
                           f'{it.search_m:g} m of {it.profile.s[0]:.1f}..'
                           f'{it.profile.s[-1]:.1f} m): another route, or the map does not '
                           'cover it')
        return register(it.profile, ref, it.search_m)

    def _fuse(self, it: DriveItem, reg: Registration, ref: Optional[MapProfile]) -> int:
        g = it.profile
        if ref is not None:
            g = g.shifted(reg.offset_m, reg.scale, reg.origin_m)
        ok = np.isfinite(g.h) & np.isfinite(g.var) & (g.var > 0)
        nodes, h, v = g.nodes[ok], g.h[ok], g.var[ok]
        r, count = 0.0, 0
        if ref is not None and ref.n:
            mh, mv, mok = ref.sample(nodes * g.grid_m)   # mv: 1/info (scale 1)
            if mok.any():
                r = float(np.sum((h[mok] - mh[mok]) ** 2 / (v[mok] + mv[mok])))
                count = int(mok.sum())
        row = {'digest': it.digest, 'source': it.source, 'vehicle': it.vehicle,
               'added_utc': _utc(), 'first_node': int(g.first),
               'last_node': int(g.first + g.h.size - 1), 'offset_m': reg.offset_m,
               'scale': reg.scale, 'origin_m': reg.origin_m, 'correlation': reg.correlation,
               'segments': reg.segments, 'speed_mps': finite_or_none(it.speed_mps),
               'residual_sum': r, 'residual_count': count}
        return self.db.add_drive(row, nodes, 1.0 / v, h / v)


def add_to_map(location, items: Sequence[DriveItem], route: str, grid_m: float,
               highpass_m: float) -> Tuple[RoadMap, bool, List[Registration]]:
    """Add ``items`` to the map at ``location``, created (route, grid, high-pass) if missing.

    Return (the open map, created, registrations).  Race-free: of two builds into a new
    map, one creates it and the other adds to it.  A new SQLite file is built complete in
    a temporary file beside it and linked into place only if no other build got there
    first (then the drives are added to that one); a failed build leaves no file.  A new
    server map is created under the write lock.
    """
    loc = _location(location)
    if loc.server:
        road_map, created = RoadMap.open_or_create(loc, route, grid_m, highpass_m)
        try:
            return road_map, created, road_map.add_drives(items)
        except BaseException:
            if created:
                road_map.drop_if_empty()
            road_map.close()
            raise
    path = loc.target
    if path == ':memory:' or os.path.exists(path):
        road_map = RoadMap.open(loc)
        try:
            return road_map, False, road_map.add_drives(items)
        except BaseException:
            road_map.close()
            raise
    directory = os.path.dirname(os.path.abspath(path))
    fd, tmp = tempfile.mkstemp(prefix='.' + os.path.basename(path) + '.', dir=directory)
    os.close(fd)
    os.remove(tmp)
    try:
        with RoadMap.create(tmp, route, grid_m, highpass_m) as new:
            regs = new.add_drives(items)
        try:
            os.link(tmp, path)                  # atomic: fails if another build made it
        except FileExistsError:
            road_map = RoadMap.open(loc)
            try:
                return road_map, False, road_map.add_drives(items)
            except BaseException:
                road_map.close()
                raise
        return RoadMap.open(loc), True, regs
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)


def _why(exc: Exception) -> str:
    text = str(exc).strip().splitlines()
    return text[0] if text else type(exc).__name__


__all__ = ['SCHEMA_VERSION', 'MIN_CORRELATION', 'MIN_MATCHED', 'MapProfile', 'Registration',
           'RoadMap', 'DriveItem', 'add_to_map', 'register', 'Comparison', 'compare']
