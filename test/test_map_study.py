"""`erva map-study`: every variant runs, the shares are computed from the means."""

import json

import pytest

from erva_ros.cli import main as erva
from erva_ros.core.studies.map_study import StudyConfig, Variant, variants


def test_variants_cover_the_grid_and_the_chain():
    cfg = StudyConfig()
    keys = {v.key() for v in variants(cfg)}
    for alpha in cfg.weights:
        for n in cfg.drives:
            for e in cfg.odometry_m:
                assert Variant('map', alpha, 20.0, n, e).key() in keys
        assert Variant('map', alpha, 20.0, 3, 0.5, True).key() in keys
        assert Variant('map', alpha, 15.0, 3, 0.5).key() in keys
        assert Variant('oracle', alpha, 15.0).key() in keys
    assert len(keys) == len(variants(cfg))


def test_a_small_study(capsys):
    argv = ['map-study', '--seeds', '1', '--first-seed', '0', '--drives', '1',
            '--odometry', '0.5', '--duration', '0.6', '--jobs', '1', '--codegen', 'off',
            '--json']      # codegen off: no compiler run for its four NMPC variants
    assert erva(argv) == 0
    out = json.loads(capsys.readouterr().out)
    rows = out['rows']
    assert len(rows) == 2 * 12       # 4 references, 1 map, variance, 3 at 15 m/s, 3 delayed
    for key, r in rows.items():
        v = r['variant']
        if v['name'] == 'oracle' and not v['delay']:
            assert r['share_pct'] == pytest.approx(100.0)
        if v['name'] == 'no_preview' and not v['delay']:
            assert r['share_pct'] == pytest.approx(0.0, abs=1e-9)
        if v['name'] in ('map', 'variance'):
            p = r['preview']
            assert p['samples'] == 80 and p['alignments'] > 0
            assert p['fallback_points'] == (p['beyond_end_points'] + p['before_start_points']
                                            + p['gap_points'] + p['unmatched_points'])
    assert set(out['goal']) == {'1,0', '0,1'}
    assert 0 < out['drive_error_m']['mean'] < 5e-4
    assert erva(['map-study', '--drives', '0', '--seeds', '1']) == 2
    assert 'between 1 and 50' in capsys.readouterr().err
