"""The session monitor's ROS side: the node of `erva run` that observes every topic of the run.

It subscribes to the live topics and ``/diagnostics`` exactly as any other
subscriber would (same QoS) and keeps what arrives with the wall time of arrival in
a :class:`Observations` store, which turns it into the run's summary
(:mod:`erva_ros.session.monitor_figures`): comfort and power metrics from the plant's
samples; the command rate; the command period jitter and the state-to-command
latency (the plant's state out -> the command for it back) as the plant measures
them where the commands are used, and also as this monitor receives them; the
sample-to-command latency from the sample time t_k;
the nodes' own counters and timings from their last diagnostics, and the messages
each node published but the monitor did not receive (dropped).

The store only deserializes messages, so its figures can be checked from synthetic
messages without DDS; :class:`Monitor` is the node that fills it.  What the nodes say
they published and the run's figures are the session's
(:mod:`erva_ros.session.monitor`, which adds them to both classes).

With ``hil=True`` (`erva run --ecu virtual`) the plant's part is played by the simulated
ECU, the CAN bridge and the state estimator: the monitor also takes the ECU's true
state, and :mod:`~erva_ros.session.hil_summary` maps the plant's figures to theirs.
"""

import time
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import AccelStamped, PointStamped
from rclpy.node import Node
from rclpy.serialization import deserialize_message
from sensor_msgs.msg import JointState
from trajectory_msgs.msg import JointTrajectory

from erva_ros.core import topics
from erva_ros.ros import qos as ros_qos
from erva_ros.ros.diagnostics import parse_status
from erva_ros.ros.msgs import joint_state_x, time_to_ns

#: Message types of the data topics the monitor takes (relative names, topics.py).
TYPES = {topics.STATE: JointState, topics.SPRUNG_ACCEL: AccelStamped,
         topics.GENERATOR: JointState, topics.ROAD_HEIGHT: PointStamped,
         topics.ROAD_PREVIEW: JointTrajectory, topics.DAMPING_CMD: JointTrajectory}


class Observations:
    """What a session's observer received, by arrival, and the tables decoded from it.

    Feed it :meth:`add` (a data topic's serialized message) and :meth:`add_diagnostics`
    (a DiagnosticArray); read the tables and :meth:`trajectory`.
    """

    def __init__(self, hil: bool = False, window_ns: Optional[Tuple[int, int]] = None):
        # Only the loop's own messages count: anything stamped outside the session's span
        # (from another process on the domain, or corrupt) is counted as foreign instead.
        # None: from this store's creation until now, in wall time (a realtime session).
        self.window_ns = window_ns or (time.time_ns(), None)
        self.types = dict(TYPES)
        self.hil = hil
        if hil:
            from erva_ros.core.hil.topics import TRUE_STATE
            self.types[TRUE_STATE] = JointState
            self.truth_topic = TRUE_STATE
        #: Every topic observed (relative names, as in topics.py).
        self.watched = (*self.types, topics.DIAGNOSTICS)
        self.raw: Dict[str, List[Tuple[int, bytes]]] = {t: [] for t in self.types}
        self.foreign = {t: 0 for t in self.types}
        self._decoded = -1
        self.received = {t: 0 for t in self.watched}
        self.diag: Dict[str, Tuple[int, str, Dict[str, str], int]] = {}
        self.diag_events: List[Tuple[int, str, int, str]] = []  # (rx_ns, node, level, msg)
        self.finished_rx: Dict[str, int] = {}   # node -> arrival of its first `finished`
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

    def add_diagnostics(self, msg: DiagnosticArray, rx_ns: int) -> None:
        """Keep each status of a DiagnosticArray: the newest per node, and its changes."""
        self.received[topics.DIAGNOSTICS] += 1
        for status in msg.status:
            name, level, text, values = parse_status(status)
            node = name.rsplit('/', 1)[-1]
            old = self.diag.get(node)
            if old is None or (old[0], old[1]) != (level, text):
                self.diag_events.append((rx_ns, node, level, text))
            self.diag[node] = (level, text, values, rx_ns)
            if values.get('finished') == 'true':
                self.finished_rx.setdefault(node, rx_ns)

    def _in_window(self, stamp: int) -> bool:
        lo, hi = self.window_ns
        # A realtime session's samples are all in the past when they are decoded.
        return lo <= stamp <= (time.time_ns() if hi is None else hi)

    def _decode(self) -> None:
        """Deserialize what arrived since the last call into the per-sample tables."""
        total = sum(len(v) for v in self.raw.values())
        if total == self._decoded:
            return
        self._decoded = total
        foreign = {t: 0 for t in self.types}

        def each(topic):
            seen = set()
            for rx, data in self.raw[topic]:
                msg = deserialize_message(data, self.types[topic])
                stamp = time_to_ns(msg.header.stamp)
                # The loop publishes each stamp once per topic, inside the session
                # (the NMPC's safe commands may repeat a stamp: kept, as commands).
                if not self._in_window(stamp) or (stamp in seen
                                                  and topic != topics.DAMPING_CMD):
                    foreign[topic] += 1
                    continue
                seen.add(stamp)
                yield rx, stamp, msg

        self.states.clear()
        self.state_rx.clear()
        for rx, stamp, msg in each(topics.STATE):
            self.states[stamp], self.state_rx[stamp] = joint_state_x(msg), rx
        if self.hil:
            self.truth = {stamp: joint_state_x(m) for _, stamp, m in each(self.truth_topic)}
        self.accel = {stamp: m.accel.linear.z for _, stamp, m in each(topics.SPRUNG_ACCEL)}
        self.power = {stamp: m.effort[0] * m.velocity[0]
                      for _, stamp, m in each(topics.GENERATOR)}
        self.heights = {stamp: m.point.z for _, stamp, m in each(topics.ROAD_HEIGHT)}
        self.previews = {stamp: np.array([p.positions[0] for p in m.points])
                         for _, stamp, m in each(topics.ROAD_PREVIEW)}
        self.commands = [(stamp, rx, np.array([p.positions[0] for p in m.points]))
                         for rx, stamp, m in each(topics.DAMPING_CMD)]
        self.foreign = foreign

    # -- queries -----------------------------------------------------------------------
    def diag_values(self, node: str) -> Dict[str, str]:
        """Return the newest diagnostic values of ``node`` (empty if none arrived)."""
        entry = self.diag.get(node)
        return {} if entry is None else entry[2]

    def diag_rx(self, node: str) -> int:
        """Return the arrival time (ns) of the newest diagnostics of ``node`` (0 if none)."""
        entry = self.diag.get(node)
        return 0 if entry is None else entry[3]

    def dropped(self, published: Dict[str, Optional[int]]) -> Dict[str, Optional[int]]:
        """Return, per topic, the messages published but not received here."""
        self._decode()
        return {t: (max(0, n - self.received[t] + self.foreign.get(t, 0))
                    if n is not None else None)
                for t, n in published.items()}

    def trajectory(self, n_steps: Optional[int] = None) -> Dict[str, np.ndarray]:
        """Return the time series by sample (t from the first state, x, u, w, accel, power)."""
        self._decode()
        stamps = sorted(self.accel)
        if n_steps is not None:
            stamps = stamps[:n_steps]
        t0 = min(self.states) if self.states else 0
        cmd = {}
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


class Monitor(Observations, Node):
    """Record every message of a session with its arrival time (wall clock, ns).

    The data topics are taken raw (serialized bytes) and decoded only for the summary:
    the observer costs the loop as little CPU as possible while it runs.
    """

    def __init__(self, namespace: str = topics.NAMESPACE, name: str = topics.MONITOR_NODE,
                 context=None, gate: Sequence[str] = (topics.ROAD_HEIGHT, topics.ROAD_PREVIEW),
                 hil: bool = False, window_ns: Optional[Tuple[int, int]] = None):
        Node.__init__(self, name, namespace=namespace, context=context,
                      start_parameter_services=False)
        Observations.__init__(self, hil, window_ns)
        self._qos = ros_qos.control_qos(depth=1000)   # a stalled erva run loses nothing
        # The time master starts when its topics have all their subscribers.  Subscribing
        # to those last, once every other subscription of this monitor is matched,
        # makes sure no message of the run is published before the monitor can get it.
        self.gate = tuple(gate)
        self.subscriptions_by_topic = {t: self._subscribe(t) for t in self.watched
                                       if t not in self.gate}

    def _subscribe(self, topic: str):
        if topic == topics.DIAGNOSTICS:
            return self.create_subscription(
                DiagnosticArray, topic, lambda msg: self.add_diagnostics(msg, time.time_ns()),
                self._qos)

        def on_message(data: bytes, info) -> None:
            # The middleware's reception time, not this callback's: erva run spins its
            # monitor between other work, and its figures must be the loop's.
            self.add(topic, info.get('received_timestamp') or time.time_ns(), data)
        return self.create_subscription(self.types[topic], topic, on_message, self._qos,
                                        raw=True)

    def connect(self, n_diagnostics: int) -> bool:
        """Return True once every subscription is matched to a publisher (call repeatedly).

        Opens the gate topics once the others are matched; ``n_diagnostics`` is the
        number of nodes publishing /diagnostics.
        """
        def matched(topic):
            sub = self.subscriptions_by_topic.get(topic)
            need = n_diagnostics if topic == topics.DIAGNOSTICS else 1
            return sub is not None and sub.get_publisher_count() >= need

        others = [t for t in self.received if t not in self.gate]
        if not all(matched(t) for t in others):
            return False
        for t in self.gate:
            if t not in self.subscriptions_by_topic:
                self.subscriptions_by_topic[t] = self._subscribe(t)
        return all(matched(t) for t in self.gate)


__all__ = ['TYPES', 'Observations', 'Monitor']
