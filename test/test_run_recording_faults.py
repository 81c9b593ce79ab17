"""`erva run` records everything even when the recorder stalls (fault injection with SIGSTOP).

The loop's writers keep ``publisher_history_s`` (10 s) of samples for reliable repair,
so a recorder stopped for seconds -- in the middle of the run or across its end --
catches up once it runs again, and `erva run` waits for it before stopping the nodes.
Checked by counts: every message each node published is in the bag (read with the
mcap reader, not ours), and `erva run` says so.
"""

import re

import pytest

from run_helpers import bag_counts as _bag_counts, run_with_node_stopped

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
