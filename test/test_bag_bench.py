"""``erva bag bench``: options are checked, and a very short run measures what it claims."""

import json

import pytest


def test_bad_rates_are_one_line(erva):
    for args in (['--flood-rates', 'fast'], ['--flood-rates', '-5'],
                 ['--contract-rates', '0'], ['--window', '0']):
        proc = erva('bag', 'bench', *args)
        assert proc.returncode == 2 and 'Traceback' not in proc.stderr, args
        assert proc.stderr.strip().splitlines()[-1].startswith('erva bag'), proc.stderr


@pytest.mark.slow
@pytest.mark.ros
def test_a_short_benchmark_run(erva):
    proc = erva('bag', 'bench', '--window', '4', '--pairs', '1', '--contract-rates', '100',
                '--flood-rates', '200', '--flood-duration', '1.5', '--json', timeout=300)
    assert proc.returncode == 0, proc.stderr
    r = json.loads(proc.stdout)
    # Latencies are benchmark figures (their values depend on the machine's load); what
    # holds anywhere: each window classed samples, and their percentiles are ordered.
    for name in ('command', 'round_trip'):
        for side in ('without_recorder_ms', 'with_recorder_ms'):
            lat = r[name][side]
            assert lat['samples'] > 0 and 0 < lat['p50'] <= lat['p99'] <= lat['max'], \
                (name, side, lat)
    # The contract traffic counts periods, not wall time: 150 periods of 7 topics and the
    # three statuses at k = 0 and 100 (once a second at 100 Hz).
    [contract] = r['contract']
    assert contract['published'] == 150 * 7 + 2 * 3, contract
    assert contract['recorded'] + contract['lost'] == contract['published'], contract
    # The flood paces itself on the wall clock for 1.5 s: never ahead of 200 msg/s.
    [flood] = r['flood']
    assert 0 < flood['published'] <= 300, flood
    assert 0 <= flood['recorded'] == flood['published'] - flood['lost'], flood
    lossless = [x['recorded_per_s'] for x in (contract, flood) if x['lost'] == 0]
    assert r['sustained_msgs_per_s'] == (max(lossless) if lossless else None)
