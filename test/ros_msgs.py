"""Test helpers (no tests here): the contract's messages as rclpy message objects.

The tests build what they send with the generated message classes and rclpy's own
serialisation -- not with erva_ros.core.contract, the codec under test -- so a test
message can also be made malformed field by field.  Builders take SI values and a stamp
in integer nanoseconds; parsers return ``(stamp_ns, values)`` and raise
:class:`~erva_ros.core.loop.validation.MessageRejected` for anything malformed.
"""

from typing import Optional, Sequence, Tuple

import numpy as np

from builtin_interfaces.msg import Duration, Time
from geometry_msgs.msg import AccelStamped, PointStamped
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

from erva_ros.core import contract, topics
from erva_ros.core.model.quarter_car import STATE_NAMES

NS = 1_000_000_000
#: Tolerance on time_from_start of trajectory points (ns): a point off the Ts grid is rejected.
GRID_TOL_NS = 1000


def ns_to_time(ns: int) -> Time:
    """Return a builtin_interfaces/Time for ``ns`` nanoseconds."""
    ns = int(ns)
    return Time(sec=ns // NS, nanosec=ns % NS)


def time_to_ns(stamp) -> int:
    """Return the nanoseconds of a builtin_interfaces/Time (or Duration)."""
    return int(stamp.sec) * NS + int(stamp.nanosec)


def ns_to_duration(ns: int) -> Duration:
    """Return a builtin_interfaces/Duration for ``ns`` >= 0 nanoseconds."""
    ns = int(ns)
    return Duration(sec=ns // NS, nanosec=ns % NS)


def s_to_ns(seconds: float) -> int:
    """Return ``seconds`` as integer nanoseconds (rounded)."""
    return int(round(float(seconds) * NS))


def state_joint_names(kind: str) -> Tuple[str, ...]:
    """Return the JointState names of the state of model ``kind`` (benchmark: no z_d)."""
    return STATE_NAMES[kind][0::2]


# -- builders ------------------------------------------------------------------------------
def state_msg(stamp_ns: int, x: Sequence[float], kind: str) -> JointState:
    """Return the state x = [z_s, ż_s, z_us, ż_us(, z_d, ż_d)] as JointState (m, m/s)."""
    x = np.asarray(x, dtype=float)
    msg = JointState()
    msg.header.stamp = ns_to_time(stamp_ns)
    msg.name = list(state_joint_names(kind))
    msg.position = x[0::2].tolist()
    msg.velocity = x[1::2].tolist()
    return msg


def accel_msg(stamp_ns: int, sprung_accel: float) -> AccelStamped:
    """Return the chassis acceleration z̈_s (m/s²) at the sample time."""
    msg = AccelStamped()
    msg.header.stamp = ns_to_time(stamp_ns)
    msg.accel.linear.z = float(sprung_accel)
    return msg


def generator_msg(stamp_ns: int, displacement: float, velocity: float,
                  damping_cmd: float) -> JointState:
    """Return the generator joint: relative displacement (m), v_gen (m/s), force u·v_gen (N).

    The harvested power is P = effort·velocity = u·v_gen² (W, paper eq. (12)).
    """
    msg = JointState()
    msg.header.stamp = ns_to_time(stamp_ns)
    msg.name = [topics.GENERATOR_JOINT]
    msg.position = [float(displacement)]
    msg.velocity = [float(velocity)]
    msg.effort = [float(damping_cmd) * float(velocity)]
    return msg


def road_height_msg(stamp_ns: int, distance_m: float, height_m: float) -> PointStamped:
    """Return the road height at the tyre (point.z, m) and distance travelled (point.x, m)."""
    msg = PointStamped()
    msg.header.stamp = ns_to_time(stamp_ns)
    msg.point.x = float(distance_m)
    msg.point.z = float(height_m)
    return msg


def _trajectory(stamp_ns: int, joint: str, values: Sequence[float], ts_ns: int,
                offset_ns: int = 0) -> JointTrajectory:
    msg = JointTrajectory()
    msg.header.stamp = ns_to_time(stamp_ns)
    msg.joint_names = [joint]
    msg.points = [JointTrajectoryPoint(positions=[float(v)],
                                       time_from_start=ns_to_duration(offset_ns + k * ts_ns))
                  for k, v in enumerate(np.asarray(values, dtype=float).ravel())]
    return msg


def preview_msg(stamp_ns: int, heights: Sequence[float], ts_ns: int) -> JointTrajectory:
    """Return the road preview w(t0 + k·Ts), k = 0..N (m) as a JointTrajectory."""
    return _trajectory(stamp_ns, topics.ROAD_JOINT, heights, ts_ns)


def damping_msg(stamp_ns: int, plan: Sequence[float], ts_ns: int,
                delay_ns: Optional[int] = None) -> JointTrajectory:
    """Return the damping command and its plan: points[k] (Ns/m) at d + k·Ts.

    ``delay_ns`` is d (default: the shipped ``command_delay_s``, as the nodes expect).
    """
    if delay_ns is None:
        from conftest import shipped_delay_s
        delay_ns = int(round(shipped_delay_s() * 1e9))
    return _trajectory(stamp_ns, topics.DAMPING_JOINT, plan, ts_ns, delay_ns)


def clock_msg(stamp_ns: int) -> Clock:
    """Return a rosgraph_msgs/Clock at ``stamp_ns``."""
    return Clock(clock=ns_to_time(stamp_ns))


# -- parsers -------------------------------------------------------------------------------
def joint_state_x(msg: JointState) -> np.ndarray:  # noqa: D401
    """Return x = [z_s, ż_s, z_us, ż_us(, z_d, ż_d)] of a state message, unchecked.

    For observers of what was published (the monitor, reports); a node acting on a
    state uses :func:`parse_state`.
    """
    x = np.empty(2 * len(msg.position))
    x[0::2], x[1::2] = msg.position, msg.velocity
    return x


def _bytes(msg) -> bytes:
    from rclpy.serialization import serialize_message
    return serialize_message(msg)


# The parsers run the contract's decoders (erva_ros.core.contract) on rclpy's bytes: what a
# node does with what it receives.
def parse_state(msg: JointState, kind: str) -> Tuple[int, np.ndarray]:
    """Return (stamp_ns, x) of a state message; reject wrong joints or bad values."""
    row = contract.decode_state(_bytes(msg), state_joint_names(kind))
    return row.stamp_ns, row.x


def parse_road_height(msg: PointStamped) -> Tuple[int, float, float]:
    """Return (stamp_ns, distance_m, height_m) of a road height message."""
    row = contract.decode_road_height(_bytes(msg), strict=True)
    return row.stamp_ns, row.distance_m, row.height_m


def parse_preview(msg: JointTrajectory, ts_ns: int, min_points: int) -> Tuple[int, np.ndarray]:
    """Return (stamp_ns, heights (m)) of a preview with at least ``min_points`` points."""
    row = contract.decode_preview(_bytes(msg), ts_ns, min_points)
    return row.stamp_ns, row.heights


def parse_damping(msg: JointTrajectory, ts_ns: int) -> Tuple[int, np.ndarray]:
    """Return (stamp_ns, plan (Ns/m)) of a damping command; plan[0] is the command."""
    row = contract.decode_command(_bytes(msg), ts_ns)
    return row.stamp_ns, row.plan


__all__ = ['NS', 'ns_to_time', 'time_to_ns', 'ns_to_duration', 's_to_ns', 'state_joint_names',
           'state_msg', 'accel_msg', 'generator_msg', 'road_height_msg', 'preview_msg',
           'damping_msg', 'clock_msg', 'joint_state_x', 'parse_state', 'parse_road_height',
           'parse_preview', 'parse_damping']


def diagnostics_msg(stamp_ns: int, reports):
    """Return a diagnostic_msgs/DiagnosticArray of typed reports (erva_ros.core.reports)."""
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
    arr = DiagnosticArray(status=[DiagnosticStatus(
        level=bytes([r.level]), name=r.node, message=r.message, hardware_id=r.hardware_id,
        values=[KeyValue(key=k, value=v) for k, v in r.values().items()]) for r in reports])
    arr.header.stamp = ns_to_time(stamp_ns)
    return arr


def decoded(bag, topics=None):
    """Yield (bag message, rclpy message) in log-time order: rclpy's reading of a bag."""
    from rclpy.serialization import deserialize_message
    from erva_ros.ros.bag_messages import message_class
    classes = {}
    for m in bag.messages(topics):
        cls = classes.get(m.type)
        if cls is None:
            cls = classes[m.type] = message_class(m.type)
        yield m, deserialize_message(m.data, cls)
