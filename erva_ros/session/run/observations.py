"""What a session's observer received, and what the session makes of it: no ROS inside.

The monitor node of `erva run` (:class:`erva_ros.ros.monitor.Monitor`) hands every
message it takes to an :class:`Observations` store.  A data message is decoded as it
arrives (by the contract's one decoder per message family, :mod:`erva_ros.core.contract`)
and folded into the session's streaming figures
(:class:`erva_ros.session.run.monitor_stats.SessionStreams`): the store's memory does not grow
with the session's length.  ``/diagnostics`` gives the nodes' typed reports
(:mod:`erva_ros.core.reports`).

Only the session's own messages count.  A status belongs to the session when its node
is in the session's namespace and carries the session's id; anything else on
``/diagnostics`` (another session on the same domain, another program) is counted as
foreign and otherwise ignored.  A data message stamped outside the session's span is
foreign too, and so is one stamped not newer than the newest of its topic: each topic
has one writer in the loop, which delivers in order (the NMPC's safe commands may repeat
a stamp: commands are only checked against the span).

From the store come the figures of the summary (:mod:`erva_ros.session.run.monitor_figures`),
what each node says it published and whether all of it arrived.
"""

import time
from typing import Any, Dict, List, Optional, Tuple

import numpy as np

from erva_ros.core import contract, topics
from erva_ros.core.hil.topics import TRUE_STATE
from erva_ros.core.levels import ERROR
from erva_ros.core.reports import NMPCReport, NodeReport, report_from_status
from erva_ros.core.settings.schemas import LIVE
from erva_ros.session.run import hil_summary
from erva_ros.session.run import monitor_figures
from erva_ros.session.run.monitor_figures import MAX_EVENTS
from erva_ros.session.run.monitor_stats import SessionStreams, TRAJECTORY_CAP
from erva_ros.session.run.segments import ParameterSetLog
from erva_ros.session.run.verdict import quality_limits


class Observations:
    """A session's observations: streaming figures of its data, typed reports, and the summary.

    ``window_ns`` is the span of the session's sample stamps (None: from this store's
    creation until each message's arrival, in wall time: a realtime session);
    ``namespace`` and ``session`` (its id, '' for any) say which statuses are the
    session's.  ``ts`` is the loop's period and ``n_steps`` the session's samples (None:
    the live defaults' Ts, and all samples); ``command_gap_s`` the command pause the
    verdict reports (None: config/session.yaml's); ``trajectory_cap`` the samples of the
    trajectory kept (the first ones).
    """

    def __init__(self, hil: bool = False, window_ns: Optional[Tuple[int, int]] = None,
                 namespace: str = topics.NAMESPACE, session: str = '',
                 ts: Optional[float] = None, n_steps: Optional[int] = None,
                 command_gap_s: Optional[float] = None,
                 trajectory_cap: int = TRAJECTORY_CAP):
        self.window_ns = window_ns or (time.time_ns(), None)
        self.hil = hil
        self.namespace = namespace.rstrip('/')
        self.session = session
        self.topics = [topics.STATE, topics.SPRUNG_ACCEL, topics.GENERATOR,
                       topics.ROAD_HEIGHT, topics.ROAD_PREVIEW, topics.DAMPING_CMD]
        if hil:
            self.topics.append(TRUE_STATE)
        #: Every topic observed (relative names, as in topics.py).
        self.watched = (*self.topics, topics.DIAGNOSTICS)
        self.received = {t: 0 for t in self.watched}
        self.foreign = {t: 0 for t in self.topics}
        #: Statuses on /diagnostics that are not the session's (other sessions, programs).
        self.foreign_statuses = 0
        #: Nodes in the session's namespace that report another session's id.
        self.other_sessions: Dict[str, str] = {}     # node name -> its session id
        #: The newest report of each of the session's nodes, by its name in the namespace.
        self.reports: Dict[str, NodeReport] = {}
        self.report_rx: Dict[str, int] = {}
        #: The first MAX_EVENTS status changes: (rx_ns, node, level, message).
        self.events: List[Tuple[int, str, int, str]] = []
        self.finished_rx: Dict[str, int] = {}    # node -> arrival of its first `finished`
        #: The stamp of the loop's first sample (its first road height), None before.
        self.first_sample_ns: Optional[int] = None
        #: HIL: the bridge's command timeouts that began before the ECU finished.
        self.bridge_timeouts = 0
        self._bridge_error = False
        live = LIVE.defaults()
        ts = live['ts'] if ts is None else ts
        # A realtime sample is stamped at its instant, before it is sent; the loop's
        # nodes accept a lead this small (clocks of several hosts), and so does this.
        self._lead_ns = int(live['max_stamp_lead_s'] * 1e9)
        if command_gap_s is None:
            command_gap_s = quality_limits()['max_command_gap_s']
        #: The session's data, folded as it arrives.
        self.streams = SessionStreams(ts, n_steps, command_gap_s, trajectory_cap,
                                      hil_summary.WARMUP)
        self._newest: Dict[str, int] = {}       # topic -> newest stamp taken
        #: The controller's parameter sets (live tuning), as its reports announce them.
        self.parameter_sets = ParameterSetLog()
        self._true_state = TRUE_STATE if hil else None

    # -- input -------------------------------------------------------------------------
    def add(self, topic: str, rx_ns: int, data: bytes) -> None:
        """Take a data message received at ``rx_ns`` (CDR): the session's, or foreign."""
        self.received[topic] += 1
        try:
            row = contract.DECODERS[topic](data)
        except contract.MessageRejected:
            self.foreign[topic] += 1
            return
        stamp = row.stamp_ns
        lo, hi = self.window_ns
        if not lo <= stamp <= (time.time_ns() + self._lead_ns if hi is None else hi):
            self.foreign[topic] += 1
            return
        if topic != topics.DAMPING_CMD:
            newest = self._newest.get(topic)
            if newest is not None and stamp <= newest:
                self.foreign[topic] += 1
                return
            self._newest[topic] = stamp
        self._take(topic, rx_ns, row)

    def _take(self, topic: str, rx_ns: int, row) -> None:
        """Fold one of the session's messages (a decoded row) into its figures."""
        s = self.streams
        if topic == topics.STATE:
            s.add_state(row.stamp_ns, rx_ns, row.x)
        elif topic == topics.SPRUNG_ACCEL:
            s.add_accel(row.stamp_ns, row.sprung_accel)
        elif topic == topics.GENERATOR:
            s.add_power(row.stamp_ns, row.power)
        elif topic == topics.ROAD_HEIGHT:
            if self.first_sample_ns is None:    # sample 0: the loop starts with the road
                self.first_sample_ns = row.stamp_ns
            s.add_height(row.stamp_ns, row.height_m)
        elif topic == topics.DAMPING_CMD:
            s.add_command(row.stamp_ns, rx_ns, float(row.plan[0]))
        elif topic == self._true_state:
            s.add_truth(row.stamp_ns, row.x)
        # road/preview: counted and checked, no figure of its own.

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
            if (old is None or (old.level, old.message) != (report.level, report.message)) \
                    and len(self.events) < MAX_EVENTS:
                self.events.append((rx_ns, name, report.level, report.message))
            if name == hil_summary.BRIDGE_COMMAND:
                # A timeout begins as the status turns ERROR; those after the ECU
                # finished are the bridge's expected tail (hil_summary module doc).
                error = report.level == ERROR
                if error and not self._bridge_error and hil_summary.ECU not in self.finished_rx:
                    self.bridge_timeouts += 1
                self._bridge_error = error
            self.reports[name] = report
            self.report_rx[name] = rx_ns
            if isinstance(report, NMPCReport):
                self.parameter_sets.add(report)
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
        return {t: (max(0, n - self.received[t] + self.foreign.get(t, 0))
                    if n is not None else None)
                for t, n in published.items()}

    def all_received(self) -> bool:
        """Return True once every node's counters arrived and nothing is missing."""
        published = self.published()
        return (all(v is not None for v in published.values())
                and not any(self.dropped(published).values()))

    def trajectory(self, n_steps: Optional[int] = None) -> Dict[str, np.ndarray]:
        """Return the time series by sample (t from the first state, x, u, w, accel, power).

        Its first ``trajectory_cap`` samples at most (the summary's ``trajectory``).
        """
        return self.streams.sampled(n_steps)

    def summary(self, ts: float, n_steps: int, realtime: bool) -> Dict[str, Any]:
        """Return the run's figures for a run of ``n_steps`` periods ``ts``.

        Commands still waiting for their sample's state count as not for a sample.
        """
        if ts != self.streams.ts:
            raise ValueError(f'the summary is for ts = {ts} s, the observations were '
                             f'folded with ts = {self.streams.ts} s')
        self.streams.settle()
        return monitor_figures.summary(self, ts, n_steps, realtime)


__all__ = ['Observations']
