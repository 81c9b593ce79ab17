"""Is a bag one whole session of its own, and was the run real time: the checks, unit level.

Bags are written with the writer and rclpy's own serialisation (not the contract under
test); the verdict is computed from a synthetic session's observations.
"""

import os

import pytest
from rclpy.serialization import serialize_message

from erva_ros.core import topics
from erva_ros.core.bag.reader import open_bag
from erva_ros.core.bag.session_check import (
    begin_session_end, END_FILE, mark_session_end, session_end, session_warnings)
from erva_ros.core.bag.writer import BagWriter
from erva_ros.core.reports import NodeReport
from erva_ros.session.run import verdict
from erva_ros.session.run.observations import Observations
import ros_msgs as msgs

T0 = 1_800_000_000 * 10 ** 9
TS_NS = 20_000_000


def _bag(path, session_id='s1', statuses=(), repeat=0):
    w = BagWriter(str(path), session={'scenario': 'x', 'session_id': session_id})
    w.add_topic('/erva/state', 'sensor_msgs/msg/JointState')
    w.add_topic('/erva/damping_cmd', 'trajectory_msgs/msg/JointTrajectory')
    w.add_topic('/diagnostics', 'diagnostic_msgs/msg/DiagnosticArray')
    for k in range(20):
        stamp = T0 + k * TS_NS
        for _ in range(1 + (repeat if k == 5 else 0)):
            w.write('/erva/state', serialize_message(msgs.state_msg(stamp, [0.0] * 6, 'erva')),
                    stamp, stamp)
    for i, (name, sid) in enumerate(statuses):
        data = serialize_message(msgs.diagnostics_msg(T0, [NodeReport(node=name, session=sid)]))
        w.write('/diagnostics', data, T0 + i, T0 + i)
    w.close()
    return str(path)


def test_a_session_bag_says_how_its_session_ended(tmp_path):
    bag = _bag(tmp_path / 'b')
    assert session_end(open_bag(bag)) is None
    # What the bag itself shows: the recorder finished it, so erva run stopped first.
    assert session_warnings(open_bag(bag)) == [
        'the session was cut short: no end record, though the recorder finished the bag '
        '(erva run was stopped before it recorded the end)']
    # erva run reserves the end file as the loop starts: killed, it says no more.
    begin_session_end(bag)
    end_file = os.path.join(bag, END_FILE)
    assert session_warnings(open_bag(bag)) == [
        'the session was cut short: erva run stopped before it recorded how the session '
        'ended (killed?)']
    size = os.path.getsize(end_file)
    assert mark_session_end(bag, completed=False,
                            reason='nmpc_node died (exit status 1)') == []
    assert os.path.getsize(end_file) == size           # written in place: a full disk takes it
    assert session_warnings(open_bag(bag)) == [
        'the session was cut short: nmpc_node died (exit status 1)']
    # The end file alone (the recorder died: no metadata.yaml) says the same.
    os.remove(os.path.join(bag, 'metadata.yaml'))
    assert session_end(open_bag(bag)) == {'completed': False,
                                          'reason': 'nmpc_node died (exit status 1)'}
    assert mark_session_end(bag, completed=True) == []
    assert session_end(open_bag(bag)) == {'completed': True, 'reason': ''}
    bag = _bag(tmp_path / 'c')
    mark_session_end(bag, completed=True)
    assert session_warnings(open_bag(bag)) == []
    assert open_bag(bag).info()['warnings'] == []           # erva bag info
    # A bag not made by erva run (no session id) is not judged as a session.
    assert session_warnings(open_bag(_bag(tmp_path / 'plain', session_id=''))) == []


def test_another_sessions_messages_in_a_bag_are_named(tmp_path):
    bag = _bag(tmp_path / 'b', statuses=[('/erva/nmpc_node', 's1'), ('/erva/nmpc_node', 's2'),
                                         ('/other/nmpc_node', 's3')], repeat=3)
    mark_session_end(bag, completed=True)
    warnings = session_warnings(open_bag(bag))
    assert warnings == [
        'holds reports of another session (s2) in /erva: /erva/nmpc_node; two sessions ran '
        'on the same topics',
        '3 messages on /erva/state repeat a stamp: another loop published on the same topic']
    # Another namespace's reports are that session's business: not a warning.
    assert not any('s3' in w for w in warnings)


def _observations(cmd_delays_ms, skipped=0, timeouts=0, misses=0, gap_s=None):
    obs = Observations(window_ns=(T0, T0 + 10 ** 12), command_gap_s=gap_s)
    for k, delay in enumerate(cmd_delays_ms):
        stamp = T0 + k * TS_NS
        obs.add(topics.STATE, stamp + 10 ** 6,
                serialize_message(msgs.state_msg(stamp, [0.0] * 6, 'erva')))
        obs.add(topics.ROAD_HEIGHT, stamp, serialize_message(msgs.road_height_msg(stamp, 0, 0)))
        obs.add(topics.DAMPING_CMD, stamp + int(delay * 1e6),
                serialize_message(msgs.damping_msg(stamp, [1e4] * 10, TS_NS)))
    summary = {'nmpc': {'deadline_misses': misses, 'state_timeouts': timeouts},
               'road': {'samples_skipped': skipped}}
    return obs, summary


def test_the_verdict_names_each_shortfall_with_its_worst_instance():
    limits = verdict.quality_limits()
    assert limits == {'max_deadline_misses': 0, 'max_state_timeouts': 0,
                      'max_skipped_road_samples': 0, 'max_command_gap_s': 0.06,
                      'max_preview_fallback_samples': 0, 'max_unmatched_preview_points': 0,
                      'max_refused_alignments': 0}
    obs, summary = _observations([3.0] * 50)
    assert verdict.warnings(obs, summary, limits) == []
    delays = [3.0] * 50
    # Sample 30's solve took 95 ms; the next ones queued behind it: a 112 ms pause after 29.
    delays[30:35] = [95.0, 80.0, 62.0, 45.0, 25.0]
    obs, summary = _observations(delays, skipped=2, timeouts=1, misses=1)
    assert verdict.warnings(obs, summary, limits) == [
        '1 missed deadline (worst sample -> command 95 ms at t = 0.60 s)',
        '1 state timeout: the controller sent passive commands (longest pause between '
        'states 20 ms at t = 0.00 s)',
        '2 road samples skipped by a late timer (widest gap 20 ms at t = 0.00 s)',
        '1 pause between commands over 60 ms (longest 112 ms at t = 0.58 s)']
    # Thresholds come from config/session.yaml, and can be raised.
    looser = verdict.quality_limits({'max_deadline_misses': 1, 'max_state_timeouts': 1,
                                     'max_skipped_road_samples': 2, 'max_command_gap_s': 0.2})
    # The monitor counts the pauses over the threshold as they come.
    with pytest.raises(ValueError, match='max_command_gap_s'):
        verdict.warnings(obs, summary, looser)
    obs, summary = _observations(delays, skipped=2, timeouts=1, misses=1, gap_s=0.2)
    assert verdict.warnings(obs, summary, looser) == []
    with pytest.raises(Exception, match="max_command_gap_s"):
        verdict.quality_limits({'max_command_gap_s': -1.0})


def _map_block(samples, fallback, before, unmatched, accepted, refused, streaks):
    """Return a summary's road.map block (monitor_figures.road), previews of 11 points."""
    block = {'samples': samples, 'points': 11 * samples, 'fallback_samples': fallback,
             'fallback_points': before + unmatched, 'before_start_points': before,
             'beyond_end_points': 0, 'gap_points': 0, 'unmatched_points': unmatched,
             'alignments': accepted, 'alignments_refused': refused,
             'tries': accepted + refused}
    for name, (n, a, b) in streaks.items():
        block[f'{name}_streak'] = {'count': n, 'from_s': a, 'to_s': b}
    return {'road': {'map': block}}


def test_the_verdict_weighs_the_map_preview():
    # The README's run of 4 s on a map that starts at 20 m: its first 1.54 s without the
    # map (before its start, then until the first alignment on it), as measured.
    limits = verdict.quality_limits()
    run = _map_block(201, 78, 561, 297, 25, 10, {'fallback': (78, 0.0, 1.54),
                                                 'unmatched': (27, 1.02, 1.54),
                                                 'refused': (10, 0.46, 1.36)})
    assert verdict.map_warnings(run, limits) == [
        "78 of 201 map previews fell back to the no-preview prediction (858 of 2211 points: "
        "561 before the map's start, 297 unmatched; longest 78 previews in a row, "
        "t = 0.00–1.54 s)",
        '297 preview points unmatched: no alignment with the map accepted recently (longest '
        '27 previews in a row, t = 1.02–1.54 s)',
        '10 of 35 alignments with the map refused (longest 10 refusals in a row, '
        't = 0.46–1.36 s)']
    looser = verdict.quality_limits({'max_preview_fallback_samples': 78,
                                     'max_unmatched_preview_points': 297,
                                     'max_refused_alignments': 10})
    assert verdict.map_warnings(run, looser) == []
    # Another route's map under the right name: never aligned, no preview from it at all.
    wrong = _map_block(201, 201, 561, 1650, 0, 38, {'fallback': (201, 0.0, 4.0),
                                                    'unmatched': (150, 1.02, 4.0),
                                                    'refused': (38, 0.46, 3.96)})
    assert verdict.map_warnings(wrong, looser)[-1] == (
        '38 of 38 alignments with the map refused (longest 38 refusals in a row, '
        't = 0.46–3.96 s); none accepted: is the map of this road?')
    assert verdict.map_warnings({'road': {}}, limits) == []     # no map preview


def test_a_streak_is_the_longest_run_in_a_row_and_when():
    from erva_ros.core.loop.road_loop import Streak
    s = Streak()
    for k, hit in enumerate([0, 1, 1, 0, 1, 1, 1, 0, 1]):
        s.mark(T0 + k * TS_NS, bool(hit))
    assert (s.longest, s.from_ns, s.to_ns) == (3, T0 + 4 * TS_NS, T0 + 6 * TS_NS)
    assert (Streak().longest, Streak().from_ns) == (0, 0)
