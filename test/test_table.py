"""`erva table`, `erva sim` and `erva pareto`: JSON shapes, files and one-line errors."""

import json

import pytest


def _json(proc):
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout)


def test_table_json_shape_with_the_bound(erva, tmp_path):
    out = tmp_path / 'table'
    # Two seeds (a mean and a spread), 0.5 s: the shape and the bound's place in it.
    res = _json(erva('table', '--seeds', 2, '--duration', 0.5, '--weights', '0,1;1,0.01',
                     '--controllers', 'passive,no_preview,preview', '--json', '--out', out))
    assert res['seeds'] == 2
    rows = res['rows']
    assert [(tuple(r['weights']), r['controller']) for r in rows] == [
        ((w1, w2), c) for (w1, w2) in [(0.0, 1.0), (1.0, 0.01)]
        for c in ('passive', 'no_preview', 'preview', 'clairvoyant')]
    for r in rows:
        for key in ('acc_2norm', 'power_w'):
            assert set(r[key]) == {'mean', 'std'} and r[key]['mean'] >= 0
        assert isinstance(r['pct_of_clairvoyant'], float)
        if r['controller'] == 'passive':
            assert r['pct_of_clairvoyant'] == pytest.approx(0.0)
        if r['controller'] == 'clairvoyant':
            assert r['pct_of_clairvoyant'] == pytest.approx(100.0)
        else:
            assert r['pct_of_clairvoyant'] < 100.0 and r['seeds_beating_bound'] == 0
    quantities = {c['quantity'] for c in res['paper_comparison']}
    assert 'average power, passive (W)' in quantities
    for name in ('table.md', 'table.json', 'table.csv'):
        assert (out / name).stat().st_size > 100
    assert '| (0, 1) | preview |' in (out / 'table.md').read_text()


def test_table_without_bound_and_bad_controller(erva):
    res = _json(erva('table', '--seeds', 1, '--duration', 0.5, '--no-bound', '--weights',
                     '1,0', '--controllers', 'passive,skyhook', '--json'))
    assert [r['controller'] for r in res['rows']] == ['passive', 'skyhook']
    assert res['rows'][0]['pct_of_clairvoyant'] is None
    proc = erva('table', '--controllers', 'passive,mpc', '--no-bound')
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines() == [
        "erva table: error: --controllers: unknown controller 'mpc'; choose from passive, "
        'skyhook, no_preview, preview, preview_long']


def test_sim_json_and_files(erva, tmp_path):
    res = _json(erva('sim', '--controller', 'preview', '--alpha', '0,1', '--duration', 1,
                     '--seed', 2, '--preview-snr', 20, '--json', '--out', tmp_path))
    for key in ('acc_2norm', 'acc_rms', 'power_w', 'realtime_factor'):
        assert res[key] > 0
    assert set(res['solve_ms']) == {'p50', 'p99', 'max'}
    assert set(res['fallbacks']) == {'fallback_plan', 'fallback_passive', 'failures',
                                     'nan_rejections', 'late'}
    assert res['samples'] == 50 and res['weights'] == [0.0, 1.0]
    assert (tmp_path / 'timeseries.png').stat().st_size > 10000
    lines = (tmp_path / 'timeseries.csv').read_text().splitlines()
    assert len(lines) == 51 and lines[0].startswith('t_s,road_m,damping_ns_per_m')


@pytest.mark.parametrize('args,message', [
    (['--horizon', '0'], "parameter 'horizon' = 0 is out of range; allowed [1, 200]"),
    (['--u-min', '3e4'], "'u_max' = 20000 must exceed u_min = 30000"),
    (['--settings', '/nonexistent.yaml'], "parameter file '/nonexistent.yaml' does not exist"),
])
def test_sim_bad_options_are_one_line(erva, args, message):
    proc = erva('sim', '--duration', 0.2, *args)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and message in lines[0] and 'Traceback' not in proc.stderr


def test_pareto_json_and_png(erva, tmp_path):
    res = _json(erva('pareto', '--seeds', 1, '--duration', 1, '--ratios', '0,1', '--json',
                     '--out', tmp_path))
    assert [(c['alpha1'], c['alpha2']) for c in res['curve']] == [(1, 0), (1, 1), (0, 1)]
    assert [b['controller'] for b in res['baselines']] == ['passive', 'skyhook']
    assert (tmp_path / 'pareto.png').stat().st_size > 10000
    assert len((tmp_path / 'pareto.csv').read_text().splitlines()) == 6
