"""What a session's observer received, and what the session makes of it: no ROS inside.

The monitor node of `erva run` (:class:`erva_ros.ros.monitor.Monitor`) hands every
message it takes to an :class:`Observations` store: the data topics as CDR bytes with
their arrival time (decoded only for the summary, by the contract's one decoder per
message family, :mod:`erva_ros.core.contract`), and ``/diagnostics`` as the nodes' typed
reports (:mod:`erva_ros.core.reports`).

Only the session's own messages count.  A status belongs to the session when its node
is in the session's namespace and carries the session's id; anything else on
``/diagnostics`` (another session on the same domain, another program) is counted as
foreign and otherwise ignored.  A data message stamped outside the session's span, or a
second message of one stamp on a topic, is foreign too.

From the store come the figures of the summary (:mod:`erva_ros.session.monitor_figures`),
what each node says it published and whether all of it arrived.
"""

import time
from typing import Any, Dict, List, Optional, Tuple

import numpy as np

from erva_ros.core import contract, topics
from erva_ros.core.reports import NodeReport, report_from_status
from erva_ros.session import hil_summary


class Observations:
    """A session's observations: raw data by arrival, typed reports, and the figures.

    ``window_ns`` is the span of the session's sample stamps (None: from this store's
    creation until now, in wall time: a realtime session); ``namespace`` and ``session``
    (its id, '' for any) say which statuses are the session's.
    """

    def __init__(self, hil: bool = False, window_ns: Optional[Tuple[int, int]] = None,
                 namespace: str = topics.NAMESPACE, session: str = ''):
        self.window_ns = window_ns or (time.time_ns(), None)
        self.hil = hil
        self.namespace = namespace.rstrip('/')
        self.session = session
        self.topics = [topics.STATE, topics.SPRUNG_ACCEL, topics.GENERATOR,
                       topics.ROAD_HEIGHT, topics.ROAD_PREVIEW, topics.DAMPING_CMD]
        if hil:
            from erva_ros.core.hil.topics import TRUE_STATE
            self.topics.append(TRUE_STATE)
        #: Every topic observed (relative names, as in topics.py).
        self.watched = (*self.topics, topics.DIAGNOSTICS)
        self.raw: Dict[str, List[Tuple[int, bytes]]] = {t: [] for t in self.topics}
        self.received = {t: 0 for t in self.watched}
        self.foreign = {t: 0 for t in self.topics}
        #: Statuses on /diagnostics that are not the session's (other sessions, programs).
        self.foreign_statuses = 0
        #: Nodes in the session's namespace that report another session's id.
        self.other_sessions: Dict[str, str] = {}     # node name -> its session id
        #: The newest report of each of the session's nodes, by its name in the namespace.
        self.reports: Dict[str, NodeReport] = {}
        self.report_rx: Dict[str, int] = {}
        self.events: List[Tuple[int, str, int, str]] = []   # (rx_ns, node, level, message)
        self.finished_rx: Dict[str, int] = {}    # node -> arrival of its first `finished`
        self._decoded = -1
        # Decoded by _decode(): by sample stamp (ns).
        self.states: Dict[int, np.ndarray] = {}
        self.state_rx: Dict[int, int] = {}
        self.accel: Dict[int, float] = {}
        self.power: Dict[int, float] = {}
        self.heights: Dict[int, float] = {}
        self.previews: Dict[int, np.ndarray] = {}
        self.commands: List[Tuple[int, int, np.ndarray]] = []   # (stamp, rx_ns, plan)
        self.truth: Dict[int, np.ndarray] = {}                  # HIL: the ECU's true state

    # -- input -------------------------------------------------------------------------
    def add(self, topic: str, rx_ns: int, data: bytes) -> None:
        """Keep a data topic's serialized message, received at ``rx_ns``."""
        self.raw[topic].append((rx_ns, data))
        self.received[topic] += 1

    def add_diagnostics(self, data: bytes, rx_ns: int) -> None:
        """Keep each of the session's statuses in a DiagnosticArray: newest, and changes."""
        self.received[topics.DIAGNOSTICS] += 1
        try:
            _, statuses = contract.decode_diagnostics(data)
        except contract.MessageRejected:
            self.foreign_statuses += 1
            return
        for status in statuses:
            name = self.own_name(status.name)
            report = report_from_status(status)
            if name is None or (self.session and report.session != self.session):
                self.foreign_statuses += 1
                if name is not None:
                    self.other_sessions[name] = report.session
                continue
            old = self.reports.get(name)
            if old is None or (old.level, old.message) != (report.level, report.message):
                self.events.append((rx_ns, name, report.level, report.message))
            self.reports[name] = report
            self.report_rx[name] = rx_ns
            if report.finished:
                self.finished_rx.setdefault(name, rx_ns)

    def own_name(self, status_name: str) -> Optional[str]:
        """Return a status's name inside the session's namespace (None: not in it)."""
        prefix = self.namespace + '/'
        if not status_name.startswith(prefix):
            return None
        name = status_name[len(prefix):]
        return None if '/' in name.split(':', 1)[0] else name

    def report(self, name: str) -> Optional[NodeReport]:
        """Return the newest report of node ``name`` (None if none arrived)."""
        return self.reports.get(name)

    def _in_window(self, stamp: int) -> bool:
        lo, hi = self.window_ns
        # A realtime session's samples are all in the past when they are decoded.
        return lo <= stamp <= (time.time_ns() if hi is None else hi)

    def _decode(self) -> None:
        """Decode what arrived since the last call into the per-sample tables."""
        total = sum(len(v) for v in self.raw.values())
        if total == self._decoded:
            return
        self._decoded = total
        foreign = {t: 0 for t in self.topics}

        def each(topic):
            seen = set()
            decode = contract.DECODERS[topic]
            for rx, data in self.raw[topic]:
                try:
                    row = decode(data)
                except contract.MessageRejected:
                    foreign[topic] += 1
                    continue
                # The loop publishes each stamp once per topic, inside the session
                # (the NMPC's safe commands may repeat a stamp: kept, as commands).
                if not self._in_window(row.stamp_ns) or (row.stamp_ns in seen
                                                         and topic != topics.DAMPING_CMD):
                    foreign[topic] += 1
                    continue
                seen.add(row.stamp_ns)
                yield rx, row

        self.states.clear()
        self.state_rx.clear()
        for rx, row in each(topics.STATE):
            self.states[row.stamp_ns], self.state_rx[row.stamp_ns] = row.x, rx
        if self.hil:
            from erva_ros.core.hil.topics import TRUE_STATE
            self.truth = {row.stamp_ns: row.x for _, row in each(TRUE_STATE)}
        self.accel = {r.stamp_ns: r.sprung_accel for _, r in each(topics.SPRUNG_ACCEL)}
        self.power = {r.stamp_ns: r.power for _, r in each(topics.GENERATOR)}
        self.heights = {r.stamp_ns: r.height_m for _, r in each(topics.ROAD_HEIGHT)}
        self.previews = {r.stamp_ns: r.heights for _, r in each(topics.ROAD_PREVIEW)}
        self.commands = [(r.stamp_ns, rx, r.plan) for rx, r in each(topics.DAMPING_CMD)]
        self.foreign = foreign

    # -- what the session makes of it --------------------------------------------------
    def published(self, final_only: bool = False) -> Dict[str, Optional[int]]:
        """Return the messages each node says it published per topic (None: not known).

        ``final_only``: only a node's final report counts (one that stopped without it,
        e.g. killed, has published an unknown number).
        """
        def count(name, field):
            r = self.reports.get(name)
            if r is None or (final_only and not r.final):
                return None
            return getattr(r, field)

        if self.hil:
            loop = hil_summary.published(self.report, final_only)
        else:
            loop = {topics.STATE: count('plant_sim_node', 'states'),
                    topics.SPRUNG_ACCEL: count('plant_sim_node', 'steps'),
                    topics.GENERATOR: count('plant_sim_node', 'steps')}
        road = count('road_preview_node', 'samples_published')
        road_node = self.reports.get('road_preview_node')
        # a map preview goes out per road estimate, not per road sample
        preview = (count('road_preview_node', 'map_samples')
                   if getattr(road_node, 'source', '') == 'map' else road)
        nmpc = self.reports.get('nmpc_node')
        cmds = None if nmpc is None or (final_only and not nmpc.final) else (
            nmpc.commands + nmpc.safe_commands)
        return {**loop, topics.ROAD_HEIGHT: road, topics.ROAD_PREVIEW: preview,
                topics.DAMPING_CMD: cmds}

    def dropped(self, published: Dict[str, Optional[int]]) -> Dict[str, Optional[int]]:
        """Return, per topic, the messages published but not received here."""
        self._decode()
        return {t: (max(0, n - self.received[t] + self.foreign.get(t, 0))
                    if n is not None else None)
                for t, n in published.items()}

    def all_received(self) -> bool:
        """Return True once every node's counters arrived and nothing is missing."""
        published = self.published()
        return (all(v is not None for v in published.values())
                and not any(self.dropped(published).values()))

    def trajectory(self, n_steps: Optional[int] = None) -> Dict[str, np.ndarray]:
        """Return the time series by sample (t from the first state, x, u, w, accel, power)."""
        self._decode()
        stamps = sorted(self.accel)
        if n_steps is not None:
            stamps = stamps[:n_steps]
        t0 = min(self.states) if self.states else 0
        cmd: Dict[int, float] = {}
        for stamp, _, plan in self.commands:
            cmd.setdefault(stamp, plan[0])
        return {
            't': np.array([(s - t0) * 1e-9 for s in stamps]),
            'x': np.array([self.states.get(s, np.full(6, np.nan)) for s in stamps]),
            'u': np.array([cmd.get(s, np.nan) for s in stamps]),
            'w': np.array([self.heights.get(s, np.nan) for s in stamps]),
            'sprung_accel': np.array([self.accel[s] for s in stamps]),
            'power': np.array([self.power.get(s, np.nan) for s in stamps]),
        }

    def summary(self, ts: float, n_steps: int, realtime: bool) -> Dict[str, Any]:
        """Return the run's figures for a run of ``n_steps`` periods ``ts``."""
        from erva_ros.session import monitor_figures
        self._decode()
        return monitor_figures.summary(self, ts, n_steps, realtime)


__all__ = ['Observations']
