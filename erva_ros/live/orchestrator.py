"""`erva run`: start the live system as separate processes, run one scenario, stop, summarise.

:func:`run_session` does, in order:

1. validates every value in-process first (physical parameters, controller settings,
   live parameters, the road), so a bad option fails with one line before any
   process starts;
2. writes the session's effective parameters to one ROS 2 params file (``/**``
   for what all nodes share, ``/**/<node>`` for each node) in a session directory;
3. starts an in-process monitor node (:class:`~erva_ros.live.monitor.Monitor`), the
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
:func:`erva_ros.hil.hil_process_specs` take plant_sim_node's place: ``erva ecu-sim``
(plant + simulated ECU on a loopback-UDP CAN bus; it ends by itself after the
scenario), ecu_bridge_node and state_estimator_node, so the loop is NMPC → bridge →
CAN → ECU → CAN → bridge → estimator → NMPC.  The recorder also records the HIL
topics, and the summary gets a ``hil`` block (:mod:`erva_ros.live.hil_summary`).
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

from erva_ros import topics
from erva_ros.controllers.settings import load_controller_settings
from erva_ros.errors import CLIError
from erva_ros.live import hil_summary
from erva_ros.live.parameters import (LIVE_CHOICES, LIVE_DEFAULTS, LIVE_INTEGERS,
                                      LIVE_NUMERIC, LIVE_OTHER)
from erva_ros.live.scenario import build_road, required_preview_steps
from erva_ros.params import check_number, load_erva_params, ParamError

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
#: How long, after that, `erva run` waits for the recorder to report every message the nodes
#: published (its status comes every 0.5 s) before stopping them: a publisher that exits
#: takes the samples not yet delivered with it.  (A known defect is not cured by waiting:
#: in ~1 run in 4 the recorder misses the plant's last samples for good; README.)
RECORDER_DRAIN_S = 2.0
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
    here = os.path.dirname(os.path.abspath(__file__))
    candidates = [os.path.join(here, '..', '..', 'config', name)]
    try:
        from ament_index_python.packages import get_package_share_directory
        candidates.append(os.path.join(get_package_share_directory('erva_ros'), 'config', name))
    except Exception:  # ament index absent or package not installed: source tree only
        pass
    for cand in candidates:
        if os.path.isfile(cand):
            return os.path.normpath(cand)
    raise ParamError(f'cannot find config/{name}')


def read_live_file(path: Optional[str]) -> Dict[str, Any]:
    """Return the live parameters of a params file: ``/**`` merged with each node's section."""
    path = path or default_config_file('live.yaml')
    if not os.path.isfile(path):
        raise ParamError(f'live parameter file {path!r} does not exist')
    try:
        with open(path, encoding='utf-8') as fh:
            doc = yaml.safe_load(fh) or {}
    except yaml.YAMLError:
        raise ParamError(f'{path}: not valid YAML') from None
    if not isinstance(doc, dict):
        raise ParamError(f'{path}: expected a mapping of node names to ros__parameters')
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
    # process's monitor and (when recording) the recorder as subscribers.
    live['wait_for_subscribers'] = 2 + (1 if recording else 0)
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


def _recorder(cfg: RunConfig, session: Session, bag_parent: str, env, log) -> NodeProcess:
    from erva_ros.bag import session as bag_session
    from erva_ros.nodes.recorder_node import DEFAULT_TOPICS
    bag_dir = bag_session.new_bag_dir(bag_parent, session.scenario)
    params = {'erva': session.erva, 'controller': session.settings.as_dict(),
              'live': session.live}
    meta = bag_session.session_metadata(
        session.scenario, parameters=params, seed=session.live['seed'],
        controller=session.settings.controller,
        extra={'mode': session.live['mode'], 'model': session.live['model'],
               'duration_s': session.live['duration_s'], 'ecu': session.ecu,
               'params_file': session.params_file})
    record = list(DEFAULT_TOPICS)
    if session.hil:
        from erva_ros.hil.topics import RECORD_TOPICS
        record += RECORD_TOPICS
    argv = [sys.executable, '-m', 'erva_ros.nodes.recorder_node',
            *bag_session.recorder_ros_args(bag_dir, meta, topics=record,
                                           namespace=cfg.namespace,
                                           use_sim_time=not session.realtime)]
    proc = NodeProcess('recorder_node', argv,
                       os.path.join(session.directory, 'recorder_node.log'), env)
    proc.bag_dir = bag_dir
    log(f'recording to {bag_dir}')
    return proc


def recorder_available() -> bool:
    """Return True when the recorder (erva_ros.bag, recorder_node) is installed."""
    import importlib.util
    return all(importlib.util.find_spec(m) is not None
               for m in ('erva_ros.bag.session', 'erva_ros.nodes.recorder_node'))


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
        from erva_ros.live.monitor import Monitor

        self.cfg, self.session, self.recording, self.log = cfg, session, recording, log
        self.procs: Dict[str, NodeProcess] = {}
        self.errors: List[str] = []
        self.dead: set = set()
        self.caught: List[int] = []
        self.phase = 'starting'
        self.t_start = time.monotonic()
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
        # The monitor subscribes to the time master's topics last (see Monitor).
        gate = ((topics.ROAD_HEIGHT, topics.ROAD_PREVIEW) if session.realtime
                else (topics.STATE,))
        self.monitor = Monitor(cfg.namespace, context=self.context, gate=gate,
                               hil=session.hil)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.monitor)

    def start(self) -> None:
        """Start the recorder (when recording) and the nodes, slowest first."""
        env = dict(os.environ)
        env.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
        env['PYTHONUNBUFFERED'] = '1'
        if self.recording:
            self.procs['recorder_node'] = _recorder(self.cfg, self.session,
                                                    self.cfg.record_dir, env, self.log)
        hil = {}
        if self.session.hil:
            from erva_ros.hil import hil_process_specs
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
                if self._graph_ready() and self.monitor.connect(
                        n_diagnostics=len(self.node_names)):
                    self.phase = 'running'
                    self.log(f'connected in {now - self.t_start:.1f} s; running '
                             f'{self.session.live["duration_s"]:g} s '
                             f'({self.session.live["mode"]})')
                elif now - self.t_start > self.cfg.startup_timeout_s:
                    self.errors.append(f'the nodes did not connect within '
                                       f'{self.cfg.startup_timeout_s:g} s')
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

    def _graph_ready(self) -> bool:
        """HIL: return True once the ROS graph shows the whole loop (always True otherwise).

        The monitor's own subscriptions (Monitor.connect) do not show that the estimator
        listens to the bridge (ecu/measurements), the ECU to the road, or the recorder
        (which subscribes to the HIL topics once it discovers their types) to all of them;
        the road, which starts the loop, must wait for them too.
        """
        if not self.session.hil:
            return True
        from erva_ros.hil import topics as hil_topics
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
        # The recorder is waited for only after a clean ending (every count in, nothing
        # missing): a node still publishing (safe commands without states) would keep it
        # behind and only add commands to the summary.
        if (not done or not self.recording or 'recorder_node' in self.dead
                or not _all_received(self.monitor)):
            return done
        return elapsed > RECORDER_DRAIN_S or self._recorder_caught_up()

    def _recorder_caught_up(self) -> bool:
        """Return True once the recorder's status counts every message the nodes published."""
        counts = next((self.monitor.diag_values(name) for name in list(self.monitor.diag)
                       if name.endswith(RECORDER_STATUS)), {})
        ns = self.cfg.namespace.rstrip('/')
        for topic, n in self.monitor.published().items():
            if n is None:         # that node's final count is unknown: nothing to wait for
                continue
            name = topic if topic.startswith('/') else f'{ns}/{topic}'
            got = counts.get(f'count:{name}')
            if got is not None and int(got) < n:
                return False
        return bool(counts)

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
        stop_processes([p for n, p in self.procs.items() if n != 'recorder_node'])
        if 'recorder_node' in self.procs:
            stop_processes([self.procs['recorder_node']], grace_s=10.0)
        self.executor.shutdown()
        self.monitor.destroy_node()
        rclpy.try_shutdown(context=self.context)

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
        if summary['commands']['received'] == 0 and not self.caught:
            self.errors.append('no damping commands were received')
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
    sup = _Supervisor(cfg, session, recording, log)
    handlers = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    for sig in handlers:   # Ctrl-C / SIGTERM: stop the nodes cleanly, then summarise
        signal.signal(sig, lambda signum, frame: sup.caught.append(signum))
    try:
        sup.start()
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
        import erva_ros.hil  # noqa: F401  (python-can, cantools, the estimator)
    except ImportError as exc:
        raise CLIError(f'--ecu {ecu} is not available: the HIL modules (erva_ros.hil) do not '
                       f'import ({exc})') from None


__all__ = ['NODES', 'HIL_NODES', 'RunConfig', 'Session', 'RunResult', 'prepare_session',
           'run_session', 'read_live_file', 'validate_live', 'stop_processes', 'NodeProcess',
           'recorder_available', 'ensure_ecu_available', 'default_config_file']
