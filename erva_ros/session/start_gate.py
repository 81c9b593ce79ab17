"""When an `erva run` session may start: every writer matched every reader it will have.

The time master starts sample 0 once its topics have ``wait_for_subscribers`` readers,
one of them the monitor's (``wait_for_reader``, :mod:`erva_ros.ros.time_master`);
before the monitor opens that last subscription (:meth:`Monitor.connect`), every
other loop writer must have matched all its subscribers -- the loop's own nodes, the
monitor, the recorder and the Foxglove server -- and the recorder every writer it
records (:mod:`erva_ros.session.accounting`).  In HIL mode the ROS graph must also show
the whole loop (:meth:`StartGate.graph_ready`).
"""

import time
from typing import Callable, Dict, List, Sequence

from erva_ros.core import topics
from erva_ros.session import accounting, hil_summary
from erva_ros.session.accounting import recorder_report
from erva_ros.session.recording import record_topics, record_writers


class StartGate:
    """What the session waits for before the loop runs (see the module doc)."""

    def __init__(self, monitor, obs, namespace: str, node_names: Sequence[str], hil: bool,
                 recording: bool, foxglove: bool, extra_readers: Sequence[Sequence[str]] = (),
                 road_estimated: bool = False, prediction: bool = True):
        self.monitor = monitor
        self.obs = obs
        self.namespace = namespace
        self.node_names = tuple(node_names)
        self.hil, self.recording = hil, recording
        #: What is still missing, for the user (the newest check).
        self.unmatched: List[str] = []
        self.road_estimated = road_estimated
        loop = (accounting.hil_loop_subscribers(road_estimated) if hil
                else dict(accounting.LOOP_SUBSCRIBERS))
        # The user's readers (`--extra-readers`) count on the time master's topics: the
        # loop's own readers must still all be matched, not stood in for by one of them.
        observers = [obs.watched, *extra_readers]
        record = record_topics(hil, road_estimated, prediction)
        if foxglove:
            observers.append(record)   # the server serves what is recorded
        self.record_writers: Dict[str, int] = {}
        if recording:
            observers.append(record)
            self.record_writers = record_writers(
                record, namespace, len(self.node_names) + 1 + (1 if foxglove else 0))
        self.expected = accounting.expected_subscribers(loop, observers, namespace)
        # Before the monitor's gate subscription exists (it opens the start), the gate
        # topic's writer needs one subscriber less.
        self.later = {accounting.qualify(t, namespace): 1 for t in monitor.gate}

    def open(self) -> bool:
        """Return True once the loop may start (call repeatedly while connecting)."""
        return (self.graph_ready() and self.matched()
                and self.monitor.connect(n_diagnostics=len(self.node_names)))

    def matched(self) -> bool:
        """Return True once every loop writer and the recorder have matched all their peers."""
        reports = self.obs.reports
        # The ECU simulator reports only once the road runs (its readers are checked by
        # graph_ready): every other node must have said what its writers matched.
        nodes = [n for n in self.node_names if n != hil_summary.ECU]
        nodes += ['recorder'] if self.recording else []
        missing = accounting.unmatched(reports, nodes, self.expected, self.later)
        if self.recording:
            missing += accounting.recorder_unmatched(recorder_report(reports),
                                                     self.record_writers)
        self.unmatched = missing
        return not missing

    def twins(self) -> List[str]:
        """Return the session nodes the ROS graph shows twice in the namespace.

        Another session started here after this one looked for it.
        """
        ns = self.namespace.rstrip('/') or '/'
        names = [name for name, node_ns in self.monitor.get_node_names_and_namespaces()
                 if node_ns == ns]
        return [f'{ns.rstrip("/")}/{n}' for n in SESSION_NODES if names.count(n) > 1]

    def graph_ready(self) -> bool:
        """HIL: return True once the ROS graph shows the whole loop (always True otherwise).

        The monitor's own subscriptions (Monitor.connect) do not show that the estimator
        listens to the bridge (ecu/measurements), the ECU to the road, or the recorder
        (which subscribes to the HIL topics once it discovers their types) to all of them;
        the road, which starts the loop, must wait for them too.
        """
        if not self.hil:
            return True
        from erva_ros.core.hil import topics as hil_topics
        ns = self.namespace.rstrip('/')
        m, rec = self.monitor, int(self.recording)
        ecu = (hil_topics.ECU_DAMPING_APPLIED, hil_topics.ECU_SPRUNG_ACCEL,
               hil_topics.ECU_SUSPENSION, hil_topics.ECU_GENERATOR)
        subs = {topics.ROAD_HEIGHT: 2 + rec,      # ECU, estimator (the monitor comes last)
                # estimated road: the ECU and the monitor; the map preview its estimate
                **({topics.ROAD_ESTIMATE: 1 + rec} if self.road_estimated else {}),
                topics.DAMPING_CMD: 2 + rec,      # bridge, monitor
                topics.STATE: 2 + rec,            # nmpc, monitor
                hil_topics.TRUE_STATE: 1 + rec,   # monitor
                hil_topics.ECU_MEASUREMENTS: 1 + rec,   # estimator
                **{t: rec for t in ecu}}          # per-frame topics: only recorded
        published = ecu + (hil_topics.ECU_MEASUREMENTS,)
        return (all(m.count_subscribers(f'{ns}/{t}') >= n for t, n in subs.items())
                and all(m.count_publishers(f'{ns}/{t}') >= 1 for t in published))


#: Node names of an erva session (the loop, its HIL stand-ins, the session's own nodes).
SESSION_NODES = ('nmpc_node', 'plant_sim_node', 'road_preview_node', 'ecu_bridge_node',
                 'state_estimator_node', 'ecu_sim', 'recorder', 'foxglove_server',
                 topics.MONITOR_NODE)
#: How long `erva run` looks for another session before it starts its own (s), from the
#: moment its monitor joined the domain: discovery on one host took up to 1.3 s on a
#: loaded 2-core machine, and a session's nodes report on /diagnostics every 0.5 s.
LOOK_S = 3.0


def other_session(monitor, obs, namespace: str, spin: Callable[[float], None],
                  until: float) -> List[str]:
    """Return the nodes of another live session on this domain and namespace ([]: none).

    Looks at the ROS graph (nodes with a session's names in ``namespace``) and at
    /diagnostics (statuses from ``namespace`` with another session's id:
    :attr:`Observations.other_sessions`) until monotonic time ``until``.
    """
    ns = namespace.rstrip('/') or '/'
    end = until
    seen = None
    while True:
        found = sorted({f'{node_ns.rstrip("/")}/{name}'
                        for name, node_ns in monitor.get_node_names_and_namespaces()
                        if node_ns == ns and name in SESSION_NODES
                        and name != topics.MONITOR_NODE})
        found += [f'{ns.rstrip("/")}/{name} (session {sid or "?"})'
                  for name, sid in sorted(obs.other_sessions.items())
                  if f'{ns.rstrip("/")}/{name}' not in found]
        now = time.monotonic()
        if found and seen is None:      # name all of them: discovery comes in pieces
            seen, end = now, min(end, now + 0.5)
        if now > end:
            return found
        spin(0.05)


__all__ = ['StartGate', 'SESSION_NODES', 'other_session']
