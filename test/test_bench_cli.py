"""`erva bench`: the JSON object of the issue, and its error lines."""

import json


def test_bench_json_shape(erva):
    proc = erva('bench', '--steps', 30, '--json')
    assert proc.returncode == 0, proc.stderr
    res = json.loads(proc.stdout)
    for key in ('solver', 'controller', 'samples', 'solve_ms', 'late',
                'suboptimality_pct', 'realtime_factor'):
        assert key in res
    assert (res['solver'], res['controller'], res['samples']) == ('sqp', 'preview', 30)
    assert set(res['solve_ms']) == {'p50', 'p99', 'max'}
    assert 0 < res['solve_ms']['p50'] <= res['solve_ms']['p99'] <= res['solve_ms']['max']
    cpu = res['solve_cpu_ms']
    assert set(cpu) == {'p50', 'p99', 'max'} and 0 < cpu['p50'] <= cpu['p99'] <= cpu['max']
    assert isinstance(res['late'], int)
    assert isinstance(res['suboptimality_pct'], float)
    assert res['reference']['solver'] == 'ipopt'
    assert res['realtime_factor'] > 0     # its value depends on the machine and its load


def test_bench_other_controller_without_reference(erva):
    proc = erva('bench', '--steps', 30, '--controller', 'preview_long', '--alpha', '0,1',
                '--no-reference', '--json')
    assert proc.returncode == 0, proc.stderr
    res = json.loads(proc.stdout)
    assert res['controller'] == 'preview_long' and res['suboptimality_pct'] is None
    assert res['max_iter'] == 8                     # its own cap, long_max_iter
    # --max-iter caps every real-time SQP, preview_long's too
    proc = erva('bench', '--steps', 30, '--controller', 'preview_long', '--alpha', '0,1',
                '--no-reference', '--json', '--max-iter', 2)
    assert proc.returncode == 0, proc.stderr
    res = json.loads(proc.stdout)
    assert res['max_iter'] == 2 and res['iterations_mean'] <= 2


def test_bench_errors_are_one_line(erva):
    for args, message in [(['--controller', 'passive'], 'has no solver to benchmark'),
                          (['--duration', '5'], '--duration applies to --live only'),
                          (['--steps', '0'], "'0' must be a positive integer")]:
        proc = erva('bench', *args)
        assert proc.returncode == 2, args
        assert message in proc.stderr.strip().splitlines()[-1]


def test_bench_several_seeds_one_line_each(erva):
    proc = erva('bench', '--steps', 20, '--seeds', '0,3', '--no-reference', '--json')
    assert proc.returncode == 0, proc.stderr
    res = json.loads(proc.stdout)
    assert [r['seed'] for r in res['runs']] == [0, 3] and res['summary']['seeds'] == [0, 3]
    assert all(r['samples'] == 20 and r['iterations_mean'] >= 1 for r in res['runs'])
    assert res['runs'][0]['acc_2norm'] != res['runs'][1]['acc_2norm']    # different roads
    text = erva('bench', '--steps', 20, '--seeds', '0,3', '--no-reference', check=True).stdout
    rows = [line.split('|')[1].strip() for line in text.splitlines() if line.startswith('| ')]
    assert rows == ['seed', '0', '3']
    for args, message in [(['--seeds', '1,1'], 'repeats a seed'),
                          (['--seeds', '1', '--seed', '2'], 'either --seed or --seeds')]:
        bad = erva('bench', *args)
        assert bad.returncode == 2 and message in bad.stderr.strip().splitlines()[-1]


def test_bench_repeat_gives_the_spread_and_the_same_loop(erva):
    proc = erva('bench', '--steps', 20, '--seeds', '0,3', '--repeat', 2, '--no-reference',
                '--json')
    assert proc.returncode == 0, proc.stderr
    res = json.loads(proc.stdout)
    runs = res['runs']
    assert [(r['seed'], r['repeat']) for r in runs] == [(0, 0), (3, 0), (0, 1), (3, 1)]
    # the loop counts, it never reads the clock: a repetition is the same loop
    costs = [r['closed_loop_cost'] for r in runs]
    assert costs[:2] == costs[2:]
    summary = res['summary']
    assert summary['seeds'] == [0, 3] and summary['repeat'] == 2
    for key in ('p50', 'p99', 'max'):
        low, high = summary['solve_ms'][key]
        assert low == min(r['solve_ms'][key] for r in runs) <= high
    assert all(len(r['load_avg']['start']) == 3 and r['load_avg']['cpus'] >= 1 for r in runs)
    text = erva('bench', '--steps', 20, '--repeat', 3, '--no-reference', check=True).stdout
    assert '3 runs of 20 samples: solve p50' in text and 'load average (1 min)' in text
    assert 'solve CPU time (the solving thread alone): p50' in text
    bad = erva('bench', '--live', '--repeat', 2)
    assert bad.returncode == 2
    assert '--repeat applies to the offline bench' in bad.stderr.strip().splitlines()[-1]
