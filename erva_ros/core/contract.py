"""The loop's messages, one family at a time: typed rows, their one decoder and encoder.

Every message of the contract (:mod:`erva_ros.core.topics`, :mod:`erva_ros.core.hil.topics`)
is read here from its CDR bytes into a small typed row and written here from one, with
no ROS import: the nodes (raw subscriptions, bytes published), the session's monitor,
the bag reports and the offline tools all use these functions, live and from bags alike.

Each decoder checks the structure (names, sizes, the Ts grid of a trajectory) when
asked for the values a node acts on (``strict``), and then also that every value is
finite and not absurd (:data:`erva_ros.core.loop.validation.LIMITS`); anything else
raises :class:`~erva_ros.core.loop.validation.MessageRejected`.  Observers (monitor,
reports) decode the same bytes without the semantic checks: they record what was sent.
Stamps are integer nanoseconds end to end: the lock-step plant matches a command to its
sample by exact stamp equality.
"""

from dataclasses import dataclass
import functools
import math
from typing import Any, Dict, List, Optional, Sequence, Tuple

import numpy as np

from erva_ros.core import topics
from erva_ros.core.hil import topics as hil_topics
from erva_ros.core.loop.validation import check_values, MessageRejected
from erva_ros.core.wire import CdrError, NS, Reader, Writer

#: Tolerance on time_from_start of trajectory points (ns): a point off the Ts grid is rejected.
GRID_TOL_NS = 1000
#: Plausibility bounds of the ECU's measurements (absurd beyond: rejected): speed is the
#: rotor speed phi' = v_gen / l (rad/s), applied the c_e's (Ns/m, >= 0), force in N.
MEASUREMENT_LIMITS = {'accel': 100.0, 'deflection': 0.5, 'speed': 1e3, 'applied': 1e6,
                      'force': 1e6}


def s_to_ns(seconds: float) -> int:
    """Return ``seconds`` as integer nanoseconds (rounded)."""
    return int(round(float(seconds) * NS))


# -- rows ----------------------------------------------------------------------------------
@dataclass(frozen=True)
class State:
    """``state`` (and ``ecu_sim/state``): x = [z_s, ż_s, z_us, ż_us(, z_d, ż_d)] at t_k."""

    stamp_ns: int
    x: np.ndarray


@dataclass(frozen=True)
class Accel:
    """``sprung_accel`` (and ``ecu/sprung_accel``): z̈_s (m/s²) at t_k."""

    stamp_ns: int
    sprung_accel: float


@dataclass(frozen=True)
class Generator:
    """``generator``: position z_d − (z_s − z_us) (m), v_gen (m/s), force u·v_gen (N)."""

    stamp_ns: int
    position: float
    velocity: float
    effort: float

    @property
    def power(self) -> float:
        """Return the harvested power effort · velocity (W)."""
        return self.effort * self.velocity


@dataclass(frozen=True)
class RoadHeight:
    """``road/height``: the distance travelled (m) and the road height at the tyre (m)."""

    stamp_ns: int
    distance_m: float
    height_m: float


@dataclass(frozen=True)
class RoadEstimate:
    """``road/estimate``: odometry distance (m), ŵ(t_k) (m) and their variances (m²).

    ``var_w`` is that of ŵ relative to the body (the absolute height is not observable).
    """

    stamp_ns: int
    distance_m: float
    height_m: float
    var_distance: float
    var_w: float


@dataclass(frozen=True)
class Alignment:
    """``road/alignment``: offset δ (m) of the map position, its std (m), last correlation."""

    stamp_ns: int
    offset_m: float
    offset_std_m: float
    correlation: float


@dataclass(frozen=True)
class Preview:
    """``road/preview``: w(t_k + j·Ts), j = 0..N (m)."""

    stamp_ns: int
    heights: np.ndarray


@dataclass(frozen=True)
class Command:
    """``damping_cmd``: plan[0] = c_e for sample t_k, plan[j] the plan for t_{k+j} (Ns/m).

    Each value acts at a fixed instant, its point's time_from_start after the stamp:
    plan[j] at t_k + d + j·Ts, where d (``delay_ns``, 0 <= d < Ts) is the loop's command
    delay -- the logical execution time of the sample's computation.
    """

    stamp_ns: int
    plan: np.ndarray
    offsets_s: Tuple[float, ...] = ()
    delay_ns: int = 0

    @property
    def u(self) -> float:
        """Return the command itself, plan[0] (Ns/m)."""
        return float(self.plan[0])

    @property
    def act_ns(self) -> int:
        """Return the instant (ns) at which the command itself acts: t_k + d."""
        return self.stamp_ns + self.delay_ns


@dataclass(frozen=True)
class Predicted:
    """``prediction``: the plan's trajectory of sample t_k at t_k + j·Ts, j = 0..N.

    ``values[j]`` holds one value per name: the model's states, then z̈_s (m/s²) and the
    harvested power (W) (core/loop/prediction.py).
    """

    stamp_ns: int
    names: Tuple[str, ...]
    values: np.ndarray          # (N + 1, len(names))
    offsets_s: Tuple[float, ...] = ()

    def column(self, name: str) -> np.ndarray:
        """Return the N + 1 predicted values of ``name`` (KeyError naming the joints)."""
        if name not in self.names:
            raise KeyError(f'{name!r} is not predicted (joints {list(self.names)})')
        return self.values[:, self.names.index(name)]


@dataclass(frozen=True)
class Status:
    """One diagnostic_msgs/DiagnosticStatus: a node's report on ``/diagnostics``."""

    name: str
    level: int
    message: str
    hardware_id: str
    values: Dict[str, str]


@dataclass(frozen=True)
class Measurements:
    """``ecu/measurements``: one ECU cycle (NaN: that CAN frame was lost).

    c_e applied now and its cycle mean (Ns/m), z̈_s (m/s²), deflection (m), rotor speed
    φ' (rad/s), generator force (N).
    """

    stamp_ns: int
    c_e: float
    c_e_mean: float
    sprung_accel: float
    deflection: float
    speed: float
    force: float

    @property
    def sensors(self) -> Tuple[float, float, float]:
        """Return (z̈_s, deflection, φ'): the EKF's measurement vector."""
        return self.sprung_accel, self.deflection, self.speed


@dataclass(frozen=True)
class Joints:
    """A sensor_msgs/JointState as sent (the HIL per-frame topics)."""

    stamp_ns: int
    names: Tuple[str, ...]
    position: Tuple[float, ...]
    velocity: Tuple[float, ...]
    effort: Tuple[float, ...]


# -- sensor_msgs/JointState ----------------------------------------------------------------
def decode_joints(data: bytes) -> Joints:
    """Return any sensor_msgs/JointState as sent."""
    r = Reader(data)
    stamp = r.header()
    return Joints(stamp, tuple(r.strings()), r.doubles(), r.doubles(), r.doubles())


class JointStateEncoder:
    """Encode sensor_msgs/JointState messages with fixed names and an empty frame_id.

    The names are encoded once; each call packs the stamp and the value arrays.
    """

    def __init__(self, names: Sequence[str]):
        self.names = tuple(names)
        w = Writer().time_ns(0).string('').strings(self.names)
        self._names = w.bytes()[12:]       # after the header and the stamp

    def encode(self, stamp_ns: int, position: Sequence[float] = (),
               velocity: Sequence[float] = (), effort: Sequence[float] = ()) -> bytes:
        """Return the message's bytes."""
        w = Writer().time_ns(stamp_ns)
        w.out += self._names
        for values in (position, velocity, effort):
            w.doubles(values)
        return w.bytes()


@functools.lru_cache(maxsize=None)
def _state_encoder(joints: Tuple[str, ...]) -> JointStateEncoder:
    return JointStateEncoder(joints)


def decode_state(data: bytes, joints: Optional[Sequence[str]] = None) -> State:
    """Return a state, as sent or (given ``joints``) checked.

    A node acting on the state gives its model's ``joints``: the names, sizes and values
    are checked.
    """
    j = decode_joints(data)
    n = len(j.position)
    if joints is not None:
        names = tuple(joints)
        if j.names != names:
            raise MessageRejected(f'joint names {list(j.names)} are not {list(names)}')
        if n != len(names) or len(j.velocity) != len(names):
            raise MessageRejected(f'need {len(names)} positions and velocities, got '
                                  f'{n} and {len(j.velocity)}')
        check_values('position', j.position, 'position')
        check_values('velocity', j.velocity, 'velocity')
    elif len(j.velocity) != n:
        raise CdrError(f'{n} positions but {len(j.velocity)} velocities')
    x = np.empty(2 * n)
    x[0::2], x[1::2] = j.position, j.velocity
    return State(j.stamp_ns, x)


def encode_state(stamp_ns: int, x: Sequence[float], joints: Sequence[str]) -> bytes:
    """Return the state x = [z_s, ż_s, z_us, ż_us(, z_d, ż_d)] as a JointState (m, m/s).

    ``joints``: the model's (``QuarterCarModel.joints``), one per position/velocity pair.
    """
    x = np.asarray(x, dtype=float)
    return _state_encoder(tuple(joints)).encode(stamp_ns, x[0::2].tolist(), x[1::2].tolist())


_GENERATOR = JointStateEncoder((topics.GENERATOR_JOINT,))


def decode_generator(data: bytes) -> Generator:
    """Return a ``generator`` sample."""
    j = decode_joints(data)
    if len(j.position) != 1 or len(j.velocity) != 1 or len(j.effort) != 1:
        raise CdrError('a generator sample has one position, velocity and effort')
    return Generator(j.stamp_ns, j.position[0], j.velocity[0], j.effort[0])


def encode_generator(stamp_ns: int, position: float, velocity: float, u: float) -> bytes:
    """Return a ``generator`` sample: effort = u·v_gen (N), so P = effort·velocity (W)."""
    return _GENERATOR.encode(stamp_ns, (float(position),), (float(velocity),),
                             (float(u) * float(velocity),))


_MEASUREMENT_NAMES = tuple(hil_topics.MEASUREMENT_NAMES)
_CHANNELS = tuple(hil_topics.MEASUREMENT_CHANNELS.values())
MEASUREMENTS_ENCODER = JointStateEncoder(_MEASUREMENT_NAMES)


def decode_measurements(data: bytes, strict: bool = True) -> Measurements:
    """Return an ECU cycle; ``strict``: reject wrong names/sizes, partly-NaN frames, absurd values.

    NaN marks a lost frame's values (all of that frame's, or the message is rejected).
    """
    j = decode_joints(data)
    if j.names != _MEASUREMENT_NAMES or len(j.position) != len(_MEASUREMENT_NAMES):
        raise MessageRejected(f'ecu/measurements has names {list(j.names)}')
    v = j.position
    if strict:
        if j.velocity or j.effort:
            raise MessageRejected('ecu/measurements carries velocities or efforts')
        for channel in _CHANNELS:
            nans = sum(math.isnan(v[i]) for i in channel)
            if 0 < nans < len(channel):
                raise MessageRejected('a CAN frame of the cycle is only partly NaN')
        lim = MEASUREMENT_LIMITS
        c_e, c_e_mean, accel, defl, speed, force = v
        if not all(math.isnan(x) or ok for x, ok in (
                (c_e, 0 <= c_e <= lim['applied']), (c_e_mean, 0 <= c_e_mean <= lim['applied']),
                (accel, abs(accel) <= lim['accel']), (defl, abs(defl) <= lim['deflection']),
                (speed, abs(speed) <= lim['speed']), (force, abs(force) <= lim['force']))):
            raise MessageRejected('an ECU measurement is absurd or infinite')
    return Measurements(j.stamp_ns, *v)


# -- geometry_msgs/AccelStamped, PointStamped ----------------------------------------------

def decode_accel(data: bytes) -> Accel:
    """Return a ``sprung_accel`` sample (accel.linear.z)."""
    r = Reader(data)
    stamp = r.header()
    linear = r.doubles(3)
    r.doubles(3)
    return Accel(stamp, linear[2])


def encode_accel(stamp_ns: int, sprung_accel: float) -> bytes:
    """Return a geometry_msgs/AccelStamped with accel.linear.z = z̈_s (m/s²)."""
    return (Writer().header(stamp_ns).doubles((0.0, 0.0, float(sprung_accel)), fixed=True)
            .doubles((0.0, 0.0, 0.0), fixed=True).bytes())


def decode_road_height(data: bytes, strict: bool = False) -> RoadHeight:
    """Return a ``road/height`` sample; ``strict``: finite, not absurd."""
    r = Reader(data)
    stamp = r.header()
    x, _, z = r.doubles(3)
    if strict:
        check_values('point.x', [x], 'distance')
        check_values('point.z', [z], 'road_height')
    return RoadHeight(stamp, x, z)


def encode_road_height(stamp_ns: int, distance_m: float, height_m: float) -> bytes:
    """Return a geometry_msgs/PointStamped: point.x distance (m), point.z height (m)."""
    return (Writer().header(stamp_ns)
            .doubles((float(distance_m), 0.0, float(height_m)), fixed=True).bytes())


# -- geometry_msgs/PoseWithCovarianceStamped: road/estimate; PointStamped: road/alignment --
def decode_road_estimate(data: bytes, strict: bool = False) -> RoadEstimate:
    """Return a ``road/estimate``; ``strict``: finite, not absurd, variances >= 0."""
    r = Reader(data)
    stamp = r.header()
    x, _, z = r.doubles(3)
    r.doubles(4)                        # orientation
    cov = r.doubles(36)
    if strict:
        check_values('pose.position.x', [x], 'distance')
        check_values('pose.position.z', [z], 'road_height')
        if not (math.isfinite(cov[0]) and math.isfinite(cov[14])
                and cov[0] >= 0 and cov[14] >= 0):
            raise MessageRejected('road/estimate: a variance is negative or not finite')
    return RoadEstimate(stamp, x, z, cov[0], cov[14])


def encode_road_estimate(stamp_ns: int, distance_m: float, height_m: float,
                         var_distance: float, var_w: float) -> bytes:
    """Return a PoseWithCovarianceStamped: position (distance, 0, ŵ), cov[0], cov[14]."""
    cov = [0.0] * 36
    cov[0], cov[14] = float(var_distance), float(var_w)
    return (Writer().header(stamp_ns)
            .doubles((float(distance_m), 0.0, float(height_m)), fixed=True)
            .doubles((0.0, 0.0, 0.0, 1.0), fixed=True).doubles(cov, fixed=True).bytes())


def decode_alignment(data: bytes) -> Alignment:
    """Return a ``road/alignment`` (point.x offset, .y its std, .z correlation)."""
    r = Reader(data)
    stamp = r.header()
    return Alignment(stamp, *r.doubles(3))


def encode_alignment(stamp_ns: int, offset_m: float, offset_std_m: float,
                     correlation: float) -> bytes:
    """Return a geometry_msgs/PointStamped: point = (δ, σ_δ, correlation)."""
    return (Writer().header(stamp_ns)
            .doubles((float(offset_m), float(offset_std_m), float(correlation)), fixed=True)
            .bytes())


# -- trajectory_msgs/JointTrajectory -------------------------------------------------------
def _decode_trajectory(data: bytes):
    """Return (stamp, joint_names, [(positions, time_from_start ns), ...])."""
    r = Reader(data)
    stamp = r.header()
    names = r.strings()
    points = []
    for _ in range(r.count()):
        positions = r.doubles()
        r.doubles()                     # velocities
        r.doubles()                     # accelerations
        r.doubles()                     # effort
        points.append((positions, r.time_ns()))
    return stamp, names, points


def _trajectory_values(data: bytes, joint: str, ts_ns: Optional[int], min_points: int,
                       limit: Optional[str], delayed: bool = False):
    """Return (stamp, values, time_from_start s, offset ns of the first point).

    With ``ts_ns`` the points must lie on the Ts grid from the first one's time, which
    is 0 -- or, ``delayed`` (a command), any d in [0, Ts).
    """
    stamp, names, points = _decode_trajectory(data)
    if limit is not None and names != [joint]:
        raise MessageRejected(f'joint names {names} are not [{joint!r}]')
    if len(points) < min_points:
        raise MessageRejected(f'{len(points)} points, need at least {min_points}')
    first = points[0][1] if points else 0
    if ts_ns is not None and not (0 <= first < ts_ns if delayed else abs(first) <= GRID_TOL_NS):
        raise MessageRejected(f'points[0].time_from_start = {first * 1e-9:g} s is not '
                              + ('in [0, Ts)' if delayed else '0') + f' (Ts = {ts_ns / NS:g} s)')
    values = np.empty(len(points))
    for k, (positions, t_ns) in enumerate(points):
        if len(positions) != 1:
            raise MessageRejected(f'points[{k}] has {len(positions)} positions, need 1')
        if ts_ns is not None and abs(t_ns - first - k * ts_ns) > GRID_TOL_NS:
            lead = f'{first * 1e-9:g} s + ' if first else ''
            raise MessageRejected(f'points[{k}].time_from_start is not {lead}{k}·Ts '
                                  f'(Ts = {ts_ns / NS:g} s)')
        values[k] = positions[0]
    if limit is not None:
        check_values(f'points.positions ({joint})', values, limit)
    return stamp, values, tuple(t * 1e-9 for _, t in points), first


def _encode_trajectory(stamp_ns: int, joint: str, values: Sequence[float], ts_ns: int,
                       first_ns: int = 0) -> bytes:
    w = Writer().header(stamp_ns).strings((joint,)).u32(len(values))
    for k, v in enumerate(values):
        w.doubles((float(v),)).u32(0).u32(0).u32(0).time_ns(first_ns + k * ts_ns)
    return w.bytes()


def decode_preview(data: bytes, ts_ns: Optional[int] = None, min_points: int = 1) -> Preview:
    """Return a preview; with ``ts_ns`` (a node acting on it) grid and values are checked."""
    stamp, heights, _, _ = _trajectory_values(data, topics.ROAD_JOINT, ts_ns, min_points,
                                              'road_height' if ts_ns is not None else None)
    return Preview(stamp, heights)


def decode_command_offsets(data: bytes) -> Tuple[float, ...]:
    """Return the time_from_start (s) of each point of a JointTrajectory (preview or plan)."""
    return tuple(t * 1e-9 for _, t in _decode_trajectory(data)[2])


def encode_preview(stamp_ns: int, heights: Sequence[float], ts_ns: int) -> bytes:
    """Return w(t_k + j·Ts), j = 0..N, as a JointTrajectory (time_from_start j·Ts)."""
    return _encode_trajectory(stamp_ns, topics.ROAD_JOINT, heights, ts_ns)


def decode_command(data: bytes, ts_ns: Optional[int] = None, strict: bool = False) -> Command:
    """Return a damping command; ``strict`` (or ``ts_ns``): joints, grid and values checked."""
    strict = strict or ts_ns is not None
    stamp, plan, offsets, first = _trajectory_values(
        data, topics.DAMPING_JOINT, ts_ns, 1, 'damping' if strict else None, delayed=True)
    return Command(stamp, plan, offsets, max(0, first))


def check_command_delay(cmd: Command, delay_ns: int) -> None:
    """Raise MessageRejected unless ``cmd`` acts at the loop's command delay d."""
    if abs(cmd.delay_ns - delay_ns) > GRID_TOL_NS:
        raise MessageRejected(f'command acts {cmd.delay_ns * 1e-9:g} s after its sample; '
                              f'this loop\'s command_delay_s is {delay_ns * 1e-9:g} s')


def encode_command(stamp_ns: int, plan: Sequence[float], ts_ns: int,
                   delay_ns: int = 0) -> bytes:
    """Return a command as a JointTrajectory: plan[j] acts at t_k + d + j·Ts (Command)."""
    return _encode_trajectory(stamp_ns, topics.DAMPING_JOINT, plan, ts_ns, delay_ns)


def decode_prediction(data: bytes) -> Predicted:
    """Return a ``prediction`` (MessageRejected if a point's size differs from the names')."""
    stamp, names, points = _decode_trajectory(data)
    values = np.empty((len(points), len(names)))
    for k, (positions, _) in enumerate(points):
        if len(positions) != len(names):
            raise MessageRejected(f'points[{k}] has {len(positions)} positions for '
                                  f'{len(names)} joints')
        values[k] = positions
    return Predicted(stamp, tuple(names), values, tuple(t * 1e-9 for _, t in points))


def encode_prediction(stamp_ns: int, names: Sequence[str], values, ts_ns: int) -> bytes:
    """Return rows ``values[j]`` (one per name) at t_k + j·Ts as a JointTrajectory."""
    w = Writer().header(stamp_ns).strings(tuple(names)).u32(len(values))
    for k, row in enumerate(values):
        w.doubles(tuple(float(v) for v in row)).u32(0).u32(0).u32(0).time_ns(k * ts_ns)
    return w.bytes()


# -- rosgraph_msgs/Clock -------------------------------------------------------------------
def decode_clock(data: bytes) -> int:
    """Return a /clock tick's time (ns)."""
    return Reader(data).time_ns()


def encode_clock(stamp_ns: int) -> bytes:
    """Return a rosgraph_msgs/Clock at ``stamp_ns``."""
    return Writer().time_ns(stamp_ns).bytes()


# -- diagnostic_msgs/DiagnosticArray -------------------------------------------------------
def decode_diagnostics(data: bytes) -> Tuple[int, List[Status]]:
    """Return (stamp ns, statuses) of a DiagnosticArray."""
    r = Reader(data)
    stamp = r.header()
    out = []
    for _ in range(r.count()):
        level = r.byte()
        name, message, hardware_id = r.string(), r.string(), r.string()
        values = {}
        for _ in range(r.count()):
            key = r.string()
            values[key] = r.string()
        out.append(Status(name, level, message, hardware_id, values))
    return stamp, out


def encode_diagnostics(stamp_ns: int, statuses: Sequence[Status]) -> bytes:
    """Return a DiagnosticArray of ``statuses`` stamped ``stamp_ns``."""
    w = Writer().header(stamp_ns).u32(len(statuses))
    for s in statuses:
        w.byte(int(s.level)).string(s.name).string(s.message).string(s.hardware_id)
        w.u32(len(s.values))
        for key, value in s.values.items():
            w.string(key).string(value)
    return w.bytes()


# -- rcl_interfaces/ParameterEvent ----------------------------------------------------------
@dataclass(frozen=True)
class ParameterEvent:
    """A node's parameter change as rclpy announces it on /parameter_events."""

    stamp_ns: int                 # the node's clock when it set them
    node: str                     # its fully qualified name
    new: Dict[str, Any]           # declared: name -> value (None: not set)
    changed: Dict[str, Any]       # set: name -> value
    deleted: Tuple[str, ...]


#: A parameter's text may be long (a session's JSON description): up to this many bytes.
_PARAMETER_TEXT = 1 << 22


def _parameter_value(r: Reader) -> Any:
    """Read an rcl_interfaces/ParameterValue: the field its ``type`` names."""
    kind = r.byte()
    fields = (r.byte(), r.i64(), r.double(), r.string(_PARAMETER_TEXT),
              [r.byte() for _ in range(r.count())], [bool(r.byte()) for _ in range(r.count())],
              [r.i64() for _ in range(r.count())], list(r.doubles()),
              [r.string(_PARAMETER_TEXT) for _ in range(r.count())])
    if kind == 0:
        return None
    if not 1 <= kind <= 9:
        raise CdrError(f'parameter type {kind} unknown')
    value = fields[kind - 1]
    return bool(value) if kind == 1 else value


def _parameters(r: Reader) -> Dict[str, Any]:
    out = {}
    for _ in range(r.count()):
        name = r.string()
        out[name] = _parameter_value(r)
    return out


def decode_parameter_event(data: bytes) -> ParameterEvent:
    """Return a /parameter_events message."""
    r = Reader(data)
    stamp = r.time_ns()
    node = r.string()
    new, changed = _parameters(r), _parameters(r)
    return ParameterEvent(stamp, node, new, changed, tuple(_parameters(r)))


#: The observer's decoder of each contract topic (relative names): monitor and reports.
DECODERS = {
    topics.STATE: decode_state,
    topics.SPRUNG_ACCEL: decode_accel,
    topics.GENERATOR: decode_generator,
    topics.ROAD_HEIGHT: decode_road_height,
    topics.ROAD_PREVIEW: decode_preview,
    topics.DAMPING_CMD: decode_command,
    topics.PREDICTION: decode_prediction,
    topics.ROAD_ESTIMATE: decode_road_estimate,
    topics.ROAD_ALIGNMENT: decode_alignment,
    hil_topics.TRUE_STATE: decode_state,
    hil_topics.ECU_MEASUREMENTS: lambda data: decode_measurements(data, strict=False),
    hil_topics.ECU_SPRUNG_ACCEL: decode_accel,
    hil_topics.ECU_SUSPENSION: decode_joints,
    hil_topics.ECU_GENERATOR: decode_joints,
    hil_topics.ECU_DAMPING_APPLIED: decode_joints,
}


__all__ = ['GRID_TOL_NS', 'MEASUREMENT_LIMITS', 'NS', 's_to_ns', 'State',
           'Accel', 'Generator', 'RoadHeight', 'RoadEstimate', 'Alignment', 'Preview', 'Command',
           'Status', 'Measurements',
           'Joints', 'decode_joints', 'JointStateEncoder', 'MEASUREMENTS_ENCODER',
           'decode_state', 'encode_state', 'decode_generator', 'encode_generator',
           'decode_measurements', 'decode_accel', 'encode_accel', 'decode_road_height',
           'encode_road_height', 'decode_road_estimate', 'encode_road_estimate',
           'decode_alignment', 'encode_alignment', 'decode_preview', 'decode_command_offsets',
           'encode_preview', 'decode_command', 'check_command_delay', 'encode_command',
           'Predicted', 'decode_prediction', 'encode_prediction', 'decode_clock',
           'encode_clock', 'decode_diagnostics', 'encode_diagnostics', 'ParameterEvent',
           'decode_parameter_event', 'DECODERS', 'CdrError',
           'MessageRejected']
