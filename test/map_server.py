"""A throw-away PostgreSQL server for the map tests (and for .ci/run), from Debian's package.

``python test/map_server.py start DIR`` runs initdb in DIR, starts the server on a Unix
socket in DIR only (no TCP port) and prints its URI; ``stop DIR`` stops it and removes
DIR.  PostgreSQL refuses to run as root: as root the server runs as the ``postgres``
system user that Debian's package creates (runuser).  The server is for tests: trust
authentication on its private socket, fsync off (``durable=True`` keeps the defaults,
for benchmarks).

In pytest: the session fixture ``pg_server`` (test/conftest.py) uses the server .ci/run
started ($ERVA_TEST_PG), else starts one of its own here, else skips the PostgreSQL
cases with the reason; under .ci/run ($ERVA_TEST_PG set) a server that does not answer
fails the tests instead.
"""

import glob
import os
import shutil
import subprocess
import sys
import uuid
from urllib.parse import quote

PORT = 5432
ENV = 'ERVA_TEST_PG'


def bindir():
    """Return the directory of initdb and pg_ctl (None: PostgreSQL is not installed)."""
    found = sorted(glob.glob('/usr/lib/postgresql/*/bin/initdb'),
                   key=lambda p: int(p.split('/')[4]) if p.split('/')[4].isdigit() else 0)
    if found:
        return os.path.dirname(found[-1])
    initdb = shutil.which('initdb')
    return os.path.dirname(os.path.realpath(initdb)) if initdb else None


def _as_server_user(argv):
    if os.geteuid() == 0:
        return ['runuser', '-u', 'postgres', '--', *argv]
    return argv


def new_base():
    """Return a new directory for a server, under /tmp.

    The postgres user can reach it (pytest's own temporary directories are root's only),
    and its socket path stays short.
    """
    import tempfile
    return tempfile.mkdtemp(prefix='erva_pg.', dir='/tmp')


def uri(base, database='postgres', user='postgres'):
    """Return the URI of the server in ``base`` (its socket directory), database ``database``."""
    return f'postgresql://{user}@/{database}?host={quote(base, safe="/")}&port={PORT}'


def start(base, durable=False):
    """Initialise and start a server in the directory ``base``; return its URI."""
    bins = bindir()
    if bins is None:
        raise RuntimeError('PostgreSQL is not installed (apt-get install postgresql-15)')
    os.makedirs(base, exist_ok=True)
    if os.geteuid() == 0:
        shutil.chown(base, 'postgres', 'postgres')
    os.chmod(base, 0o700)
    data = os.path.join(base, 'data')
    run = dict(check=True, capture_output=True, text=True)
    subprocess.run(_as_server_user([os.path.join(bins, 'initdb'), '-D', data, '-A', 'trust',
                                    '-U', 'postgres', '--no-sync', '-E', 'UTF8',
                                    '--locale', 'C']), **run)
    opts = f"-k {base} -c listen_addresses='' -p {PORT} -c max_connections=60"
    if not durable:
        opts += ' -c fsync=off -c synchronous_commit=off -c full_page_writes=off'
    subprocess.run(_as_server_user([os.path.join(bins, 'pg_ctl'), '-D', data, '-l',
                                    os.path.join(base, 'server.log'), '-o', opts, '-w', '-t',
                                    '60', 'start']), **run)
    return uri(base)


def stop(base, remove=True):
    """Stop the server in ``base`` (fast shutdown); remove the directory."""
    bins = bindir()
    data = os.path.join(base, 'data')
    if bins and os.path.isdir(data):
        subprocess.run(_as_server_user([os.path.join(bins, 'pg_ctl'), '-D', data, '-m', 'fast',
                                        '-w', 'stop']), capture_output=True)
    if remove:
        shutil.rmtree(base, ignore_errors=True)


def restart(base):
    """Start the stopped server in ``base`` again (same data, same socket)."""
    bins = bindir()
    data = os.path.join(base, 'data')
    opts = f"-k {base} -c listen_addresses='' -p {PORT} -c fsync=off"
    subprocess.run(_as_server_user([os.path.join(bins, 'pg_ctl'), '-D', data, '-l',
                                    os.path.join(base, 'server.log'), '-o', opts, '-w',
                                    'start']), check=True, capture_output=True)


def new_database(server_uri, prefix='erva_t'):
    """Create a fresh database on the server; return its URI (same host, user)."""
    import psycopg
    name = f'{prefix}_{uuid.uuid4().hex[:12]}'
    with psycopg.connect(server_uri, autocommit=True) as conn:
        conn.execute(f'CREATE DATABASE {name}')
    return server_uri.replace('/postgres?', f'/{name}?', 1)


def with_user(db_uri, user):
    """Return ``db_uri`` with another user name."""
    head, rest = db_uri.split('://', 1)
    return f'{head}://{user}@{rest.split("@", 1)[1]}'


def session_server(tmp_path_factory=None):
    """Yield the URI of a server for this test session (module doc); pytest skips if none."""
    import pytest
    given = os.environ.get(ENV)
    if given:
        try:
            import psycopg
            psycopg.connect(given, connect_timeout=10).close()
        except Exception as exc:                        # under .ci/run: fail, never skip
            pytest.fail(f'${ENV} is set but its server does not answer: {exc}')
        yield given
        return
    try:
        import psycopg  # noqa: F401
    except ImportError:
        pytest.skip('psycopg is not installed (erva_ros[fleet])')
    if bindir() is None:
        pytest.skip('no PostgreSQL server binaries (apt-get install postgresql-15), and '
                    f'${ENV} is not set')
    base = new_base()
    try:
        server = start(base)
    except (subprocess.CalledProcessError, RuntimeError) as exc:
        out = getattr(exc, 'stderr', '') or str(exc)
        pytest.fail(f'cannot start a throw-away PostgreSQL server: {out.strip()[-400:]}')
    try:
        yield server
    finally:
        stop(base)


def main(argv):
    if len(argv) != 3 or argv[1] not in ('start', 'stop'):
        print('usage: map_server.py start|stop DIR', file=sys.stderr)
        return 2
    if argv[1] == 'start':
        try:
            print(start(argv[2]))
        except (subprocess.CalledProcessError, RuntimeError) as exc:
            out = getattr(exc, 'stderr', '') or str(exc)
            print(f'map_server: cannot start PostgreSQL: {out.strip()}', file=sys.stderr)
            stop(argv[2], remove=False)
            return 1
        return 0
    stop(argv[2])
    return 0


if __name__ == '__main__':
    sys.exit(main(sys.argv))
