"""One `erva run` session's processes and phases: start, connect, run, drain, stop, summarise.

:class:`Supervisor` starts the recorder (when recording), the Foxglove server (when
serving) and the loop's processes, each in its own process group
(:mod:`erva_ros.session.processes`); an in-process monitor node
(:class:`~erva_ros.ros.monitor.Monitor`) observes the run.  It waits until the graph
is connected (:class:`~erva_ros.session.run.start_gate.StartGate`), runs the scenario until
every node reports it finished (or a node dies, or SIGINT/SIGTERM arrives), lets the
last diagnostics and the recorder catch up, then stops the nodes with SIGINT (SIGTERM,
SIGKILL after a grace period) and the recorder last, so the bag is finished.
"""

import os
import shutil
import signal
import time
from typing import Any, Dict, List, Optional

from erva_ros.core import topics
from erva_ros.core.bag.session_check import begin_session_end, mark_session_end
from erva_ros.core.errors import CLIError
from erva_ros.ros.context import RosContext
from erva_ros.ros.realtime import set_fifo_priority
from erva_ros.session.run import accounting, foxglove_process, segments
from erva_ros.session.run import hil_summary
from erva_ros.core.reports import FoxgloveReport, RecorderReport
from erva_ros.session.run.accounting import check_recording
from erva_ros.session.run.bringup import Timeline
from erva_ros.session.run.recording import (PROCESS as RECORDER, RECORDER_PRIORITY_BELOW,
                                            RecorderDrain, start_recorder)
from erva_ros.session.processes import (ChildProcess, child_env, node_argv, ros_params,
                                        STOP_GRACE_S, stop_processes, use_session_profile)
from erva_ros.session.run.observations import Observations
from erva_ros.session.run.run_config import (ACTIVATION_ORDER, HIL_NODES, HIL_PROCESSES, NODES,
                                             RunConfig)
from erva_ros.session.run.session_file import Session, session_description
from erva_ros.session.run.start_gate import Contest, extra_nodes, StartGate
from erva_ros.session.run.tuning_schedule import ScheduledChanges
from erva_ros.session.run.verdict import quality_limits, warnings

#: Once the ECU finished (no state comes any more), how long the others may take.
HIL_FINISH_WAIT_S = 2.0
#: HIL: the bridge and the estimator send no final status; after the finish, wait up to
#: this long for their next periodic one (period 0.5 s, config/hil.yaml).
HIL_DRAIN_S = 1.5
#: Exit status of a run stopped by SIGINT / SIGTERM (shell convention 128 + signal).
SIGNAL_EXIT = {signal.SIGINT: 130, signal.SIGTERM: 143}
#: Processes stopped after the loop's nodes: they take what the nodes published.
LAST = (RECORDER, 'foxglove_server')
#: Processes that load their compiled functions as they start, not when configured:
#: started once the session has compiled what the cache lacked (the others before).
COMPILE_AT_START = (hil_summary.ECU,)


class Supervisor:
    """One `erva run` session: the node processes, the monitor, and the run's phases."""

    #: Nodes without which the run cannot go on (lock-step also needs the controller).
    NEEDED = {'plant_sim_node', 'road_preview_node'}
    #: The same in HIL mode (real time only): without the controller the bridge sends
    #: the safe passive command, which is worth seeing.
    HIL_NEEDED = {*HIL_PROCESSES, 'road_preview_node'}

    def __init__(self, cfg: RunConfig, session: Session, recording: bool, log,
                 timeline: Optional[Timeline] = None):
        self.cfg, self.session, self.recording, self.log = cfg, session, recording, log
        self.timeline = timeline or Timeline()
        self.procs: Dict[str, ChildProcess] = {}
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
        self.scenario_done = False  # every node reported the scenario finished
        self._ecu_done: Optional[float] = None
        # The managed nodes, in activation order (run_config.ACTIVATION_ORDER).
        self.managed = [n for n in ACTIVATION_ORDER[session.live['mode']]
                        if n in self.node_names]
        self._to_activate: List[str] = []
        self.scheduled = None        # --set: live changes sent at their samples (connect)
        self.drain = RecorderDrain()
        self.ros = None

    def start(self) -> None:
        """Start the Foxglove server and the recorder (when asked) and the nodes, slowest first.

        They start at once: whether another session runs here is heard while they start
        (:meth:`connect`, :class:`~erva_ros.session.run.start_gate.Contest`), and a session
        that must not run stops them before any is configured.
        """
        env = child_env()
        if self.cfg.foxglove:   # first: it listens before the loop runs
            self._spawned(foxglove_process.PROCESS, foxglove_process.start_process(
                self.cfg, self.session, env, self.log, session_description(self.session)))
        if self.recording:
            self._spawned(RECORDER, start_recorder(
                self.session, self.cfg.namespace, self.cfg.record_dir, env, self.log,
                self.cfg.recorder_overrides))
        hil = {}
        if self.session.hil:
            from erva_ros.session.hil.hil_processes import hil_process_specs
            live = self.session.live
            hil = {spec.name: spec for spec in hil_process_specs(
                self.session.params_file, self.cfg.namespace, live['duration_s'],
                model=live['model'], ts=live['ts'], env=env, stamp_on_road_grid=True,
                realtime_priority=live['realtime_priority'], prefix=self.cfg.ecu_prefix,
                can_log=self.cfg.can_log)}
        self._later = []
        for name in self.node_names:
            spec = hil.get(name)
            if name in COMPILE_AT_START:     # after the session's compile (start_rest)
                self._later.append((name, spec))
                continue
            managed = {'autostart': False} if name in self.managed else None
            argv = spec.argv + ros_params(managed) if spec else node_argv(
                name, self.cfg.namespace, [self.session.params_file],
                managed)
            if not self.session.realtime:   # lock-step: the session's own /clock
                argv += topics.clock_remap(self.cfg.namespace)
            self._spawned(name, ChildProcess(name, argv, spec.env if spec else env,
                                             os.path.join(self.session.directory,
                                                          f'{name}.log')))
        self.timeline.mark('processes started')

    def start_rest(self) -> None:
        """Start the processes that build their compiled functions at once (the ECU)."""
        for name, spec in self._later:
            self._spawned(name, ChildProcess(name, spec.argv, spec.env, os.path.join(
                self.session.directory, f'{name}.log')))
        if self._later:
            self.timeline.mark('ECU simulator started')
        self.log('started ' + ', '.join(f'{n} (pid {p.pid})' for n, p in self.procs.items()))

    def _spawned(self, name: str, proc: ChildProcess) -> None:
        self.procs[name] = proc
        self.timeline.spawn(name)

    def connect(self) -> None:
        """Join the domain while the nodes start: the monitor, the claim, the lifecycle client."""
        from erva_ros.ros.lifecycle import LifecycleDriver
        from erva_ros.ros.monitor import Monitor
        from erva_ros.ros.session_claim import ClaimChannel

        cfg, session = self.cfg, self.session
        self.t_start = time.monotonic()     # the start-up timeout: from here (compiled)
        use_session_profile(os.environ)     # as its nodes: heard, and hearing, at once
        self.ros = RosContext()
        # The monitor subscribes to the time master's gate topic last (see Monitor): the
        # time master starts only once that subscription is matched too.
        gate = (topics.ROAD_PREVIEW,) if session.realtime else (topics.STATE,)
        self.obs = Observations(session.hil, session.sim_window_ns, cfg.namespace,
                                session.session_id, ts=session.live['ts'],
                                n_steps=session.n_steps)
        self.monitor = self.ros.add(Monitor(self.obs, cfg.namespace, context=self.ros.context,
                                            gate=gate))
        self.contest = Contest(session.session_id, cfg.namespace, force=cfg.force,
                               nodes=self.own_node_names())
        self.claims = ClaimChannel(self.monitor, cfg.namespace, self.contest.hear)
        self.claims.publish(self.contest.claim())
        self.gate = StartGate(self.monitor, self.obs, cfg.namespace, self.node_names,
                              session.hil, recording=self.recording,
                              foxglove=bool(cfg.foxglove),
                              extra_readers=[topics.time_master_topics(session.realtime)]
                              * cfg.extra_readers,
                              road_estimated=session.road_estimated,
                              prediction=session.live['publish_prediction'])
        self.lifecycle = LifecycleDriver(self.monitor, self.managed, cfg.namespace)
        if session.steps:
            from erva_ros.ros.param_client import RemoteParameters
            self.scheduled = ScheduledChanges(
                session.steps, RemoteParameters(self.monitor, f'{cfg.namespace}/nmpc_node'),
                not session.realtime, session.live['ts'])
        self.phase = 'looking'
        self.timeline.mark('joined the domain (rclpy, monitor, claim)')

    def own_node_names(self) -> List[str]:
        """Return the ROS node names of this session's processes."""
        names = {RECORDER: 'recorder'}
        return [names.get(n, n) for n in self.procs]

    def observe_at_priority(self) -> None:
        """Run this process (the monitor's DDS threads) at the recorder's priority.

        Called after the nodes are started (children would inherit it).  Under load a
        monitor at normal priority receives late: its timing figures would be the
        machine's, not the loop's.  Without the right it stays at normal priority.
        """
        live = self.session.live
        loop = live['realtime_priority'] if self.session.realtime else 0
        if loop > 1:
            self.scheduling = set_fifo_priority(
                max(1, loop - RECORDER_PRIORITY_BELOW), lambda line: None)

    def supervise(self) -> None:
        """Look, bring up, connect, run, drain: until the scenario ends, a node dies or a signal.

        Raises CLIError (exit 2) if another session runs here (:meth:`_look`).
        """
        last_progress, last_states, finish_seen, finish_ns = time.monotonic(), 0, 0.0, 0
        while True:
            self.ros.spin_once(0.02)
            if self.caught:
                self.errors.append(f'interrupted by {signal.Signals(self.caught[0]).name} '
                                   f'while {self.phase}')
                return
            if self.phase == 'looking':
                self._look()        # before deaths: a refused start is said as such
            if self._check_deaths():
                return
            now = time.monotonic()
            if self.phase == 'looking':
                if self._startup_late(now, 'the nodes\' first statuses'):
                    return
            elif self.phase in ('configuring', 'activating'):
                if self._bring_up(now):
                    return
            elif self.phase == 'connecting':
                if self._connecting(now):
                    return
                if self.phase == 'running':
                    last_progress = now   # the no-progress limit starts when connected
            elif self.phase == 'running':
                if self.scheduled is not None:
                    st = self.obs.streams.state_stamp
                    self.scheduled.poll(st.first, st.last)
                states = self.obs.received[topics.STATE]
                if states and not last_states:
                    self.timeline.mark('first sample')
                if states != last_states:
                    last_states, last_progress = states, now
                if self._finished(now):
                    self.phase, finish_seen, finish_ns = 'draining', now, time.time_ns()
                    self.scenario_done = True
                    self.timeline.mark('scenario finished')
                    continue
                limit = 10.0 + (5.0 if last_states == 0 else 0.0)
                if now - last_progress > limit + self.session.live['start_delay_s']:
                    self.errors.append(f'no progress for {now - last_progress:.0f} s '
                                       f'({last_states} states received)')
                    return
            elif self._drained(now - finish_seen, finish_ns):
                self.timeline.mark('drained (final counts in)')
                return   # drained: the final diagnostics and messages in flight arrived

    def _look(self) -> None:
        """While the nodes start: refuse if another session beats this one; commit once alone.

        Raises CLIError (exit 2) naming the other session
        (:class:`~erva_ros.session.run.start_gate.Contest`).  Commits -- renews the claim as
        bringing up, and moves on to configuring -- once every managed node reported
        with this session's id, its lifecycle services are there, and no node or claim
        of a beaten session is left in the graph.
        """
        if not self.cfg.force:
            winners = self.contest.winners(self.obs.other_sessions)
            if winners:
                raise CLIError(f'another session runs on ROS_DOMAIN_ID '
                               f'{os.environ.get("ROS_DOMAIN_ID", "0")} in namespace '
                               f'{self.cfg.namespace}: {", ".join(winners[:6])}; stop it, use '
                               '--namespace or another ROS_DOMAIN_ID, or --force')
        reported = {name.split(':', 1)[0] for name in self.obs.reports}  # (bridge: 3 reports)
        if not reported.issuperset(self.managed):
            return
        self.timeline.mark('nodes up (first statuses)')
        if not self.lifecycle.ready():
            return
        if self._others_here():
            return
        self.claims.publish(self.contest.commit())
        self.timeline.mark('alone on the namespace (committed)')
        self.phase = 'configuring'

    def _others_here(self) -> List[str]:
        """Return the nodes and claims of other sessions in the graph now ([] with --force).

        Raises CLIError if there are nodes of this session's names that no session
        claims (started by hand, or a --force session's): they would take this
        session's lifecycle requests.
        """
        if self.cfg.force:
            return []
        extra = extra_nodes(self.monitor.get_node_names_and_namespaces(), self.cfg.namespace,
                            self.own_node_names())
        claims = self.claims.others()
        if extra and not claims and self.phase != 'looking':
            raise CLIError(f'another program runs nodes in namespace {self.cfg.namespace}: '
                           f'two of {", ".join(extra)}; the run was not started')
        return extra + ([f'{claims} other session(s) leaving'] if claims else [])

    def _bring_up(self, now: float) -> bool:
        """Configure every managed node, then activate them in order; True: it failed.

        The order: :data:`~erva_ros.session.run.run_config.ACTIVATION_ORDER`.
        """
        lc = self.lifecycle
        for name in lc.pending():
            ok = lc.result(name)
            if ok is False:
                log = self.procs[name].cause()
                self.errors.append(f'{name} refused to {self.phase[:-3] + "e"}'
                                   + (f': {log}' if log else ''))
                return True
        if lc.pending():
            return self._startup_late(now, f'{self.phase} {", ".join(lc.pending())}')
        others = self._others_here()
        if others:     # a session that leaves: its nodes would take the requests too
            return self._startup_late(now, 'another session to leave: ' + ', '.join(others))
        if self.phase == 'configuring':
            if not lc.ready():
                return self._startup_late(now, 'the nodes\' lifecycle services')
            if not self._to_activate:          # not asked yet
                self._to_activate = list(self.managed)
                for name in self.managed:
                    lc.request(name, 'configure')
                return False
            self.phase = 'activating'
            self.timeline.mark('configured')
            self.log(f'configured {", ".join(self.managed)} at {self.timeline.now():.1f} s; '
                     f'activating them in this order')
        if self._to_activate:
            lc.request(self._to_activate.pop(0), 'activate')
            return False
        self.timeline.mark('activated')
        self.phase = 'connecting'
        return False

    def _startup_late(self, now: float, waiting: str) -> bool:
        """Return True (an error recorded) once the start-up took longer than allowed."""
        if now - self.t_start > self.cfg.startup_timeout_s:
            self.errors.append(f'the nodes did not start within '
                               f'{self.cfg.startup_timeout_s:g} s (waiting for: {waiting})')
            return True
        return False

    def _connecting(self, now: float) -> bool:
        """One look at the start gate; return True if the run must stop (it never opened)."""
        if self.gate.open():
            self.phase = 'running'
            self._begin_bag_end()
            t = self.timeline.mark('running (every writer matched its readers)')
            self.log(f'connected in {t:.1f} s; running '
                     f'{self.session.live["duration_s"]:g} s ({self.session.live["mode"]})')
        elif now - self.t_start > 10.0 and not getattr(self, '_told_waiting', False):
            self._told_waiting = True     # say once what a slow start waits for
            self.log('still connecting; waiting for: '
                     + ('; '.join(self.gate.unmatched[:6]) or 'the graph'))
        elif now - self.t_start > self.cfg.startup_timeout_s:
            waiting = '; '.join(self.gate.unmatched[:4]) or 'the monitor\'s subscriptions'
            self.errors.append(f'the nodes did not connect within '
                               f'{self.cfg.startup_timeout_s:g} s (waiting for: {waiting})')
            return True
        return False

    def _finished(self, now: float) -> bool:
        """Return True once every node that reports `finished` did (or died)."""
        def done(name):
            report = self.obs.report(name)
            return name in self.ended or (report is not None and report.finished)
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
            done = elapsed > 1.0 or self.obs.all_received()
        else:
            fresh = all(self.obs.report_rx.get(n, 0) > finish_ns for n in hil_summary.PERIODIC
                        if n.split(':')[0] not in self.dead)
            done = elapsed > HIL_DRAIN_S or (fresh and self.obs.all_received())
        if not done or not self.recording or RECORDER in self.dead:
            return done
        caught_up = self.drain.caught_up(self.obs.reports)
        if self.drain.gave_up and caught_up:
            self.log(self.drain.gave_up)
        return caught_up

    def _check_deaths(self) -> bool:
        """Record nodes that exited on their own; return True if the run must stop."""
        for name, p in self.procs.items():
            if name in self.dead or name in self.ended or p.poll() is None:
                continue
            if name == hil_summary.ECU and p.poll() == 0:
                self.ended.add(name)    # `erva ecu-sim --duration` ends by itself
                continue
            self.dead.add(name)
            where = (f'at t = {self.obs.received[topics.STATE] * self.session.live["ts"]:.2f}'
                     f' s' if self.phase == 'running' else f'while {self.phase}')
            cause = p.cause()
            self.errors.append(f'{name} died (exit status {p.poll()}) {where}'
                               + (f': {cause}' if cause else ''))
            # Without the controller the real-time plant falls back to the plan, then
            # passive damping, which is worth seeing; without the recorder the loop
            # runs on unrecorded.
            goes_on = self.phase == 'running' and name not in self.needed
            self.log(self.errors[-1] + ('; the run goes on without it' if goes_on else ''))
        return bool(self.dead) and (self.phase != 'running' or bool(self.dead & self.needed))

    def stop(self) -> None:
        """Stop the nodes, then the recorder (so it records to the end), then the monitor."""
        ecu = self.procs.get(hil_summary.ECU)
        if ecu is not None and self.ros is not None and hil_summary.ECU in self.obs.finished_rx:
            ecu.wait(STOP_GRACE_S)   # it ends by itself after its last status: let it
            if ecu.poll() == 0:      # print its summary
                self.ended.add(hil_summary.ECU)
        stop_processes([p for n, p in self.procs.items() if n not in LAST])
        self.timeline.mark('nodes stopped')
        # Each node published its final status (its final counts) before it exited: take
        # them, so the summary and the bag check count what was really published.
        if self.ros is not None:
            self._take_pending()
            self.timeline.mark('final statuses taken')
        if any(n in self.procs for n in LAST):
            stop_processes([self.procs[n] for n in LAST if n in self.procs], grace_s=10.0)
            self.timeline.mark('recorder stopped (bag finished)')
        if self.ros is not None:
            self.ros.close()

    def _take_pending(self, quiet_s: float = 0.2, limit_s: float = 3.0) -> None:
        """Spin the monitor until it took every stopped node's final status and all queued.

        Without a final status from each (a node died), until no loop node's message came
        for ``quiet_s``; at most ``limit_s``.  (The recorder and the Foxglove server,
        still running, keep reporting: not counted.)
        """
        def loop_arrivals():
            data = sum(n for t, n in self.obs.received.items() if t != topics.DIAGNOSTICS)
            return data, tuple(self.obs.report_rx[n] for n, r in self.obs.reports.items()
                               if not isinstance(r, (RecorderReport, FoxgloveReport)))
        stopped = [n for n in self.procs if n not in LAST]
        end = time.monotonic() + limit_s
        last, quiet_since = None, time.monotonic()
        while time.monotonic() < end and time.monotonic() - quiet_since < quiet_s:
            self.ros.spin_once(0.02)
            if self._all_final(stopped):
                # Each node exited once its readers acknowledged everything: what is
                # left is in the monitor's queues, taken by spins that wait for nothing.
                idle = 0
                while idle < 5 and time.monotonic() < end:
                    before = loop_arrivals()
                    self.ros.spin_once(0.0)
                    idle = idle + 1 if loop_arrivals() == before else 0
                break
            now = loop_arrivals()
            if now != last:
                last, quiet_since = now, time.monotonic()

    def _all_final(self, names) -> bool:
        """Return True once every report of the processes ``names`` is a final one."""
        reports = [r for key, r in self.obs.reports.items()
                   if key.split(':', 1)[0] in names]
        return bool(reports) and all(r.final for r in reports) and {
            key.split(':', 1)[0] for key in self.obs.reports}.issuperset(names)

    def summary(self) -> Dict[str, Any]:
        """Return the run's summary: the monitor's figures plus scenario, nodes and errors."""
        s = self.session
        summary = self.obs.summary(s.live['ts'], s.n_steps, s.realtime)
        nodes = {}
        for name, p in self.procs.items():
            status = p.poll()
            nodes[name] = {'pid': p.pid, 'exit_status': status, 'died': name in self.dead,
                           'stopped_cleanly': status == 0 and (p.stopped_by_us
                                                               or name in self.ended),
                           'log': p.log_path}
            # A recorder whose bag failed exits 1: said once, by the recording check.
            bag_failed = name == RECORDER and bool(getattr(
                accounting.recorder_report(self.obs.reports), 'error', ''))
            if name not in self.dead and status != 0 and not bag_failed:
                cause = p.cause()
                self.errors.append(f'{name} did not stop cleanly (exit status {status})'
                                   + (f': {cause}' if cause else ''))
        if RECORDER in self.procs:
            summary['bag'] = self.procs[RECORDER].bag_dir
            summary['recording'] = self._check_recording()
            self.timeline.mark('bag read back and checked')
        if 'foxglove_server' in self.procs:
            summary['foxglove'] = foxglove_process.summary(self.obs.reports)
        summary['tuning'] = self._tuning()
        if summary['commands']['received'] == 0 and not self.caught:
            self.errors.append('no damping commands were received')
        self._check_rejections(summary)
        summary['warnings'] = []
        if s.realtime:
            summary['warnings'] = warnings(self.obs, summary, quality_limits())
            if self.cfg.strict:     # --strict: a run that was not real time fails
                self.errors += [f'{w} (--strict)' for w in summary['warnings']]
        if RECORDER in self.procs:     # also with the recorder dead or its disk full
            self._mark_bag_end(summary['bag'])
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
        self.timeline.mark('summary')
        summary['timing'] = self.timeline.as_dict(self.process_reports())
        return summary

    def _begin_bag_end(self) -> None:
        """Reserve the bag's end record as the loop starts (session_check.begin_session_end)."""
        if RECORDER in self.procs and RECORDER not in self.dead:
            try:
                begin_session_end(self.procs[RECORDER].bag_dir)
            except OSError as exc:
                self.log(f'could not reserve the session\'s end record in the bag: {exc}')

    def _tuning(self) -> Dict[str, Any]:
        """Return the run's segments by parameter set (and the --set requests' outcome)."""
        st = self.obs.streams
        tr, n = st.trajectory, st.trajectory.rows
        segs = segments.from_sets(self.obs.parameter_sets.sets, st.state_stamp.first or 0,
                                  tr.stamp[:n], tr.sprung_accel[:n], tr.power[:n],
                                  self.session.live['ts'])
        out = segments.block(segs, complete=n == st.accels)
        if self.scheduled is not None:
            out['set'] = self.scheduled.results()
            nmpc = self.obs.report('nmpc_node')
            out['hold_timeouts'] = None if nmpc is None else nmpc.hold_timeouts
            self.errors += self.scheduled.errors(out['hold_timeouts'])
        return out

    def process_reports(self) -> Dict[str, Any]:
        """Return the newest report of each started process, by its process name."""
        out = {name: self.obs.report(name) or next(
            (r for key, r in sorted(self.obs.reports.items())
             if key.split(':', 1)[0] == name), None) for name in self.procs}
        if RECORDER in self.procs:
            out[RECORDER] = accounting.recorder_report(self.obs.reports)
        return {name: r for name, r in out.items() if r is not None}

    def discard_bag(self) -> None:
        """Remove the bag of a session that was refused (its recorder stopped)."""
        rec = self.procs.get(RECORDER)
        if rec is not None:
            shutil.rmtree(rec.bag_dir, ignore_errors=True)

    def _mark_bag_end(self, bag_dir: str) -> None:
        """Record in the bag whether the session ran to its end (else why not)."""
        why = self.errors[0] if self.errors else (
            '' if self.scenario_done else f'stopped while {self.phase}')
        for line in mark_session_end(bag_dir, completed=self.scenario_done and not self.errors,
                                     reason=why, loop_start_ns=self.obs.first_sample_ns,
                                     yielded=self.contest.yielded(self.obs.other_sessions)):
            self.log(f'could not record the session\'s end: {line}')

    def _check_rejections(self, summary: Dict[str, Any]) -> None:
        """Fail the run if rejected inputs cost the loop a sample of control."""
        m = summary['messages']
        error = accounting.rejections_cost(m['rejected_total'], self.obs.report('nmpc_node'),
                                           m['foreign_total'])
        if error:
            self.errors.append(error)

    def _check_recording(self) -> Dict[str, Any]:
        """Compare the bag with what every node published; add an error per loss."""
        # Stamps outside `erva run`'s lifetime (realtime), or the simulated span
        # (lock-step), are not the loop's.
        window = self.session.sim_window_ns or (self.t_start_ns, time.time_ns())
        report, errors = check_recording(self.procs[RECORDER].bag_dir, self.obs.reports,
                                         window, self.session.session_id)
        if self.drain.gave_up:
            report = {'gave_up': self.drain.gave_up, **report}
        self.errors += errors
        return report

    def exit_code(self) -> int:
        """Return 128 + signal if interrupted, 1 on any error, else 0."""
        if self.caught:
            return SIGNAL_EXIT.get(self.caught[0], 1)
        return 1 if self.errors else 0


__all__ = ['Supervisor', 'SIGNAL_EXIT', 'HIL_FINISH_WAIT_S', 'HIL_DRAIN_S']
