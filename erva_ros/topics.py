"""Topic names, message types and QoS of the live system: the one contract all nodes share.

Only common_interfaces types; every message is stamped where the type allows, so
latencies can be measured from a recording alone.  Names are relative to the
``/erva`` namespace (remappable with ``--ros-args -r __ns:=/car1`` etc.).

topic          type                              content (SI units)
-------------  --------------------------------  ---------------------------------------------
state          sensor_msgs/JointState            joints [z_s, z_us, z_d]: position (m),
                                                 velocity (m/s); stamp = sample time t_k
sprung_accel   geometry_msgs/AccelStamped        accel.linear.z = z̈_s (m/s²) at t_k
generator      sensor_msgs/JointState            joint [generator]: position = z_d - (z_s -
                                                 z_us) (m), velocity = v_gen (m/s), effort =
                                                 u·v_gen (N); harvested P = effort·velocity (W)
road/height    geometry_msgs/PointStamped        point.x = distance travelled (m),
                                                 point.z = road height at the tyre (m)
road/preview   trajectory_msgs/JointTrajectory   joint [road_height]: points[k].positions =
                                                 [w(t0 + k·Ts)] (m), time_from_start = k·Ts,
                                                 header.stamp = t0
damping_cmd    trajectory_msgs/JointTrajectory   joint [c_e]: points[0] = command to apply now
                                                 (Ns/m), points[k] = plan at t0 + k·Ts;
                                                 header.stamp = stamp of the state used
/diagnostics   diagnostic_msgs/DiagnosticArray   per-node status, counters, timings
/clock         rosgraph_msgs/Clock               lock-step mode only
"""

import math

NAMESPACE = '/erva'

STATE = 'state'
SPRUNG_ACCEL = 'sprung_accel'
GENERATOR = 'generator'
ROAD_HEIGHT = 'road/height'
ROAD_PREVIEW = 'road/preview'
DAMPING_CMD = 'damping_cmd'
DIAGNOSTICS = '/diagnostics'
CLOCK = '/clock'

STATE_JOINTS = ('z_s', 'z_us', 'z_d')
GENERATOR_JOINT = 'generator'
ROAD_JOINT = 'road_height'
DAMPING_JOINT = 'c_e'

#: ROS type names (as in rosbag2 metadata) of each fully-qualified topic.
TOPIC_TYPES = {
    f'{NAMESPACE}/{STATE}': 'sensor_msgs/msg/JointState',
    f'{NAMESPACE}/{SPRUNG_ACCEL}': 'geometry_msgs/msg/AccelStamped',
    f'{NAMESPACE}/{GENERATOR}': 'sensor_msgs/msg/JointState',
    f'{NAMESPACE}/{ROAD_HEIGHT}': 'geometry_msgs/msg/PointStamped',
    f'{NAMESPACE}/{ROAD_PREVIEW}': 'trajectory_msgs/msg/JointTrajectory',
    f'{NAMESPACE}/{DAMPING_CMD}': 'trajectory_msgs/msg/JointTrajectory',
    DIAGNOSTICS: 'diagnostic_msgs/msg/DiagnosticArray',
    CLOCK: 'rosgraph_msgs/msg/Clock',
}


def control_qos(depth: int = 10):
    """Return the control topics' QoS: reliable, volatile, keep-last ``depth``.

    Reliable so that nothing published is silently lost (the recorder's counts must
    equal the publishers'); a subscriber's depth 10 absorbs a 200 ms stall at 50 Hz
    (a controller wants the newest sample, not a backlog).
    """
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth,
                      reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.VOLATILE)


def diagnostics_qos():
    """Return the QoS of a node's /diagnostics publisher: :func:`control_qos`, keep-last 100.

    A status comes about twice a second: 100 of them (~50 s) let reliable delivery repair
    a stalled recorder, as :func:`publisher_qos` does for the data.
    """
    return control_qos(100)


def publisher_depth(history_s: float, ts: float) -> int:
    """Return the keep-last depth that holds ``history_s`` of samples every ``ts`` (>= 10)."""
    return max(10, int(math.ceil(history_s / ts - 1e-9)))


def publisher_qos(history_s: float, ts: float):
    """Return a loop publisher's QoS: :func:`control_qos` keeping ``history_s`` of samples.

    A reliable writer repairs what a subscriber missed only from its own history: with
    keep-last 10, a recorder that stalls longer than the transports buffer (~1.5 s
    measured) loses those samples for good.  A deeper history costs the writer memory,
    not latency: a keep-last writer never waits for a slow reader.
    """
    return control_qos(publisher_depth(history_s, ts))
