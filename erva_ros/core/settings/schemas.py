"""Every node's parameters: one schema per node, with no ROS import.

A :class:`NodeSchema` names the parameters a node declares, each from one group of
specs (:mod:`erva_ros.core.settings.specs`) whose defaults are one section of a shipped
``config/*.yaml`` (:class:`Group`).  Everything else is derived from it: the ROS
descriptors a node declares (:mod:`erva_ros.ros.parameters`), the sections of the
session params file `erva run` writes (:func:`session_sections`), the launch file's
arguments (:data:`LAUNCH_ARGUMENTS`, :func:`launch_arguments`) and the command line's
options (:func:`argparse_kwargs`).  ``test/test_specs.py`` checks that they agree.

The sample time ``ts`` and the command delay ``command_delay_s`` are parameters of the
whole loop: config/live.yaml's ``/**``.
"""

from dataclasses import dataclass
import functools
from typing import Any, Dict, Mapping, Optional, Sequence, Tuple

from erva_ros.core.road.profiles import ISO_CLASSES, ROAD_KINDS
from erva_ros.core.settings import hil
from erva_ros.core.settings.controller import SPECS as CONTROLLER_SPECS
from erva_ros.core.settings.erva import ERVA_SPECS
from erva_ros.core.settings.files import shipped_checked
from erva_ros.core.settings.hil import COMMAND_LINE_DEFAULTS
from erva_ros.core.settings.loop import (COMMAND_DELAY_SPEC, MAX_PRIORITY, MODEL_KINDS, MODES,
                                         TS_SPEC)
from erva_ros.core.settings.specs import Choice, Flag, Integer, Number, Text, Texts


@functools.lru_cache(maxsize=None)
def live_specs() -> Dict[str, Any]:
    """Return the live nodes' parameter specs (defaults: config/live.yaml ``/**``)."""
    return {
        'mode': Choice(MODES, 'time base: realtime (wall clock) or lockstep (the plant '
                       'publishes /clock)'),
        'model': Choice(MODEL_KINDS, 'model: erva (nonlinear, eq. (11)) or benchmark (linear, '
                        'eq. (15))'),
        'ts': TS_SPEC,
        'command_delay_s': COMMAND_DELAY_SPEC,
        'autostart': Flag('configure and activate at start-up (false: a managed node, '
                          'driven by `erva run` or `ros2 lifecycle set`)'),
        'session_id': Text('id of the `erva run` session the node belongs to, reported with '
                           'its status (\'\': none); one per session, so two sessions on one '
                           'DDS domain never count each other\'s messages'),
        'duration_s': Number(0.0, 86400.0, 's', 'scenario length: the road ends and the plant '
                             'stops', lo_open=True),
        'road': Choice(ROAD_KINDS[:-1], 'road profile (a recorded one: set road_file)'),
        'road_file': Text('recorded road: CSV file of time (s), height (m) rows; overrides '
                          'road'),
        'seed': Integer(0, 1_000_000_000, '-', 'seed of the road noise and the preview error'),
        'road_class': Choice(tuple(ISO_CLASSES), 'ISO 8608 road class'),
        'speed_mps': Number(0.0, 100.0, 'm/s', 'vehicle speed (time to distance)',
                            lo_open=True),
        'bump_height_m': Number(-0.5, 0.5, 'm', 'bump road: height of the cosine bump'),
        'bump_length_m': Number(0.0, 100.0, 'm', 'bump road: length of the bump', lo_open=True),
        'bump_start_s': Number(0.0, 86400.0, 's', 'bump road: time the tyre reaches the bump'),
        'preview_steps': Integer(1, 10000, 'steps',
                                 'preview intervals N (N + 1 points from t_k on)'),
        'preview_noise': Flag('preview error: add noise at preview_snr_db'),
        'preview_snr_db': Number(-40.0, 200.0, 'dB', 'preview error: SNR of the added noise'),
        'preview_delay_s': Number(0.0, 10.0, 's', 'preview error: age of the preview estimate'),
        'command_timeout_s': Number(0.0, 60.0, 's', 'plant: age after which a command\'s plan '
                                    'is not used (passive)'),
        'lockstep_timeout_s': Number(0.01, 3600.0, 's',
                                     'lock-step: wall time the plant waits for a command'),
        'state_timeout_periods': Integer(1, 1000, 'periods', 'NMPC: passive command + ERROR '
                                         'after this many periods without a state', live=True),
        'publish_prediction': Flag('NMPC: publish the plan\'s predicted states, chassis '
                                   'acceleration and power on `prediction` after each '
                                   'command'),
        'lockstep_hold_s': Number(0.0, 86400.0, 's', 'NMPC, lock-step: before solving the '
                                  'sample at this time (s after the first) wait until a '
                                  'parameter request comes, so that a change acts from '
                                  'exactly that sample (erva run --set); 0 = never',
                                  live=True),
        'wait_for_subscribers': Integer(0, 100, '-', 'time master: subscribers each of its '
                                        'topics needs first'),
        'wait_for_reader': Text('time master: one subscriber of each of its topics must be '
                                'the node of this name (\'\': any)'),
        'start_delay_s': Number(0.0, 600.0, 's',
                                'time master: settling time before the first sample'),
        'diagnostics_period_s': Number(0.05, 3600.0, 's', 'period of the /diagnostics status'),
        'reject_log_period_s': Number(0.0, 3600.0, 's',
                                      'rejected messages are logged once per period'),
        'max_stamp_lead_s': Number(0.0, 3600.0, 's', 'inputs stamped further ahead of the '
                                   'node\'s clock are rejected (clock skew between hosts; at '
                                   'least Ts)'),
        'max_stamp_age_s': Number(0.0, 86400.0, 's', 'inputs stamped longer ago than this are '
                                  'rejected as stale', lo_open=True),
        'publisher_history_s': Number(0.0, 3600.0, 's', 'history each loop publisher keeps for '
                                      'reliable repair: a subscriber (the recorder) may stall '
                                      'this long losing nothing', lo_open=True),
        'realtime_priority': Integer(0, MAX_PRIORITY, '-', 'realtime mode: SCHED_FIFO priority '
                                     'of the node\'s threads, 0 = normal scheduling (needs '
                                     'CAP_SYS_NICE, else a warning)'),
    }


#: The session nodes' own parameters (defaults: config/session.yaml).
RECORDER_SPECS: Dict[str, Any] = {
    'bag_dir': Text('bag directory to create (must not exist)'),
    'topics': Texts('topics to record; relative names resolve against the node namespace'),
    'session_metadata': Text('JSON object stored as the erva_session MCAP metadata record'),
    'chunk_size': Integer(1024, 64 * 1024 * 1024, 'B', 'close an MCAP chunk at this size'),
    'flush_period_s': Number(0.01, 60.0, 's', 'close the chunk and hand it to the OS at least '
                             'this often: at most this much is lost if the process is killed'),
    'compression': Choice(('none', 'zstd', 'lz4'), 'MCAP chunk compression'),
    'max_bag_duration_s': Number(0.0, 366 * 86400.0, 's', 'split the bag: start the next '
                                 '<bag>_<i>.mcap file once a message is this much later than '
                                 'the file\'s first (log time), as ros2 bag record '
                                 '--max-bag-duration; 0 = no limit'),
    'max_bag_size_bytes': Integer(0, 2 ** 53, 'B', 'split the bag: start the next file once '
                                  'this one holds this many bytes, as ros2 bag record '
                                  '--max-bag-size; 0 = no limit, else at least 1024'),
    'fsync': Flag('also fsync the file at every flush (survives power loss)'),
    'diagnostics_period_s': Number(0.1, 60.0, 's', 'period of the recorder status on '
                                   '/diagnostics'),
    'nice': Integer(0, 19, '-', 'CPU niceness added to the recorder with normal scheduling'),
    'realtime_priority': Integer(0, MAX_PRIORITY, '-', 'SCHED_FIFO priority of the recorder\'s '
                                 'threads (0: normal scheduling); below the loop\'s'),
}
FOXGLOVE_SPECS: Dict[str, Any] = {
    'host': Text('address to listen on (loopback by default; anything else exposes the '
                 'session to that network)'),
    'port': Integer(0, 65535, '-', 'TCP port to listen on (0: any free port)'),
    'topics': Texts('topics to serve; relative names resolve against the node namespace'),
    'session_metadata': Text('JSON object sent on <namespace>/session'),
    'message_backlog_size': Integer(16, 1_000_000, 'messages', 'messages queued per client '
                                    'before its oldest are dropped'),
    'diagnostics_period_s': Number(0.1, 60.0, 's', 'period of the status on /diagnostics'),
    'nice': Integer(0, 19, '-', 'CPU niceness added to this process, so the control loop goes '
                    'first'),
}


#: The vehicle's own road (config/road.yaml): the estimator's road and odometry.
ROAD_AT_TYRE = ('truth', 'estimated')
ROAD_ESTIMATE_SPECS: Dict[str, Any] = {
    'road_at_tyre': Choice(ROAD_AT_TYRE, 'the road at the tyre: truth (road/height, the '
                           'simulator\'s) or estimated (RoadEKF on the ECU\'s sensors, '
                           'published on road/estimate with the odometry)'),
    'road_sigma_m': Number(0.0, 10.0, 'm', 'estimated road: random-walk std of w per sample '
                           '(1 m: no prior, the unknown-input limit)', lo_open=True),
    'odometry_bias_m': Number(-1e4, 1e4, 'm', 'odometry: position error at the start'),
    'odometry_scale': Number(-0.5, 0.5, '-', 'odometry: relative speed error (0.005: reads '
                             '0.5 % fast)'),
    'odometry_speed_noise_mps': Number(0.0, 10.0, 'm/s', 'odometry: white noise std on each '
                                       'speed sample'),
    'odometry_seed': Integer(0, 2 ** 31 - 1, '-', 'odometry: seed of the speed noise'),
}
#: The preview from a map (config/road.yaml): road_preview_node with source map.
PREVIEW_SOURCES = ('road', 'map')
MAP_PREVIEW_SPECS: Dict[str, Any] = {
    'source': Choice(PREVIEW_SOURCES, 'preview source: road (the scenario\'s road, with the '
                     'preview error model) or map (map_file at the road/estimate position, '
                     'aligned by profile matching)'),
    'map_file': Text('road map file (erva map build); needed with source map'),
    'map_weighting': Choice(('none', 'variance'), 'map preview: each point as the map has it '
                            '(none) or shrunk by its variance'),
    'map_window_m': Number(0.0, 1000.0, 'm', 'map preview: the live road estimate is matched '
                           'with the map over this many metres', lo_open=True),
    'map_search_m': Number(0.0, 1000.0, 'm', 'map preview: search +- this around the odometry '
                           'position until a match', lo_open=True),
    'map_min_correlation': Number(-1.0, 1.0, '-', 'map preview: a match below this '
                                  'correlation is refused (counted)'),
    'map_speed_window_s': Number(0.0, 60.0, 's', 'map preview: the speed is the odometry\'s '
                                 'slope over this window', lo_open=True),
}


#: What `erva run` judges a real-time session by (config/session.yaml ``erva_run``).
QUALITY_SPECS: Dict[str, Any] = {
    'max_deadline_misses': Integer(0, 10**9, '-', 'deadline misses allowed (commands later '
                                   'than t_k + Ts, or solves over the budget)'),
    'max_state_timeouts': Integer(0, 10**9, '-', 'outages of the controller\'s state allowed'),
    'max_skipped_road_samples': Integer(0, 10**9, '-', 'road samples a late real-time timer '
                                        'may skip'),
    'max_command_gap_s': Number(0.0, 3600.0, 's', 'longest pause between two commands',
                                lo_open=True),
    'max_preview_fallback_samples': Integer(0, 10**9, '-', 'map previews allowed to fall '
                                            'back (a point with the no-preview prediction)'),
    'max_unmatched_preview_points': Integer(0, 10**9, '-', 'map preview points allowed '
                                            'without a recent accepted alignment'),
    'max_refused_alignments': Integer(0, 10**9, '-', 'alignments with the map allowed to '
                                      'be refused'),
}


@dataclass(frozen=True)
class Group:
    """A table of specs whose defaults are one section of a shipped config file."""

    config: str                      # file name in config/ ('': COMMAND_LINE)
    section: Optional[str] = None    # a node's section ('/**/<node>'), None: '/**'

    def specs(self) -> Dict[str, Any]:
        """Return the group's specs."""
        return _GROUP_SPECS[self](self)

    def defaults(self) -> Dict[str, Any]:
        """Return the group's defaults: its section of the shipped file, checked."""
        return _defaults(self)


@functools.lru_cache(maxsize=None)
def _defaults(group: Group) -> Dict[str, Any]:
    specs = group.specs()
    if group is COMMAND_LINE:
        return {k: v for k, v in COMMAND_LINE_DEFAULTS.items() if k in specs}
    return shipped_checked(specs, group.config, group.section)


def _controller_specs(_) -> Dict[str, Any]:
    return {k: v for k, v in CONTROLLER_SPECS.items() if k not in ('ts', 'command_delay_s')}


def _hil(name):
    def specs(_):
        return getattr(hil, name)
    return specs


def _erva_specs(_) -> Dict[str, Any]:
    return ERVA_SPECS


ERVA = Group('erva_paper.yaml')
LIVE = Group('live.yaml')
CONTROLLER = Group('nmpc.yaml', 'nmpc_node')
BRIDGE = Group('hil.yaml', 'ecu_bridge_node')
ESTIMATOR = Group('hil.yaml', 'state_estimator_node')
ECU_SIM = Group('hil.yaml', 'ecu_sim')
#: Set on the command line only (-p): rcl lets a /**/<node> key of a params file win over
#: ``-p name:=value``, so these have no key in config/hil.yaml (hil/settings.py).
COMMAND_LINE = Group('', 'command line')
RECORDER = Group('session.yaml', 'recorder')
FOXGLOVE = Group('session.yaml', 'foxglove_server')
QUALITY = Group('session.yaml', 'erva_run')
ROAD_ESTIMATE = Group('road.yaml', 'state_estimator_node')
MAP_PREVIEW = Group('road.yaml', 'road_preview_node')
_GROUP_SPECS = {ERVA: _erva_specs, LIVE: lambda _: live_specs(), CONTROLLER: _controller_specs,
                BRIDGE: _hil('BRIDGE_SPECS'), ESTIMATOR: _hil('ESTIMATOR_SPECS'),
                ECU_SIM: _hil('ECU_SIM_SPECS'), COMMAND_LINE: _hil('COMMAND_LINE_SPECS'),
                RECORDER: lambda _: RECORDER_SPECS, QUALITY: lambda _: QUALITY_SPECS,
                FOXGLOVE: lambda _: FOXGLOVE_SPECS,
                ROAD_ESTIMATE: lambda _: ROAD_ESTIMATE_SPECS,
                MAP_PREVIEW: lambda _: MAP_PREVIEW_SPECS}


@dataclass(frozen=True)
class NodeSchema:
    """The parameters of one node: (group, names) pairs; names () = the whole group."""

    node: str
    parts: Tuple[Tuple[Group, Tuple[str, ...]], ...]

    def items(self):
        """Yield (name, spec, group) of every parameter, in declaration order."""
        for group, names in self.parts:
            specs = group.specs()
            for name in names or tuple(specs):
                yield name, specs[name], group

    def specs(self) -> Dict[str, Any]:
        """Return {name: spec}."""
        return {name: spec for name, spec, _ in self.items()}

    def defaults(self) -> Dict[str, Any]:
        """Return {name: default} of every parameter."""
        out = {}
        for name, _, group in self.items():
            defaults = group.defaults()
            out[name] = defaults[name] if name in defaults else COMMAND_LINE_DEFAULTS[name]
        return out

    def live(self) -> Tuple[str, ...]:
        """Return the names of the node's dynamic parameters (their specs are ``live``)."""
        return tuple(name for name, spec, _ in self.items() if spec.live)

    def group(self, name: str) -> Group:
        """Return the group of parameter ``name``."""
        for n, _, group in self.items():
            if n == name:
                return group
        raise KeyError(f'{self.node} has no parameter {name!r}')


#: What every loop node declares from the live group.
_LOOP = ('autostart', 'mode', 'ts', 'session_id', 'duration_s', 'diagnostics_period_s',
         'reject_log_period_s', 'publisher_history_s', 'realtime_priority')
_HIL = ('autostart', 'ts', 'model', 'session_id', 'realtime_priority', 'publisher_history_s')

SCHEMAS: Dict[str, NodeSchema] = {s.node: s for s in (
    NodeSchema('road_preview_node', ((LIVE, _LOOP + (
        'road', 'road_file', 'seed', 'road_class', 'speed_mps', 'bump_height_m',
        'bump_length_m', 'bump_start_s', 'preview_steps', 'preview_noise', 'preview_snr_db',
        'preview_delay_s', 'wait_for_subscribers', 'wait_for_reader', 'start_delay_s')),
        (MAP_PREVIEW, ()))),
    NodeSchema('plant_sim_node', ((ERVA, ()), (LIVE, _LOOP + (
        'model', 'command_delay_s', 'command_timeout_s', 'lockstep_timeout_s',
        'wait_for_subscribers', 'wait_for_reader', 'start_delay_s', 'max_stamp_lead_s',
        'max_stamp_age_s')))),
    NodeSchema('nmpc_node', ((ERVA, ()), (CONTROLLER, ()), (LIVE, _LOOP + (
        'model', 'command_delay_s', 'state_timeout_periods', 'publish_prediction',
        'lockstep_hold_s', 'max_stamp_lead_s', 'max_stamp_age_s')))),
    NodeSchema('ecu_bridge_node', ((ERVA, ()), (LIVE, _HIL + ('command_delay_s',)),
                                   (BRIDGE, ()))),
    NodeSchema('state_estimator_node', ((ERVA, ()), (LIVE, _HIL + ('speed_mps',)),
                                        (ESTIMATOR, ()), (ROAD_ESTIMATE, ()),
                                        (COMMAND_LINE, ('stamp_on_road_grid',)))),
    NodeSchema('recorder', ((LIVE, ('session_id',)), (RECORDER, ()))),
    NodeSchema('foxglove_server', ((LIVE, ('session_id',)), (FOXGLOVE, ()))),
)}
#: The loop nodes of `erva run` (full state), whose params the session file carries.
LOOP_NODES = ('nmpc_node', 'plant_sim_node', 'road_preview_node')


def session_sections(values: Mapping[str, Any], nodes: Sequence[str] = LOOP_NODES
                     ) -> Dict[str, Dict[str, Any]]:
    """Return a session params file's sections: ``/**`` and ``/**/<node>``.

    A value goes to ``/**`` when it is in a ``/**`` group declared by more than one of
    ``nodes``, else to the section of each node that declares it (so a node-only value,
    like the road's, is not offered to the others).
    """
    users: Dict[str, list] = {}
    for node in nodes:
        for name, _, group in SCHEMAS[node].items():
            users.setdefault(name, []).append((node, group))
    doc: Dict[str, Dict[str, Any]] = {'/**': {}}
    doc.update({f'/**/{n}': {} for n in nodes})
    for name, value in values.items():
        who = users.get(name)
        if not who:
            continue
        shared = len(who) > 1 and all(g.section is None for _, g in who)
        for section in (['/**'] if shared else [f'/**/{n}' for n, _ in who]):
            doc[section][name] = value
    return {k: {'ros__parameters': v} for k, v in doc.items() if v}


#: The launch file's arguments (besides ``namespace``): parameters of the loop's nodes.
LAUNCH_ARGUMENTS = ('autostart', 'mode', 'model', 'controller', 'alpha1', 'alpha2', 'road', 'seed',
                    'duration_s')


def launch_arguments() -> Tuple[Tuple[str, str, type, str], ...]:
    """Return (name, default text, python type, description) of each launch argument."""
    specs, defaults = {}, {}
    for node in LOOP_NODES:
        specs.update(SCHEMAS[node].specs())
        defaults.update(SCHEMAS[node].defaults())
    out = []
    for name in LAUNCH_ARGUMENTS:
        spec = specs[name]
        kind = getattr(spec, 'python_type', str)
        out.append((name, str(defaults[name]), kind, f'{spec.doc} ({spec.describe()})'))
    return tuple(out)


#: Why a parameter stays read-only while its node runs: (reason, names).  Every parameter
#: of a node is live (its spec says so) or has its reason here (or the default:
#: READ_AT_START); ``ros2 param describe`` shows it, `erva param set` says it on a refusal.
READ_ONLY_REASONS: Tuple[Tuple[str, Tuple[str, ...]], ...] = (
    ('the compiled solver is built for it: a new value needs a new solver (compiled '
     'seconds to minutes), which a running loop cannot wait for; restart with it',
     ('controller', 'horizon', 'cost', 'long_cost', 'solver', 'hessian', 'terminal_cost',
      'terminal_weight', 'collocation_degree', 'long_steps', 'long_step_s', 'max_iter',
      'long_max_iter', 'sqp_tol', 'codegen', 'ipopt_max_iter', 'ipopt_starts')),
    ('it fixes the sample grid (Ts) or the command instant (t_k + d) that the plant, the '
     'road, the ECU and the controller share: they would all have to change at one sample',
     ('ts', 'command_delay_s')),
    ('it is the scenario: a run is one reproducible scenario (road, seed, length, time base, '
     'identification signal), the same in lock-step and in `erva sim`',
     ('mode', 'duration_s', 'road', 'road_file', 'seed', 'road_class', 'speed_mps',
      'bump_height_m', 'bump_length_m', 'bump_start_s', 'preview_steps', 'preview_noise',
      'preview_snr_db', 'preview_delay_s', 'excite_signal', 'excite_bit_s', 'excite_seed',
      'excite_f0_hz', 'excite_f1_hz', 'excite_sweep_s')),
    ('a topic or a connection: the session matches every writer with every reader before '
     'the loop starts, and its loss accounting counts on it',
     ('publish_prediction', 'publisher_history_s', 'wait_for_subscribers', 'wait_for_reader',
      'start_delay_s')),
)
#: The reason of the model and the device's physical parameters (config/erva_paper.yaml).
DEVICE_REASON = ('the device\'s physics: the plant and the prediction model (compiled) are '
                 'built on it; another device is another run (erva identify, --params)')
#: The reason of every other read-only parameter.
READ_AT_START = ('read when the node starts or is configured (start-up, scheduling, input '
                 'checks, diagnostics); restart the node to change it')


def read_only_reason(name: str) -> str:
    """Return why parameter ``name`` stays read-only while its node runs."""
    if name == 'model' or name in ERVA.specs():
        return DEVICE_REASON
    for reason, names in READ_ONLY_REASONS:
        if name in names:
            return reason
    return READ_AT_START


def spec_of(name: str, node: Optional[str] = None):
    """Return the spec of parameter ``name`` (of ``node``, else of any node that has it)."""
    for schema in ([SCHEMAS[node]] if node else SCHEMAS.values()):
        specs = schema.specs()
        if name in specs:
            return specs[name]
    raise KeyError(name)


def argparse_kwargs(name: str, help: str = '', node: Optional[str] = None) -> Dict[str, Any]:
    """Return ``add_argument`` keywords of the option for parameter ``name`` (its spec)."""
    return spec_of(name, node).argparse(help)


__all__ = ['MAX_PRIORITY', 'MODES', 'TS_SPEC', 'live_specs', 'RECORDER_SPECS', 'FOXGLOVE_SPECS',
           'Group', 'ERVA', 'LIVE', 'CONTROLLER', 'BRIDGE', 'ESTIMATOR', 'ECU_SIM', 'RECORDER',
           'FOXGLOVE', 'QUALITY', 'ROAD_ESTIMATE', 'MAP_PREVIEW', 'ROAD_ESTIMATE_SPECS',
           'MAP_PREVIEW_SPECS', 'ROAD_AT_TYRE', 'PREVIEW_SOURCES', 'QUALITY_SPECS', 'NodeSchema',
           'SCHEMAS', 'LOOP_NODES',
           'session_sections', 'LAUNCH_ARGUMENTS', 'launch_arguments', 'READ_ONLY_REASONS',
           'DEVICE_REASON', 'READ_AT_START', 'read_only_reason', 'spec_of', 'argparse_kwargs']
