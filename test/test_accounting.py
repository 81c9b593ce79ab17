"""Message accounting of a session (session/run/accounting.py): start gate and bag check."""

import pytest

from erva_ros.core import topics
from erva_ros.core.reports import NMPCReport, NodeReport, PlantReport, RecorderReport
from erva_ros.ros import qos as ros_qos
from erva_ros.session.run import accounting
from erva_ros.core.wire import header_stamp_ns
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
    reports = {'plant_sim_node': NodeReport(subscribers={'/erva/state': 2}),
               'road_preview_node': NodeReport(subscribers={'/erva/road/preview': 2})}
    missing = accounting.unmatched(reports, ['plant_sim_node', 'road_preview_node',
                                             'nmpc_node'], expected, later)
    assert missing == ['nmpc_node: no status yet',
                       'plant_sim_node: /erva/state has 2 of 3 subscribers']
    reports['plant_sim_node'].subscribers['/erva/state'] = 3
    reports['nmpc_node: controller'] = NodeReport()
    assert accounting.unmatched(reports, ['plant_sim_node', 'road_preview_node',
                                          'nmpc_node'], expected, later) == []
    assert accounting.recorder_unmatched(RecorderReport(publishers={'/erva/state': 1}),
                                         {'/erva/state': 1, '/diagnostics': 4}) == [
        'recorder: /diagnostics matched 0 of 4 publishers']


def test_extra_readers_count_on_the_time_masters_topics_only():
    # erva run --extra-readers N: the user's readers add to what the time master's
    # writers must match, so one of them cannot stand in for a loop reader.
    from erva_ros.session.run.start_gate import StartGate

    from erva_ros.session.run.observations import Observations

    class Monitor:
        gate = (topics.STATE,)

    obs = Observations()
    nodes = ('plant_sim_node', 'road_preview_node', 'nmpc_node')
    plain = StartGate(Monitor(), obs, '/erva', nodes, False, False, False).expected
    for realtime, grown in ((False, {'/erva/state'}),
                            (True, {'/erva/road/height', '/erva/road/preview'})):
        extra = StartGate(Monitor(), obs, '/erva', nodes, False, False, False,
                          [topics.time_master_topics(realtime)] * 2).expected
        assert {t for t in plain if extra[t] != plain[t]} == grown
        assert all(extra[t] == plain[t] + 2 for t in grown)


def test_rejected_inputs_that_cost_samples_fail_the_run():
    ok = NMPCReport(missed_samples=3, superseded_states=3, safe_commands=0)
    # A foreign state rejected, the loop untouched: fine.  A busy controller's skipped
    # samples are load, not rejection.
    assert accounting.rejections_cost(1, ok) is None
    # Every state refused after a wrong first stamp: passive for want of a state, which
    # fails the run although no sample was missed.
    refused = NMPCReport(missed_samples=0, superseded_states=0, safe_commands=319)
    assert accounting.rejections_cost(400, refused) == (
        '319 samples went without a command of their own while 400 input messages were '
        'rejected')
    assert accounting.rejections_cost(0, refused) is None
    assert accounting.rejections_cost(2, NMPCReport(
        missed_samples=5, superseded_states=1)).startswith('4 samples')
    assert accounting.rejections_cost(2, None) is None
    # Under load, samples without a command while only another publisher's (foreign)
    # message was refused: the refusal took no sample (its message was an extra one).
    busy = NMPCReport(missed_samples=0, superseded_states=0, safe_commands=3)
    assert accounting.rejections_cost(1, busy, foreign_total=1) is None
    assert accounting.rejections_cost(2, busy, foreign_total=1).startswith('3 samples')


def test_published_counts_sum_the_nodes_and_the_recorder_catches_up():
    reports = [PlantReport(published={'/erva/state': 101}, steps=100, final=True),
               NodeReport(published={'/erva/ecu/measurements': 100}, final=True),
               NodeReport(published={'/erva/state': 1})]
    published = accounting.published_counts(reports)
    assert published == {'/erva/state': 102, '/erva/ecu/measurements': 100}
    recorder = RecorderReport(count={'/erva/state': 102, '/erva/ecu/measurements': 97})
    assert accounting.recorder_behind(recorder, published) == {
        '/erva/ecu/measurements': (97, 100)}
    # Without the final report of one of them, the bag check cannot know its count.
    assert accounting.published_counts(reports, final_only=True) == {
        '/erva/state': None, '/erva/ecu/measurements': 100}
    assert accounting.recorder_behind(recorder, {'/erva/state': None}) == {}


def _bag(tmp_path, stamps_by_topic, statuses):
    """Write a bag with real CDR messages (rclpy's serializer) through our writer."""
    from rclpy.serialization import serialize_message

    from erva_ros.core.bag.qos import profile_to_dict
    from erva_ros.core.bag.writer import BagWriter
    from ros_msgs import diagnostics_msg, state_msg

    bag_dir = str(tmp_path / 'bag')
    w = BagWriter(bag_dir)
    offered = [profile_to_dict(ros_qos.control_qos())]
    w.add_topic('/erva/state', 'sensor_msgs/msg/JointState', offered)
    w.add_topic('/diagnostics', 'diagnostic_msgs/msg/DiagnosticArray', offered)
    for stamp in stamps_by_topic['/erva/state']:
        w.write('/erva/state', serialize_message(state_msg(stamp, [0.0] * 6, 'erva')),
                stamp, stamp)
    for i, (name, seq, session) in enumerate(statuses):
        arr = diagnostics_msg(10**9 + i, [NodeReport(node=f'/erva/{name}', status_seq=seq,
                                                     session=session)])
        w.write('/diagnostics', serialize_message(arr), 10**9 + i, 10**9 + i)
    w.close()
    return bag_dir


def test_check_bag_counts_the_loops_messages_and_finds_gaps(tmp_path):
    t0 = 1_000 * 10**9
    loop = [t0 + k * 20_000_000 for k in range(50)]
    foreign = [t0 + 3600 * 10**9]
    statuses = ([('plant_sim_node', s, 's1') for s in (3, 4, 6)] + [('nmpc_node', 1, 's1')]
                + [('plant_sim_node', 5, 'other session')])
    bag = _bag(tmp_path, {'/erva/state': loop[:48] + foreign}, statuses)
    out = accounting.check_bag(bag, {'/erva/state': 50},
                               {'/erva/plant_sim_node': 7, '/erva/nmpc_node': 1,
                                '/erva/road_preview_node': 2},
                               window_ns=(t0, t0 + 60 * 10**9), session='s1')
    assert out['topics']['/erva/state'] == {'published': 50, 'recorded': 48, 'lost': 2,
                                            'foreign': 1}
    assert out['lost'] == 2 and out['unknown'] == [] and out['foreign_statuses'] == 1
    # The other session's status 5 does not fill this one's gap.
    assert out['diagnostics_missing'] == {'/erva/plant_sim_node': [5, 7],
                                          '/erva/road_preview_node': 'none recorded'}
    # A node killed before its final report: its count is unknown, never a loss.
    out = accounting.check_bag(bag, {'/erva/state': None}, {}, session='s1')
    assert out['topics']['/erva/state']['lost'] is None and out['unknown'] == ['/erva/state']
    assert out['lost'] == 0


def test_cdr_stamp_matches_rclpy():
    from rclpy.serialization import serialize_message

    from ros_msgs import diagnostics_msg, state_msg
    stamp = 1_796_000_000 * 10**9 + 123_456_789
    assert header_stamp_ns(serialize_message(state_msg(stamp, [0.0] * 4, 'benchmark'))) == stamp
    data = serialize_message(diagnostics_msg(stamp, [NodeReport(node='/ns/a_node')]))
    assert header_stamp_ns(data) == stamp


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
