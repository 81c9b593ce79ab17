"""One `erva run` session's processes and phases: start, connect, run, drain, stop, summarise.

:class:`Supervisor` starts the recorder (when recording), the Foxglove server (when
serving) and the loop's processes, each in its own process group
(:mod:`erva_ros.session.processes`); an in-process monitor node
(:class:`~erva_ros.ros.monitor.Monitor`) observes the run.  It waits until the graph
is connected (:class:`~erva_ros.session.start_gate.StartGate`), runs the scenario until
every node reports it finished (or a node dies, or SIGINT/SIGTERM arrives), lets the
last diagnostics and the recorder catch up, then stops the nodes with SIGINT (SIGTERM,
SIGKILL after a grace period) and the recorder last, so the bag is finished.
"""

import os
import signal
import time
from typing import Any, Dict, List, Optional

from erva_ros.core import topics
from erva_ros.core.errors import CLIError
from erva_ros.session import accounting, hil_summary
from erva_ros.core.reports import FoxgloveReport, RecorderReport
from erva_ros.session.accounting import check_recording
from erva_ros.session.recording import (PROCESS as RECORDER, RECORDER_PRIORITY_BELOW,
                                        RecorderDrain, start_recorder)
from erva_ros.session.processes import (ChildProcess, child_env, node_argv, ros_params,
                                        STOP_GRACE_S, stop_processes)
from erva_ros.session.run_config import (ACTIVATION_ORDER, HIL_NODES, HIL_PROCESSES, NODES,
                                         RunConfig)
from erva_ros.session.session_file import Session, session_description

#: Once the ECU finished (no state comes any more), how long the others may take.
HIL_FINISH_WAIT_S = 2.0
#: HIL: the bridge and the estimator send no final status; after the finish, wait up to
#: this long for their next periodic one (period 0.5 s, config/hil.yaml).
HIL_DRAIN_S = 1.5
#: Exit status of a run stopped by SIGINT / SIGTERM (shell convention 128 + signal).
SIGNAL_EXIT = {signal.SIGINT: 130, signal.SIGTERM: 143}
#: Processes stopped after the loop's nodes: they take what the nodes published.
LAST = (RECORDER, 'foxglove_server')


class Supervisor:
    """One `erva run` session: the node processes, the monitor, and the run's phases."""

    #: Nodes without which the run cannot go on (lock-step also needs the controller).
    NEEDED = {'plant_sim_node', 'road_preview_node'}
    #: The same in HIL mode (real time only): without the controller the bridge sends
    #: the safe passive command, which is worth seeing.
    HIL_NEEDED = {*HIL_PROCESSES, 'road_preview_node'}

    def __init__(self, cfg: RunConfig, session: Session, recording: bool, log):
        from erva_ros.ros.context import RosContext
        from erva_ros.ros.monitor import Monitor
        from erva_ros.session.observations import Observations
        from erva_ros.session.start_gate import StartGate

        self.cfg, self.session, self.recording, self.log = cfg, session, recording, log
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
        self.ros = RosContext()
        # The monitor subscribes to the time master's gate topic last (see Monitor): the
        # time master starts only once that subscription is matched too.
        gate = (topics.ROAD_PREVIEW,) if session.realtime else (topics.STATE,)
        self.obs = Observations(session.hil, session.sim_window_ns, cfg.namespace,
                                session.session_id, ts=session.live['ts'],
                                n_steps=session.n_steps)
        self.monitor = self.ros.add(Monitor(self.obs, cfg.namespace, context=self.ros.context,
                                            gate=gate))
        self.gate = StartGate(self.monitor, self.obs, cfg.namespace, self.node_names,
                              session.hil, recording, bool(cfg.foxglove),
                              [topics.time_master_topics(session.realtime)] * cfg.extra_readers,
                              road_estimated=session.road_estimated,
                              prediction=session.live['publish_prediction'])
        self.drain = RecorderDrain()
        # The managed nodes, in activation order (run_config.ACTIVATION_ORDER).
        from erva_ros.ros.lifecycle import LifecycleDriver
        self.managed = [n for n in ACTIVATION_ORDER[session.live['mode']]
                        if n in self.node_names]
        self.lifecycle = LifecycleDriver(self.monitor, self.managed, cfg.namespace)
        self._to_activate: List[str] = []
        self.scheduled = None        # --set: live changes sent at their samples
        if session.steps:
            from erva_ros.ros.param_client import RemoteParameters
            from erva_ros.session.tuning_schedule import ScheduledChanges
            self.scheduled = ScheduledChanges(
                session.steps, RemoteParameters(self.monitor, f'{cfg.namespace}/nmpc_node'),
                not session.realtime, session.live['ts'])

    def start(self) -> None:
        """Start the recorder (when recording) and the nodes, slowest first.

        Unless ``--force``, refuses first (CLIError, exit 2) if another session runs on
        this domain and namespace: two loops on the same topics merge and each bag holds
        both.
        """
        if not self.cfg.force:
            from erva_ros.session.start_gate import LOOK_S, other_session
            others = other_session(self.monitor, self.obs, self.cfg.namespace,
                                   self.ros.spin_once, self.t_start + LOOK_S)
            if others:
                raise CLIError(f'another session runs on ROS_DOMAIN_ID '
                               f'{os.environ.get("ROS_DOMAIN_ID", "0")} in namespace '
                               f'{self.cfg.namespace}: {", ".join(others[:6])}; stop it, use '
                               '--namespace or another ROS_DOMAIN_ID, or --force')
        env = child_env()
        if self.cfg.foxglove:   # first: it listens before the loop runs
            from erva_ros.session import foxglove_process
            self.procs[foxglove_process.PROCESS] = foxglove_process.start_process(
                self.cfg, self.session, env, self.log, session_description(self.session))
        if self.recording:
            self.procs[RECORDER] = start_recorder(
                self.session, self.cfg.namespace, self.cfg.record_dir, env, self.log,
                self.cfg.recorder_overrides)
        hil = {}
        if self.session.hil:
            from erva_ros.session.hil_processes import hil_process_specs
            live = self.session.live
            hil = {spec.name: spec for spec in hil_process_specs(
                self.session.params_file, self.cfg.namespace, live['duration_s'],
                model=live['model'], ts=live['ts'], env=env, stamp_on_road_grid=True,
                realtime_priority=live['realtime_priority'], prefix=self.cfg.ecu_prefix,
                can_log=self.cfg.can_log)}
        for name in self.node_names:
            spec = hil.get(name)
            managed = {'autostart': False} if name in self.managed else None
            argv = spec.argv + ros_params(managed) if spec else node_argv(
                name, self.cfg.namespace, [self.session.params_file],
                managed)
            if not self.session.realtime:   # lock-step: the session's own /clock
                argv += topics.clock_remap(self.cfg.namespace)
            self.procs[name] = ChildProcess(name, argv, spec.env if spec else env,
                                            os.path.join(self.session.directory, f'{name}.log'))
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
            self.scheduling = set_fifo_priority(
                max(1, loop - RECORDER_PRIORITY_BELOW), lambda line: None)

    def supervise(self) -> None:
        """Bring up, connect, run and drain, until the scenario ends, a node dies or a signal."""
        self.phase = 'configuring'
        last_progress, last_states, finish_seen, finish_ns = time.monotonic(), 0, 0.0, 0
        while True:
            self.ros.spin_once(0.02)
            if self.caught:
                self.errors.append(f'interrupted by {signal.Signals(self.caught[0]).name} '
                                   f'while {self.phase}')
                return
            if self._check_deaths():
                return
            now = time.monotonic()
            if self.phase in ('configuring', 'activating'):
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
                if states != last_states:
                    last_states, last_progress = states, now
                if self._finished(now):
                    self.phase, finish_seen, finish_ns = 'draining', now, time.time_ns()
                    self.scenario_done = True
                    continue
                limit = 10.0 + (5.0 if last_states == 0 else 0.0)
                if now - last_progress > limit + self.session.live['start_delay_s']:
                    self.errors.append(f'no progress for {now - last_progress:.0f} s '
                                       f'({last_states} states received)')
                    return
            elif self._drained(now - finish_seen, finish_ns):
                return   # drained: the final diagnostics and messages in flight arrived

    def _bring_up(self, now: float) -> bool:
        """Configure every managed node, then activate them in order; True: it failed.

        The order: :data:`~erva_ros.session.run_config.ACTIVATION_ORDER`.
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
        if self.phase == 'configuring':
            if not lc.ready():
                return self._startup_late(now, 'the nodes\' lifecycle services')
            if not self._to_activate:          # not asked yet
                self._to_activate = list(self.managed)
                for name in self.managed:
                    lc.request(name, 'configure')
                return False
            self.phase = 'activating'
            self.log(f'configured {", ".join(self.managed)} in {now - self.t_start:.1f} s; '
                     f'activating them in this order')
        if self._to_activate:
            lc.request(self._to_activate.pop(0), 'activate')
            return False
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
        twins = self.gate.twins()
        if twins:   # another session started here too: neither loop may start
            self.errors.append(f'another session runs in namespace {self.cfg.namespace}: '
                               f'two of {", ".join(twins)}; the run was not started')
            return True
        if self.gate.open():
            self.phase = 'running'
            self._begin_bag_end()
            self.log(f'connected in {now - self.t_start:.1f} s; running '
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
        if ecu is not None and hil_summary.ECU in self.obs.finished_rx:
            ecu.wait(STOP_GRACE_S)   # it ends by itself after its last status: let it
            if ecu.poll() == 0:      # print its summary
                self.ended.add(hil_summary.ECU)
        stop_processes([p for n, p in self.procs.items() if n not in LAST])
        # Each node published its final status (its final counts) before it exited: take
        # them, so the summary and the bag check count what was really published.
        self._take_pending()
        if any(n in self.procs for n in LAST):
            stop_processes([self.procs[n] for n in LAST if n in self.procs], grace_s=10.0)
        self.ros.close()

    def _take_pending(self, quiet_s: float = 0.2, limit_s: float = 3.0) -> None:
        """Spin the monitor until no loop node's message came for ``quiet_s`` (<= ``limit_s``).

        (The recorder and the Foxglove server, still running, keep reporting: not counted.)
        """
        def loop_arrivals():
            data = sum(n for t, n in self.obs.received.items() if t != topics.DIAGNOSTICS)
            return data, tuple(self.obs.report_rx[n] for n, r in self.obs.reports.items()
                               if not isinstance(r, (RecorderReport, FoxgloveReport)))
        end = time.monotonic() + limit_s
        last, quiet_since = None, time.monotonic()
        while time.monotonic() < end and time.monotonic() - quiet_since < quiet_s:
            self.ros.spin_once(0.02)
            now = loop_arrivals()
            if now != last:
                last, quiet_since = now, time.monotonic()

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
        if 'foxglove_server' in self.procs:
            from erva_ros.session import foxglove_process
            summary['foxglove'] = foxglove_process.summary(self.obs.reports)
        summary['tuning'] = self._tuning()
        if summary['commands']['received'] == 0 and not self.caught:
            self.errors.append('no damping commands were received')
        self._check_rejections(summary)
        summary['warnings'] = []
        if s.realtime:
            from erva_ros.session.verdict import quality_limits, warnings
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
        return summary

    def _begin_bag_end(self) -> None:
        """Reserve the bag's end record as the loop starts (session_check.begin_session_end)."""
        from erva_ros.core.bag.session_check import begin_session_end
        if RECORDER in self.procs and RECORDER not in self.dead:
            try:
                begin_session_end(self.procs[RECORDER].bag_dir)
            except OSError as exc:
                self.log(f'could not reserve the session\'s end record in the bag: {exc}')

    def _tuning(self) -> Dict[str, Any]:
        """Return the run's segments by parameter set (and the --set requests' outcome)."""
        from erva_ros.session import segments
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

    def _mark_bag_end(self, bag_dir: str) -> None:
        """Record in the bag whether the session ran to its end (else why not)."""
        from erva_ros.core.bag.session_check import mark_session_end
        why = self.errors[0] if self.errors else (
            '' if self.scenario_done else f'stopped while {self.phase}')
        for line in mark_session_end(bag_dir, completed=self.scenario_done and not self.errors,
                                     reason=why):
            self.log(f'could not record the session\'s end: {line}')

    def _check_rejections(self, summary: Dict[str, Any]) -> None:
        """Fail the run if rejected inputs cost the loop a sample of control."""
        error = accounting.rejections_cost(summary['messages']['rejected_total'],
                                           self.obs.report('nmpc_node'))
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
