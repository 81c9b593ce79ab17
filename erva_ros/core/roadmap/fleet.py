"""A fleet's map on a server, as a vehicle uses it: a local cache, migration, roles.

**The loop never waits on the network.**  Before a drive the vehicle fetches its route's
section from the server into a local SQLite map (:func:`fetch_section`: one snapshot,
written to a temporary file and renamed into place, so a cache is always whole), and the
preview reads only that file.  A server that cannot be reached at the start is no stop
when a cache of that map exists (:func:`session_map`: one WARN line); a drive recorded
meanwhile is uploaded later (``erva map build`` / ``erva map sync``: a drive is known by
its digest, so nothing is added twice and nothing is lost).

:func:`migrate` copies a map between the databases (SQLite ↔ PostgreSQL) value for value;
:func:`grant_roles` creates the roles a fleet needs (:meth:`~erva_ros.core.roadmap.
backends.PostgresDb.grant_roles`).
"""

from dataclasses import dataclass
import os
import tempfile
import time
from typing import Any, Callable, Dict, List, Mapping, Optional, Sequence, Tuple

from erva_ros.core.roadmap import MapError, MapUnreachable
from erva_ros.core.roadmap.backends import DRIVE_COLUMNS, PostgresDb
from erva_ros.core.roadmap.bag_drive import route_of_live
from erva_ros.core.roadmap.location import cache_path, MapLocation, parse_location
from erva_ros.core.roadmap.store import _utc, RoadMap

#: Metres fetched beyond what a session needs at either end (odometry error, alignment).
SECTION_MARGIN_M = 20.0
#: Meta keys of a cache (the server map's own keys are copied as they are).
CACHE_KEYS = ('cache_source', 'cache_fetched_utc', 'cache_start_m', 'cache_end_m')


@dataclass(frozen=True)
class Fetched:
    """A route section in a local cache: where, from which map, what it holds."""

    cache: str
    source: str              # the server map, as it may be shown (no password)
    start_m: float           # the section asked for
    end_m: float
    nodes: int               # nodes with data in the cache
    fetched_utc: str
    seconds: float           # the fetch's wall time (0 for a cache used offline)


def fetch_section(location, start_m: float, end_m: float,
                  cache: Optional[str] = None) -> Fetched:
    """Copy the map's section [start_m, end_m] from ``location`` into a local SQLite cache.

    One snapshot of the server; written to a temporary file beside the cache and renamed
    over it, so a reader never sees half a cache.  The cache keeps the server map's meta,
    its variance scale (the residual totals over all drives) and where it came from.
    """
    loc = location if isinstance(location, MapLocation) else parse_location(location)
    cache = cache or cache_path(loc)
    t0 = time.perf_counter()
    with RoadMap.open(loc) as road_map:
        with road_map.snapshot():
            p = road_map.profile(start_m, end_m)
            meta = dict(road_map.meta)
    fetched = _utc()
    os.makedirs(os.path.dirname(os.path.abspath(cache)), exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix='.fetch.', suffix='.db',
                               dir=os.path.dirname(os.path.abspath(cache)))
    os.close(fd)
    os.remove(tmp)
    try:
        with RoadMap.create(tmp, p.route, p.grid_m, p.highpass_m) as out:
            extra = {k: v for k, v in meta.items() if k not in (
                'schema_version', 'route', 'grid_m', 'highpass_m', *CACHE_KEYS)}
            extra.update(residual_sum=repr(p.residual_sum),
                         residual_count=str(p.residual_count), cache_source=loc.display,
                         cache_fetched_utc=fetched, cache_start_m=repr(float(start_m)),
                         cache_end_m=repr(float(end_m)))
            db = out.db
            db.begin_write(1.0)
            db.execute('DELETE FROM meta WHERE key NOT IN '
                       "('schema_version', 'route', 'grid_m', 'highpass_m')")
            db.copy_rows('meta', ('key', 'value'), sorted(extra.items()))
            ok = p.info > 0
            db.copy_rows('nodes', ('i', 'info', 'info_height', 'drives'), zip(
                (p.first + i for i in range(p.n) if ok[i]), p.info[ok].tolist(),
                p.info_height[ok].tolist(), p.drives[ok].tolist()))
            db.commit()
        os.replace(tmp, cache)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)
    return Fetched(cache, loc.display, float(start_m), float(end_m), int(ok.sum()), fetched,
                   time.perf_counter() - t0)


def cached(cache: str) -> Optional[Fetched]:
    """Return what the cache file ``cache`` holds (None: no cache there)."""
    if not os.path.isfile(cache):
        return None
    with RoadMap.open(cache) as m:
        meta = m.meta
        if 'cache_source' not in meta:
            return None
        nodes = int(m.db.execute('SELECT COUNT(*) FROM nodes')[0][0])
    return Fetched(cache, meta['cache_source'], float(meta['cache_start_m']),
                   float(meta['cache_end_m']), nodes, meta['cache_fetched_utc'], 0.0)


def session_map(text: str, start_m: float, end_m: float,
                say: Callable[[str], None]) -> tuple:
    """Return (the local file a session previews from, what it shows as the map's location).

    An SQLite path is used as it is.  A server map's section [start_m, end_m] (± the
    margin) is fetched into its cache; a server that cannot be reached falls back to an
    existing cache with one WARN line through ``say``; without a cache it is a MapError.
    """
    loc = parse_location(text)
    if not loc.server:
        return text, text
    lo, hi = start_m - SECTION_MARGIN_M, end_m + SECTION_MARGIN_M
    cache = cache_path(loc)
    try:
        f = fetch_section(loc, lo, hi, cache)
    except MapUnreachable as exc:
        old = cached(cache)
        if old is None:
            raise MapError(f'{exc}; no local cache of this map ({cache})') from None
        say(f'WARN map server unreachable ({str(exc).split(": ", 1)[-1]}): the preview '
            f'comes from the cache fetched {old.fetched_utc}, {old.start_m:.0f}..'
            f'{old.end_m:.0f} m ({old.cache})')
        return old.cache, loc.display
    say(f'map: fetched {lo:.0f}..{hi:.0f} m of {loc.display} ({f.nodes} nodes, '
        f'{f.seconds * 1e3:.0f} ms) into {f.cache}; the preview reads only that')
    return f.cache, loc.display


def session_span(live: Mapping[str, Any]) -> Tuple[float, float]:
    """Return the part of the route a session drives and previews: (0, end) in m."""
    drive_m = live['speed_mps'] * live['duration_s']
    return 0.0, drive_m + live['speed_mps'] * live['preview_steps'] * live['ts']


def check_session_map(path: str, live: Mapping[str, Any], margin_m: float = 3.0) -> str:
    """Return ``path`` made absolute once the map serves this session; MapError (one line).

    The map must open, be of the session's route (its road, seed and speed), reach
    ``margin_m`` beyond the drive's end plus the preview horizon, and have no gap from its
    start on.  The metres before its start (a map from drives starts after their filters
    settled) get the no-preview prediction, counted; a map that starts only after the
    drive's end is refused.
    """
    path = os.path.abspath(path)
    with RoadMap.open(path) as road_map:
        profile = road_map.profile()
    drive_m = live['speed_mps'] * live['duration_s']
    end_m = session_span(live)[1]
    try:
        if profile.valid.any() and profile.start_m >= drive_m:
            raise MapError(f'the map starts at {profile.start_m:.1f} m, after the session\'s '
                           f'drive (0..{drive_m:.1f} m)')
        profile.check_covers(route_of_live(live), max(profile.start_m, 0.0) + margin_m, end_m,
                             margin_m)
    except MapError as exc:
        raise MapError(f'{path}: {exc}') from None
    return path


def map_for_session(text: str, live: Mapping[str, Any], say: Callable[[str], None]) -> tuple:
    """Return (the checked local map file of a session's preview, the map as shown).

    The session's span of the route (:func:`session_span`) from a file or a server's
    section (:func:`session_map`), then checked against the session
    (:func:`check_session_map`); MapError (one line) if it cannot serve.
    """
    path, shown = session_map(text, *session_span(live), say)
    return check_session_map(path, live), shown


# -- migration ----------------------------------------------------------------------------
def migrate(source, target) -> Dict[str, int]:
    """Copy the map ``source`` to the new map ``target``, value for value; return counts.

    Any direction (SQLite ↔ PostgreSQL, or the same kind).  The target must not exist
    (a server: no map in that database / schema).  Rows keep their ids; a version-1 file
    is read as it is and written as the current version.
    """
    with RoadMap.open(source) as src:
        with src.snapshot():
            meta = dict(src.db.execute('SELECT key, value FROM meta'))
            nodes = src.db.execute('SELECT i, info, info_height, drives FROM nodes ORDER BY i')
            names, rows = src.db.columns('SELECT * FROM drives ORDER BY id')
        drives = [dict(zip(names, r)) for r in rows]
    if RoadMap.exists(target):
        raise MapError(f'{parse_location(target).display}: exists already (migrate writes a '
                       'new map only)')
    dst = RoadMap.create(target, meta.get('route', ''), float(meta['grid_m']),
                         float(meta['highpass_m']))
    cols = ('id',) + DRIVE_COLUMNS
    try:
        db = dst.db
        db.begin_write(10.0)
        db.execute('DELETE FROM meta')
        meta['schema_version'] = dst.meta['schema_version']
        db.copy_rows('meta', ('key', 'value'), sorted(meta.items()))
        db.copy_rows('nodes', ('i', 'info', 'info_height', 'drives'), nodes)
        db.copy_rows('drives', cols, ([d.get(c, _V1_FILL.get(c)) for c in cols]
                                      for d in drives))
        if isinstance(db, PostgresDb) and drives:
            db.execute("SELECT setval(pg_get_serial_sequence('drives', 'id'), ?)",
                       (max(d['id'] for d in drives),))
        db.commit()
    except BaseException as exc:
        dst.db.rollback()
        dst.close()
        err = None if isinstance(exc, MapError) else dst.db.map_error(exc, 'cannot migrate')
        if err is not None:
            raise err from None
        raise
    dst.close()
    return {'meta': len(meta), 'nodes': len(nodes), 'drives': len(drives)}


#: The drive columns a version-1 map lacks, as schema 2 fills them in an upgrade.
_V1_FILL = {'residual_sum': 0.0, 'residual_count': 0, 'added_by': ''}


def grant_roles(location, group: str, vehicles: Sequence[str],
                passwords: Dict[str, str]) -> List[str]:
    """Create a fleet's roles on the server map ``location`` (PostgresDb.grant_roles)."""
    with RoadMap.open(location) as m:
        if not isinstance(m.db, PostgresDb):
            raise MapError(f'{m.path}: roles are a server\'s (a postgresql:// map); a file '
                           'has the file system\'s permissions')
        try:
            return m.db.grant_roles(group, vehicles, passwords)
        except Exception as exc:
            err = m.db.map_error(exc, 'cannot create the roles')
            if err is None:
                raise
            raise err from None


__all__ = ['Fetched', 'fetch_section', 'cached', 'session_map', 'migrate', 'grant_roles',
           'SECTION_MARGIN_M']
