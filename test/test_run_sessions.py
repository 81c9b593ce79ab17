"""Sessions know who they are: two on one DDS domain, in two namespaces or in one.

* Two concurrent `erva run` on different namespaces are isolated: each records exactly
  what its own nodes published, each summary's figures are its own loop's (its own
  seed, its own plant's energy), and each saw the other's reports as foreign only.
* A second session on a namespace where one runs is refused (exit 2, naming the other's
  nodes) before any of its nodes is configured; with --force it runs, and its bag says
  it holds another session's messages.
* Two sessions started at once on one namespace: the first to start runs, the other is
  refused (exit 2) and leaves no bag and no temporary directory behind.

Real processes over real DDS; bags read back with the mcap reader (run_helpers).
"""

import json
import re

import pytest

from conftest import sim_delay_args
from run_helpers import bag_counts, SampleWatch, start_run

pytestmark = pytest.mark.ros   # every test here starts DDS


def _finish(proc, timeout=240):
    out, err = proc.communicate(timeout=timeout)
    return proc.returncode, out, err


def test_two_sessions_on_two_namespaces_are_isolated(tmp_path):
    runs = {ns: start_run('--namespace', ns, '--seed', seed, '--duration', 3, '--road',
                          'iso8608', '--record', tmp_path / ns.strip('/'), '--json')
            for ns, seed in (('/a', 1), ('/b', 2))}
    results = {ns: _finish(p) for ns, p in runs.items()}
    for ns, (code, out, err) in results.items():
        assert code == 0, (ns, err[-2000:])
    s = {ns: json.loads(out) for ns, (_, out, _) in results.items()}
    for ns, summary in s.items():
        other = '/b' if ns == '/a' else '/a'
        assert summary['ok'] and summary['scenario']['namespace'] == ns
        rec = summary['recording']
        assert rec['lost'] == 0 and rec['unknown'] == [] and not rec['diagnostics_missing']
        # Exact: every message of its own loop, each stamp once, nothing of the other's.
        published = summary['messages']['published']
        counts = bag_counts(summary['bag'])
        for topic, n in published.items():
            assert counts[f'{ns}/{topic}'] == n, (ns, topic)
        assert not any(t.startswith(other + '/') for t in counts), counts
        assert rec['topics'][f'{ns}/damping_cmd']['published'] == published['damping_cmd']
        assert summary['messages']['dropped_total'] == 0
    # Figures of their own loops: two seeds of one road, two different rides.
    assert s['/a']['scenario']['seed'] == 1 and s['/b']['scenario']['seed'] == 2
    assert s['/a']['metrics']['acc_2norm'] != s['/b']['metrics']['acc_2norm']
    assert s['/a']['metrics']['harvested_j'] != s['/b']['metrics']['harvested_j']


def test_a_second_session_on_the_same_namespace_is_refused(tmp_path, erva):
    first = start_run('--duration', 30, '--no-record', '--json')
    watch = SampleWatch()
    try:
        watch.wait(5, proc=first)
        second = erva('run', '--duration', 2, '--no-record')
        assert second.returncode == 2, second.stderr
        line = second.stderr.strip().splitlines()[-1]
        assert 'another session runs on ROS_DOMAIN_ID' in line
        assert re.search(r'/erva/\w+_node', line), line
        assert '--force' in line
    finally:
        watch.close()
        first.send_signal(2)
        code, out, err = _finish(first)
    # The first session was not disturbed: it was stopped by us, nothing else.
    summary = json.loads(out)
    assert code == 130 and summary['errors'] == ['interrupted by SIGINT while running'], err
    assert summary['messages']['foreign_total'] == 0


def test_two_sessions_started_at_once_on_one_namespace_give_one_run_and_one_refusal(
        tmp_path, erva):
    # Started together, each hears the other while its nodes start: the one that started
    # first runs, the other refuses (exit 2) before any of its nodes is configured, and
    # leaves no bag and no temporary directory.  (Both crashed before: each one's
    # lifecycle requests reached the other's nodes of the same names.)
    tmp = tmp_path / 'tmp'
    tmp.mkdir()
    env = {'TMPDIR': str(tmp)}
    runs = [start_run('--duration', 1, '--record', tmp_path / f'bags{i}', '--json', env=env)
            for i in range(2)]
    results = [_finish(p) for p in runs]
    codes = [code for code, _, _ in results]
    assert sorted(codes) == [0, 2], [err[-2000:] for _, _, err in results]
    won, lost = (results[0], results[1]) if codes[0] == 0 else (results[1], results[0])
    line = lost[2].strip().splitlines()[-1]
    assert 'another session runs on ROS_DOMAIN_ID' in line and '--force' in line, lost[2]
    assert lost[1] == ''                             # no summary: it did not run
    s = json.loads(won[1])
    assert s['ok'] and s['errors'] == [] and s['commands']['received'] > 0
    assert s['recording']['lost'] == 0 and s['messages']['foreign_total'] == 0
    # The winner's bag is one whole session of its own: the other's nodes were never
    # configured, so its statuses there are not "another session on the same topics".
    info = json.loads(erva('bag', 'info', s['bag'], '--json', check=True).stdout)
    assert info['warnings'] == [], info['warnings']
    bags = [b for i in range(2) for b in (tmp_path / f'bags{i}').glob('*') if b.is_dir()]
    assert [str(b) for b in bags] == [s['bag']]
    assert list(tmp.iterdir()) == []


def test_two_lockstep_sessions_keep_their_own_clocks(tmp_path, erva):
    # Lock-step runs on /clock: outside the default namespace a session's clock is
    # <namespace>/clock, so two of them on one domain each step their own loop -- and each
    # is still the offline closed loop, to the last digit.
    runs = [start_run('--mode', 'lockstep', '--namespace', ns, '--duration', 2, '--record',
                      tmp_path / ns.strip('/'), '--json') for ns in ('/a', '/b')]
    sim = json.loads(erva('sim', '--duration', 2, *sim_delay_args(), '--json', check=True).stdout)
    for proc in runs:
        code, out, err = _finish(proc)
        assert code == 0, err[-2000:]
        s = json.loads(out)
        ns = s['scenario']['namespace']
        assert s['metrics']['acc_2norm'] == pytest.approx(sim['acc_2norm'], rel=1e-12)
        counts = bag_counts(s['bag'])
        assert counts[f'{ns}/clock'] >= 100 and '/clock' not in counts, counts
