"""A fleet's map on a live PostgreSQL server (and the same guarantees in SQLite files).

With real processes: K writers at once equal the serial result; a writer whose section
another changed meanwhile starts again; two vehicles with the same bag add it once; two
builds into a new map both land; a writer killed mid-transaction leaves the map as it was;
registration reads one snapshot.  Roles: a vehicle adds and reads, the server refuses the
rest.  Migration file <-> server value for value; a version-1 file upgraded.  The local
cache: fetched, used when the server is gone (one WARN line), offline drives uploaded
later; no password in any output.

The drives are the map bench's (core/roadmap/bench.py: the paper road as a route, the
estimator's error) or HIL bags written by test/road_helpers.py.
"""

import json
import os
import signal
import sqlite3
import subprocess
import sys

import numpy as np
import pytest

from erva_ros.core.roadmap import bench as B, MapError
from erva_ros.core.roadmap.fleet import cached, session_map
from erva_ros.core.roadmap.location import cache_path, parse_location
from erva_ros.core.roadmap.store import DriveItem, register, RoadMap
from erva_ros.core.roadmap.vehicle import OdometryError

import map_server
import road_helpers as rh
from conftest import REPO, ros_env

#: A short route where every drive overlaps every other (so writers do meet).
FLEET = B.Fleet(route_km=2.0, drives=12, drive_km=1.5, error_std_m=1e-4, var_m2=2e-9)
SECRET = 'S3cr3tPw'


@pytest.fixture(params=['sqlite', 'postgresql'])
def new_map(request, tmp_path):
    """Return a function that gives a fresh map location: a file, or a new server database."""
    if request.param == 'sqlite':
        return lambda name='m': str(tmp_path / f'{name}.db')
    server = request.getfixturevalue('pg_server')
    return lambda name='m': map_server.new_database(server)


def _surveyed(location):
    with RoadMap.create(location, FLEET.route_name, FLEET.grid_m, FLEET.highpass_m) as m:
        m.add(B.survey(FLEET), B.digest(FLEET, -1), 'survey')
    return location


def _item(k):
    return DriveItem(B.drive(FLEET, k), B.digest(FLEET, k), f'drive {k}')


def _python(code, *args, **kw):
    """Start ``python -c code args`` as its own process (repo and test/ on its path)."""
    env = ros_env({'PYTHONPATH': os.pathsep.join([REPO, os.path.join(REPO, 'test')])})
    return subprocess.Popen([sys.executable, '-c', code, *map(str, args)], env=env, cwd=REPO,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, **kw)


def _serial(location, order, new):
    """Build the same map with the drives added one after another in ``order``."""
    _surveyed(new)
    with RoadMap.open(new) as m:
        for k in order:
            m.add_drives([_item(k)])
    return new


def _drive_order(location):
    with RoadMap.open(location) as m:
        return [int(d['digest'].rsplit('-', 1)[1]) for d in m.drives()[1:]]


def _assert_same_map(a, b):
    """Assert that two maps' nodes and registrations are equal to 1e-12 (relative)."""
    na, nb = rh.nodes(a), rh.nodes(b)
    assert na.shape == nb.shape and np.array_equal(na[:, 0], nb[:, 0])
    assert np.allclose(na[:, 1:], nb[:, 1:], rtol=1e-12, atol=0)
    with RoadMap.open(a) as ma, RoadMap.open(b) as mb:
        for x, y in zip(ma.drives(), mb.drives()):
            assert x['digest'] == y['digest']
            for key in ('offset_m', 'scale', 'correlation', 'residual_sum'):
                assert x[key] == pytest.approx(y[key], rel=1e-12, abs=1e-15), key
            assert x['residual_count'] == y['residual_count']


# -- concurrency --------------------------------------------------------------------------
def test_k_writers_at_once_equal_the_serial_map(new_map):
    """4 processes add 12 overlapping drives at once (after a barrier), one transaction each.

    The map equals the one built by adding the drives one after another in the order they
    committed (to 1e-12 relative: the same sums in the same order).
    """
    loc = _surveyed(new_map('fleet'))
    r = B.run_writers(FLEET, loc, 4)
    assert r['drives'] == FLEET.drives
    order = _drive_order(loc)
    assert sorted(order) == list(range(FLEET.drives))
    _assert_same_map(loc, _serial(loc, order, new_map('serial')))


LATE_WRITER = '''
import json, os, sys, time
from erva_ros.core.roadmap import bench as B, store
import test_map_fleet as t
calls = []
real = store.register

def register(*args, **kwargs):   # the first registration waits until the other committed
    out = real(*args, **kwargs)
    calls.append(1)
    if len(calls) == 1:
        print('registered', flush=True)
        while not os.path.exists(sys.argv[2]):
            time.sleep(0.01)
    return out

store.register = register
timing = {}
with store.RoadMap.open(sys.argv[1]) as m:
    m.add_drives([t._item(0)], timing=timing)
print(json.dumps(timing), flush=True)
'''


def test_a_writer_whose_section_changed_meanwhile_starts_again(new_map, tmp_path):
    """A registers drive 0 on the survey; B commits drive 1 there; A must not use its placing.

    A's add starts again (a retry: snapshot, registration) and the map equals drive 1
    then drive 0 added one after another -- where A's first placing (on the survey alone)
    differs.
    """
    loc = _surveyed(new_map('fleet'))
    flag = tmp_path / 'b_committed'
    a = _python(LATE_WRITER, loc, flag)
    try:
        assert a.stdout.readline().strip() == 'registered', a.stderr.read()
        with RoadMap.open(loc) as m:
            first_look = register(B.drive(FLEET, 0), m.profile(), 3.0)
            m.add_drives([_item(1)])
        flag.touch()
        out, err = a.communicate(timeout=120)
    finally:
        if a.poll() is None:
            a.kill()
    assert a.returncode == 0, err
    timing = json.loads(out)
    assert timing['retries'] == 1 and timing['again'] == 0
    assert _drive_order(loc) == [1, 0]
    serial = _serial(loc, [1, 0], new_map('serial'))
    _assert_same_map(loc, serial)
    with RoadMap.open(loc) as m:
        stored = m.drives()[2]
    assert stored['offset_m'] != first_look.offset_m        # the first placing was stale


def _build(location, *bags):
    return subprocess.Popen([sys.executable, '-m', 'erva_ros.cli', 'map', 'build', *bags,
                             '--out', location], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=ros_env(), cwd=REPO)


@pytest.fixture(scope='module')
def bags(tmp_path_factory):
    """Three HIL bags of drives on the paper road, seed 0 (different sensor noise, odometry)."""
    d = tmp_path_factory.mktemp('bags')
    rt = rh.route(0)
    return [rh.write_bag(str(d / f'drive{i}'), rh.drive(rt, 30 + i, odometry=odo))
            for i, odo in enumerate((OdometryError(), OdometryError(0.3, 0.002, 0.05, 1),
                                     OdometryError(-0.2, -0.002, 0.05, 2)))]


def test_two_vehicles_with_the_same_bag_add_it_once(bags, new_map):
    loc = new_map()
    assert _build(loc, bags[0]).wait(timeout=300) == 0
    procs = [_build(loc, bags[1]) for _ in range(2)]
    results = [(p.wait(timeout=300), p.stderr.read()) for p in procs]
    assert sorted(code for code, _ in results) == [0, 2], results
    refused = [err.strip() for code, err in results if code == 2][0]
    assert '\n' not in refused and 'already in the map' in refused
    with RoadMap.open(loc) as m:
        assert len(m.drives()) == 2


def test_two_builds_into_a_new_map_both_land(bags, new_map):
    """Issue 38's fault probe: the loser said 'exists already' and its drive was lost."""
    loc = new_map()
    procs = [_build(loc, bags[0]), _build(loc, bags[2])]
    results = [(p.wait(timeout=300), p.stderr.read()) for p in procs]
    assert [code for code, _ in results] == [0, 0], results
    with RoadMap.open(loc) as m:
        assert len(m.drives()) == 2


KILLED_WRITER = '''
import sys, time
from erva_ros.core.roadmap import store
import test_map_fleet as t
m = store.RoadMap.open(sys.argv[1])
it = t._item(5)
with m.snapshot():
    ref = m._section(*it.span())
reg = m._register(it, ref)
m.db.begin_write(10.0)
m._fuse(it, reg, ref)           # the drive's row and its node sums, not committed
print('inside', flush=True)
time.sleep(600)
'''


def test_a_writer_killed_mid_transaction_leaves_the_map_as_before(new_map):
    loc = _surveyed(new_map())
    with RoadMap.open(loc) as m:
        m.add_drives([_item(1)])
    before = rh.table(loc, 'nodes'), rh.table(loc, 'drives')
    p = _python(KILLED_WRITER, loc)
    try:
        assert p.stdout.readline().strip() == 'inside', p.stderr.read()
    finally:
        p.send_signal(signal.SIGKILL)
        p.wait(timeout=60)
    assert (rh.table(loc, 'nodes'), rh.table(loc, 'drives')) == before
    with RoadMap.open(loc) as m:                      # the lock is free, the drive is new
        m.add_drives([_item(5)])
        assert len(m.drives()) == 3


ONE_WRITER = '''
import sys
from erva_ros.core.roadmap import store
import test_map_fleet as t
with store.RoadMap.open(sys.argv[1]) as m:
    m.add_drives([t._item(int(sys.argv[2]))])
'''


def test_registration_reads_one_snapshot(new_map):
    """Inside a snapshot the map does not change while another process adds a drive.

    On the server the other commits meanwhile; an SQLite file's writer waits for the
    snapshot to end (its journal shows it is inside its transaction).
    """
    loc = _surveyed(new_map())
    with RoadMap.open(loc) as m:
        with m.snapshot():
            p0, d0 = m.profile(), m.drives()
            w = _python(ONE_WRITER, loc, 2)
            if loc.endswith('.db'):
                while not os.path.exists(loc + '-journal') and w.poll() is None:
                    pass                                   # inside its write transaction
                assert w.poll() is None, w.stderr.read()
            else:
                assert w.wait(timeout=120) == 0, w.stderr.read()
            p1, d1 = m.profile(), m.drives()
            assert d1 == d0 and np.array_equal(p1.info, p0.info) \
                and np.array_equal(p1.info_height, p0.info_height)
        assert w.wait(timeout=120) == 0, w.stderr.read()
        assert len(m.drives()) == len(d0) + 1
        assert not np.array_equal(m.profile().info_height, p0.info_height)


# -- roles --------------------------------------------------------------------------------
def test_a_vehicle_adds_and_reads_and_the_server_refuses_the_rest(pg_server, tmp_path, capsys):
    import psycopg
    from erva_ros.cli import main as erva
    loc = _surveyed(map_server.new_database(pg_server))
    tag = os.urandom(4).hex()
    group, v1, v2 = f'fleet_{tag}', f'car1_{tag}', f'car2_{tag}'
    assert erva(['map', 'roles', loc, '--vehicle', v1, '--vehicle', v2, '--group', group]) == 0
    capsys.readouterr()
    as1, as2 = map_server.with_user(loc, v1), map_server.with_user(loc, v2)
    with RoadMap.open(as1) as m:
        m.add_drives([_item(0)])
    with RoadMap.open(as2) as m:
        m.add_drives([_item(1)])
        assert [d['added_by'] for d in m.drives()] == ['postgres', v1, v2]
    before = [rh.table(loc, t) for t in ('meta', 'nodes', 'drives')]
    attempts = ['DELETE FROM drives', f"DELETE FROM drives WHERE added_by = '{v1}'",
                f"UPDATE drives SET vehicle = 'x' WHERE added_by = '{v1}'",
                'UPDATE nodes SET info = 0', 'DELETE FROM nodes', 'INSERT INTO nodes VALUES '
                '(-5, 1, 1, 1)', "UPDATE meta SET value = 'x'", 'TRUNCATE nodes',
                'DROP TABLE nodes', 'ALTER TABLE nodes ADD COLUMN x int']
    with psycopg.connect(as2, autocommit=True) as conn:
        for sql in attempts:
            with pytest.raises(psycopg.errors.InsufficientPrivilege):
                conn.execute(sql)
    assert [rh.table(loc, t) for t in ('meta', 'nodes', 'drives')] == before
    # The CLI says it in one line: a vehicle cannot make a map or hand out roles.
    src = _surveyed(str(tmp_path / 'src.db'))
    other = map_server.with_user(map_server.new_database(pg_server), v1)
    for argv in (['map', 'migrate', src, other], ['map', 'roles', as1, '--vehicle', 'x']):
        assert erva(argv) == 2
        err = capsys.readouterr().err.strip()
        assert '\n' not in err and f"refused by the server for role '{v1}'" in err, err
    # A role outside the group may not even read.
    with psycopg.connect(pg_server, autocommit=True) as conn:
        conn.execute(f'CREATE ROLE stranger_{tag} LOGIN')
    with pytest.raises(MapError, match="cannot read the map: refused by the server for role"):
        RoadMap.open(map_server.with_user(loc, f'stranger_{tag}'))


# -- migration ----------------------------------------------------------------------------
def test_migrate_file_to_server_and_back_value_for_value(pg_server, tmp_path, capsys):
    from erva_ros.cli import main as erva
    src = _surveyed(str(tmp_path / 'src.db'))
    with RoadMap.open(src) as m:
        m.add_drives([_item(0)])
        m.add_drives([DriveItem(B.drive(FLEET, 1), B.digest(FLEET, 1), 'drive 1', 'car',
                                speed_mps=float('nan'))])
    server = map_server.new_database(pg_server)
    back = str(tmp_path / 'back.db')
    assert erva(['map', 'migrate', src, server]) == 0
    assert erva(['map', 'migrate', server, back]) == 0
    for name in ('meta', 'nodes', 'drives'):
        a, b, c = (rh.table(x, name) for x in (src, server, back))
        assert a == b == c, name
    assert rh.table(src, 'drives')[2][12] is None               # NaN speed: NULL in both
    capsys.readouterr()
    assert erva(['map', 'migrate', src, server]) == 2
    assert 'exists already' in capsys.readouterr().err
    with RoadMap.open(server) as m:                             # and it goes on growing
        m.add_drives([_item(2)])
        assert [d['id'] for d in m.drives()] == [1, 2, 3, 4]


V1_SCHEMA = """
CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE nodes (i INTEGER PRIMARY KEY, info REAL NOT NULL, info_height REAL NOT NULL,
                    drives INTEGER NOT NULL);
CREATE TABLE drives (id INTEGER PRIMARY KEY AUTOINCREMENT, digest TEXT UNIQUE NOT NULL,
                     source TEXT, vehicle TEXT, added_utc TEXT, first_node INTEGER,
                     last_node INTEGER, offset_m REAL, scale REAL, origin_m REAL,
                     correlation REAL, segments INTEGER, speed_mps REAL);
"""


def test_a_version_1_file_is_read_and_upgraded_when_written(tmp_path):
    new = _surveyed(str(tmp_path / 'v2.db'))
    old = str(tmp_path / 'v1.db')
    with sqlite3.connect(old) as conn:               # the same map as version 1 wrote it
        conn.executescript(V1_SCHEMA)
        conn.executemany('INSERT INTO meta VALUES (?, ?)', [
            (k, '1' if k == 'schema_version' else v) for k, v in rh.table(new, 'meta')]
            + [('residual_sum', '2.0'), ('residual_count', '4')])
        conn.executemany('INSERT INTO nodes VALUES (?, ?, ?, ?)', rh.table(new, 'nodes'))
        conn.executemany('INSERT INTO drives VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)',
                         [r[:13] for r in rh.table(new, 'drives')])
    with RoadMap.open(old) as m:
        assert m.version == 1 and m.profile().variance_scale == 0.5
        m.add_drives([_item(0)])
        assert m.version == 2
    with RoadMap.open(old) as m, RoadMap.open(new) as n:
        n.add_drives([_item(0)])
        r = n.drives()[1]
        assert m.profile().residual_sum == pytest.approx(2.0 + r['residual_sum'], rel=1e-12)
        assert m.profile().residual_count == 4 + r['residual_count']
    assert np.array_equal(rh.nodes(old), rh.nodes(new))


# -- the local cache, offline ---------------------------------------------------------------
@pytest.fixture
def own_server():
    """Start a server of this test's own (the test stops and starts it again)."""
    if map_server.bindir() is None:
        if os.environ.get(map_server.ENV):
            pytest.fail('PostgreSQL binaries missing under .ci/run')
        pytest.skip('no PostgreSQL server binaries (apt-get install postgresql-15)')
    base = map_server.new_base()
    server = map_server.start(base)
    yield base, server
    map_server.stop(base)


def _erva(*args, env=None):
    return subprocess.run([sys.executable, '-m', 'erva_ros.cli', *map(str, args)],
                          capture_output=True, text=True, env=ros_env(env), cwd=REPO,
                          timeout=300)


def test_the_cache_serves_when_the_server_is_gone_and_drives_upload_later(
        own_server, bags, tmp_path, monkeypatch):
    base, server = own_server
    db = map_server.new_database(server)
    loc = db.replace('postgres@', f'postgres:{SECRET}@', 1)     # trust: the password is unused
    cache_dir = str(tmp_path / 'cache')
    monkeypatch.setenv('ERVA_MAP_CACHE_DIR', cache_dir)
    env = {'ERVA_MAP_CACHE_DIR': cache_dir}
    outputs = []

    def run(*args):
        r = _erva(*args, env=env)
        outputs.append(r.stdout + r.stderr)
        return r

    assert run('map', 'build', bags[0], bags[1], '--out', loc).returncode == 0
    # Fetched as erva run does it: one snapshot of the section, into the cache.
    lines = []
    path, shown = session_map(loc, 0.0, 60.0, lines.append)
    assert path == cache_path(parse_location(loc)) and os.path.dirname(path) == cache_dir
    assert len(lines) == 1 and lines[0].startswith('map: fetched -20..80 m of ')
    with RoadMap.open(loc) as m, RoadMap.open(path) as c:
        full, part = m.profile(), c.profile()
        assert part.variance_scale == full.variance_scale
        i = part.first - full.first
        assert np.array_equal(part.info, full.info[i:i + part.n]) and part.first * 0.1 >= -20
    # The server stops: the same location is served from the cache, one WARN line.
    map_server.stop(base, remove=False)
    lines.clear()
    assert session_map(loc, 0.0, 60.0, lines.append) == (path, shown)
    assert len(lines) == 1 and lines[0].startswith('WARN map server unreachable (')
    assert cached(path).fetched_utc in lines[0]
    # No cache: one line, no start.
    monkeypatch.setenv('ERVA_MAP_CACHE_DIR', str(tmp_path / 'empty'))
    with pytest.raises(MapError, match='no local cache of this map'):
        session_map(loc, 0.0, 60.0, lines.append)
    # A drive recorded meanwhile: its upload waits for the server, nothing is lost.
    r = run('map', 'sync', loc, os.path.dirname(bags[0]))
    assert r.returncode == 2 and 'cannot reach the map server' in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1
    map_server.restart(base)
    r = run('map', 'sync', loc, os.path.dirname(bags[0]), '--json')
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert [a['bag'] for a in out['added']] == [bags[2]] and len(out['already_in_map']) == 2
    r = run('map', 'sync', loc, os.path.dirname(bags[0]), '--json')
    assert json.loads(r.stdout)['added'] == [] and len(json.loads(r.stdout)['already_in_map']) \
        == 3
    run('map', 'info', loc)
    run('map', 'fetch', loc, '--end', 50)
    # The password appears nowhere: outputs, the cache's name and content.
    assert all(SECRET not in o for o in outputs) and len(outputs) == 6
    assert SECRET not in path and SECRET not in json.dumps(rh.table(path, 'meta'))
    assert SECRET not in shown and shown == parse_location(loc).display


def test_the_preview_node_reads_only_a_local_file():
    """road_preview_node's map mode refuses a server URI: it would put the network in the loop."""
    from erva_ros.core.model.params import ParamError
    from erva_ros.core.reports import RoadReport
    from erva_ros.core.loop.road_loop import MapPreviewLoop
    with pytest.raises(ParamError, match='map_file: a local map file; a server map is fetched'):
        MapPreviewLoop({'map_file': f'postgresql://car:{SECRET}@maps/paper'}, RoadReport())
