"""`erva run` records everything even when the recorder stalls (fault injection with SIGSTOP).

The loop's writers keep ``publisher_history_s`` (10 s) of samples for reliable repair,
so a recorder stopped for seconds -- in the middle of the run or across its end --
catches up once it runs again, and `erva run` waits for it before stopping the nodes.
Checked by counts: every message each node published is in the bag (read with the
mcap reader, not ours), and `erva run` says so.  A full disk is one error line, the loop
runs on, and the bag keeps every message written before it.
"""

import json
import re
import subprocess
import sys

import pytest

from conftest import REPO, ros_env
from run_helpers import (bag_counts as _bag_counts, run_with_node_killed,
                         run_with_node_stopped, start_run)

pytestmark = pytest.mark.ros


@pytest.mark.parametrize('duration, stop_after_s, where', [
    (6, 1.0, 'in the middle'),
    (3, 2.0, 'across the end'),
])
def test_a_recorder_stopped_for_three_seconds_loses_nothing(
        tmp_path, duration, stop_after_s, where):
    code, s, err = run_with_node_stopped('recorder_node', tmp_path, duration,
                                         stop_after_s, 3.0)
    assert code == 0 and s['ok'], (where, s['errors'], err[-2000:])
    rec = s['recording']
    assert rec['lost'] == 0 and rec['lost_in_transport'] == 0, rec
    assert not rec['diagnostics_missing'] and 'gave_up' not in rec, rec
    counts = _bag_counts(s['bag'])
    n = int(round(duration / 0.02))
    published = s['messages']['published']
    assert published['state'] == published['road/height'] == n + 1
    assert published['sprung_accel'] == published['generator'] == n
    for topic, count in published.items():
        assert counts[f'/erva/{topic}'] == count, (where, topic, counts)


def test_a_stall_longer_than_the_writers_history_is_reported_as_a_loss(tmp_path):
    # The writers keep 1 s here (publisher_history_s, 10 s by default) and the recorder is
    # stopped for 5 s: about 2.5 s of samples are gone for good (the transport buffers
    # ~1.5 s more) -- and erva run must say so, with exit status 1.
    live = tmp_path / 'live.yaml'
    live.write_text('/**:\n  ros__parameters:\n    publisher_history_s: 1.0\n')
    bags = tmp_path / 'bags'
    bags.mkdir()
    code, s, _ = run_with_node_stopped('recorder_node', bags, 6, 0.5, 5.0, '--live', live)
    assert code == 1 and not s['ok']
    rec = s['recording']
    assert rec['lost'] > 0
    lost = [e for e in s['errors'] if e.startswith('the bag lost')]
    assert lost and re.fullmatch(r'the bag lost \d+ of \d+ messages on /erva/\S+', lost[0])
    counts = _bag_counts(s['bag'])
    for topic, c in rec['topics'].items():
        assert counts.get(topic, 0) == c['recorded'] == c['published'] - c['lost'], topic


@pytest.fixture
def small_disk(tmp_path):
    """Mount a 256 kB tmpfs, which a 4 s session's bag (~0.7 MB) fills (root only)."""
    disk = tmp_path / 'disk'
    disk.mkdir()
    if subprocess.run(['mount', '-t', 'tmpfs', '-o', 'size=256k', 'tmpfs', str(disk)],
                      capture_output=True).returncode:
        pytest.skip('mounting a small tmpfs needs root')
    try:
        yield disk
    finally:
        subprocess.run(['umount', '-l', str(disk)], check=False)


def test_a_full_disk_is_one_error_line_and_the_bag_keeps_what_was_written(
        tmp_path, small_disk):
    proc = start_run('--duration', 4, '--record', small_disk, '--json')
    out, err = proc.communicate(timeout=240)
    s = json.loads(out)
    assert proc.returncode == 1 and len(s['errors']) == 1, (s['errors'], err[-2000:])
    assert s['errors'][0].startswith('recording failed: cannot write ')
    assert 'No space left on device' in s['errors'][0]
    # The loop ran on, to the scenario's end.
    assert s['plant']['steps'] == 200 and s['commands']['for_samples'] > 0, s['plant']
    rec = s['recording']
    kept = {t: c['recorded'] for t, c in rec['topics'].items()}
    assert 0 < sum(kept.values()) < sum(c['published'] for c in rec['topics'].values())
    # Completed on another disk, the bag holds exactly what was written before the error.
    repaired = tmp_path / 'repaired'
    code = subprocess.run([sys.executable, '-m', 'erva_ros.cli', 'bag', 'repair', s['bag'],
                           '--out', str(repaired)], env=ros_env(), cwd=REPO,
                          capture_output=True, text=True)
    assert code.returncode == 0, code.stderr
    counts = _bag_counts(repaired)
    assert all(counts.get(t, 0) == n for t, n in kept.items()), (counts, kept)
    # The bag says what happened, before and after the repair (erva run was not killed).
    for bag in (s['bag'], repaired):
        end = _cut_short(bag)
        assert end == [f'the session was cut short: {s["errors"][0]}'], (bag, end)
    assert any(w.startswith('repaired: ') for w in _warnings(repaired))


def _warnings(bag):
    info = subprocess.run([sys.executable, '-m', 'erva_ros.cli', 'bag', 'info', str(bag),
                           '--json'], env=ros_env(), cwd=REPO, capture_output=True, text=True)
    assert info.returncode == 0, info.stderr
    return json.loads(info.stdout)['warnings']


def _cut_short(bag):
    return [w for w in _warnings(bag) if 'cut short' in w]


def test_a_killed_recorder_is_named_as_the_bags_end_and_no_log_line_is_its_cause(tmp_path):
    # The recorder's last log line says what it was doing ("running at SCHED_FIFO 10"),
    # not why it ended: the error names the signal.  Its bag, unfinished, says the same
    # as its cut-short cause (not "erva run was killed"), and so does the repaired bag.
    code, s, err, _ = run_with_node_killed('recorder_node', 50, '--duration', 3, '--record',
                                           tmp_path / 'bags')
    assert code == 1, err[-2000:]
    # The loop went on to the scenario's end (how many samples a stalled controller
    # missed meanwhile depends on the load: counted, not checked here).
    assert s['plant']['steps'] == 150 and s['commands']['for_samples'] > 0, s['plant']
    died = [e for e in s['errors'] if 'recorder_node died' in e]
    assert len(died) == 1 and re.fullmatch(r'recorder_node died \(exit status -9\) at t = '
                                           r'\d+\.\d\d s: killed by SIGKILL', died[0]), died
    assert _cut_short(s['bag']) == [f'the session was cut short: {died[0]}']
    repaired = tmp_path / 'repaired'
    fixed = subprocess.run([sys.executable, '-m', 'erva_ros.cli', 'bag', 'repair', s['bag'],
                            '--out', str(repaired)], env=ros_env(), cwd=REPO,
                           capture_output=True, text=True)
    assert fixed.returncode == 0, fixed.stderr
    assert _cut_short(repaired) == [f'the session was cut short: {died[0]}']
    assert any(w.startswith('repaired: ') for w in _warnings(repaired))
