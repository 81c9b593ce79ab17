"""``erva bag bench``: options are checked, and a very short run measures what it claims."""

import json

import pytest


def test_bad_rates_are_one_line(erva):
    for args in (['--flood-rates', 'fast'], ['--flood-rates', '-5'],
                 ['--contract-rates', '0'], ['--window', '0']):
        proc = erva('bag', 'bench', *args)
        assert proc.returncode == 2 and 'Traceback' not in proc.stderr, args
        assert proc.stderr.strip().splitlines()[-1].startswith('erva bag'), proc.stderr


@pytest.mark.ros
def test_a_short_benchmark_run(erva):
    proc = erva('bag', 'bench', '--window', '4', '--pairs', '1', '--contract-rates', '100',
                '--flood-rates', '200', '--flood-duration', '1.5', '--json', timeout=300)
    assert proc.returncode == 0, proc.stderr
    r = json.loads(proc.stdout)
    for name in ('command', 'round_trip'):
        assert r[name]['without_recorder_ms']['samples'] > 40      # 50 Hz over ~1.5 s
        assert r[name]['with_recorder_ms']['samples'] > 40
        assert 0 < r[name]['with_recorder_ms']['p50'] < 50
    [contract] = r['contract']
    assert contract['published'] > 700 and contract['lost'] == 0   # 7 topics at 100 Hz
    [flood] = r['flood']
    assert flood['published'] == 300 and flood['recorded'] <= 300
    assert r['sustained_msgs_per_s'] >= contract['recorded_per_s']
