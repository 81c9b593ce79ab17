"""`erva map`: drives from HIL bags into a map; fusion, increments, bad input.

Every test that does not look at a file itself runs against both databases: an SQLite
file and a live PostgreSQL server (the ``pg_server`` fixture: .ci/run's, or one started
here; test/map_server.py).
"""

import json
import os
import sqlite3

import numpy as np
import pytest

from erva_ros.cli import main as erva
from erva_ros.core.model.quarter_car import make_model
from erva_ros.core.roadmap import MapError
from erva_ros.core.roadmap.bag_drive import read_bag_drive
from erva_ros.core.roadmap.drive import estimate_drive, grid_profile
from erva_ros.core.roadmap.store import RoadMap
from erva_ros.core.roadmap.vehicle import OdometryError

import map_server
import road_helpers as rh
from conftest import REPO


@pytest.fixture(params=['sqlite', 'postgresql'])
def new_map(request, tmp_path):
    """Return a function that gives a fresh map location: a file, or a new server database."""
    if request.param == 'sqlite':
        return lambda name='m': str(tmp_path / f'{name}.db')
    server = request.getfixturevalue('pg_server')
    return lambda name='m': map_server.new_database(server)


@pytest.fixture(scope='module')
def bags(tmp_path_factory):
    """Three drives on route 0 (different sensor noise and odometry), one on route 5."""
    d = tmp_path_factory.mktemp('bags')
    rt = rh.route(0)
    out = {}
    for i, odo in enumerate((OdometryError(), OdometryError(0.4, 0.004, 0.05, 1),
                             OdometryError(-0.3, -0.003, 0.05, 2))):
        run = rh.drive(rt, 10 + i, odometry=odo)
        out[i] = rh.write_bag(str(d / f'drive{i}'), run, drop=(40, 41) if i == 1 else ())
    other = rh.drive(rh.route(5), 20)
    out['other'] = rh.write_bag(str(d / 'other'), other, road_seed=5)
    out['other_unnamed'] = rh.write_bag(str(d / 'other_unnamed'), other, road_seed=0)
    return out


def test_a_bag_gives_its_drive(bags):
    d = read_bag_drive(bags[1])
    assert d.missing_cycles == 2 and d.repeated_cycles == 0 and d.malformed == 0
    assert d.record.route == 'paper:seed=0@20m/s'
    assert d.distance_topic == '/erva/road/height'
    assert np.isnan(d.record.y[40]).all() and np.isfinite(d.record.y[39, :4]).all()
    assert np.all(np.diff(d.record.distance) > 0) and d.record.speed_mps == pytest.approx(
        20 * 1.004, rel=2e-3)


def test_fusion_is_by_inverse_variance(bags, new_map):
    """The map's nodes equal Σ(h/v)/Σ(1/v) computed here from each drive on its own.

    Each drive is estimated and put on the grid again, placed with the offset and scale
    the map stored for it, and fused with numpy; one drive's variance is made 4 times
    another's so that the weights matter.
    """
    path = new_map()
    params = rh.P
    profiles = []
    with RoadMap.create(path, 'r', 0.1, 6.0) as road_map:
        for i in range(3):
            rec = read_bag_drive(bags[i]).record
            g = grid_profile(estimate_drive(rec, make_model(params)), 0.1, 6.0)
            if i == 2:
                g.var = 4 * g.var
            profiles.append(g)
            road_map.add(g, rec.digest(), rec.source)
        stored = road_map.drives()
        m = road_map.profile()
    num, den = {}, {}
    for g, d in zip(profiles, stored):
        placed = g.shifted(d['offset_m'], d['scale'], d['origin_m'])
        for i, h, v in zip(placed.nodes, placed.h, placed.var):
            if np.isfinite(h):
                num[i] = num.get(i, 0.0) + h / v
                den[i] = den.get(i, 0.0) + 1 / v
    idx = np.array(sorted(den))
    mh = m.h[idx - m.first]
    assert m.valid[idx - m.first].all() and m.valid.sum() == idx.size
    assert np.allclose(mh, [num[i] / den[i] for i in idx], rtol=1e-12, atol=1e-15)
    assert np.allclose(1 / m.info[idx - m.first], [1 / den[i] for i in idx], rtol=1e-12)
    assert 0 < m.drives.min() and m.drives.max() == 3
    # The drives with an odometry error were placed back: offsets near 0.4 and -0.3 m.
    assert abs(stored[1]['offset_m'] + 0.4) < 0.1 and abs(stored[2]['offset_m'] - 0.3) < 0.1


def test_incremental_equals_batch_and_info(bags, new_map):
    batch, inc = new_map('batch'), new_map('inc')
    assert erva(['map', 'build', bags[0], bags[1], bags[2], '--out', batch]) == 0
    for i in range(3):
        assert erva(['map', 'build', bags[i], '--out', inc]) == 0
    a, b = rh.nodes(batch), rh.nodes(inc)
    assert a.shape == b.shape and a.shape[0] > 700          # 80 m at 0.1 m
    assert np.allclose(a, b, rtol=1e-12, atol=0)
    with RoadMap.open(inc) as m:
        assert m.route == 'paper:seed=0@20m/s' and len(m.drives()) == 3


def test_info_and_compare(bags, new_map, capsys):
    path = new_map()
    assert erva(['map', 'build', bags[0], bags[2], '--out', path, '--json']) == 0
    built = json.loads(capsys.readouterr().out)
    assert [a['segments'] > 0 for a in built['added']] == [False, True]
    assert erva(['map', 'info', path, '--json']) == 0
    info = json.loads(capsys.readouterr().out)
    assert info['drives'] == 2 and info['gaps_m'] == [] and info['grid_m'] == 0.1
    assert erva(['map', 'compare', path, '--road', 'paper', '--seed', '0', '--json']) == 0
    c = json.loads(capsys.readouterr().out)
    # Two drives: the map's detail within 0.25 mm of the road's (0.8 mm RMS), placed.
    assert c['error_rms_m'] < 2.5e-4 < c['road_detail_rms_m'] and c['correlation'] > 0.9
    # Against another road it cannot be placed.
    assert erva(['map', 'compare', path, '--road', 'paper', '--seed', '5']) == 2
    assert 'matches the map nowhere' in capsys.readouterr().err


def _one_line_exit_2(capsys, argv, needle):
    assert erva(argv) == 2
    err = capsys.readouterr().err.strip()
    assert '\n' not in err and needle in err, err


def test_bad_input_exits_2_and_leaves_the_map_unchanged(bags, new_map, capsys):
    path = new_map()
    assert erva(['map', 'build', bags[0], '--out', path]) == 0
    capsys.readouterr()
    before = rh.nodes(path)
    sample = os.path.join(REPO, 'bags', 'sample')
    _one_line_exit_2(capsys, ['map', 'build', bags[1], sample, '--out', path],
                     'no ecu/measurements topic')
    _one_line_exit_2(capsys, ['map', 'build', bags['other'], '--out', path],
                     "route 'paper:seed=5@20m/s', the map is of route 'paper:seed=0@20m/s'")
    # Without a route in the session, registration finds no match.
    _one_line_exit_2(capsys, ['map', 'build', bags[1], bags['other_unnamed'], '--out', path],
                     'matches the map nowhere')
    _one_line_exit_2(capsys, ['map', 'build', bags[0], '--out', path], 'already in the map')
    assert np.array_equal(rh.nodes(path), before)
    # A failed build of a new map leaves no map behind (no file; no tables on the server).
    new = new_map('new')
    _one_line_exit_2(capsys, ['map', 'build', bags[0], bags['other_unnamed'], '--out', new],
                     'matches the map nowhere')
    assert not RoadMap.exists(new)
    _one_line_exit_2(capsys, ['map', 'info', new], 'no such map file' if new.endswith('.db')
                     else 'no road map on this server')


def test_corrupt_foreign_and_missing_files(tmp_path, capsys):
    new = str(tmp_path / 'new.db')
    _one_line_exit_2(capsys, ['map', 'build', os.path.join(REPO, 'bags', 'sample'), '--out',
                              new], 'not a HIL session')
    assert not os.path.exists(new)
    bad = tmp_path / 'bad.db'
    bad.write_bytes(b'not a database at all' * 50)
    _one_line_exit_2(capsys, ['map', 'info', str(bad)], 'not a readable road map')
    other = str(tmp_path / 'other.db')
    sqlite3.connect(other).execute('CREATE TABLE x (a)').connection.close()
    _one_line_exit_2(capsys, ['map', 'info', other], 'not a readable road map')
    _one_line_exit_2(capsys, ['map', 'info', str(tmp_path / 'none.db')], 'no such map file')


def test_a_locked_map_is_refused(bags, new_map, capsys, monkeypatch):
    import erva_ros.core.roadmap.store as store
    from erva_ros.core.roadmap.backends import PG_LOCK
    path = new_map()
    assert erva(['map', 'build', bags[0], '--out', path]) == 0
    monkeypatch.setattr(store, 'LOCK_TIMEOUT_S', 0.2)
    if path.endswith('.db'):
        holder = sqlite3.connect(path, isolation_level=None)
        holder.execute('BEGIN IMMEDIATE')                  # another writer holds the map
    else:
        import psycopg
        holder = psycopg.connect(path, autocommit=True)
        holder.execute('BEGIN')
        holder.execute(f'SELECT {PG_LOCK}')
    try:
        capsys.readouterr()
        _one_line_exit_2(capsys, ['map', 'build', bags[2], '--out', path],
                         'cannot write the map (database is locked)' if path.endswith('.db')
                         else 'cannot write the map: another writer holds the map')
    finally:
        holder.execute('ROLLBACK')
        holder.close()
    with RoadMap.open(path) as m:
        assert len(m.drives()) == 1


def test_grid_and_open_errors(new_map, capsys):
    with pytest.raises(MapError, match=r'grid 5.0 m: allowed \[0.01, 2\] m'):
        RoadMap.create(new_map('g'), 'r', 5.0, 6.0)
    path = new_map('v')
    with RoadMap.create(path, 'r', 0.1, 6.0) as m:
        m.db.execute("UPDATE meta SET value = '99' WHERE key = 'schema_version'")
    with pytest.raises(MapError, match="schema version '99'"):
        RoadMap.open(path)
    _one_line_exit_2(capsys, ['map', 'info', path], "map schema version '99', this erva_ros "
                                                    'reads 2')


def test_a_standstill_adds_nothing_and_reversing_is_refused():
    from erva_ros.core.roadmap.drive import DriveEstimate
    s = np.concatenate([np.arange(0, 20, 0.4), np.full(30, 20.0), np.arange(20.4, 40, 0.4)])
    w = np.sin(s)
    g = grid_profile(DriveEstimate(s, w, np.full(s.size, 1e-8), w), 0.1, 6.0, skip_s=0.0)
    assert g.first == 0 and g.h.size == 397 and np.isfinite(g.h).all()
    back = s.copy()
    back[60] -= 1.0
    with pytest.raises(MapError, match='decreases'):
        grid_profile(DriveEstimate(back, w, np.full(s.size, 1e-8), w), 0.1, 6.0, skip_s=0.0)
    with pytest.raises(MapError, match='did not move'):
        grid_profile(DriveEstimate(np.full(5, 3.0), w[:5], np.ones(5), w[:5]), 0.1, 6.0,
                     skip_s=0.0)
