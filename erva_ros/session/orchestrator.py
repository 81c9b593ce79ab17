"""`erva run`: start the live system as separate processes, run one scenario, stop, summarise.

:func:`run_session` does, in order:

1. validates every value in-process first (physical parameters, controller settings,
   live parameters, the road), so a bad option fails with one line before any
   process starts;
2. writes the session's effective parameters to one ROS 2 params file (``/**``
   for what all nodes share, ``/**/<node>`` for each node) in a session directory;
3. starts an in-process monitor node (:class:`~erva_ros.session.monitor.Monitor`), the
   recorder (when recording), nmpc_node, plant_sim_node and road_preview_node, each as
   ``python -m erva_ros.nodes.<name> --ros-args -r __ns:=<ns> --params-file F`` in its
   own process group (and with a parent-death signal, so no node outlives `erva run`);
4. waits until the graph is connected, runs the scenario until every node reports
   it finished (or a node dies, or SIGINT/SIGTERM arrives), lets the last
   diagnostics arrive, then stops the nodes with SIGINT (SIGTERM, SIGKILL after a
   grace period) and the recorder last, so the bag is finished;
5. returns the summary (comfort and power, command rate, jitter and latency,
   solve times, deadline misses, fallbacks, dropped and rejected messages).

With ``ecu='virtual'`` (hardware-in-the-loop, real time only) the processes of
:func:`erva_ros.core.hil.hil_process_specs` take plant_sim_node's place: ``erva ecu-sim``
(plant + simulated ECU on a loopback-UDP CAN bus; it ends by itself after the
scenario), ecu_bridge_node and state_estimator_node, so the loop is NMPC → bridge →
CAN → ECU → CAN → bridge → estimator → NMPC.  The recorder also records the HIL
topics, and the summary gets a ``hil`` block (:mod:`erva_ros.session.hil_summary`).
"""

import ctypes
from dataclasses import dataclass, field
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from typing import Any, Callable, Dict, List, Optional

import yaml

from erva_ros.core import topics
from erva_ros.core.controllers.settings import load_controller_settings
from erva_ros.core.errors import CLIError
from erva_ros.session import accounting, hil_summary
from erva_ros.ros.parameters import (LIVE_CHOICES, LIVE_DEFAULTS, LIVE_INTEGERS,
                                     LIVE_NUMERIC, LIVE_OTHER)
from erva_ros.core.loop.scenario import build_road, required_preview_steps
from erva_ros.core.config import shipped_config
from erva_ros.core.params import check_number, load_erva_params, load_params_yaml, ParamError

#: The live nodes in start order (the slowest to start first).
NODES = ('nmpc_node', 'plant_sim_node', 'road_preview_node')
#: The processes replacing plant_sim_node with --ecu virtual, in start order.
HIL_PROCESSES = ('ecu_sim', 'ecu_bridge_node', 'state_estimator_node')
HIL_NODES = ('nmpc_node', *HIL_PROCESSES, 'road_preview_node')
#: Once the ECU finished (no state comes any more), how long the others may take.
HIL_FINISH_WAIT_S = 2.0
#: Least settling time before sample 0 in HIL mode (live start_delay_s, default 0.5 s).
#: Seven processes discover each other on a loaded machine: with 0.5 s the recorder's
#: readers were sometimes matched ~0.2 s into the run and it lost the first samples.
HIL_START_DELAY_S = 1.5
#: HIL: the bridge and the estimator send no final status; after the finish, wait up to
#: this long for their next periodic one (period 0.5 s, config/hil.yaml).
HIL_DRAIN_S = 1.5
#: After that, `erva run` waits for the recorder to report every message the nodes
#: published (its status comes every RECORDER_STATUS_S) before stopping them, while it
#: makes progress, giving up after this long without any (the reason goes in the summary).
RECORDER_STALL_S = 5.0
#: The recorder's status period in a session (the start gate and the drain read it).
RECORDER_STATUS_S = 0.25
#: The recorder runs at SCHED_FIFO this much below the loop's nodes: above other work on
#: the machine, so the record is not starved, below the loop, so the loop goes first.
RECORDER_PRIORITY_BELOW = 10
#: The end of the recorder's /diagnostics status name ('<its node name>: bag recorder').
RECORDER_STATUS = ': bag recorder'
#: Live parameters that belong to one node's section of the session params file.
NODE_PARAMETERS = {
    'road_preview_node': ('road', 'road_file', 'seed', 'road_class', 'speed_mps',
                          'bump_height_m', 'bump_length_m', 'bump_start_s', 'preview_steps',
                          'preview_noise', 'preview_snr_db', 'preview_delay_s'),
    'plant_sim_node': ('command_timeout_s', 'lockstep_timeout_s'),
    'nmpc_node': ('state_timeout_periods',),
}
#: Grace period (s) between SIGINT, SIGTERM and SIGKILL when stopping a process.
STOP_GRACE_S = 5.0
#: Exit status of a run stopped by SIGINT / SIGTERM (shell convention 128 + signal).
SIGNAL_EXIT = {signal.SIGINT: 130, signal.SIGTERM: 143}


def default_config_file(name: str) -> str:
    """Return the path of a shipped config file (source tree or installed share)."""
    return shipped_config(name)


def read_live_file(path: Optional[str]) -> Dict[str, Any]:
    """Return the live parameters of a params file: ``/**`` merged with each node's section."""
    path = path or default_config_file('live.yaml')
    if not os.path.isfile(path):
        raise ParamError(f'live parameter file {path!r} does not exist')
    doc = load_params_yaml(path)
    out: Dict[str, Any] = {}
    for section in ('/**', *(f'/**/{n}' for n in NODES)):
        params = (doc.get(section) or {}).get('ros__parameters') or {}
        unknown = sorted(set(params) - set(LIVE_DEFAULTS) - {'use_sim_time'})
        if unknown:
            raise ParamError(f'{path}: unknown live parameter(s) {", ".join(unknown)} '
                             f'in {section}')
        out.update(params)
    return out


def validate_live(values: Dict[str, Any], source: str = '') -> Dict[str, Any]:
    """Return the live parameters (defaults filled in) checked against the tables."""
    where = f'{source}: ' if source else ''
    out = dict(LIVE_DEFAULTS)
    out.update({k: v for k, v in values.items() if k != 'use_sim_time'})
    for key, value in out.items():
        if key in LIVE_NUMERIC:
            spec = LIVE_NUMERIC[key]
            if key in LIVE_INTEGERS and (isinstance(value, bool) or not isinstance(value, int)):
                raise ParamError(f'{where}parameter {key!r} must be an integer in '
                                 f'{spec.describe()}, got {value!r}')
            out[key] = check_number(key, value, spec, source)
            if key in LIVE_INTEGERS:
                out[key] = int(out[key])
        elif key in LIVE_CHOICES:
            choices, doc = LIVE_CHOICES[key]
            if value not in choices:
                raise ParamError(f'{where}parameter {key!r} = {value!r} is not allowed; '
                                 f'choose one of {", ".join(choices)} ({doc})')
        elif isinstance(LIVE_DEFAULTS[key], bool) and not isinstance(value, bool):
            raise ParamError(f'{where}parameter {key!r} must be true or false '
                             f'({LIVE_OTHER[key]}), got {value!r}')
        elif isinstance(LIVE_DEFAULTS[key], str) and not isinstance(value, str):
            raise ParamError(f'{where}parameter {key!r} must be a string, got {value!r}')
    return out


@dataclass
class RunConfig:
    """What `erva run` runs; ``None`` means "as in the config files"."""

    controller: Optional[str] = None
    alpha1: Optional[float] = None
    alpha2: Optional[float] = None
    road: Optional[str] = None
    seed: Optional[int] = None
    mode: Optional[str] = None
    model: Optional[str] = None
    duration_s: Optional[float] = None
    params_file: Optional[str] = None      # physical parameters (config/erva_paper.yaml)
    nmpc_file: Optional[str] = None        # controller settings (config/nmpc.yaml)
    live_file: Optional[str] = None        # live parameters (config/live.yaml)
    record_dir: Optional[str] = None       # parent of the session bag; None: no recording
    namespace: str = '/erva'
    startup_timeout_s: float = 90.0
    live_overrides: Dict[str, Any] = field(default_factory=dict)
    settings_overrides: Dict[str, Any] = field(default_factory=dict)
    session_dir: Optional[str] = None      # where the params file and node logs go
    ecu: str = 'none'                      # 'virtual': the HIL loop (simulated ECU, CAN)
    foxglove: Optional[str] = None         # [HOST:]PORT: serve the session to Foxglove
    ecu_prefix: tuple = ()                 # argv prefix of the HIL processes (--ecu-prefix)


@dataclass
class Session:
    """A validated scenario: effective parameters and the params file the nodes read."""

    erva: Dict[str, float]
    settings: Any
    live: Dict[str, Any]
    directory: str
    params_file: str
    scenario: str
    ecu: str = 'none'

    @property
    def hil(self) -> bool:
        """Return True for the hardware-in-the-loop loop (--ecu virtual)."""
        return self.ecu != 'none'

    @property
    def realtime(self) -> bool:
        """Return True for a wall-clock run."""
        return self.live['mode'] == 'realtime'

    @property
    def n_steps(self) -> int:
        """Return the number of control periods of the scenario."""
        return int(round(self.live['duration_s'] / self.live['ts']))


def prepare_session(cfg: RunConfig, recording: bool) -> Session:
    """Validate everything and write the session params file; raise ParamError (one line)."""
    erva = load_erva_params(cfg.params_file)
    overrides = {'controller': cfg.controller, 'alpha1': cfg.alpha1, 'alpha2': cfg.alpha2}
    overrides.update(cfg.settings_overrides)
    settings = load_controller_settings(cfg.nmpc_file, overrides)
    live_path = cfg.live_file or default_config_file('live.yaml')
    values = read_live_file(live_path)
    if 'ts' in values and abs(float(values['ts']) - settings.ts) > 1e-12:
        raise ParamError(f'{live_path}: ts = {values["ts"]} s differs from the controller\'s '
                         f'ts = {settings.ts:g} s; set both to the same sample time')
    values['ts'] = settings.ts
    for key, value in (('mode', cfg.mode), ('model', cfg.model), ('road', cfg.road),
                       ('seed', cfg.seed), ('duration_s', cfg.duration_s)):
        if value is not None:
            values[key] = value
    values.update(cfg.live_overrides)
    live = validate_live(values, source=live_path)
    if cfg.ecu != 'none':
        if live['mode'] != 'realtime':
            raise CLIError(f'--ecu {cfg.ecu} runs in real time only (the ECU keeps wall-clock '
                           f'time), not with mode {live["mode"]}')
        live['start_delay_s'] = max(live['start_delay_s'], HIL_START_DELAY_S)
    live['preview_steps'] = max(live['preview_steps'], required_preview_steps(settings))
    # The time master starts when each of its topics has the other loop node, this
    # process's monitor and (when recording / serving) the recorder / Foxglove server.
    live['wait_for_subscribers'] = 2 + (1 if recording else 0) + (1 if cfg.foxglove else 0)
    build_road(live)   # a bad road option fails here, not in a node
    directory = cfg.session_dir or tempfile.mkdtemp(prefix='erva_run_')
    os.makedirs(directory, exist_ok=True)
    scenario = live['road'] if not live['road_file'] else 'recorded'
    shared = {k: v for k, v in live.items()
              if not any(k in names for names in NODE_PARAMETERS.values())}
    shared.update(erva.as_dict())
    if live['mode'] == 'lockstep':
        shared['use_sim_time'] = True
    doc = {'/**': {'ros__parameters': shared}}
    for node, names in NODE_PARAMETERS.items():
        doc[f'/**/{node}'] = {'ros__parameters': {k: live[k] for k in names}}
    doc['/**/nmpc_node']['ros__parameters'].update(settings.as_dict())
    path = os.path.join(directory, 'session_params.yaml')
    with open(path, 'w', encoding='utf-8') as fh:
        fh.write('# Effective parameters of an `erva run` session (ROS 2 params file).\n')
        yaml.safe_dump(doc, fh, sort_keys=False)
    return Session(erva.as_dict(), settings, live, directory, path, scenario, cfg.ecu)


def _die_with_parent() -> None:
    """Ask the kernel to SIGTERM this child when `erva run` dies (Linux prctl)."""
    try:
        libc = ctypes.CDLL('libc.so.6', use_errno=True)
        libc.prctl(1, signal.SIGTERM)   # PR_SET_PDEATHSIG
    except OSError:
        pass


class NodeProcess:
    """One node process in its own process group, its output in a log file."""

    def __init__(self, name: str, argv: List[str], log_path: str, env: Dict[str, str]):
        self.name = name
        self.log_path = log_path
        self._log = open(log_path, 'w', encoding='utf-8')
        self.popen = subprocess.Popen(argv, stdout=self._log, stderr=subprocess.STDOUT,
                                      stdin=subprocess.DEVNULL, env=env,
                                      start_new_session=True, preexec_fn=_die_with_parent)
        self.pid = self.popen.pid
        self.stopped_by_us = False

    def poll(self) -> Optional[int]:
        """Return the exit status, or None while running."""
        return self.popen.poll()

    def signal(self, sig: int) -> None:
        """Send ``sig`` to the process group (the node and anything it started)."""
        try:
            os.killpg(self.pid, sig)
        except ProcessLookupError:
            pass

    def tail(self, lines: int = 5) -> str:
        """Return the last lines of the node's output."""
        if not self._log.closed:
            self._log.flush()
        try:
            with open(self.log_path, encoding='utf-8', errors='replace') as fh:
                return ''.join(fh.readlines()[-lines:]).rstrip()
        except OSError:
            return ''

    def close(self) -> None:
        """Close the log file."""
        self._log.close()


def stop_processes(procs: List[NodeProcess], grace_s: float = STOP_GRACE_S) -> None:
    """Stop processes with SIGINT, then SIGTERM, then SIGKILL; reap them all."""
    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGKILL):
        alive = [p for p in procs if p.poll() is None]
        if not alive:
            break
        for p in alive:
            p.stopped_by_us = True
            p.signal(sig)
        deadline = time.monotonic() + grace_s
        while time.monotonic() < deadline and any(p.poll() is None for p in alive):
            time.sleep(0.02)
    for p in procs:
        try:
            p.popen.wait(timeout=grace_s)
        except subprocess.TimeoutExpired:
            pass
        p.close()


@dataclass
class RunResult:
    """What a session produced: the summary, the exit status and the sampled trajectory."""

    summary: Dict[str, Any]
    exit_code: int
    trajectory: Dict[str, Any]
    session: Optional[Session] = None


def session_description(session: Session) -> Dict[str, str]:
    """Return what describes the session (the bag's erva_session record)."""
    from erva_ros.core.bag import session as bag_session
    params = {'erva': session.erva, 'controller': session.settings.as_dict(),
              'live': session.live}
    return bag_session.session_metadata(
        session.scenario, parameters=params, seed=session.live['seed'],
        controller=session.settings.controller,
        extra={'mode': session.live['mode'], 'model': session.live['model'],
               'duration_s': session.live['duration_s'], 'ecu': session.ecu,
               'params_file': session.params_file})


def _recorder(cfg: RunConfig, session: Session, bag_parent: str, env, log) -> NodeProcess:
    from erva_ros.core.bag import session as bag_session
    from erva_ros.nodes.recorder_node import DEFAULT_TOPICS
    bag_dir = bag_session.new_bag_dir(bag_parent, session.scenario)
    meta = session_description(session)
    record = list(DEFAULT_TOPICS)
    if session.hil:
        from erva_ros.core.hil.topics import RECORD_TOPICS
        record += RECORD_TOPICS
    loop_priority = session.live['realtime_priority'] if session.realtime else 0
    argv = [sys.executable, '-m', 'erva_ros.nodes.recorder_node',
            *bag_session.recorder_ros_args(
                bag_dir, meta, topics=record, namespace=cfg.namespace,
                use_sim_time=not session.realtime,
                parameters={'diagnostics_period_s': RECORDER_STATUS_S,
                            'realtime_priority': max(0, loop_priority - RECORDER_PRIORITY_BELOW)
                            if loop_priority > 1 else 0})]
    proc = NodeProcess('recorder_node', argv,
                       os.path.join(session.directory, 'recorder_node.log'), env)
    proc.bag_dir = bag_dir
    proc.topics = record
    log(f'recording to {bag_dir}')
    return proc


def recorder_available() -> bool:
    """Return True when the recorder (erva_ros.core.bag, recorder_node) is installed."""
    import importlib.util
    return all(importlib.util.find_spec(m) is not None
               for m in ('erva_ros.core.bag.session', 'erva_ros.nodes.recorder_node'))


class _Supervisor:
    """One `erva run` session: the node processes, the monitor, and the run's phases."""

    #: Nodes without which the run cannot go on (lock-step also needs the controller).
    NEEDED = {'plant_sim_node', 'road_preview_node'}
    #: The same in HIL mode (real time only): without the controller the bridge sends
    #: the safe passive command, which is worth seeing.
    HIL_NEEDED = {*HIL_PROCESSES, 'road_preview_node'}

    def __init__(self, cfg: RunConfig, session: Session, recording: bool, log):
        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.signals import SignalHandlerOptions
        from erva_ros.session.monitor import Monitor

        self.cfg, self.session, self.recording, self.log = cfg, session, recording, log
        self.procs: Dict[str, NodeProcess] = {}
        self.errors: List[str] = []
        self.dead: set = set()
        self.caught: List[int] = []
        self.phase = 'starting'
        self.t_start = time.monotonic()
        self.t_start_ns = time.time_ns()
        self.needed = set(self.NEEDED) | (set() if session.realtime else {'nmpc_node'})
        # Processes run, and those that report `finished` on /diagnostics.
        self.node_names, self.finishers = NODES, NODES
        if session.hil:
            self.node_names = HIL_NODES
            self.finishers = ('nmpc_node', 'road_preview_node', hil_summary.ECU)
            self.needed = set(self.HIL_NEEDED)
        self.ended: set = set()     # exited 0 by themselves at the end (the ECU)
        self._ecu_done: Optional[float] = None
        self.context = rclpy.Context()
        rclpy.init(args=[], context=self.context,
                   signal_handler_options=SignalHandlerOptions.NO)
        # The monitor subscribes to the time master's gate topic last (see Monitor): the
        # time master starts only once that subscription is matched too.
        self.gate = (topics.ROAD_PREVIEW,) if session.realtime else (topics.STATE,)
        window = None if session.realtime else (
            0, int((session.live['duration_s'] + 10.0) * 1e9))   # simulated time from 0
        self.monitor = Monitor(cfg.namespace, context=self.context, gate=self.gate,
                               hil=session.hil, window_ns=window)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.monitor)
        self.recording_report: Dict[str, Any] = {}
        self._unmatched: List[str] = []
        self._expect_matches()

    def _expect_matches(self) -> None:
        """Work out how many subscribers each loop writer must match before the start."""
        ns = self.cfg.namespace
        loop = accounting.hil_loop_subscribers() if self.session.hil else dict(
            accounting.LOOP_SUBSCRIBERS)
        observers = [self.monitor.watched]
        if self.cfg.foxglove:
            from erva_ros.session import foxglove_process
            observers.append(foxglove_process.session_topics(self.session.hil))
        if self.recording:
            from erva_ros.nodes.recorder_node import DEFAULT_TOPICS
            record = list(DEFAULT_TOPICS)
            if self.session.hil:
                from erva_ros.core.hil.topics import RECORD_TOPICS
                record += RECORD_TOPICS
            observers.append(record)
            # One writer per data topic; /diagnostics: every node, the recorder itself and
            # the Foxglove server.
            self.record_writers = {accounting.qualify(t, ns): 1 for t in record
                                   if t not in (topics.CLOCK, topics.DIAGNOSTICS)}
            self.record_writers[topics.DIAGNOSTICS] = (len(self.node_names) + 1
                                                       + (1 if self.cfg.foxglove else 0))
        self.expected = accounting.expected_subscribers(loop, observers, ns)
        self.later = {accounting.qualify(t, ns): 1 for t in self.gate}

    def start(self) -> None:
        """Start the recorder (when recording) and the nodes, slowest first."""
        env = dict(os.environ)
        env.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
        env['PYTHONUNBUFFERED'] = '1'
        if self.cfg.foxglove:   # first: it listens before the loop runs
            from erva_ros.session import foxglove_process
            self.procs[foxglove_process.PROCESS] = foxglove_process.start_process(
                self.cfg, self.session, env, self.log, session_description(self.session))
        if self.recording:
            self.procs['recorder_node'] = _recorder(self.cfg, self.session,
                                                    self.cfg.record_dir, env, self.log)
        hil = {}
        if self.session.hil:
            from erva_ros.session.hil_processes import hil_process_specs
            live = self.session.live
            hil = {spec.name: spec for spec in hil_process_specs(
                self.session.params_file, self.cfg.namespace, live['duration_s'],
                model=live['model'], ts=live['ts'], env=env, stamp_on_road_grid=True,
                realtime_priority=live['realtime_priority'], prefix=self.cfg.ecu_prefix)}
        for name in self.node_names:
            argv = [sys.executable, '-m', f'erva_ros.nodes.{name}', '--ros-args',
                    '-r', f'__ns:={self.cfg.namespace}',
                    '--params-file', self.session.params_file]
            spec = hil.get(name)
            self.procs[name] = NodeProcess(
                name, spec.argv if spec else argv,
                os.path.join(self.session.directory, f'{name}.log'), spec.env if spec else env)
        self.log('started ' + ', '.join(f'{n} (pid {p.pid})' for n, p in self.procs.items()))

    def observe_at_priority(self) -> None:
        """Run this process (the monitor's DDS threads) at the recorder's priority.

        Called after the nodes are started (children would inherit it).  Under load a
        monitor at normal priority receives late: its timing figures would be the
        machine's, not the loop's.  Without the right it stays at normal priority.
        """
        from erva_ros.ros.realtime import set_fifo_priority
        live = self.session.live
        loop = live['realtime_priority'] if self.session.realtime else 0
        if loop > 1:
            self.scheduling = set_fifo_priority(max(1, loop - RECORDER_PRIORITY_BELOW),
                                                lambda line: None)

    def supervise(self) -> None:
        """Connect, run and drain, until the scenario ends, a needed node dies or a signal."""
        self.phase = 'connecting'
        last_progress, last_states, finish_seen, finish_ns = time.monotonic(), 0, 0.0, 0
        while True:
            self.executor.spin_once(timeout_sec=0.02)
            if self.caught:
                self.errors.append(f'interrupted by {signal.Signals(self.caught[0]).name} '
                                   f'while {self.phase}')
                return
            if self._check_deaths():
                return
            now = time.monotonic()
            if self.phase == 'connecting':
                if self._graph_ready() and self._matched() and self.monitor.connect(
                        n_diagnostics=len(self.node_names)):
                    self.phase, last_progress = 'running', now   # (not the connecting time)
                    self.log(f'connected in {now - self.t_start:.1f} s; running '
                             f'{self.session.live["duration_s"]:g} s '
                             f'({self.session.live["mode"]})')
                elif now - self.t_start > 10.0 and not getattr(self, '_told_waiting', False):
                    self._told_waiting = True     # say once what a slow start waits for
                    self.log('still connecting; waiting for: '
                             + ('; '.join(self._unmatched[:6]) or 'the graph'))
                elif now - self.t_start > self.cfg.startup_timeout_s:
                    waiting = '; '.join(self._unmatched[:4]) or 'the monitor\'s subscriptions'
                    self.errors.append(f'the nodes did not connect within '
                                       f'{self.cfg.startup_timeout_s:g} s (waiting for: '
                                       f'{waiting})')
                    return
            elif self.phase == 'running':
                states = self.monitor.received[topics.STATE]
                if states != last_states:
                    last_states, last_progress = states, now
                if self._finished(now):
                    self.phase, finish_seen, finish_ns = 'draining', now, time.time_ns()
                    continue
                limit = 10.0 + (5.0 if last_states == 0 else 0.0)
                if now - last_progress > limit + self.session.live['start_delay_s']:
                    self.errors.append(f'no progress for {now - last_progress:.0f} s '
                                       f'({last_states} states received)')
                    return
            elif self._drained(now - finish_seen, finish_ns):
                return   # drained: the final diagnostics and messages in flight arrived

    def _matched(self) -> bool:
        """Return True once every loop writer and the recorder have matched all their peers.

        Before the monitor's gate subscription exists (it opens the start), so the gate
        topic's writer needs one subscriber less here.
        """
        statuses = {n: v[2] for n, v in self.monitor.diag.items()}
        # The ECU simulator reports only once the road runs (its readers are checked by
        # _graph_ready): every other node must have said what its writers matched.
        nodes = [n for n in self.node_names if n != hil_summary.ECU]
        nodes += ['recorder'] if self.recording else []
        missing = accounting.unmatched(statuses, nodes, self.expected, self.later)
        if self.recording:
            recorder = next((v for n, v in statuses.items() if n.endswith(RECORDER_STATUS)), {})
            missing += accounting.recorder_unmatched(recorder, self.record_writers)
        self._unmatched = missing
        return not missing

    def _graph_ready(self) -> bool:
        """HIL: return True once the ROS graph shows the whole loop (always True otherwise).

        The monitor's own subscriptions (Monitor.connect) do not show that the estimator
        listens to the bridge (ecu/measurements), the ECU to the road, or the recorder
        (which subscribes to the HIL topics once it discovers their types) to all of them;
        the road, which starts the loop, must wait for them too.
        """
        if not self.session.hil:
            return True
        from erva_ros.core.hil import topics as hil_topics
        ns = self.cfg.namespace.rstrip('/')
        m, rec = self.monitor, int(self.recording)
        ecu = (hil_topics.ECU_DAMPING_APPLIED, hil_topics.ECU_SPRUNG_ACCEL,
               hil_topics.ECU_SUSPENSION, hil_topics.ECU_GENERATOR)
        subs = {topics.ROAD_HEIGHT: 2 + rec,      # ECU, estimator (the monitor comes last)
                topics.DAMPING_CMD: 2 + rec,      # bridge, monitor
                topics.STATE: 2 + rec,            # nmpc, monitor
                hil_topics.TRUE_STATE: 1 + rec,   # monitor
                hil_topics.ECU_MEASUREMENTS: 1 + rec,   # estimator
                **{t: rec for t in ecu}}          # per-frame topics: only recorded
        published = ecu + (hil_topics.ECU_MEASUREMENTS,)
        return (all(m.count_subscribers(f'{ns}/{t}') >= n for t, n in subs.items())
                and all(m.count_publishers(f'{ns}/{t}') >= 1 for t in published))

    def _finished(self, now: float) -> bool:
        """Return True once every node that reports `finished` did (or died)."""
        def done(name):
            return name in self.ended or self.monitor.diag_values(name).get('finished') == 'true'
        waiting = [n for n in self.finishers if n not in self.dead and not done(n)]
        if not waiting:
            return True
        if self.session.hil and done(hil_summary.ECU):
            # No state comes after the ECU's last cycle: a node still waiting for one
            # (the NMPC, had it missed the first state) would never finish.
            self._ecu_done = self._ecu_done or now
            if now - self._ecu_done > HIL_FINISH_WAIT_S:
                self.log(f'the ECU finished; {", ".join(waiting)} did not report finished')
                return True
        return False

    def _drained(self, elapsed: float, finish_ns: int) -> bool:
        """Return True once the final counters arrived and nothing is missing (or timed out)."""
        if not self.session.hil:
            done = elapsed > 1.0 or _all_received(self.monitor)
        else:
            fresh = all(self.monitor.diag_rx(n) > finish_ns for n in hil_summary.PERIODIC
                        if n.split(':')[0] not in self.dead)
            done = elapsed > HIL_DRAIN_S or (fresh and _all_received(self.monitor))
        if not done or not self.recording or 'recorder_node' in self.dead:
            return done
        return self._recorder_caught_up()

    def _recorder_caught_up(self) -> bool:
        """Return True once the recorder holds every message the nodes published (so far).

        A publisher that exits takes what it has not delivered with it, so the nodes stay
        up until then -- as long as the recorder makes progress; after RECORDER_STALL_S
        without any, give up and say why in the summary.
        """
        recorder = next((self.monitor.diag_values(name) for name in list(self.monitor.diag)
                         if name.endswith(RECORDER_STATUS)), {})
        statuses = {n: v[2] for n, v in self.monitor.diag.items()
                    if not n.endswith(RECORDER_STATUS)}
        behind = accounting.recorder_behind(recorder, accounting.published_counts(statuses))
        if not behind:
            return True
        total = sum(got for got, _ in behind.values())
        now = time.monotonic()
        if total != getattr(self, '_drain_total', None):
            self._drain_total, self._drain_progress = total, now
        if now - self._drain_progress > RECORDER_STALL_S:
            topic, (got, n) = next(iter(behind.items()))
            self.recording_report['gave_up'] = (
                f'the recorder made no progress for {RECORDER_STALL_S:g} s with {topic} at '
                f'{got} of {n} messages; the nodes were stopped')
            self.log(self.recording_report['gave_up'])
            return True
        return False

    def _check_deaths(self) -> bool:
        """Record nodes that exited on their own; return True if the run must stop."""
        for name, p in self.procs.items():
            if name in self.dead or name in self.ended or p.poll() is None:
                continue
            if name == hil_summary.ECU and p.poll() == 0:
                self.ended.add(name)    # `erva ecu-sim --duration` ends by itself
                continue
            self.dead.add(name)
            where = (f'at t = {self.monitor.received[topics.STATE] * self.session.live["ts"]:.2f}'
                     f' s' if self.phase == 'running' else f'while {self.phase}')
            self.errors.append(f'{name} died (exit status {p.poll()}) {where}'
                               + (f': {p.tail(1)}' if p.tail(1) else ''))
            # Without the controller the real-time plant falls back to the plan, then
            # passive damping, which is worth seeing; without the recorder the loop
            # runs on unrecorded.
            goes_on = self.phase == 'running' and name not in self.needed
            self.log(self.errors[-1] + ('; the run goes on without it' if goes_on else ''))
        return bool(self.dead) and (self.phase != 'running' or bool(self.dead & self.needed))

    def stop(self) -> None:
        """Stop the nodes, then the recorder (so it records to the end), then the monitor."""
        import rclpy
        ecu = self.procs.get(hil_summary.ECU)
        if ecu is not None and hil_summary.ECU in self.monitor.finished_rx:
            try:    # it ends by itself after its last status: let it print its summary
                ecu.popen.wait(timeout=STOP_GRACE_S)
            except subprocess.TimeoutExpired:
                pass
            if ecu.poll() == 0:
                self.ended.add(hil_summary.ECU)
        last = ('recorder_node', 'foxglove_server')   # they take what the nodes published
        stop_processes([p for n, p in self.procs.items() if n not in last])
        # Each node published its final status (its final counts) before it exited: take
        # them, so the summary and the bag check count what was really published.
        self._take_pending()
        if any(n in self.procs for n in last):
            stop_processes([self.procs[n] for n in last if n in self.procs], grace_s=10.0)
        self.executor.shutdown()
        self.monitor.destroy_node()
        rclpy.try_shutdown(context=self.context)

    def _take_pending(self, quiet_s: float = 0.2, limit_s: float = 3.0) -> None:
        """Spin the monitor until no loop node's message came for ``quiet_s`` (<= ``limit_s``).

        (The recorder and the Foxglove server, still running, keep reporting: not counted.)
        """
        def loop_arrivals():
            data = sum(n for t, n in self.monitor.received.items() if t != topics.DIAGNOSTICS)
            return data, tuple(v[3] for n, v in self.monitor.diag.items()
                               if not n.endswith((RECORDER_STATUS, ': foxglove server')))
        end = time.monotonic() + limit_s
        last, quiet_since = None, time.monotonic()
        while time.monotonic() < end and time.monotonic() - quiet_since < quiet_s:
            self.executor.spin_once(timeout_sec=0.02)
            now = loop_arrivals()
            if now != last:
                last, quiet_since = now, time.monotonic()

    def summary(self) -> Dict[str, Any]:
        """Return the run's summary: the monitor's figures plus scenario, nodes and errors."""
        s = self.session
        summary = self.monitor.summary(s.live['ts'], s.n_steps, s.realtime)
        nodes = {}
        for name, p in self.procs.items():
            status = p.poll()
            nodes[name] = {'pid': p.pid, 'exit_status': status, 'died': name in self.dead,
                           'stopped_cleanly': status == 0 and (p.stopped_by_us
                                                               or name in self.ended),
                           'log': p.log_path}
            if name not in self.dead and status != 0:
                self.errors.append(f'{name} did not stop cleanly (exit status {status})'
                                   + (f': {p.tail(1)}' if p.tail(1) else ''))
        if 'recorder_node' in self.procs:
            summary['bag'] = self.procs['recorder_node'].bag_dir
            summary['recording'] = self._check_recording()
        if 'foxglove_server' in self.procs:
            from erva_ros.session import foxglove_process
            summary['foxglove'] = foxglove_process.summary(self.monitor.diag)
        if summary['commands']['received'] == 0 and not self.caught:
            self.errors.append('no damping commands were received')
        self._check_rejections(summary)
        summary.update({
            'scenario': {'controller': s.settings.controller,
                         'weights': list(s.settings.weights), 'road': s.scenario,
                         'seed': s.live['seed'], 'mode': s.live['mode'],
                         'model': s.live['model'], 'duration_s': s.live['duration_s'],
                         'ts': s.live['ts'], 'namespace': self.cfg.namespace,
                         'ecu': s.ecu},
            'nodes': nodes, 'errors': self.errors, 'ok': not self.errors,
            'wall_time_s': round(time.monotonic() - self.t_start, 3),
            'session_dir': s.directory,
        })
        return summary

    def _check_rejections(self, summary: Dict[str, Any]) -> None:
        """Fail the run if rejected inputs cost the loop a sample of control."""
        rejected = summary['messages']['rejected_total']
        nm = summary['nmpc']
        # Samples whose state never became the controller's (a busy controller's
        # superseded states are load, not rejection).
        unseen = (nm.get('missed_samples') or 0) - (nm.get('superseded_states') or 0)
        if rejected and unseen > 0:
            self.errors.append(f'{unseen} samples went without a command of their own while '
                               f'{rejected} input messages were rejected')

    def _check_recording(self) -> Dict[str, Any]:
        """Compare the bag file with what every node published; add an error per loss."""
        report = dict(self.recording_report)
        rec = self.procs['recorder_node']
        statuses = {n: v[2] for n, v in self.monitor.diag.items()}
        recorder = next((v for n, v in statuses.items() if n.endswith(RECORDER_STATUS)), {})
        report['lost_in_transport'] = int(recorder.get('lost_in_transport', 0))
        published = accounting.published_counts(
            {n: v for n, v in statuses.items() if not n.endswith(RECORDER_STATUS)})
        seqs = {n: int(v['status_seq']) for n, v in statuses.items() if 'status_seq' in v}
        if self.session.realtime:   # stamps outside `erva run`'s lifetime are not the loop's
            window = (self.t_start_ns, time.time_ns())
        else:
            window = (0, int((self.session.live['duration_s'] + 10.0) * 1e9))
        try:
            report.update(accounting.check_bag(rec.bag_dir, published, seqs, window))
        except Exception as exc:    # BagError, CdrError: the file itself is the problem
            report['error'] = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
            self.errors.append(f'the bag cannot be checked: {report["error"]}')
            return report
        for topic, c in report['topics'].items():
            if c['lost']:
                self.errors.append(f'the bag lost {c["lost"]} of {c["published"]} messages '
                                   f'on {topic}')
        for name, gaps in report['diagnostics_missing'].items():
            self.errors.append(f'the bag lacks /diagnostics statuses of {name}: {gaps}')
        if report['lost_in_transport']:
            self.errors.append(f'the middleware reported {report["lost_in_transport"]} '
                               f'messages lost before the recorder took them')
        return report

    def exit_code(self) -> int:
        """Return 128 + signal if interrupted, 1 on any error, else 0."""
        if self.caught:
            return SIGNAL_EXIT.get(self.caught[0], 1)
        return 1 if self.errors else 0


def run_session(cfg: RunConfig, log: Callable[[str], None] = lambda s: None) -> RunResult:
    """Run one scenario (see module doc); ``log`` gets progress lines for stderr."""
    recording = cfg.record_dir is not None and recorder_available()
    if cfg.record_dir is not None and not recording:
        log('recorder not available yet: summary only')
    session = prepare_session(cfg, recording)
    if recording:
        check_record_dir(cfg.record_dir)
    sup = _Supervisor(cfg, session, recording, log)
    handlers = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    for sig in handlers:   # Ctrl-C / SIGTERM: stop the nodes cleanly, then summarise
        signal.signal(sig, lambda signum, frame: sup.caught.append(signum))
    try:
        sup.start()
        sup.observe_at_priority()
        sup.supervise()
    finally:
        sup.stop()
        for sig, handler in handlers.items():
            signal.signal(sig, handler)
    summary = sup.summary()
    code = sup.exit_code()
    interrupted_only = sup.caught and len(summary['errors']) == 1
    if cfg.session_dir is None and (code == 0 or interrupted_only):
        # Nothing to look into: drop the temporary params file and node logs.
        shutil.rmtree(session.directory, ignore_errors=True)
        summary['session_dir'] = None
        for node in summary['nodes'].values():
            node['log'] = None
    elif summary['errors']:
        log(f'node logs and the session params file are in {session.directory}')
    return RunResult(summary, code, sup.monitor.trajectory(session.n_steps), session)


def check_record_dir(parent: str) -> None:
    """Raise CLIError unless bags can be written under ``parent`` (created if missing).

    Refused before anything starts: a session whose record cannot be written is not
    the session the user asked for (a disk that fills up *during* the run is reported
    by the recorder and fails the run's bag check instead).
    """
    try:
        os.makedirs(parent, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=parent, prefix='.erva-write-test-'):
            pass
    except OSError as exc:
        raise CLIError(f'--record {parent}: cannot write bags there '
                       f'({exc.strerror or exc}); pick another directory or --no-record'
                       ) from None


def _all_received(monitor) -> bool:
    """Return True once every node's final counters arrived and nothing is missing."""
    published = monitor.published()
    return (all(v is not None for v in published.values())
            and not any(monitor.dropped(published).values()))


def ensure_ecu_available(ecu: str) -> None:
    """Raise CLIError unless the HIL loop for ``--ecu`` can run (its modules import)."""
    if ecu == 'none':
        return
    try:
        import erva_ros.core.hil  # noqa: F401  (python-can, cantools, the estimator)
    except ImportError as exc:
        raise CLIError(f'--ecu {ecu} is not available: the HIL modules (erva_ros.core.hil) do not '
                       f'import ({exc})') from None


__all__ = ['NODES', 'HIL_NODES', 'RunConfig', 'Session', 'RunResult', 'prepare_session',
           'run_session', 'read_live_file', 'validate_live', 'stop_processes', 'NodeProcess',
           'recorder_available', 'ensure_ecu_available', 'default_config_file']
