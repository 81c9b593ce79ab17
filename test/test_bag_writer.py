"""The MCAP writer against readers we did not write (mcap + mcap-ros2-support, rosbags)."""

import os

from builtin_interfaces.msg import Duration, Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import AccelStamped, PointStamped
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
import pytest
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint
import yaml

from erva_ros.core import topics as contract

from erva_ros.ros.bag_messages import serialize, write_message
from erva_ros.ros import qos as ros_qos
from erva_ros.core.bag import BagError
from erva_ros.core.bag.metadata import dump_yaml
from erva_ros.core.bag.qos import dump_profiles, profile_to_dict
from erva_ros.core.bag.schemas import message_definition, share_directory, type_description_hash
from erva_ros.core.bag.writer import BagWriter
T0 = 1_800_000_000 * 10 ** 9


def _messages(k):
    """Return one message of every contract topic for step k, with distinctive values."""
    stamp = Time(sec=1_800_000_000 + k // 50, nanosec=(k % 50) * 20_000_000)
    state = JointState(name=list(contract.STATE_JOINTS), position=[k * 1e-3, 2e-3, -3e-3],
                       velocity=[0.1, -0.2, 0.3 + k])
    state.header.stamp = stamp
    accel = AccelStamped()
    accel.header.stamp = stamp
    accel.accel.linear.z = -9.5 + k
    gen = JointState(name=['generator'], position=[1e-4], velocity=[0.05], effort=[500.0 + k])
    gen.header.stamp = stamp
    road = PointStamped()
    road.header.stamp = stamp
    road.point.x, road.point.z = 20.0 * k, 1e-3 * k
    preview = JointTrajectory(joint_names=['road_height'], points=[
        JointTrajectoryPoint(positions=[1e-3 * i],
                             time_from_start=Duration(nanosec=i * 20_000_000))
        for i in range(11)])
    preview.header.stamp = stamp
    cmd = JointTrajectory(joint_names=['c_e'], points=[
        JointTrajectoryPoint(positions=[1e4 + k + i]) for i in range(10)])
    cmd.header.stamp = stamp
    prediction = JointTrajectory(joint_names=['z_s', 'sprung_accel', 'power'], points=[
        JointTrajectoryPoint(positions=[1e-3 * i, -0.5 + k, 2.0 * i],
                             time_from_start=Duration(nanosec=i * 20_000_000))
        for i in range(11)])
    prediction.header.stamp = stamp
    diag = DiagnosticArray(status=[DiagnosticStatus(
        level=DiagnosticStatus.WARN, name='nmpc_node: ünïcode', message='odd length ' * (k % 3),
        values=[KeyValue(key='solve_ms_p99', value=str(1.5 * k))])])
    diag.header.stamp = stamp
    return {'/erva/state': state, '/erva/sprung_accel': accel, '/erva/generator': gen,
            '/erva/road/height': road, '/erva/road/preview': preview,
            '/erva/damping_cmd': cmd, '/erva/prediction': prediction, '/diagnostics': diag,
            '/clock': Clock(clock=stamp)}


@pytest.fixture
def session_bag(tmp_path):
    """Write 20 steps of every contract topic; return (bag dir, {topic: [messages]})."""
    bag_dir = str(tmp_path / 'session')
    offered = [profile_to_dict(ros_qos.control_qos())]
    written = {}
    with BagWriter(bag_dir, session={'scenario': 'unit', 'seed': '7'},
                   custom_data={'scenario': 'unit'}) as w:
        for topic, type_name in contract.TOPIC_TYPES.items():
            w.add_topic(topic, type_name, offered)
        for k in range(20):
            for topic, msg in _messages(k).items():
                t = T0 + k * 20_000_000
                write_message(w, topic, msg, t + 500_000, t + 100_000)
                written.setdefault(topic, []).append(msg)
    return bag_dir, written


def test_schema_is_rosbag2s_concatenated_definition():
    encoding, text = message_definition('trajectory_msgs/msg/JointTrajectory')
    assert encoding == 'ros2msg'
    sections = text.split('\n' + '=' * 80 + '\n')
    own = open(os.path.join(share_directory('trajectory_msgs'), 'msg',
                            'JointTrajectory.msg')).read()
    assert sections[0] == own  # the root definition verbatim, no header
    # Dependencies depth first, each once, named as written in the .msg files.
    assert [s.split('\n', 1)[0] for s in sections[1:]] == [
        'MSG: std_msgs/Header', 'MSG: builtin_interfaces/Time',
        'MSG: trajectory_msgs/JointTrajectoryPoint', 'MSG: builtin_interfaces/Duration']
    header = open(os.path.join(share_directory('std_msgs'), 'msg', 'Header.msg')).read()
    assert sections[1] == 'MSG: std_msgs/Header\n' + header


def test_type_hash_comes_from_the_type_description():
    assert type_description_hash('sensor_msgs/msg/JointState').startswith('RIHS01_')
    assert len(type_description_hash('rosgraph_msgs/msg/Clock')) == len('RIHS01_') + 64
    assert type_description_hash('sensor_msgs/msg/NoSuchType') == ''


def test_qos_profile_text_is_rosbag2s():
    # A publisher's offered QoS as rosbag2 Jazzy stores it (metadata.yaml of a real bag).
    offered = {'history': 'unknown', 'depth': 0, 'reliability': 'reliable',
               'durability': 'volatile', 'deadline': {'sec': 9223372036, 'nsec': 854775807},
               'lifespan': {'sec': 9223372036, 'nsec': 854775807}, 'liveliness': 'automatic',
               'liveliness_lease_duration': {'sec': 9223372036, 'nsec': 854775807},
               'avoid_ros_namespace_conventions': False}
    assert dump_profiles([offered]) == (
        '- history: unknown\n  depth: 0\n  reliability: reliable\n  durability: volatile\n'
        '  deadline:\n    sec: 9223372036\n    nsec: 854775807\n'
        '  lifespan:\n    sec: 9223372036\n    nsec: 854775807\n  liveliness: automatic\n'
        '  liveliness_lease_duration:\n    sec: 9223372036\n    nsec: 854775807\n'
        '  avoid_ros_namespace_conventions: false')
    assert dump_profiles([]) == '[]'
    ours = profile_to_dict(ros_qos.control_qos())
    assert (ours['history'], ours['depth'], ours['reliability'], ours['durability']) == (
        'keep_last', 10, 'reliable', 'volatile')


def test_mcap_layout_and_mcap_ros2_decoding(session_bag):
    bag_dir, written = session_bag
    path = os.path.join(bag_dir, 'session_0.mcap')
    with open(path, 'rb') as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        assert reader.get_header().profile == 'ros2'
        summary = reader.get_summary()
        assert summary.statistics.message_count == 20 * len(contract.TOPIC_TYPES)
        assert summary.chunk_indexes and summary.statistics.chunk_count >= 1
        for channel in summary.channels.values():
            schema = summary.schemas[channel.schema_id]
            assert channel.message_encoding == 'cdr'
            assert schema.encoding == 'ros2msg'
            assert schema.name == contract.TOPIC_TYPES[channel.topic]
            assert schema.data.decode() == message_definition(schema.name)[1]
            assert channel.metadata['topic_type_hash'] == type_description_hash(schema.name)
            assert yaml.safe_load(channel.metadata['offered_qos_profiles'])[0][
                'reliability'] == 'reliable'
        seen = {}
        for schema, channel, message, decoded in reader.iter_decoded_messages():
            k = seen.setdefault(channel.topic, 0)
            seen[channel.topic] += 1
            assert type(decoded).__name__ == schema.name.split('/')[-1]
            assert message.log_time - message.publish_time == 400_000
            original = written[channel.topic][k]
            if channel.topic == '/erva/damping_cmd':
                assert [p.positions[0] for p in decoded.points] == [
                    p.positions[0] for p in original.points]
            if channel.topic == '/diagnostics':
                assert decoded.status[0].name == original.status[0].name
                assert decoded.status[0].message == original.status[0].message
            if channel.topic == '/erva/state':
                assert list(decoded.velocity) == list(original.velocity)
        assert seen == {t: 20 for t in contract.TOPIC_TYPES}
        records = {m.name: m.metadata for m in reader.iter_metadata()}
    assert records['erva_session'] == {'scenario': 'unit', 'seed': '7'}
    # The rosbag2 record holds metadata.yaml's mapping, as rosbag2 stores it on close.
    inner = yaml.safe_load(records['rosbag2']['serialized_metadata'])
    outer = yaml.safe_load(open(os.path.join(bag_dir, 'metadata.yaml')))
    assert inner == outer['rosbag2_bagfile_information']


def test_rosbags_reads_metadata_and_every_message(session_bag):
    from rosbags.rosbag2 import Reader
    from rosbags.typesys import get_typestore, Stores
    bag_dir, written = session_bag
    store = get_typestore(Stores.ROS2_JAZZY)
    with Reader(bag_dir) as reader:
        assert reader.message_count == 20 * len(contract.TOPIC_TYPES)
        assert {c.topic: c.msgtype for c in reader.connections} == contract.TOPIC_TYPES
        assert all(c.ext.offered_qos_profiles[0].reliability.name == 'RELIABLE'
                   for c in reader.connections)
        count = 0
        for connection, timestamp, raw in reader.messages():
            msg = store.deserialize_cdr(raw, connection.msgtype)  # strict about CDR length
            assert type(msg).__name__.endswith(connection.msgtype.split('/')[-1])
            count += 1
        assert count == 20 * len(contract.TOPIC_TYPES)
        assert reader.start_time == T0 + 500_000


def test_metadata_yaml_is_version_9_as_rosbag2_writes_it(session_bag):
    bag_dir, _ = session_bag
    text = open(os.path.join(bag_dir, 'metadata.yaml')).read()
    assert text.startswith('rosbag2_bagfile_information:\n  version: 9\n'
                           '  storage_identifier: mcap\n  duration:\n    nanoseconds: ')
    meta = yaml.safe_load(text)['rosbag2_bagfile_information']
    assert list(meta) == ['version', 'storage_identifier', 'duration', 'starting_time',
                          'message_count', 'topics_with_message_count', 'compression_format',
                          'compression_mode', 'relative_file_paths', 'files', 'custom_data',
                          'ros_distro']
    assert meta['duration']['nanoseconds'] == 19 * 20_000_000
    assert meta['starting_time']['nanoseconds_since_epoch'] == T0 + 500_000
    assert meta['relative_file_paths'] == ['session_0.mcap']
    n = 20 * len(contract.TOPIC_TYPES)
    assert meta['files'][0]['message_count'] == meta['message_count'] == n
    assert meta['compression_format'] == meta['compression_mode'] == ''
    assert meta['custom_data'] == {'scenario': 'unit'} and meta['ros_distro'] == 'jazzy'
    topic = meta['topics_with_message_count'][0]
    assert list(topic['topic_metadata']) == ['name', 'type', 'serialization_format',
                                             'offered_qos_profiles', 'type_description_hash']
    assert topic['topic_metadata']['offered_qos_profiles'][0]['history'] == 'keep_last'
    assert '    - topic_metadata:\n        name: ' in text  # yaml-cpp's sequence indent


def test_yaml_scalars_that_need_quotes_round_trip():
    odd = {'a': '', 'b': 'yes', 'c': '12', 'd': 'x: y', 'e': '{"json": [1, 2]}',
           'f': 'line\nbreak', 'g': '2026-11-22', 'h': 'null', 'i': '# not a comment'}
    assert yaml.safe_load(dump_yaml({'custom_data': odd}))[
        'rosbag2_bagfile_information']['custom_data'] == odd


def test_serialized_length_is_the_exact_cdr_length():
    from rosbags.typesys import get_typestore, Stores
    store = get_typestore(Stores.ROS2_JAZZY)
    for k in range(3):
        for topic, msg in _messages(k).items():
            data = serialize(msg)
            type_name = contract.TOPIC_TYPES[topic]
            back = store.deserialize_cdr(data, type_name)
            # rosbags' own encoder gives the exact length of the same content.
            assert len(store.serialize_cdr(back, type_name)) == len(data), topic


def test_writer_refuses_an_existing_directory_and_bad_options(tmp_path):
    (tmp_path / 'taken').mkdir()
    with pytest.raises(BagError, match='already exists'):
        BagWriter(str(tmp_path / 'taken'))
    with pytest.raises(BagError, match='compression'):
        BagWriter(str(tmp_path / 'x'), compression='gzip')
    (tmp_path / 'file').write_text('not a directory')
    with pytest.raises(BagError, match='cannot create bag directory') as err:
        BagWriter(str(tmp_path / 'file' / 'bag'))
    assert '\n' not in str(err.value)


def test_flush_period_closes_chunks_on_time(tmp_path):
    now = [0.0]
    w = BagWriter(str(tmp_path / 'b'), flush_period_s=0.5, clock=lambda: now[0])
    w.add_topic('/clock', 'rosgraph_msgs/msg/Clock')
    size0 = os.path.getsize(w.file_path)
    for k in range(10):
        now[0] = 0.1 * k
        write_message(w, '/clock', Clock(), T0 + k)
    assert w.flushes == 1 and os.path.getsize(w.file_path) > size0  # flushed at t = 0.5 s
    w.close()
    assert w.closed


def test_zstd_chunks_read_back(tmp_path):
    from rosbags.rosbag2 import Reader
    with BagWriter(str(tmp_path / 'z'), compression='zstd') as w:
        w.add_topic('/clock', 'rosgraph_msgs/msg/Clock')
        for k in range(100):
            write_message(w, '/clock', Clock(clock=Time(sec=k)), T0 + k)
    with Reader(str(tmp_path / 'z')) as reader:
        assert sum(1 for _ in reader.messages()) == 100


def test_the_recorded_command_has_no_machine_paths():
    # A bag travels: its session record names the command, not where this checkout lives.
    import erva_ros
    from erva_ros.core.bag.session import command_line
    module = os.path.join(os.path.dirname(erva_ros.__file__), 'session', 'bag', 'offline_bag.py')
    assert command_line([module, 'bags/x', '--seed', '1']) == \
        'python -m erva_ros.session.bag.offline_bag bags/x --seed 1'
    assert command_line(['/opt/venv/bin/erva', 'run']) == 'erva run'
