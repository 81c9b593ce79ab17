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
prediction     trajectory_msgs/JointTrajectory   joints [state names, sprung_accel, power]:
                                                 points[j].positions = the plan's predicted
                                                 x, z̈_s (m/s²), P (W) at t0 + j·Ts, j = 0..N
                                                 (time_from_start); header.stamp = t0, as
                                                 its damping_cmd's
road/estimate  geometry_msgs/                    the road at the tyre estimated from the ECU's
               PoseWithCovarianceStamped         sensors (state_estimator_node, road_at_tyre
                                                 estimated): pose.position.x = odometry
                                                 distance (m), .z = ŵ(t_k) (m),
                                                 covariance[0] = var of x (m²),
                                                 covariance[14] = var of ŵ relative to the
                                                 body (m²); stamp = t_k
road/alignment geometry_msgs/PointStamped        the map preview's position correction
                                                 (road_preview_node, source map): point.x =
                                                 offset δ (m; position = odometry + δ),
                                                 point.y = its std σ_δ (m), point.z =
                                                 correlation of the last match (NaN: none
                                                 yet); stamp = t_k of the preview
/diagnostics   diagnostic_msgs/DiagnosticArray   per-node status, counters, timings
/clock         rosgraph_msgs/Clock               lock-step mode only
"""

from erva_ros.core.hil.topics import TOPIC_TYPES as HIL_TYPES
from erva_ros.core.namespace import NAMESPACE

#: The node name of `erva run`'s monitor (the time master waits for its readers).
MONITOR_NODE = 'erva_run_monitor'
#: Where each `erva run` claims its namespace (hidden, transient local: a session that
#: joins later gets the claims of those already there; erva_ros/session/run/start_gate.py).
SESSION_CLAIM = '_session_claim'

STATE = 'state'
SPRUNG_ACCEL = 'sprung_accel'
GENERATOR = 'generator'
ROAD_HEIGHT = 'road/height'
ROAD_PREVIEW = 'road/preview'
DAMPING_CMD = 'damping_cmd'
PREDICTION = 'prediction'
#: The vehicle's own road (docs/road.md): published only by a session that estimates the
#: road (``--preview map:FILE``), so in MAP_TOPIC_TYPES, not TOPIC_TYPES (the recorders
#: and their tests take every topic there as published).
ROAD_ESTIMATE = 'road/estimate'
ROAD_ALIGNMENT = 'road/alignment'
ROAD_ESTIMATE_TYPE = 'geometry_msgs/msg/PoseWithCovarianceStamped'
DIAGNOSTICS = '/diagnostics'
CLOCK = '/clock'
#: Every node announces its parameters' changes here (rclpy); sessions record it.
PARAMETER_EVENTS = '/parameter_events'


def time_master_topics(realtime: bool) -> tuple:
    """Return the topics whose readers the time master waits for before sample 0.

    In real time the road starts the loop (its height and preview); in lock-step the
    plant (its state, which the controller answers).
    """
    return (ROAD_HEIGHT, ROAD_PREVIEW) if realtime else (STATE,)


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
    f'{NAMESPACE}/{PREDICTION}': 'trajectory_msgs/msg/JointTrajectory',
    DIAGNOSTICS: 'diagnostic_msgs/msg/DiagnosticArray',
    CLOCK: 'rosgraph_msgs/msg/Clock',
}
#: Topics of ROS itself that a session records: published by every node, not per sample.
ROS_TOPIC_TYPES = {PARAMETER_EVENTS: 'rcl_interfaces/msg/ParameterEvent'}
#: The topics of a session with the vehicle's own road and a map preview.
MAP_TOPIC_TYPES = {
    f'{NAMESPACE}/{ROAD_ESTIMATE}': ROAD_ESTIMATE_TYPE,
    f'{NAMESPACE}/{ROAD_ALIGNMENT}': 'geometry_msgs/msg/PointStamped',
}


def type_of(name: str, namespace: str = NAMESPACE):
    """Return the ROS type name of a contract topic (relative or absolute name), or None."""
    full = name if name.startswith('/') else f'{NAMESPACE}/{name}'
    if full in ROS_TOPIC_TYPES:
        return ROS_TOPIC_TYPES[full]
    if not name.startswith('/') or full in TOPIC_TYPES or full in HIL_TYPES \
            or full in MAP_TOPIC_TYPES:
        return TOPIC_TYPES.get(full) or HIL_TYPES.get(full) or MAP_TOPIC_TYPES.get(full)
    # An absolute name in another namespace: the contract's type of the same relative name.
    prefix = namespace.rstrip('/') + '/'
    if name.startswith(prefix):
        return type_of(name[len(prefix):])
    return None


def clock_topic(namespace: str) -> str:
    """Return the lock-step clock of a session in ``namespace``.

    ``/clock`` in the default namespace (what ROS tools expect), ``<namespace>/clock``
    in any other: two lock-step sessions on one DDS domain must not share a clock.
    The nodes get it as a remapping of ``/clock`` (:func:`clock_remap`).
    """
    ns = namespace.rstrip('/')
    return CLOCK if ns in ('', NAMESPACE) else f'{ns}{CLOCK}'


def clock_remap(namespace: str) -> list:
    """Return the ``--ros-args`` remapping of ``/clock`` for ``namespace`` ([] if none)."""
    clock = clock_topic(namespace)
    return [] if clock == CLOCK else ['-r', f'{CLOCK}:={clock}']
