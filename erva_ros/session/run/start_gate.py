"""When an `erva run` session may start: alone here, and every writer matched every reader.

Of sessions started on one namespace, the first runs and the others refuse
(:class:`Contest`).

The time master starts sample 0 once its topics have ``wait_for_subscribers`` readers,
one of them the monitor's (``wait_for_reader``, :mod:`erva_ros.ros.time_master`);
before the monitor opens that last subscription (:meth:`Monitor.connect`), every
other loop writer must have matched all its subscribers -- the loop's own nodes, the
monitor, the recorder and the Foxglove server -- and the recorder every writer it
records (:mod:`erva_ros.session.run.accounting`).  In HIL mode the ROS graph must also show
the whole loop (:meth:`StartGate.graph_ready`).
"""

import os
import time
from typing import Callable, Dict, List, Mapping, Sequence, Tuple

from erva_ros.core import topics
from erva_ros.core.contract import decode_diagnostics, encode_diagnostics, MessageRejected
from erva_ros.core.hil import topics as hil_topics
from erva_ros.core.reports import report_from_status, report_status, SessionClaim
from erva_ros.session.run import accounting
from erva_ros.session.run import hil_summary
from erva_ros.session.run.accounting import recorder_report
from erva_ros.session.run.recording import record_topics, record_writers


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

    def graph_ready(self) -> bool:
        """HIL: return True once the ROS graph shows the whole loop (always True otherwise).

        The monitor's own subscriptions (Monitor.connect) do not show that the estimator
        listens to the bridge (ecu/measurements), the ECU to the road, or the recorder
        (which subscribes to the HIL topics once it discovers their types) to all of them;
        the road, which starts the loop, must wait for them too.
        """
        if not self.hil:
            return True
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


class Contest:
    """Which of the sessions that start on one namespace runs: the one that started first.

    There is no fixed look for another session: `erva run` starts its processes at once
    and, while they start, hears what the domain says -- every node's status names its
    session (ids sort by start, :func:`erva_ros.session.run.session_file.new_session_id`),
    and every session claims its namespace (:class:`erva_ros.ros.session_claim.ClaimChannel`,
    transient local: heard as soon as discovery matches it).  Another session *beats*
    this one if it started earlier, if it already brings its nodes up or runs
    (``committed``), if it runs with ``--force``, or if it is no session at all (nodes
    started by hand report the id '').  A beaten session refuses (exit 2) and stops what
    it started; the other waits until the beaten one's nodes and claim are gone before
    it asks its own nodes for any lifecycle transition -- two nodes of one name share
    the request -- and then commits.
    """

    def __init__(self, session_id: str, namespace: str, force: bool = False,
                 nodes: Sequence[str] = (), clock: Callable[[], int] = time.time_ns):
        ns = namespace.rstrip('/')
        self.own = SessionClaim(node=f'{ns}/{topics.MONITOR_NODE}', session=session_id,
                                claimed_ns=clock(), pid=os.getpid(), force=force,
                                nodes=','.join(nodes))
        self._clock = clock
        #: The newest claim of every other session heard, by session id.
        self.heard: Dict[str, SessionClaim] = {}

    def claim(self) -> bytes:
        """Return this session's claim as a DiagnosticArray (CDR)."""
        self.own.status_seq += 1
        return encode_diagnostics(self._clock(), [report_status(self.own)])

    def commit(self) -> bytes:
        """Mark this session as bringing its nodes up; return its renewed claim."""
        self.own.committed = True
        return self.claim()

    def hear(self, data: bytes) -> None:
        """Take a claim heard on the claim topic (this session's own is ignored)."""
        try:
            _, statuses = decode_diagnostics(data)
        except MessageRejected:
            return
        for status in statuses:
            claim = report_from_status(status)
            if isinstance(claim, SessionClaim) and claim.session != self.own.session:
                self.heard[claim.session] = claim

    def beats(self, session_id: str) -> bool:
        """Return True if the session ``session_id`` runs rather than this one (class doc)."""
        if self.own.force or self.own.committed:
            return False
        claim = self.heard.get(session_id)
        return (not session_id or session_id < self.own.session
                or (claim is not None and (claim.committed or claim.force)))

    def yielded(self, statuses: Mapping[str, str] = ()) -> List[str]:
        """Return the ids of the sessions that stood down for this one.

        Those that started later, heard by their claims or by their nodes' statuses
        (``statuses``: node name -> session id; a session may stand down before its
        claim reaches this one), and that did not claim to bring nodes up or --force.
        """
        ids = set(self.heard) | set(dict(statuses).values())
        unheard = SessionClaim()
        return sorted(sid for sid in ids if sid > self.own.session
                      and not (self.heard.get(sid, unheard).committed
                               or self.heard.get(sid, unheard).force))

    def winners(self, statuses: Mapping[str, str]) -> List[str]:
        """Return who beats this session: nodes (name -> session id heard) and claims."""
        ns = self.own.node.rsplit('/', 1)[0]
        out = [f'{ns}/{name} (session {sid or "none"})'
               for name, sid in sorted(statuses.items()) if self.beats(sid)]
        named = set(statuses.values())
        out += [f'session {sid} (pid {c.pid}{", running" if c.committed else ""})'
                + ''.join(f' {ns}/{n}' for n in c.nodes.split(',') if n)
                for sid, c in sorted(self.heard.items())
                if sid not in named and self.beats(sid)]
        return out


def extra_nodes(graph: Sequence[Tuple[str, str]], namespace: str, own: Sequence[str]
                ) -> List[str]:
    """Return the session nodes the graph shows in ``namespace`` beyond this session's own.

    ``graph`` is (name, namespace) of every node; ``own`` the node names of this session.
    """
    ns = namespace.rstrip('/') or '/'
    names = [name for name, node_ns in graph if node_ns == ns and name in SESSION_NODES
             and name != topics.MONITOR_NODE]
    return [f'{ns.rstrip("/")}/{n}' for n in sorted(set(names))
            if names.count(n) > (1 if n in own else 0)]


__all__ = ['StartGate', 'SESSION_NODES', 'Contest', 'extra_nodes']
