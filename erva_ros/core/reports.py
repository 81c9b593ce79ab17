"""What each node reports on ``/diagnostics``: one typed dataclass per node, no ROS.

A node fills its report (counters, timings, state, what it published per topic) and
publishes it as one diagnostic_msgs/DiagnosticStatus; the session's monitor, the
accounting, the bag reports and the summaries read it back as the same dataclass
(:func:`report_from_status`), never by string key.  On the wire a report is the usual
key/value list, so ``ros2 topic echo /diagnostics`` and rqt show it as before:

* a scalar field ``name`` is the key ``name`` (floats exactly, booleans
  ``true``/``false``);
* a :class:`Timing` field ``name`` is ``name_p50``, ``name_p99``, ``name_max`` (ms) and
  ``name_samples``;
* a per-topic (or per-name) field is ``<prefix><key>`` for each entry, e.g.
  ``published:/erva/damping_cmd`` (:func:`keyed`).

Every report carries the node's name (the status name: its fully qualified name), its
``session`` (the id `erva run` gives all nodes of one session; '' outside one), a
``status_seq`` (1, 2, ... so a recording shows that none is missing) and ``final``
(true on the status a node publishes as it stops, with its final counts).
"""

from dataclasses import dataclass, field, fields, MISSING
import functools
import math
import typing
from typing import Any, ClassVar, Dict, Mapping, Optional, Type

import numpy as np

from erva_ros.core.contract import Status
from erva_ros.core.levels import OK

#: The key naming a report's type on the wire.
KIND_KEY = 'report'


@dataclass
class Timing:
    """p50 / p99 / max (ms) and the sample count of a duration statistic."""

    p50: float = math.nan
    p99: float = math.nan
    max: float = math.nan
    samples: int = 0

    @classmethod
    def of(cls, summary: Mapping[str, float]) -> 'Timing':
        """Return the Timing of a ``DurationStats.summary()`` (p50/p99/max ms, samples)."""
        return cls(float(summary.get('p50', math.nan)), float(summary.get('p99', math.nan)),
                   float(summary.get('max', math.nan)), int(summary.get('samples', 0)))

    def as_dict(self) -> Dict[str, Any]:
        """Return {'p50', 'p99', 'max', 'samples'} (for JSON summaries)."""
        return {'p50': self.p50, 'p99': self.p99, 'max': self.max, 'samples': self.samples}


def keyed(prefix: str, value_type=int):
    """Return a per-key field written as ``<prefix><key>`` entries (e.g. 'published:')."""
    return field(default_factory=dict, metadata={'prefix': prefix, 'type': value_type})


def format_value(value: Any) -> str:
    """Return ``value`` as diagnostic text (floats exactly: their shortest repr).

    A numpy scalar is written as the Python number it holds: its own repr
    (``np.float64(0.048)`` under numpy 2) is no number to a reader.
    """
    if isinstance(value, (bool, np.bool_)):
        return 'true' if value else 'false'
    if isinstance(value, (float, np.floating)):
        value = float(value)
        return repr(value) if math.isfinite(value) else str(value)
    if isinstance(value, np.integer):
        return str(int(value))
    return str(value)


#: What each declared field type takes: exactly these Python types (a numpy scalar is
#: not one: the node converts, so nothing but the declared type crosses to the session).
_ACCEPTS = {float: (float, int), int: (int,), str: (str,), bool: (bool,)}


def _check_type(cls_name: str, name: str, kind, value) -> None:
    """Raise TypeError unless ``value`` is exactly of the declared field type ``kind``."""
    inner = [a for a in typing.get_args(kind) if a is not type(None)]
    if inner:                                   # Optional[X]
        if value is None:
            return
        kind = inner[0]
    accepted = _ACCEPTS.get(kind)
    if accepted is None:
        return
    if type(value) not in accepted:
        raise TypeError(f'{cls_name}.{name} is {type(value).__module__}.'
                        f'{type(value).__qualname__} {value!r}, not {kind.__name__}')


@functools.lru_cache(maxsize=None)
def _hints(cls) -> Dict[str, Any]:
    """Return the declared types of a report class's fields (resolved once per class)."""
    return typing.get_type_hints(cls)


def _parse(text: str, kind) -> Any:
    if kind is bool:
        return text == 'true'
    if kind is int:
        if not text:
            return 0
        try:
            return int(text)
        except ValueError:
            return int(float(text))
    if kind is float:
        return float(text) if text else math.nan
    return text


@dataclass
class NodeReport:
    """What every node reports (see the module doc)."""

    KIND: ClassVar[str] = 'node'

    node: str = ''
    level: int = OK
    message: str = ''
    hardware_id: str = ''
    session: str = ''
    status_seq: int = 0
    final: bool = False
    finished: bool = False
    scheduling: str = 'off'
    lifecycle: str = ''       # managed nodes: unconfigured | inactive | active
    published: Dict[str, int] = keyed('published:')
    subscribers: Dict[str, int] = keyed('subscribers:')
    #: When each bring-up stage of the node's process ended, s since the process started
    #: (imported, initialised, constructed, configuring, configured, activated: `erva run
    #: --timing`).
    startup: Dict[str, float] = keyed('startup:', float)

    #: Fields that are the status itself, not key/values.
    HEADER: ClassVar[tuple] = ('node', 'level', 'message', 'hardware_id')

    @property
    def short_name(self) -> str:
        """Return the node's name without its namespace (``/erva/nmpc_node`` -> ``nmpc_node``)."""
        return self.node.rsplit('/', 1)[-1]

    def values(self) -> Dict[str, str]:
        """Return this report as the key/value strings of a status (module doc).

        Every value must be of its field's declared type (TypeError otherwise): a float
        field holds a Python float (or int), an int field an int, and so on, so what a
        reader parses back is what the node meant.
        """
        out = {KIND_KEY: self.KIND}
        hints = _hints(type(self))
        name = type(self).__name__
        for f in fields(self):
            if f.name in self.HEADER:
                continue
            value = getattr(self, f.name)
            prefix = f.metadata.get('prefix')
            if prefix is not None:
                for k, v in value.items():
                    _check_type(name, f'{f.name}[{k!r}]', f.metadata['type'], v)
                out.update({f'{prefix}{k}': format_value(v) for k, v in sorted(value.items())})
            elif isinstance(value, Timing):
                for k, t in (('p50', float), ('p99', float), ('max', float), ('samples', int)):
                    _check_type(name, f'{f.name}.{k}', t, getattr(value, k))
                out.update({f'{f.name}_{k}': format_value(v)
                            for k, v in value.as_dict().items()})
            else:
                _check_type(name, f.name, hints[f.name], value)
                if value is not None:
                    out[f.name] = format_value(value)
        return out

    @classmethod
    def from_values(cls, node: str, level: int, message: str, values: Mapping[str, str],
                    hardware_id: str = '') -> 'NodeReport':
        """Return the report of a status (missing keys keep their defaults)."""
        hints = _hints(cls)
        kw: Dict[str, Any] = {'node': node, 'level': level, 'message': message,
                              'hardware_id': hardware_id}
        for f in fields(cls):
            if f.name in cls.HEADER:
                continue
            prefix = f.metadata.get('prefix')
            kind = hints[f.name]
            try:
                if prefix is not None:
                    kw[f.name] = {k[len(prefix):]: _parse(v, f.metadata['type'])
                                  for k, v in values.items() if k.startswith(prefix)}
                elif kind is Timing:
                    kw[f.name] = Timing(*(_parse(values.get(f'{f.name}_{k}', ''), t)
                                          for k, t in (('p50', float), ('p99', float),
                                                       ('max', float), ('samples', int))))
                elif f.name in values:
                    inner = [a for a in typing.get_args(kind) if a is not type(None)]
                    kw[f.name] = _parse(values[f.name], inner[0] if inner else kind)
            except ValueError:
                continue   # a value that is not what this version expects: the default
        return cls(**kw)


# -- the live loop -------------------------------------------------------------------------
@dataclass
class RoadReport(NodeReport):
    """road_preview_node: the samples of the scenario it published (and skipped)."""

    KIND: ClassVar[str] = 'road'

    mode: str = ''
    road: str = ''
    seed: int = 0
    samples_published: int = 0
    samples_total: int = 0
    samples_skipped: int = 0
    preview_points: int = 0
    preview_error: str = ''
    rejected_clock: int = 0
    # source map (MapPreviewCounts): what the map preview did, per sample and point
    source: str = 'road'
    map_file: str = ''
    map_samples: int = 0
    map_points: int = 0
    map_fallback_points: int = 0        # points that got the no-preview prediction
    map_fallback_samples: int = 0
    map_beyond_end_points: int = 0
    map_before_start_points: int = 0
    map_gap_points: int = 0
    map_unmatched_points: int = 0
    map_alignments: int = 0
    map_alignments_refused: int = 0
    map_unaligned_samples: int = 0
    map_offset_m: float = math.nan
    map_offset_std_m: float = math.nan
    map_correlation: float = math.nan
    # the worst instance of each: the longest run in a row (samples; refused: tries) and
    # the stamps of its first and last (ns; 0: none)
    map_fallback_streak: int = 0
    map_fallback_streak_from_ns: int = 0
    map_fallback_streak_to_ns: int = 0
    map_unmatched_streak: int = 0
    map_unmatched_streak_from_ns: int = 0
    map_unmatched_streak_to_ns: int = 0
    map_refused_streak: int = 0
    map_refused_streak_from_ns: int = 0
    map_refused_streak_to_ns: int = 0
    rejected_estimate: int = 0


@dataclass
class PlantReport(NodeReport):
    """plant_sim_node: its steps, where each u_k came from, its metrics and timings."""

    KIND: ClassVar[str] = 'plant'

    mode: str = ''
    model: str = ''
    steps: int = 0
    steps_total: int = 0
    sim_time_s: float = 0.0
    harvested_j: float = 0.0
    acc_rms_continuous: float = math.nan
    states: int = 0
    clock: int = 0
    u_from_command: int = 0
    u_from_plan: int = 0
    u_from_passive: int = 0
    late_commands: int = 0
    command_delay_ms: float = 0.0     # d: each command acts at its sample + d
    road_gaps: int = 0
    lockstep_timeouts: int = 0
    out_of_order_commands: int = 0
    rejected_road_height: int = 0
    rejected_damping_cmd: int = 0
    road_latency_ms: Timing = field(default_factory=Timing)
    step_ms: Timing = field(default_factory=Timing)
    loop_latency_ms: Timing = field(default_factory=Timing)
    cmd_jitter_ms: Timing = field(default_factory=Timing)
    # realtime: sample t_k -> its command received; the smallest d with 99.9 % on time
    command_arrival_ms: Timing = field(default_factory=Timing)
    arrival_p999_ms: float = math.nan


@dataclass
class NMPCReport(NodeReport):
    """nmpc_node: its commands and solves, the scheduler's and the controller's counters."""

    KIND: ClassVar[str] = 'nmpc'

    mode: str = ''
    controller: str = ''
    model: str = ''
    horizon: int = 0
    time_budget_s: float = 0.0
    commands: int = 0
    solves: int = 0
    late: int = 0
    deadline_misses: int = 0
    safe_commands: int = 0
    # the sample scheduler (core/loop/sample_schedule.py)
    out_of_order: int = 0
    superseded_states: int = 0
    missed_samples: int = 0
    stale_previews: int = 0
    no_preview: int = 0
    state_timeouts: int = 0
    rejected_state: int = 0
    rejected_preview: int = 0
    # the controller's own (core/controllers/base.py): steps, statuses, fallbacks
    controller_steps: int = 0
    controller_ok: int = 0
    controller_late: int = 0
    controller_fallback_plan: int = 0
    controller_fallback_passive: int = 0
    controller_failures: int = 0
    controller_nan_rejections: int = 0
    # live tuning (core/controllers/tuning.py): the parameter set in force, numbered 0, 1,
    # ... as changes take effect, the stamp of its first sample (0: from the start), its
    # live values as text (``live:alpha1``...), and lock-step holds that timed out
    parameter_set: int = 0
    parameter_set_from_ns: int = 0
    live: Dict[str, str] = keyed('live:', str)
    hold_timeouts: int = 0
    solve_ms: Timing = field(default_factory=Timing)
    latency_ms: Timing = field(default_factory=Timing)
    rx_latency_ms: Timing = field(default_factory=Timing)
    cmd_jitter_ms: Timing = field(default_factory=Timing)
    tick_jitter_ms: Timing = field(default_factory=Timing)
    tick_phase_ms: Timing = field(default_factory=Timing)


@dataclass
class RecorderReport(NodeReport):
    """recorder_node: messages taken and written, per topic; writers matched per topic."""

    KIND: ClassVar[str] = 'recorder'

    bag_dir: str = ''
    error: str = ''           # the first write error (disk full...): nothing written after it
    received: int = 0
    lost: int = 0
    lost_in_transport: int = 0
    written: int = 0
    bytes: int = 0
    flushes: int = 0
    topics: int = 0
    count: Dict[str, int] = keyed('count:')
    publishers: Dict[str, int] = keyed('publishers:')


@dataclass
class FoxgloveReport(NodeReport):
    """foxglove_node: what it received and forwarded to Foxglove clients."""

    KIND: ClassVar[str] = 'foxglove'

    url: str = ''
    received: int = 0
    forwarded: int = 0
    clients_seen: int = 0
    clients_subscribed: int = 0
    overflow_events: int = 0
    topics: int = 0
    awaiting_publisher: int = 0
    offered: Dict[str, int] = keyed('offered:')


# -- hardware in the loop ------------------------------------------------------------------
@dataclass
class EstimatorReport(NodeReport):
    """state_estimator_node: its updates, gaps and waits, NIS, std per state, latencies."""

    KIND: ClassVar[str] = 'estimator'

    updates: int = 0
    incomplete: int = 0
    gaps: int = 0
    restarts: int = 0
    late_or_repeated: int = 0
    rejected: int = 0
    no_road: int = 0
    road_waits: int = 0
    road_extrapolated: int = 0
    before_road: int = 0
    road_at_tyre: str = 'truth'
    road_estimates: int = 0             # road/estimate published (road_at_tyre estimated)
    distance_m: float = math.nan        # odometry distance of the last estimate
    road_std_m: float = math.nan        # std of ŵ relative to the body, last estimate
    nis_mean: float = math.nan
    std: Dict[str, float] = keyed('std_', float)
    latency_ms: Timing = field(default_factory=Timing)
    compute_ms: Timing = field(default_factory=Timing)
    sample_to_measurements_ms: Timing = field(default_factory=Timing)
    sample_to_state_ms: Timing = field(default_factory=Timing)


@dataclass
class BridgeCommandReport(NodeReport):
    """ecu_bridge_node's command link: commands in, frames out, timeouts, latencies."""

    KIND: ClassVar[str] = 'bridge_command'

    commands_received: int = 0
    commands_rejected: int = 0
    commands_stale: int = 0
    commands_clamped: int = 0
    commands_wrong_delay: int = 0     # acting at another d than the loop's (also rejected)
    command_timeouts: int = 0
    frames_sent: int = 0
    safe_frames_sent: int = 0
    plan_frames_sent: int = 0
    frames_not_sent: int = 0
    messages_rejected: int = 0
    timeout_plan_frames_max: int = 0
    timeout_age_ms_max: float = 0.0
    command_age_s: float = math.nan
    sent_c_e_ns_per_m: float = math.nan
    sent_duty: float = math.nan
    sent_mode: str = ''
    hardware_c_e_range_ns_per_m: str = ''
    ros_to_can_ms: Timing = field(default_factory=Timing)
    ros_to_can_proc_ms: Timing = field(default_factory=Timing)
    sample_to_can_ms: Timing = field(default_factory=Timing)


@dataclass
class BridgeBusReport(NodeReport):
    """ecu_bridge_node's CAN bus: E2E rejections of received frames, losses, reconnects."""

    KIND: ClassVar[str] = 'bridge_bus'

    accepted: int = 0
    resyncs: int = 0
    wrong_length: int = 0
    bad_crc: int = 0
    repeated: int = 0
    skipped: int = 0
    bad_counter: int = 0
    unknown_id: int = 0
    remote_or_error: int = 0
    send_errors: int = 0
    bus_losses: int = 0
    bus_open_attempts: int = 0
    bus_open_failures: int = 0
    reconnects: int = 0
    error: str = ''


@dataclass
class BridgeEcuReport(NodeReport):
    """ecu_bridge_node's view of the ECU: its cycles, heartbeat, mode and generator."""

    KIND: ClassVar[str] = 'bridge_ecu'

    ecu_cycles: int = 0
    incomplete_cycles: int = 0
    ecu_silences: int = 0
    ecu_mode: str = ''
    c_e_applied_ns_per_m: float = math.nan
    c_e_mean_ns_per_m: float = math.nan
    ecu_cmd_rejected_mod256: int = 0
    ecu_cmd_timeouts_mod256: int = 0
    generator_speed_rad_s: float = math.nan
    generator_current_a: float = math.nan
    generator_voltage_v: float = math.nan
    can_to_ros_ms: Timing = field(default_factory=Timing)
    can_to_ros_proc_ms: Timing = field(default_factory=Timing)


@dataclass
class EcuSimReport(NodeReport):
    """The simulated ECU (`erva ecu-sim`): its cycles, commands applied, the true metrics."""

    KIND: ClassVar[str] = 'ecu_sim'

    ecu_mode: str = ''
    samples_published: int = 0
    cycles: int = 0
    commands_applied: int = 0
    duty_out_of_range: int = 0
    command_timeouts: int = 0
    frames_sent: int = 0
    send_errors: int = 0
    bus_losses: int = 0
    reconnects: int = 0
    overruns: int = 0
    cycles_skipped: int = 0
    recomputed: int = 0
    mode_changes_unlogged: int = 0
    # Logical execution time (d > 0): each command acts at its cycle's t_k + d
    command_delay_ms: float = 0.0
    late_commands: int = 0            # CONTROLLED frames received after their instant
    late_plan_frames: int = 0
    first_late_cycle: int = -1        # the cycle k of the first late command (-1: none)
    u_from_command: int = 0           # at each t_k + d: the cycle's command,
    u_from_plan: int = 0              # an earlier command's plan,
    u_from_passive: int = 0           # or passive c_e0
    mode_changes: str = ''
    harvested_j: float = 0.0
    acc_rms_continuous: float = math.nan
    start_lag_ms: Optional[float] = None
    road_checked: Optional[int] = None
    road_mismatches: Optional[int] = None
    rx: Dict[str, int] = keyed('rx_')
    sample_to_can_ms: Timing = field(default_factory=Timing)
    sample_to_applied_ms: Timing = field(default_factory=Timing)
    # t_k -> its command frame received; the smallest d with 99.9 % on time; the frames'
    # period |Δt − Ts|; the actuation instant's lateness (taken − (t_k + d))
    command_arrival_ms: Timing = field(default_factory=Timing)
    arrival_p999_ms: float = math.nan
    cmd_jitter_ms: Timing = field(default_factory=Timing)
    actuation_jitter_ms: Timing = field(default_factory=Timing)


# -- the session itself ---------------------------------------------------------------------
@dataclass
class SessionClaim(NodeReport):
    """`erva run`'s claim on its namespace (``session``: its id), for the other sessions.

    Of two sessions that claim one namespace, the one that claimed first runs
    (``claimed_ns``, then the id); one that brings its nodes up (``committed``) or runs
    with ``--force`` never yields (erva_ros/session/run/start_gate.py).
    """

    KIND: ClassVar[str] = 'session_claim'

    claimed_ns: int = 0
    pid: int = 0
    committed: bool = False
    force: bool = False
    nodes: str = ''           # the session's node names, comma-separated


#: Every report type by its KIND.
REPORT_TYPES: Dict[str, Type[NodeReport]] = {
    cls.KIND: cls for cls in (NodeReport, RoadReport, PlantReport, NMPCReport, RecorderReport,
                              FoxgloveReport, EstimatorReport, BridgeCommandReport,
                              BridgeBusReport, BridgeEcuReport, EcuSimReport, SessionClaim)}


#: The type of a status without a ``report`` value (bags recorded before it existed), by
#: the status name's last element.
KIND_OF_NAME = {'plant_sim_node': 'plant', 'nmpc_node': 'nmpc', 'road_preview_node': 'road',
                'state_estimator_node': 'estimator', 'ecu_sim': 'ecu_sim',
                'ecu_bridge_node: command': 'bridge_command',
                'ecu_bridge_node: can bus': 'bridge_bus', 'ecu_bridge_node: ecu': 'bridge_ecu',
                'recorder: bag recorder': 'recorder', 'plant': 'plant', 'controller': 'nmpc'}


def report_from_status(status) -> NodeReport:
    """Return the typed report of a :class:`~erva_ros.core.contract.Status`.

    Its ``report`` value names the type (else the node's name does, in older bags); a
    status of another program is read as a plain :class:`NodeReport`.
    """
    kind = status.values.get(KIND_KEY) or KIND_OF_NAME.get(status.name.rsplit('/', 1)[-1], '')
    cls = REPORT_TYPES.get(kind, NodeReport)
    return cls.from_values(status.name, status.level, status.message, status.values,
                           status.hardware_id)


def report_status(report: NodeReport):
    """Return the :class:`~erva_ros.core.contract.Status` that carries ``report``."""
    return Status(report.node, report.level, report.message, report.hardware_id,
                  report.values())


def field_default(cls: Type[NodeReport], name: str) -> Any:
    """Return the default of a report field (tests, documentation)."""
    for f in fields(cls):
        if f.name == name:
            return f.default if f.default is not MISSING else f.default_factory()
    raise KeyError(name)


__all__ = ['KIND_KEY', 'Timing', 'keyed', 'format_value', 'NodeReport', 'RoadReport',
           'PlantReport', 'NMPCReport', 'RecorderReport', 'FoxgloveReport', 'EstimatorReport',
           'BridgeCommandReport', 'BridgeBusReport', 'BridgeEcuReport', 'EcuSimReport',
           'SessionClaim', 'REPORT_TYPES', 'KIND_OF_NAME', 'report_from_status',
           'report_status', 'field_default']
