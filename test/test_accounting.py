"""Message accounting of a session (erva_ros/session/accounting.py): start gate and bag check."""

import pytest

from erva_ros.core import topics
from erva_ros.ros import qos as ros_qos
from erva_ros.session import accounting
from erva_ros.ros.cdr import header_stamp_ns, status_seqs
from erva_ros.core.loop.validation import MessageRejected, StampWindow


def test_expected_subscribers_add_each_observer_that_watches_a_topic():
    monitor = [topics.STATE, topics.DAMPING_CMD, topics.DIAGNOSTICS]
    recorder = [topics.STATE, topics.SPRUNG_ACCEL, topics.DAMPING_CMD, topics.DIAGNOSTICS,
                topics.CLOCK]
    exp = accounting.expected_subscribers(accounting.LOOP_SUBSCRIBERS, [monitor, recorder],
                                          '/car1')
    assert exp['/car1/state'] == 3                 # nmpc, monitor, recorder
    assert exp['/car1/sprung_accel'] == 1          # the recorder only
    assert exp['/car1/damping_cmd'] == 3           # plant, monitor, recorder
    assert exp['/car1/road/preview'] == 1          # nmpc only
    assert exp['/diagnostics'] == 2
    assert '/clock' not in exp                     # not a loop topic: not gated


def test_unmatched_names_what_the_start_waits_for():
    expected = {'/erva/state': 3, '/erva/road/preview': 3}
    later = {'/erva/road/preview': 1}               # the monitor's gate subscription
    statuses = {'plant_sim_node': {'subscribers:/erva/state': '2'},
                'road_preview_node': {'subscribers:/erva/road/preview': '2'}}
    missing = accounting.unmatched(statuses, ['plant_sim_node', 'road_preview_node',
                                              'nmpc_node'], expected, later)
    assert missing == ['nmpc_node: no status yet',
                       'plant_sim_node: /erva/state has 2 of 3 subscribers']
    statuses['plant_sim_node']['subscribers:/erva/state'] = '3'
    statuses['nmpc_node: controller'] = {}
    assert accounting.unmatched(statuses, ['plant_sim_node', 'road_preview_node',
                                           'nmpc_node'], expected, later) == []
    assert accounting.recorder_unmatched({'publishers:/erva/state': '1'},
                                         {'/erva/state': 1, '/diagnostics': 4}) == [
        'recorder: /diagnostics matched 0 of 4 publishers']


def test_extra_readers_count_on_the_time_masters_topics_only():
    # erva run --extra-readers N: the user's readers add to what the time master's
    # writers must match, so one of them cannot stand in for a loop reader.
    from erva_ros.session.start_gate import StartGate

    class Monitor:
        watched = [topics.STATE, topics.DAMPING_CMD, topics.ROAD_HEIGHT, topics.DIAGNOSTICS]
        gate = (topics.STATE,)

    nodes = ('plant_sim_node', 'road_preview_node', 'nmpc_node')
    plain = StartGate(Monitor(), '/erva', nodes, False, False, False).expected
    for realtime, grown in ((False, {'/erva/state'}),
                            (True, {'/erva/road/height', '/erva/road/preview'})):
        extra = StartGate(Monitor(), '/erva', nodes, False, False, False,
                          [topics.time_master_topics(realtime)] * 2).expected
        assert {t for t in plain if extra[t] != plain[t]} == grown
        assert all(extra[t] == plain[t] + 2 for t in grown)


def test_rejected_inputs_that_cost_samples_fail_the_run():
    ok = {'missed_samples': 3, 'superseded_states': 3, 'safe_commands': 0}
    # A foreign state rejected, the loop untouched: fine.  A busy controller's skipped
    # samples are load, not rejection.
    assert accounting.rejections_cost({'rejected_total': 1}, ok) is None
    # Every state refused after a wrong first stamp: passive for want of a state, which
    # fails the run although no sample was missed.
    refused = {'missed_samples': 0, 'superseded_states': 0, 'safe_commands': 319}
    assert accounting.rejections_cost({'rejected_total': 400}, refused) == (
        '319 samples went without a command of their own while 400 input messages were '
        'rejected')
    assert accounting.rejections_cost({'rejected_total': 0}, refused) is None
    assert accounting.rejections_cost({'rejected_total': 2}, {
        'missed_samples': 5, 'superseded_states': 1}).startswith('4 samples')


def test_published_counts_sum_the_nodes_and_the_recorder_catches_up():
    statuses = {'plant_sim_node': {'published:/erva/state': '101', 'steps': '100'},
                'ecu_bridge_node: command': {'published:/erva/ecu/measurements': '100'},
                'other': {'published:/erva/state': '1'}}
    published = accounting.published_counts(statuses)
    assert published == {'/erva/state': 102, '/erva/ecu/measurements': 100}
    recorder = {'count:/erva/state': '102', 'count:/erva/ecu/measurements': '97'}
    assert accounting.recorder_behind(recorder, published) == {
        '/erva/ecu/measurements': (97, 100)}


def _bag(tmp_path, stamps_by_topic, statuses):
    """Write a bag with real CDR messages (rclpy's serializer) through our writer."""
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.serialization import serialize_message

    from erva_ros.core.bag.qos import profile_to_dict
    from erva_ros.core.bag.writer import BagWriter
    from erva_ros.ros.diagnostics import status_msg
    from erva_ros.ros.msgs import ns_to_time, state_msg

    bag_dir = str(tmp_path / 'bag')
    w = BagWriter(bag_dir)
    offered = [profile_to_dict(ros_qos.control_qos())]
    w.add_topic('/erva/state', 'sensor_msgs/msg/JointState', offered)
    w.add_topic('/diagnostics', 'diagnostic_msgs/msg/DiagnosticArray', offered)
    for stamp in stamps_by_topic['/erva/state']:
        w.write('/erva/state', serialize_message(state_msg(stamp, [0.0] * 6, 'erva')),
                stamp, stamp)
    for i, (name, seq) in enumerate(statuses):
        arr = DiagnosticArray(status=[status_msg(f'/erva/{name}', 0, 'ok',
                                                 {'status_seq': seq, 'x': 1.5})])
        arr.header.stamp = ns_to_time(10**9 + i)
        w.write('/diagnostics', serialize_message(arr), 10**9 + i, 10**9 + i)
    w.close()
    return bag_dir


def test_check_bag_counts_the_loops_messages_and_finds_gaps(tmp_path):
    t0 = 1_000 * 10**9
    loop = [t0 + k * 20_000_000 for k in range(50)]
    foreign = [t0 + 3600 * 10**9]
    statuses = [('plant_sim_node', s) for s in (3, 4, 6)] + [('nmpc_node', 1)]
    bag = _bag(tmp_path, {'/erva/state': loop[:48] + foreign}, statuses)
    out = accounting.check_bag(bag, {'/erva/state': 50},
                               {'plant_sim_node': 7, 'nmpc_node': 1, 'road_preview_node': 2},
                               window_ns=(t0, t0 + 60 * 10**9))
    assert out['topics']['/erva/state'] == {'published': 50, 'recorded': 48, 'lost': 2,
                                            'foreign': 1}
    assert out['lost'] == 2
    assert out['diagnostics_missing'] == {'plant_sim_node': [5, 7],
                                          'road_preview_node': 'none recorded'}


def test_cdr_stamp_and_status_sequence_match_rclpy():
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.serialization import serialize_message

    from erva_ros.ros.diagnostics import status_msg
    from erva_ros.ros.msgs import ns_to_time, state_msg
    stamp = 1_796_000_000 * 10**9 + 123_456_789
    assert header_stamp_ns(serialize_message(state_msg(stamp, [0.0] * 4, 'benchmark'))) == stamp
    arr = DiagnosticArray(status=[status_msg('/ns/a_node', 1, 'warn', {'status_seq': 17}),
                                  status_msg('b: part', 0, '', {'other': 'x'})])
    arr.header.stamp = ns_to_time(stamp)
    data = serialize_message(arr)
    assert header_stamp_ns(data) == stamp
    assert status_seqs(data) == [('a_node', 17)]


def test_stamp_window_rejects_the_future_and_the_stale_with_the_reason():
    w = StampWindow(max_lead_ns=50_000_000, max_age_ns=10**9)
    now = 5 * 10**9
    w.check('state', now, now)
    w.check('state', now + 50_000_000, now)
    w.check('state', now - 10**9, now)
    with pytest.raises(MessageRejected, match=r'state stamp is 3600\.000 s in the future'):
        w.check('state', now + 3600 * 10**9, now)
    with pytest.raises(MessageRejected, match=r'command stamp is 2\.000 s old'):
        w.check('command', now - 2 * 10**9, now)
