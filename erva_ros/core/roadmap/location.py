"""Where a road map lives: an SQLite file (the default) or a PostgreSQL server.

A location is a path (an SQLite file, as always) or a ``postgresql://`` URI (also
``postgres://``).  The URI is handed to libpq as it is, so libpq's own environment
(``PGHOST``, ``PGUSER``, ``PGDATABASE``, ...) and password file (``~/.pgpass``) fill in
what it leaves out: ``postgresql://`` alone is the server the environment names.

:attr:`MapLocation.display` is the location without any secret (the URI's password and
the ``password`` / ``sslpassword`` query keys): it is what every message, log line, bag
record and summary shows.  The secret itself stays in :attr:`MapLocation.target` and goes
to libpq only.
"""

from dataclasses import dataclass
import hashlib
import os
import re
from urllib.parse import urlsplit

from erva_ros.core.redact import redact

SCHEMES = ('postgresql://', 'postgres://')


@dataclass(frozen=True)
class MapLocation:
    """A map's location: ``kind`` 'sqlite' (``target`` a path) or 'postgresql' (a URI)."""

    kind: str
    target: str = ''

    @property
    def server(self) -> bool:
        """Return True for a map on a PostgreSQL database server."""
        return self.kind == 'postgresql'

    @property
    def display(self) -> str:
        """Return the location as it may be shown: without password (module doc)."""
        return redact(self.target) if self.server else self.target

    def __str__(self) -> str:
        return self.display

    def __repr__(self) -> str:          # never the secret, not even in a traceback's repr
        return f'MapLocation({self.kind!r}, {self.display!r})'


def parse_location(text: str) -> MapLocation:
    """Return the location ``text`` names: a ``postgresql://`` URI, else an SQLite path."""
    text = str(text)
    if text.startswith(SCHEMES):
        return MapLocation('postgresql', text)
    return MapLocation('sqlite', text)


def cache_dir() -> str:
    """Return the directory of the local map caches ($ERVA_MAP_CACHE_DIR, ~/.cache/erva/maps)."""
    base = os.environ.get('ERVA_MAP_CACHE_DIR') or os.path.join(
        os.environ.get('XDG_CACHE_HOME') or os.path.expanduser('~/.cache'), 'erva', 'maps')
    return os.path.abspath(base)


def cache_path(location: MapLocation) -> str:
    """Return the local SQLite cache of the server map ``location`` (one file per map).

    Named by a hash of the displayed location (host, port, database, user, options: never
    the password), so the same map finds its cache again when the server is unreachable.
    """
    key = hashlib.sha256(location.display.encode()).hexdigest()[:16]
    name = re.sub(r'[^A-Za-z0-9_.-]+', '_', urlsplit(location.target).path.strip('/')) or 'map'
    return os.path.join(cache_dir(), f'{name[:40]}_{key}.db')


__all__ = ['MapLocation', 'parse_location', 'cache_dir', 'cache_path', 'SCHEMES']
