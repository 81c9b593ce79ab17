"""The hot path's direct CDR codec (erva_ros/ros/cdr.py) against rclpy's own serialization."""

import math
import struct

import pytest

rclpy_serialization = pytest.importorskip('rclpy.serialization')
from sensor_msgs.msg import JointState  # noqa: E402
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint  # noqa: E402

from erva_ros.ros.cdr import (CdrError, decode_joint_state,  # noqa: E402
                              decode_joint_trajectory, JointStateEncoder, MAX_ELEMENTS)
from erva_ros.nodes.ecu_bridge_node import parse_command  # noqa: E402

serialize = rclpy_serialization.serialize_message
deserialize = rclpy_serialization.deserialize_message


def _joint_state(names, position=(), velocity=(), effort=(), frame='', sec=0, nsec=0):
    msg = JointState(name=list(names), position=list(position), velocity=list(velocity),
                     effort=list(effort))
    msg.header.frame_id = frame
    msg.header.stamp.sec, msg.header.stamp.nanosec = sec, nsec
    return msg


@pytest.mark.parametrize('names,position,velocity,effort,frame', [
    ((), (), (), (), ''),
    (('z_s',), (1.5,), (), (), 'x'),                       # odd offsets before doubles
    (('a', 'bb', 'ccc'), (1.0, -2.0, 3e-9), (4.0,), (5.0, 6.0), 'base_link'),
    (('c_e', 'c_e_mean', 'sprung_accel', 'suspension', 'v_gen', 'f_gen'),
     (1e4, math.nan, -0.3, 0.002, 0.05, 40.0), (), (), ''),
    (('zürich',), (7.0,), (8.0,), (9.0,), 'ü'),            # multi-byte UTF-8
])
def test_joint_state_decodes_what_rclpy_serializes(names, position, velocity, effort, frame):
    msg = _joint_state(names, position, velocity, effort, frame, sec=1_700_000_123,
                       nsec=999_999_999)
    stamp, n, p, v, e = decode_joint_state(serialize(msg))
    assert stamp == 1_700_000_123 * 10**9 + 999_999_999
    assert n == list(names)
    for got, want in ((p, position), (v, velocity), (e, effort)):
        assert len(got) == len(want)
        assert all(a == b or (math.isnan(a) and math.isnan(b)) for a, b in zip(got, want))


@pytest.mark.parametrize('names', [('z_s', 'z_us', 'z_d'), ('z_s', 'z_us'), ('ü',)])
def test_joint_state_encoder_is_read_back_by_rclpy(names):
    enc = JointStateEncoder(names)
    k = len(names)
    pos, vel = [0.1 * i - 1 for i in range(k)], [1e-3 * i for i in range(k)]
    msg = deserialize(enc.encode(12_345_678_901, pos, vel), JointState)
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (12, 345_678_901)
    assert msg.header.frame_id == ''
    assert list(msg.name) == list(names)
    assert list(msg.position) == pos and list(msg.velocity) == vel and list(msg.effort) == []
    # and the bytes decode to the same with our own reader
    assert decode_joint_state(enc.encode(5, pos, vel)) == (5, list(names), tuple(pos),
                                                           tuple(vel), ())


def _trajectory(values, dt_ns=20_000_000, joint='c_e', extra=False):
    msg = JointTrajectory(joint_names=[joint])
    msg.header.frame_id = 'f'
    for i, v in enumerate(values):
        pt = JointTrajectoryPoint(positions=list(v) if isinstance(v, tuple) else [v])
        if extra:          # fields the bridge skips must not shift what it reads
            pt.velocities, pt.accelerations, pt.effort = [1.0] * i, [2.0], [3.0] * (i % 2)
        pt.time_from_start.sec, pt.time_from_start.nanosec = divmod(i * dt_ns, 10**9)
        msg.points.append(pt)
    return msg


@pytest.mark.parametrize('extra', [False, True])
def test_joint_trajectory_decodes_what_rclpy_serializes(extra):
    values = [1e4 + 100 * i for i in range(60)]      # 60 points: offsets past 1 s
    _, names, points = decode_joint_trajectory(serialize(_trajectory(values, extra=extra)))
    assert names == ['c_e']
    assert [p[0][0] for p in points] == values
    assert [p[1] for p in points] == [divmod(i * 20_000_000, 10**9) for i in range(60)]


def test_damping_command_parsing():
    msg = _trajectory([1e4, 2e4, 0.0])
    msg.header.stamp.sec, msg.header.stamp.nanosec = 1_700_000_000, 20_000_000
    stamp, plan, offsets = parse_command(serialize(msg))
    assert stamp == 1_700_000_000_020_000_000          # the sample it is for
    assert plan == [1e4, 2e4, 0.0] and offsets == pytest.approx([0.0, 0.02, 0.04])
    for bad in (_trajectory([]), _trajectory([1e4], joint='other'),
                _trajectory([(1e4, 2e4)]), _trajectory([math.nan]), _trajectory([2e6]),
                _trajectory([math.inf])):
        assert parse_command(serialize(bad)) == (None, None, None)
    assert parse_command(b'') == (None, None, None)


def test_every_truncation_and_corruption_is_a_cdr_error():
    state = serialize(_joint_state(('a', 'b'), (1.0, 2.0), (3.0,), (), 'frame'))
    traj = serialize(_trajectory([1.0, 2.0, 3.0], extra=True))
    for data, decode in ((state, decode_joint_state), (traj, decode_joint_trajectory)):
        full = decode(data)
        # Cut anywhere: either a CdrError (never IndexError, struct.error, ...) or, once
        # past the last field (rclpy's buffer has trailing bytes), the full message.
        outcomes = []
        for cut in range(len(data) + 1):
            try:
                outcomes.append(decode(data[:cut]) == full)
            except CdrError:
                outcomes.append(None)
        first = outcomes.index(True)
        assert first > len(data) // 2 and outcomes[:first] == [None] * first
        assert all(outcomes[first:])
    # frame_id '': stamp at bytes 4-11, frame_id 12-16 (+pad), name count 20, name 24-29
    state = serialize(_joint_state(('a', 'b'), (1.0, 2.0)))
    assert struct.unpack_from('<I', state, 20)[0] == 2 and state[28:30] == b'a\x00'
    huge = state[:20] + struct.pack('<I', MAX_ELEMENTS + 1) + state[24:]
    with pytest.raises(CdrError, match='elements'):
        decode_joint_state(huge)
    with pytest.raises(CdrError, match='encapsulation'):
        decode_joint_state(b'\x00\x00\x00\x00' + state[4:])
    bad_utf8 = bytearray(state)
    bad_utf8[20 + 4 + 4] = 0xff                      # first name's first byte
    with pytest.raises(CdrError, match='UTF-8'):
        decode_joint_state(bytes(bad_utf8))


@pytest.mark.parametrize('kind', ['erva', 'benchmark'])
def test_estimator_state_bytes_equal_the_state_message(kind):
    import numpy as np
    from erva_ros.ros.msgs import state_joint_names, state_msg
    x = np.array([0.01, -0.2, 0.002, 0.3, 0.004, -0.5])[:6 if kind == 'erva' else 4]
    data = JointStateEncoder(state_joint_names(kind)).encode(
        98_765_432_101, x[0::2].tolist(), x[1::2].tolist())
    assert deserialize(data, JointState) == state_msg(98_765_432_101, x, kind)


def test_accel_stamped_encoding_is_read_back_by_rclpy():
    from geometry_msgs.msg import AccelStamped
    from erva_ros.ros.cdr import encode_accel_stamped
    msg = deserialize(encode_accel_stamped(3_000_000_007, (1.0, 2.0, -9.81)), AccelStamped)
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (3, 7)
    assert (msg.accel.linear.x, msg.accel.linear.y, msg.accel.linear.z) == (1.0, 2.0, -9.81)
    assert (msg.accel.angular.x, msg.accel.angular.y, msg.accel.angular.z) == (0.0, 0.0, 0.0)
