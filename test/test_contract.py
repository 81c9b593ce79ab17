"""The contract's messages (erva_ros/core/contract.py) against rclpy's own serialization.

Each family both ways: our bytes are what rclpy serializes for the same message, and
what rclpy serializes decodes to the same values.  Truncated or corrupt bytes are a
CdrError (a MessageRejected: counted and dropped by a node), never another exception.
"""

import math

import numpy as np
import pytest

rclpy_serialization = pytest.importorskip('rclpy.serialization')
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue  # noqa: E402
from geometry_msgs.msg import AccelStamped, PointStamped  # noqa: E402
from rosgraph_msgs.msg import Clock  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint  # noqa: E402

from erva_ros.core import contract as c  # noqa: E402
from erva_ros.core.loop.validation import MessageRejected  # noqa: E402
from erva_ros.core.model.quarter_car import make_model  # noqa: E402
from erva_ros.core.model.params import paper_params  # noqa: E402
from erva_ros.core.topics import STATE_JOINTS  # noqa: E402
from erva_ros.core.wire import CdrError, MAX_ELEMENTS  # noqa: E402
from erva_ros.ros.bag_messages import encoded_size  # noqa: E402

serialize = rclpy_serialization.serialize_message
deserialize = rclpy_serialization.deserialize_message
STAMP = 1_700_000_123 * 10**9 + 999_999_999
TS_NS = 20_000_000


def _stamp(msg, ns=STAMP):
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(ns, 10**9)
    return msg


def _same_bytes(ours: bytes, msg) -> None:
    """Check that rclpy reads our bytes as the same message, of the same size.

    (rclpy leaves its padding bytes uninitialised and may return a longer buffer: the
    bytes themselves are not compared; the size is the exact one of the type description.)
    """
    assert deserialize(ours, type(msg)) == msg
    assert len(ours) == 4 + encoded_size(msg)


def _trajectory(joint, values, ts_ns=TS_NS, first_ns=0):
    msg = _stamp(JointTrajectory(joint_names=[joint]))
    for k, v in enumerate(values):
        p = JointTrajectoryPoint(positions=[v])
        p.time_from_start.sec, p.time_from_start.nanosec = divmod(first_ns + k * ts_ns, 10**9)
        msg.points.append(p)
    return msg


@pytest.mark.parametrize('kind', ['erva', 'benchmark'])
def test_state(kind):
    names = make_model(paper_params(), kind).joints
    assert names == ('z_s', 'z_us', 'z_d')[:len(names)]     # the model's joints
    x = np.arange(2 * len(names)) * 0.01 - 0.02
    msg = _stamp(JointState(name=list(names), position=list(x[0::2]), velocity=list(x[1::2])))
    _same_bytes(c.encode_state(STAMP, x, names), msg)
    for row in (c.decode_state(serialize(msg)), c.decode_state(serialize(msg), names)):
        assert row.stamp_ns == STAMP and np.array_equal(row.x, x)
    other = make_model(paper_params(), 'benchmark' if kind == 'erva' else 'erva').joints
    with pytest.raises(MessageRejected, match='joint names'):
        c.decode_state(serialize(msg), other)
    msg.position[0] = math.nan
    c.decode_state(serialize(msg))              # an observer records what was sent
    with pytest.raises(MessageRejected, match='not finite'):
        c.decode_state(serialize(msg), names)


def test_accel_generator_road_clock():
    msg = _stamp(AccelStamped())
    msg.accel.linear.z = -3.25
    _same_bytes(c.encode_accel(STAMP, -3.25), msg)
    assert c.decode_accel(serialize(msg)) == c.Accel(STAMP, -3.25)

    msg = _stamp(JointState(name=['generator'], position=[0.001], velocity=[0.5],
                            effort=[5000.0]))
    _same_bytes(c.encode_generator(STAMP, 0.001, 0.5, 10000.0), msg)
    row = c.decode_generator(serialize(msg))
    assert (row.position, row.velocity, row.effort, row.power) == (0.001, 0.5, 5000.0, 2500.0)

    msg = _stamp(PointStamped())
    msg.point.x, msg.point.z = 123.5, -0.012
    _same_bytes(c.encode_road_height(STAMP, 123.5, -0.012), msg)
    assert c.decode_road_height(serialize(msg), strict=True) == c.RoadHeight(STAMP, 123.5,
                                                                             -0.012)
    msg.point.z = 5.0
    with pytest.raises(MessageRejected, match='absurd'):
        c.decode_road_height(serialize(msg), strict=True)

    clock = Clock()
    clock.clock.sec, clock.clock.nanosec = 3, 20_000_000
    _same_bytes(c.encode_clock(3_020_000_000), clock)
    assert c.decode_clock(serialize(clock)) == 3_020_000_000


def test_preview_and_command():
    heights = [0.001 * k for k in range(11)]
    msg = _trajectory('road_height', heights)
    _same_bytes(c.encode_preview(STAMP, heights, TS_NS), msg)
    row = c.decode_preview(serialize(msg), TS_NS, 11)
    assert row.stamp_ns == STAMP and list(row.heights) == heights
    with pytest.raises(MessageRejected, match='need at least 12'):
        c.decode_preview(serialize(msg), TS_NS, 12)
    with pytest.raises(MessageRejected, match='not 1·Ts'):
        c.decode_preview(serialize(_trajectory('road_height', heights, 10_000_000)), TS_NS)

    plan = [10000.0, 20000.0, 0.0]
    msg = _trajectory('c_e', plan)
    _same_bytes(c.encode_command(STAMP, plan, TS_NS), msg)
    row = c.decode_command(serialize(msg), TS_NS)
    assert row.u == 10000.0 and list(row.plan) == plan
    assert row.offsets_s == (0.0, 0.02, 0.04)
    with pytest.raises(MessageRejected, match='joint names'):
        c.decode_command(serialize(_trajectory('road_height', plan)), strict=True)
    assert row.delay_ns == 0 and row.act_ns == STAMP

    # A command acts d after its sample: every point d + j·Ts, 0 <= d < Ts.
    d = 6_000_000
    msg = _trajectory('c_e', plan, first_ns=d)
    _same_bytes(c.encode_command(STAMP, plan, TS_NS, d), msg)
    row = c.decode_command(serialize(msg), TS_NS)
    assert row.delay_ns == d and row.act_ns == STAMP + d and list(row.plan) == plan
    assert row.offsets_s == pytest.approx((0.006, 0.026, 0.046), abs=1e-12)
    c.check_command_delay(row, d)
    with pytest.raises(MessageRejected, match="command_delay_s is 0.004 s"):
        c.check_command_delay(row, 4_000_000)
    with pytest.raises(MessageRejected, match=r'not in \[0, Ts\)'):
        c.decode_command(serialize(_trajectory('c_e', plan, first_ns=TS_NS)), TS_NS)
    with pytest.raises(MessageRejected, match='is not 0'):      # a preview starts at t_k
        c.decode_preview(serialize(_trajectory('road_height', heights, first_ns=d)), TS_NS)
    bad = _trajectory('c_e', [-1.0])
    assert c.decode_command(serialize(bad)).u == -1.0      # observer: as sent
    with pytest.raises(MessageRejected, match='absurd'):
        c.decode_command(serialize(bad), strict=True)


def test_diagnostics_both_ways():
    arr = _stamp(DiagnosticArray(status=[
        DiagnosticStatus(level=b'\x01', name='/erva/nmpc_node', message='läuft',
                         hardware_id='controller:preview',
                         values=[KeyValue(key='commands', value='12'),
                                 KeyValue(key='published:/erva/damping_cmd', value='12')]),
        DiagnosticStatus(level=b'\x02', name='/erva/x', message='', hardware_id='', values=[]),
    ]))
    stamp, statuses = c.decode_diagnostics(serialize(arr))
    assert stamp == STAMP
    assert statuses[0] == c.Status('/erva/nmpc_node', 1, 'läuft', 'controller:preview',
                                   {'commands': '12', 'published:/erva/damping_cmd': '12'})
    assert statuses[1] == c.Status('/erva/x', 2, '', '', {})
    _same_bytes(c.encode_diagnostics(STAMP, statuses), arr)
    back = deserialize(c.encode_diagnostics(STAMP, statuses), DiagnosticArray)
    assert [s.name for s in back.status] == ['/erva/nmpc_node', '/erva/x']


def test_a_report_crosses_as_its_declared_types_and_nothing_else():
    # road_preview_node once reported its map offset as a numpy float: under numpy 2 its
    # text was 'np.float64(0.048)', which no reader parses, and the summary said nan.
    from erva_ros.core.reports import (EstimatorReport, format_value, report_from_status,
                                       report_status, RoadReport, Timing)
    assert format_value(np.float64(0.048)) == '0.048' and format_value(np.int64(7)) == '7'
    assert format_value(np.bool_(True)) == 'true'
    r = RoadReport(node='/erva/road_preview_node', source='map', map_offset_m=0.048,
                   map_samples=3, map_fallback_streak_from_ns=STAMP)
    back = report_from_status(report_status(r))
    assert back.values() == r.values()        # NaN fields too, as text
    assert back.map_offset_m == 0.048 and back.map_fallback_streak_from_ns == STAMP
    bad = [(RoadReport, 'map_offset_m', np.float64(0.048)), (RoadReport, 'map_samples', 3.0),
           (RoadReport, 'map_samples', True), (RoadReport, 'source', 1),
           (EstimatorReport, 'latency_ms', Timing(np.float64(1.0))),
           (EstimatorReport, 'std', {'z_s': np.float64(1e-3)})]
    for cls, name, value in bad:
        report = cls(node='/erva/x')
        setattr(report, name, value)
        with pytest.raises(TypeError, match=f'{cls.__name__}.{name}'):
            report.values()
    ok = EstimatorReport(node='/erva/x', nis_mean=2, std={'z_s': 1e-3})   # an int is a number
    assert report_from_status(report_status(ok)).nis_mean == 2.0


def test_measurements_strict_and_observed():
    values = [1e4, 9e3, -0.3, 0.002, 0.05, 40.0]
    data = c.MEASUREMENTS_ENCODER.encode(STAMP, values)
    row = c.decode_measurements(data)
    assert row.sensors == (-0.3, 0.002, 0.05) and row.c_e == 1e4
    half = list(values)
    half[2] = math.nan                  # half of the chassis frame: not a lost frame
    with pytest.raises(MessageRejected, match='partly NaN'):
        c.decode_measurements(c.MEASUREMENTS_ENCODER.encode(STAMP, half))
    assert math.isnan(c.decode_measurements(c.MEASUREMENTS_ENCODER.encode(STAMP, half),
                                            strict=False).sprung_accel)
    lost = list(values)
    lost[2] = lost[3] = math.nan        # the whole chassis frame lost: accepted
    assert math.isnan(c.decode_measurements(c.MEASUREMENTS_ENCODER.encode(STAMP, lost))
                      .deflection)


def test_every_truncation_and_corruption_is_rejected():
    samples = [c.encode_state(STAMP, np.zeros(6), STATE_JOINTS), c.encode_accel(STAMP, 1.0),
               c.encode_preview(STAMP, [0.0] * 11, TS_NS),
               c.encode_command(STAMP, [1.0, 2.0], TS_NS), c.encode_road_height(STAMP, 1, 0),
               c.encode_diagnostics(STAMP, [c.Status('n', 0, 'm', 'h', {'k': 'v'})])]
    decoders = [c.decode_state, c.decode_accel, c.decode_preview, c.decode_command,
                c.decode_road_height, c.decode_diagnostics]
    for data, decode in zip(samples, decoders):
        decode(data)
        for cut in range(len(data)):
            with pytest.raises(MessageRejected):
                decode(data[:cut])
    huge = bytearray(c.encode_state(STAMP, np.zeros(6), STATE_JOINTS))
    huge[20:24] = (MAX_ELEMENTS + 1).to_bytes(4, 'little')      # the name count
    with pytest.raises(CdrError, match='limit'):
        c.decode_state(bytes(huge))
    with pytest.raises(CdrError, match='encapsulation'):
        c.decode_state(b'\x01' + samples[0][1:])
