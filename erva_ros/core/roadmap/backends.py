"""The map's two databases behind one small interface: SQLite (a file) and PostgreSQL.

:class:`~erva_ros.core.roadmap.store.RoadMap` holds the map's logic (registration,
fusion, the order of reads and writes); a backend holds what differs between the two
databases: connecting, the schema and its version, the write lock, the one statement that
adds a drive, bulk copies, and how a database error reads as one line.

Both backends run their transactions by explicit ``BEGIN`` / ``COMMIT`` on a connection
in autocommit mode, with ``?`` placeholders (turned into ``%s`` for psycopg):

* a **read** (:meth:`begin_read`) is one consistent snapshot: SQLite's deferred
  transaction (its shared lock), PostgreSQL's ``REPEATABLE READ READ ONLY``;
* a **write** (:meth:`begin_write`) holds the map's write lock until it ends: SQLite's
  ``BEGIN IMMEDIATE``, PostgreSQL's transaction-scoped advisory lock (only writers wait
  for it; readers never do).  A drive's node sums are added by
  ``INSERT ... ON CONFLICT (i) DO UPDATE SET info = nodes.info + excluded.info ...``;
  on the server inside ``erva_add_drive``, a ``SECURITY DEFINER`` function, so that a
  vehicle's role can add drives without any right to change the tables itself
  (:func:`PostgresDb.grant_roles`).
"""

import math
import sqlite3
from typing import Dict, Iterable, List, Optional, Sequence

import numpy as np

from erva_ros.core.roadmap import MapError, MapUnreachable
from erva_ros.core.roadmap.location import MapLocation

SCHEMA_VERSION = 2
#: Columns of the drives table after ``id``, in order (both backends).
DRIVE_COLUMNS = ('digest', 'source', 'vehicle', 'added_utc', 'first_node', 'last_node',
                 'offset_m', 'scale', 'origin_m', 'correlation', 'segments', 'speed_mps',
                 'residual_sum', 'residual_count', 'added_by')
SQLITE_SCHEMA = """
CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE nodes (i INTEGER PRIMARY KEY, info REAL NOT NULL, info_height REAL NOT NULL,
                    drives INTEGER NOT NULL);
CREATE TABLE drives (id INTEGER PRIMARY KEY AUTOINCREMENT, digest TEXT UNIQUE NOT NULL,
                     source TEXT, vehicle TEXT, added_utc TEXT, first_node INTEGER,
                     last_node INTEGER, offset_m REAL, scale REAL, origin_m REAL,
                     correlation REAL, segments INTEGER, speed_mps REAL,
                     residual_sum REAL NOT NULL DEFAULT 0,
                     residual_count INTEGER NOT NULL DEFAULT 0,
                     added_by TEXT NOT NULL DEFAULT '');
"""
#: Version 1 (before per-drive residuals): upgraded in place when opened for writing.
SQLITE_UPGRADE_1 = """
ALTER TABLE drives ADD COLUMN residual_sum REAL NOT NULL DEFAULT 0;
ALTER TABLE drives ADD COLUMN residual_count INTEGER NOT NULL DEFAULT 0;
ALTER TABLE drives ADD COLUMN added_by TEXT NOT NULL DEFAULT '';
UPDATE meta SET value = '2' WHERE key = 'schema_version';
"""
ADD_ARGS = ('p_digest text, p_source text, p_vehicle text, p_added_utc text, '
            'p_first bigint, p_last bigint, p_offset float8, p_scale float8, '
            'p_origin float8, p_correlation float8, p_segments integer, p_speed float8, '
            'p_residual_sum float8, p_residual_count bigint, p_nodes bigint[], '
            'p_info float8[], p_info_height float8[]')
ADD_SIGNATURE = ('erva_add_drive(text, text, text, text, bigint, bigint, float8, float8, '
                 'float8, float8, integer, float8, float8, bigint, bigint[], float8[], '
                 'float8[])')
#: The advisory lock every writer of a map takes (one map per database or schema).
PG_LOCK = "pg_advisory_xact_lock(hashtext(current_schema() || '.erva_roadmap'))"
PG_SCHEMA = f"""
CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE nodes (i BIGINT PRIMARY KEY, info DOUBLE PRECISION NOT NULL,
                    info_height DOUBLE PRECISION NOT NULL, drives INTEGER NOT NULL);
CREATE TABLE drives (id BIGSERIAL PRIMARY KEY, digest TEXT UNIQUE NOT NULL,
                     source TEXT, vehicle TEXT, added_utc TEXT, first_node BIGINT,
                     last_node BIGINT, offset_m DOUBLE PRECISION, scale DOUBLE PRECISION,
                     origin_m DOUBLE PRECISION, correlation DOUBLE PRECISION,
                     segments INTEGER, speed_mps DOUBLE PRECISION,
                     residual_sum DOUBLE PRECISION NOT NULL DEFAULT 0,
                     residual_count BIGINT NOT NULL DEFAULT 0,
                     added_by TEXT NOT NULL DEFAULT '');
CREATE FUNCTION erva_add_drive({ADD_ARGS}) RETURNS bigint
LANGUAGE plpgsql SECURITY DEFINER SET search_path = @SCHEMA@, pg_temp AS $$
DECLARE new_id bigint;
BEGIN
  PERFORM {PG_LOCK};
  INSERT INTO drives (digest, source, vehicle, added_utc, first_node, last_node, offset_m,
                      scale, origin_m, correlation, segments, speed_mps, residual_sum,
                      residual_count, added_by)
  VALUES (p_digest, p_source, p_vehicle, p_added_utc, p_first, p_last, p_offset, p_scale,
          p_origin, p_correlation, p_segments, p_speed, p_residual_sum, p_residual_count,
          session_user)
  RETURNING id INTO new_id;
  INSERT INTO nodes (i, info, info_height, drives)
  SELECT n, a, b, 1 FROM unnest(p_nodes, p_info, p_info_height) AS t(n, a, b)
  ON CONFLICT (i) DO UPDATE SET info = nodes.info + excluded.info,
      info_height = nodes.info_height + excluded.info_height, drives = nodes.drives + 1;
  RETURN new_id;
END $$;
REVOKE ALL ON FUNCTION {ADD_SIGNATURE} FROM PUBLIC;
"""
UPSERT = ('INSERT INTO nodes (i, info, info_height, drives) VALUES (?, ?, ?, 1) '
          'ON CONFLICT(i) DO UPDATE SET info = nodes.info + excluded.info, '
          'info_height = nodes.info_height + excluded.info_height, '
          'drives = nodes.drives + 1')


def first_line(exc: BaseException) -> str:
    """Return the first line of an error's message (its type's name if empty)."""
    text = str(exc).strip().splitlines()
    return text[0].strip() if text else type(exc).__name__


def finite_or_none(v) -> Optional[float]:
    """Return ``v`` as a float, None for NaN/inf (SQLite stores NaN as NULL: both do)."""
    if v is None:
        return None
    v = float(v)
    return v if math.isfinite(v) else None


class Db:
    """What a map's database offers (module doc); one connection."""

    kind = ''

    def __init__(self, location: MapLocation):
        self.location = location
        self.name = location.display
        self.in_tx = False

    # -- transactions ---------------------------------------------------------------------
    def begin_read(self) -> None:
        raise NotImplementedError

    def begin_write(self, timeout_s: float) -> None:
        raise NotImplementedError

    def commit(self) -> None:
        self.execute('COMMIT')
        self.in_tx = False

    def rollback(self) -> None:
        try:
            self.execute('ROLLBACK')
        finally:
            self.in_tx = False

    def execute(self, sql: str, params: Sequence = ()) -> List[tuple]:
        raise NotImplementedError

    def columns(self, sql: str, params: Sequence = ()) -> tuple:
        """Return (column names, rows) of a query."""
        raise NotImplementedError


class SqliteDb(Db):
    """A map file: sqlite3 (stdlib), one connection, explicit transactions."""

    kind = 'sqlite'

    def __init__(self, location: MapLocation, timeout_s: float, create: bool = False):
        super().__init__(location)
        path = location.target
        try:
            if create or path == ':memory:':
                self.conn = sqlite3.connect(path, timeout=timeout_s, isolation_level=None)
            else:
                self.conn = sqlite3.connect(f'file:{path}?mode=rw', uri=True,
                                            timeout=timeout_s, isolation_level=None)
        except sqlite3.Error as exc:
            raise MapError(f'{self.name}: cannot open the map ({first_line(exc)})') from None

    def execute(self, sql, params=()):
        return self.conn.execute(sql, tuple(params)).fetchall()

    def columns(self, sql, params=()):
        cur = self.conn.execute(sql, tuple(params))
        return [d[0] for d in cur.description], cur.fetchall()

    def begin_read(self):
        self.conn.execute('BEGIN')
        self.in_tx = True

    def begin_write(self, timeout_s):
        self.conn.execute('BEGIN IMMEDIATE')
        self.in_tx = True

    def create_schema(self, meta: Dict[str, str]) -> None:
        self.conn.executescript('BEGIN;' + SQLITE_SCHEMA + 'COMMIT;')
        self.conn.executemany('INSERT INTO meta VALUES (?, ?)', sorted(meta.items()))

    def upgrade(self, version: str) -> None:
        """Bring a version-1 file to the current schema (in one transaction)."""
        if version == '1':
            self.conn.executescript('BEGIN IMMEDIATE;' + SQLITE_UPGRADE_1 + 'COMMIT;')

    def add_drive(self, row: Dict, nodes: np.ndarray, info: np.ndarray,
                  info_height: np.ndarray) -> int:
        cols = [c for c in DRIVE_COLUMNS if c != 'added_by']
        cur = self.conn.execute(
            f'INSERT INTO drives ({", ".join(cols)}) VALUES ({", ".join("?" * len(cols))})',
            [row[c] for c in cols])
        self.conn.executemany(UPSERT, zip(nodes.tolist(), info.tolist(),
                                          info_height.tolist()))
        return int(cur.lastrowid)

    def copy_rows(self, table: str, columns: Sequence[str], rows: Iterable[tuple]) -> None:
        self.conn.executemany(f'INSERT INTO {table} ({", ".join(columns)}) VALUES '
                              f'({", ".join("?" * len(columns))})', rows)

    def map_error(self, exc: BaseException, doing: str) -> Optional[MapError]:
        """Return the one-line MapError of a database error (None: not a database error)."""
        if not isinstance(exc, sqlite3.Error):
            return None
        if isinstance(exc, sqlite3.IntegrityError) and 'digest' in str(exc):
            return MapError(f'{self.name}: {doing}: the drive is in the map already')
        return MapError(f'{self.name}: {doing} ({first_line(exc)})')

    def close(self) -> None:
        self.conn.close()


def _psycopg():
    try:
        import psycopg
    except ImportError:
        raise MapError('a map on a PostgreSQL server needs psycopg: pip install '
                       '"erva_ros[fleet]"') from None
    return psycopg


class PostgresDb(Db):
    """A map on a PostgreSQL server (psycopg 3), one connection, explicit transactions."""

    kind = 'postgresql'
    CONNECT_TIMEOUT_S = 5

    def __init__(self, location: MapLocation, timeout_s: float):
        super().__init__(location)
        psycopg = _psycopg()
        self.errors = psycopg.errors
        self.psycopg = psycopg
        try:
            kwargs = {} if 'connect_timeout' in location.target else \
                {'connect_timeout': self.CONNECT_TIMEOUT_S}
            self.conn = psycopg.connect(location.target, autocommit=True,
                                        application_name='erva map', **kwargs)
        except psycopg.Error as exc:
            raise MapUnreachable(f'{self.name}: cannot reach the map server '
                                 f'({first_line(exc)})') from None
        except ValueError as exc:        # a malformed URI (psycopg.conninfo)
            raise MapError(f'{self.name}: not a valid PostgreSQL URI ({first_line(exc)})') \
                from None
        self.user = self.conn.info.user

    def execute(self, sql, params=()):
        cur = self.conn.execute(sql.replace('?', '%s'), tuple(params) or None)
        return cur.fetchall() if cur.description else []

    def columns(self, sql, params=()):
        cur = self.conn.execute(sql.replace('?', '%s'), tuple(params) or None)
        return [d.name for d in cur.description], cur.fetchall()

    def begin_read(self):
        self.conn.execute('BEGIN ISOLATION LEVEL REPEATABLE READ READ ONLY')
        self.in_tx = True

    def begin_write(self, timeout_s):
        self.conn.execute('BEGIN ISOLATION LEVEL READ COMMITTED')
        self.in_tx = True
        self.conn.execute(f"SET LOCAL lock_timeout = '{int(timeout_s * 1000)}ms'")
        self.conn.execute(f'SELECT {PG_LOCK}')

    def schema_exists(self) -> bool:
        return bool(self.execute("SELECT to_regclass('meta') IS NOT NULL")[0][0])

    def create_schema(self, meta: Dict[str, str]) -> None:
        """Create the tables and erva_add_drive (inside the caller's write transaction).

        The function's search path is the map's schema, then pg_temp (last: a caller's
        temporary table never stands in for the map's).
        """
        from psycopg import sql
        schema = self.execute('SELECT current_schema()')[0][0]
        if schema is None:
            raise MapError(f'{self.name}: no schema to create the map in (search_path)')
        ident = sql.Identifier(schema).as_string(self.conn)
        self.conn.execute(PG_SCHEMA.replace('@SCHEMA@', ident))
        with self.conn.cursor() as cur:
            cur.executemany('INSERT INTO meta VALUES (%s, %s)', sorted(meta.items()))

    def upgrade(self, version: str) -> None:
        """Nothing to upgrade: the server schema starts at version 2."""

    def drop_schema(self) -> None:
        """Drop the map's tables and function (inside the caller's write transaction)."""
        self.conn.execute(f'DROP FUNCTION {ADD_SIGNATURE}; DROP TABLE drives, nodes, meta')

    def add_drive(self, row, nodes, info, info_height):
        cols = [c for c in DRIVE_COLUMNS if c != 'added_by']
        args = [row[c] for c in cols] + [nodes.astype(np.int64).tolist(), info.tolist(),
                                         info_height.tolist()]
        sql = ('SELECT erva_add_drive(%s, %s, %s, %s, %s, %s, %s, %s, %s, %s, %s, %s, %s, %s, '
               '%s::bigint[], %s::float8[], %s::float8[])')
        return int(self.conn.execute(sql, args).fetchone()[0])

    def copy_rows(self, table, columns, rows):
        with self.conn.cursor() as cur:
            with cur.copy(f'COPY {table} ({", ".join(columns)}) FROM STDIN') as copy:
                for r in rows:
                    copy.write_row(r)

    def map_error(self, exc, doing):
        e = self.errors
        if not isinstance(exc, self.psycopg.Error):
            return None
        if isinstance(exc, e.UniqueViolation) and 'digest' in str(exc):
            return MapError(f'{self.name}: {doing}: the drive is in the map already')
        if isinstance(exc, e.InsufficientPrivilege):
            return MapError(f'{self.name}: {doing}: refused by the server for role '
                            f'{self.user!r} ({first_line(exc)}); a vehicle\'s role may add '
                            'drives and read the map, nothing else (erva map roles)')
        if isinstance(exc, e.LockNotAvailable):
            return MapError(f'{self.name}: {doing}: another writer holds the map '
                            f'({first_line(exc)})')
        if isinstance(exc, self.psycopg.OperationalError):
            return MapUnreachable(f'{self.name}: {doing}: lost the map server '
                                  f'({first_line(exc)})')
        return MapError(f'{self.name}: {doing} ({first_line(exc)})')

    def rollback(self):
        try:
            super().rollback()
        except self.psycopg.Error:       # the connection is gone: the server rolled back
            self.in_tx = False

    def close(self):
        self.conn.close()

    # -- roles ----------------------------------------------------------------------------
    def grant_roles(self, group: str, vehicles: Sequence[str],
                    passwords: Dict[str, str]) -> List[str]:
        """Create the vehicles' group role and its grants, and each vehicle's login role.

        The group may read the three tables and call ``erva_add_drive``; nothing else:
        no INSERT, UPDATE or DELETE on any table, so a vehicle can neither change the
        fused map nor touch another vehicle's drives (each drive records the role that
        added it).  Idempotent.  Returns what was done, one line each.
        """
        from psycopg import sql
        done = []
        g = sql.Identifier(group)
        with self.conn.transaction():
            if not self.execute('SELECT 1 FROM pg_roles WHERE rolname = ?', (group,)):
                self.conn.execute(sql.SQL('CREATE ROLE {} NOLOGIN').format(g))
                done.append(f'created group role {group}')
            schema = self.execute('SELECT current_schema()')[0][0]
            self.conn.execute(sql.SQL('REVOKE ALL ON meta, nodes, drives FROM PUBLIC'))
            self.conn.execute(sql.SQL('REVOKE ALL ON meta, nodes, drives FROM {}').format(g))
            self.conn.execute(sql.SQL('GRANT USAGE ON SCHEMA {} TO {}').format(
                sql.Identifier(schema), g))
            self.conn.execute(sql.SQL('GRANT SELECT ON meta, nodes, drives TO {}').format(g))
            self.conn.execute(sql.SQL(f'GRANT EXECUTE ON FUNCTION {ADD_SIGNATURE} TO {{}}'
                                      ).format(g))
            done.append(f'{group}: SELECT on meta, nodes, drives; EXECUTE erva_add_drive; '
                        'no INSERT, UPDATE or DELETE')
            for v in vehicles:
                ident = sql.Identifier(v)
                if not self.execute('SELECT 1 FROM pg_roles WHERE rolname = ?', (v,)):
                    self.conn.execute(sql.SQL('CREATE ROLE {} LOGIN').format(ident))
                    done.append(f'created vehicle role {v}')
                self.conn.execute(sql.SQL('GRANT {} TO {}').format(g, ident))
                if v in passwords:
                    self.conn.execute(sql.SQL('ALTER ROLE {} PASSWORD {}').format(
                        ident, sql.Literal(passwords[v])))
                    done.append(f'{v}: password set')
                done.append(f'{v}: member of {group}')
        return done


def connect(location: MapLocation, timeout_s: float, create: bool = False) -> Db:
    """Return the database of ``location`` (MapError, one line, if it cannot be reached)."""
    if location.server:
        return PostgresDb(location, timeout_s)
    return SqliteDb(location, timeout_s, create)


__all__ = ['SCHEMA_VERSION', 'DRIVE_COLUMNS', 'SQLITE_SCHEMA', 'PG_SCHEMA', 'Db', 'SqliteDb',
           'PostgresDb', 'connect', 'first_line', 'finite_or_none']
