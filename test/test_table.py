"""`erva table`, `erva sim` and `erva pareto`: JSON shapes, files and one-line errors."""

import json

import pytest


def _json(proc):
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout)


def test_table_json_shape_with_the_bound(erva, tmp_path):
    out = tmp_path / 'table'
    # Short runs, a light search: the plant objective of n = 25 samples is compiled once
    # per machine and shared with the Dask test below (slow on a loaded machine).
    res = _json(erva('table', '--seeds', 2, '--duration', 0.5, '--weights', '0,1;1,0.01',
                     '--controllers', 'passive,no_preview,preview', '--bound-search', 1,
                     '--bound-polish', 5, '--json', '--out', out, timeout=900))
    assert res['seeds'] == 2
    rows = res['rows']
    assert [(tuple(r['weights']), r['controller']) for r in rows] == [
        ((w1, w2), c) for (w1, w2) in [(0.0, 1.0), (1.0, 0.01)]
        for c in ('passive', 'no_preview', 'preview', 'clairvoyant')]
    for r in rows:
        for key in ('acc_2norm', 'acc_rms_continuous', 'power_w', 'time_s'):
            assert set(r[key]) == {'mean', 'std'} and r[key]['mean'] >= 0
        assert isinstance(r['pct_of_clairvoyant'], float)
        if r['controller'] == 'passive':
            assert r['pct_of_clairvoyant'] == pytest.approx(0.0)
        if r['controller'] == 'clairvoyant':
            assert r['pct_of_clairvoyant'] == pytest.approx(100.0)
            assert r['plant_agreement_max'] < 1e-9 and r['start_spread_J']['mean'] >= 0
            assert 'projected L-BFGS' in r['method']
        else:
            assert r['pct_of_clairvoyant'] < 100.0 and r['seeds_beating_bound'] == 0
    quantities = {c['quantity'] for c in res['paper_comparison']}
    assert 'average power, passive (W)' in quantities
    for name in ('table.md', 'table.json', 'table.csv'):
        assert (out / name).stat().st_size > 100
    md = (out / 'table.md').read_text()
    assert '| (0, 1) | preview |' in md and 'Bound: IPOPT' in md
    header = (out / 'table.csv').read_text().splitlines()[0]
    assert header == ('seed,alpha1,alpha2,controller,acc_2norm,acc_rms,acc_rms_continuous,'
                      'power_w,J,time_s')


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


def _numbers(rows):
    keys = ('acc_2norm', 'acc_rms_continuous', 'power_w', 'objective_J')
    return [(r['controller'], tuple(r['weights'])) + tuple(r[k]['mean'] for k in keys)
            for r in rows]


def test_table_and_pareto_on_a_dask_cluster_give_the_local_numbers(erva):
    distributed = pytest.importorskip('distributed')
    args = ('--seeds', 2, '--duration', 0.5, '--weights', '0,1', '--controllers',
            'passive,preview', '--bound-search', 1, '--bound-polish', 5, '--json')
    local = _json(erva('table', *args, '--jobs', 1, timeout=900))
    p_args = ('--seeds', 2, '--duration', 0.5, '--ratios', '1', '--json')
    p_local = _json(erva('pareto', *p_args, '--jobs', 1))
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as cluster:
        remote = _json(erva('table', *args, '--scheduler', cluster.scheduler_address,
                            timeout=900))
        p_remote = _json(erva('pareto', *p_args, '--scheduler', cluster.scheduler_address))
    assert [r['controller'] for r in local['rows']] == ['passive', 'preview', 'clairvoyant']
    assert _numbers(remote['rows']) == _numbers(local['rows'])
    assert p_remote['curve'] == p_local['curve']
    assert p_remote['baselines'] == p_local['baselines']


def test_scheduler_that_does_not_answer_is_one_line(erva):
    pytest.importorskip('distributed')
    proc = erva('pareto', '--seeds', 1, '--duration', 0.2, '--ratios', '1',
                '--scheduler', 'tcp://127.0.0.1:9')
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "--scheduler: cannot connect to 'tcp://127.0.0.1:9'" in lines[0]
