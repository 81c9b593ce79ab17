"""`erva run`: start the live system as separate processes, run one scenario, stop, summarise.

:func:`run_session` does, in order:

1. validates every value in-process first and writes the session's params file
   (:func:`erva_ros.session.run.session_file.prepare_session`), so a bad option fails with
   one line before any process starts;
2. starts the processes below at once, and while they start compiles what the nodes
   will load and the cache lacks, one line per part (:mod:`erva_ros.session.run.warmup`):
   no node is configured before, so no node's start-up timeout is spent compiling;
3. starts an in-process monitor node (:class:`~erva_ros.ros.monitor.Monitor`), the
   recorder (when recording, :mod:`erva_ros.session.run.recording`), nmpc_node,
   plant_sim_node and road_preview_node, each as ``python -m erva_ros.nodes.<name>
   --ros-args -r __ns:=<ns> --params-file F`` in its own process group (and with a
   parent-death signal, so no node outlives `erva run`; :mod:`erva_ros.session.processes`);
4. hears, while they start, whether another session runs on the namespace (the first
   to start runs, the other refuses: :class:`erva_ros.session.run.start_gate.Contest`),
   configures and activates the nodes,
   waits until the graph is connected (:mod:`erva_ros.session.run.start_gate`), runs the
   scenario until every node reports it finished (or a node dies, or SIGINT/SIGTERM
   arrives), lets the last diagnostics arrive, then stops the nodes with SIGINT
   (SIGTERM, SIGKILL after a grace period) and the recorder last, so the bag is
   finished (:class:`~erva_ros.session.run.supervisor.Supervisor`);
5. returns the summary (comfort and power, command rate, jitter and latency,
   solve times, deadline misses, fallbacks, dropped and rejected messages).

With ``ecu='virtual'`` (hardware-in-the-loop, real time only) the processes of
:func:`erva_ros.session.hil.hil_processes.hil_process_specs` take plant_sim_node's place:
``erva ecu-sim`` (plant + simulated ECU on a loopback-UDP CAN bus; it ends by itself
after the scenario), ecu_bridge_node and state_estimator_node, so the loop is NMPC →
bridge → CAN → ECU → CAN → bridge → estimator → NMPC.  The recorder also records the
HIL topics, and the summary gets a ``hil`` block (:mod:`erva_ros.session.run.hil_summary`).
"""

from dataclasses import dataclass
import os
import shutil
import signal
from typing import Any, Callable, Dict, Optional

from erva_ros.core.errors import CLIError
from erva_ros.core.model.params import ParamError
from erva_ros.ros.context import check_domain_id
from erva_ros.session.run.bringup import Timeline
from erva_ros.session.run.recording import check_record_dir, recorder_available
from erva_ros.session.run.run_config import RunConfig
from erva_ros.session.run.session_file import prepare_session, Session
from erva_ros.session.run.session_dirs import FAILED_NOTE
from erva_ros.session.run.supervisor import Supervisor
from erva_ros.session.run.warmup import warm_session


@dataclass
class RunResult:
    """What a session produced: the summary, the exit status and the sampled trajectory."""

    summary: Dict[str, Any]
    exit_code: int
    trajectory: Dict[str, Any]
    session: Optional[Session] = None


def run_session(cfg: RunConfig, log: Callable[[str], None] = lambda s: None,
                timeline: Optional[Timeline] = None) -> RunResult:
    """Run one scenario (see module doc); ``log`` gets progress lines for stderr.

    ``timeline`` gets each stage's time (``erva run --timing``).  A refused run (bad
    input, another session here: CLIError/ParamError, exit 2) leaves nothing behind:
    no temporary session directory, no bag.
    """
    timeline = timeline or Timeline()
    check_domain_id()           # before anything is written
    recording = cfg.record_dir is not None and recorder_available()
    if cfg.record_dir is not None and not recording:
        log('recorder not available yet: summary only')
    session = prepare_session(cfg, recording)
    timeline.mark('options checked, session params file written')
    try:
        if recording:       # after every other check: a refused run leaves no bags dir
            check_record_dir(cfg.record_dir)
        sup = _supervise(cfg, session, recording, log, timeline)
    except (CLIError, ParamError):
        if cfg.session_dir is None:     # refused: nothing to keep
            shutil.rmtree(session.directory, ignore_errors=True)
        raise
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
        # Kept to look into (the next run's clean-up of stale directories leaves it).
        with open(os.path.join(session.directory, FAILED_NOTE), 'w', encoding='utf-8') as fh:
            fh.write('\n'.join(summary['errors']) + '\n')
        log(f'node logs and the session params file are in {session.directory}')
    return RunResult(summary, code, sup.obs.trajectory(session.n_steps), session)


def _supervise(cfg: RunConfig, session: Session, recording: bool,
               log: Callable[[str], None], timeline: Timeline) -> Supervisor:
    """Start, look, bring up, run and stop the session; return its supervisor.

    A session refused while its nodes start (another session here: CLIError) stops
    them and removes the bag its recorder began.
    """
    sup = Supervisor(cfg, session, recording, log, timeline)
    handlers = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    for sig in handlers:   # Ctrl-C / SIGTERM: stop the nodes cleanly, then summarise
        signal.signal(sig, lambda signum, frame: sup.caught.append(signum))
    refused = False
    try:
        sup.start()
        # While the nodes start (imports), not before: none is configured -- none loads
        # a compiled function -- until this is done, so no node's start-up timeout is
        # spent compiling, and on a warm cache it costs no wall time.
        warm_session(session, log)
        timeline.mark('compiled functions found in the cache')
        sup.start_rest()
        sup.connect()
        sup.observe_at_priority()
        sup.supervise()
    except CLIError:
        refused = True
        raise
    finally:
        sup.stop()
        for sig, handler in handlers.items():
            signal.signal(sig, handler)
        if refused:
            sup.discard_bag()
    return sup


__all__ = ['RunResult', 'run_session']
