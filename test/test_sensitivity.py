"""`erva sensitivity`: one row per factor, the tornado plot, the same numbers on Dask."""

import json

import pytest

ARGS = ('sensitivity', '--factors', 'M_s,command_delay', '--levels', '10',
        '--command-delays', '0.006', '--weights', '0,1', '--duration', 0.3, '--json')


def _numbers(res):
    return [(r['factor'], tuple(r['weights']),
             tuple((v['level'], v['J'], v['comfort'], v['power_w']) for v in r['levels']))
            for r in res['rows']]


def test_sensitivity_rows_plot_and_a_dask_cluster_give_the_local_numbers(erva, tmp_path):
    distributed = pytest.importorskip('distributed')
    local = json.loads(erva(*ARGS, '--jobs', 1, '--out', tmp_path, check=True).stdout)
    assert [r['factor'] for r in local['rows']] == ['M_s', 'command_delay']
    assert len(local['runs']) == 3                       # nominal, M_s +10 %, 6 ms delay
    nominal = [r for r in local['runs'] if r['factor'] == '']
    assert len(nominal) == 1 and local['rows'][0]['nominal']['J'] == nominal[0]['J']
    for row in local['rows']:
        (lv,) = row['levels']
        # J = -P at (0, 1): its change is minus the power's, in per cent of |J|.
        assert lv['dJ_pct'] == pytest.approx(-lv['dpower_pct'], rel=1e-9)
        assert lv['J'] == pytest.approx(-lv['power_w'], rel=1e-12)
    assert (tmp_path / 'sensitivity.png').stat().st_size > 10000
    assert json.loads((tmp_path / 'sensitivity.json').read_text())['rows'] == local['rows']
    assert '| M_s | % | +10: ' in (tmp_path / 'sensitivity.md').read_text()
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as cluster:
        remote = json.loads(erva(*ARGS, '--scheduler', cluster.scheduler_address,
                                 check=True).stdout)
    assert _numbers(remote) == _numbers(local)


@pytest.mark.parametrize('args,message', [
    (('--factors', 'mass'), "--factors: unknown factor 'mass'"),
    (('--command-delays', '0.03'), '--command-delays: 0.03 s must be in [0, ts = 0.02 s)'),
    (('--levels=-100',), '--levels: \'-100\': a mismatch must be above -100 %'),
])
def test_sensitivity_bad_options_are_one_line(erva, args, message):
    proc = erva('sensitivity', *args)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and message in lines[0], proc.stderr
