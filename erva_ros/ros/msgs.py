"""Convert between numpy values and the live system's messages (contract: erva_ros/core/topics.py).

Builders take SI values and a stamp in integer nanoseconds; parsers return
``(stamp_ns, values)`` and raise :class:`~erva_ros.core.loop.validation.MessageRejected`
for anything malformed, non-finite or absurd, so a node never acts on a bad value.
Stamps are kept as integer nanoseconds end to end: the lock-step plant matches a
command to its sample by exact stamp equality.
"""

from typing import Sequence, Tuple

import numpy as np

from builtin_interfaces.msg import Duration, Time
from geometry_msgs.msg import AccelStamped, PointStamped
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

from erva_ros.core import topics
from erva_ros.core.loop.validation import check_values, MessageRejected

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
    return topics.STATE_JOINTS if kind == 'erva' else topics.STATE_JOINTS[:2]


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


def _trajectory(stamp_ns: int, joint: str, values: Sequence[float], ts_ns: int
                ) -> JointTrajectory:
    msg = JointTrajectory()
    msg.header.stamp = ns_to_time(stamp_ns)
    msg.joint_names = [joint]
    msg.points = [JointTrajectoryPoint(positions=[float(v)],
                                       time_from_start=ns_to_duration(k * ts_ns))
                  for k, v in enumerate(np.asarray(values, dtype=float).ravel())]
    return msg


def preview_msg(stamp_ns: int, heights: Sequence[float], ts_ns: int) -> JointTrajectory:
    """Return the road preview w(t0 + k·Ts), k = 0..N (m) as a JointTrajectory."""
    return _trajectory(stamp_ns, topics.ROAD_JOINT, heights, ts_ns)


def damping_msg(stamp_ns: int, plan: Sequence[float], ts_ns: int) -> JointTrajectory:
    """Return the damping command (points[0], Ns/m) and its plan (points[k] at t0 + k·Ts)."""
    return _trajectory(stamp_ns, topics.DAMPING_JOINT, plan, ts_ns)


def clock_msg(stamp_ns: int) -> Clock:
    """Return a rosgraph_msgs/Clock at ``stamp_ns``."""
    return Clock(clock=ns_to_time(stamp_ns))


# -- parsers -------------------------------------------------------------------------------
def joint_state_x(msg: JointState) -> np.ndarray:
    """Return x = [z_s, ż_s, z_us, ż_us(, z_d, ż_d)] of a state message, unchecked.

    For observers of what was published (the monitor, reports); a node acting on a
    state uses :func:`parse_state`.
    """
    x = np.empty(2 * len(msg.position))
    x[0::2], x[1::2] = msg.position, msg.velocity
    return x


def parse_state(msg: JointState, kind: str) -> Tuple[int, np.ndarray]:
    """Return (stamp_ns, x) of a state message; reject wrong joints or bad values."""
    names = state_joint_names(kind)
    if tuple(msg.name) != names:
        raise MessageRejected(f'joint names {list(msg.name)} are not {list(names)}')
    if len(msg.position) != len(names) or len(msg.velocity) != len(names):
        raise MessageRejected(f'need {len(names)} positions and velocities, got '
                              f'{len(msg.position)} and {len(msg.velocity)}')
    pos = np.asarray(msg.position, dtype=float)
    vel = np.asarray(msg.velocity, dtype=float)
    check_values('position', pos, 'position')
    check_values('velocity', vel, 'velocity')
    x = np.empty(2 * len(names))
    x[0::2] = pos
    x[1::2] = vel
    return time_to_ns(msg.header.stamp), x


def parse_road_height(msg: PointStamped) -> Tuple[int, float, float]:
    """Return (stamp_ns, distance_m, height_m) of a road height message."""
    check_values('point.x', [msg.point.x], 'distance')
    check_values('point.z', [msg.point.z], 'road_height')
    return time_to_ns(msg.header.stamp), float(msg.point.x), float(msg.point.z)


def _parse_trajectory(msg: JointTrajectory, joint: str, ts_ns: int, min_points: int,
                      limit: str) -> Tuple[int, np.ndarray]:
    if list(msg.joint_names) != [joint]:
        raise MessageRejected(f'joint names {list(msg.joint_names)} are not [{joint!r}]')
    if len(msg.points) < min_points:
        raise MessageRejected(f'{len(msg.points)} points, need at least {min_points}')
    values = np.empty(len(msg.points))
    for k, p in enumerate(msg.points):
        if len(p.positions) != 1:
            raise MessageRejected(f'points[{k}] has {len(p.positions)} positions, need 1')
        if abs(time_to_ns(p.time_from_start) - k * ts_ns) > GRID_TOL_NS:
            raise MessageRejected(f'points[{k}].time_from_start is not {k}·Ts '
                                  f'(Ts = {ts_ns / NS:g} s)')
        values[k] = p.positions[0]
    check_values(f'points.positions ({joint})', values, limit)
    return time_to_ns(msg.header.stamp), values


def parse_preview(msg: JointTrajectory, ts_ns: int, min_points: int) -> Tuple[int, np.ndarray]:
    """Return (stamp_ns, heights (m)) of a preview with at least ``min_points`` points."""
    return _parse_trajectory(msg, topics.ROAD_JOINT, ts_ns, min_points, 'road_height')


def parse_damping(msg: JointTrajectory, ts_ns: int) -> Tuple[int, np.ndarray]:
    """Return (stamp_ns, plan (Ns/m)) of a damping command; plan[0] is the command."""
    return _parse_trajectory(msg, topics.DAMPING_JOINT, ts_ns, 1, 'damping')


__all__ = ['NS', 'ns_to_time', 'time_to_ns', 'ns_to_duration', 's_to_ns', 'state_joint_names',
           'state_msg', 'accel_msg', 'generator_msg', 'road_height_msg', 'preview_msg',
           'damping_msg', 'clock_msg', 'joint_state_x', 'parse_state', 'parse_road_height',
           'parse_preview', 'parse_damping']
