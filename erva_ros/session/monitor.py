"""The session monitor: an in-process node of `erva run` that observes every topic of the run.

It subscribes to the live topics and ``/diagnostics`` exactly as any other
subscriber would (same QoS), keeps what arrives with the wall time of arrival, and
turns it into the run's summary: comfort and power metrics from the plant's
samples; the command rate; the command period jitter and the state-to-command
latency (the plant's state out -> the command for it back) as the plant measures
them where the commands are used, and also as this monitor receives them; the
sample-to-command latency from the sample time t_k;
the nodes' own counters and timings from their last diagnostics, and the messages
each node published but the monitor did not receive (dropped).

With ``hil=True`` (`erva run --ecu virtual`) the plant's part is played by the simulated
ECU, the CAN bridge and the state estimator: the monitor also takes the ECU's true
state, and :mod:`~erva_ros.session.hil_summary` maps the plant's figures to theirs.
"""

import time
from typing import Any, Dict, List, Optional, Sequence, Tuple

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import AccelStamped, PointStamped
from rclpy.node import Node
from rclpy.serialization import deserialize_message
from sensor_msgs.msg import JointState
from trajectory_msgs.msg import JointTrajectory

from erva_ros.core import topics
from erva_ros.ros import qos as ros_qos
from erva_ros.session import hil_summary
from erva_ros.ros.diagnostics import LEVEL_NAMES, parse_status, value_float, value_int
from erva_ros.ros.msgs import time_to_ns
from erva_ros.core.metrics import comfort_power, percentiles_ms

#: Status changes kept in the summary (the first ones; a flapping node could make many).
MAX_EVENTS = 200


class Monitor(Node):
    """Record every message of a session with its arrival time (wall clock, ns).

    The data topics are taken raw (serialized bytes) and decoded only for the summary:
    the observer costs the loop as little CPU as possible while it runs.
    """

    def __init__(self, namespace: str = topics.NAMESPACE, name: str = 'erva_run_monitor',
                 context=None, gate: Sequence[str] = (topics.ROAD_HEIGHT, topics.ROAD_PREVIEW),
                 hil: bool = False, window_ns: Optional[Tuple[int, int]] = None):
        super().__init__(name, namespace=namespace, context=context,
                         start_parameter_services=False)
        # Only the loop's own messages count: anything stamped outside the session's span
        # (from another process on the domain, or corrupt) is counted as foreign instead.
        # None: from this monitor's creation until now, in wall time (a realtime session).
        self.window_ns = window_ns or (time.time_ns(), None)
        self._qos = ros_qos.control_qos(depth=1000)   # a stalled erva run loses nothing
        self._types = {topics.STATE: JointState, topics.SPRUNG_ACCEL: AccelStamped,
                       topics.GENERATOR: JointState, topics.ROAD_HEIGHT: PointStamped,
                       topics.ROAD_PREVIEW: JointTrajectory, topics.DAMPING_CMD: JointTrajectory}
        self.hil = hil
        if hil:
            from erva_ros.core.hil.topics import TRUE_STATE
            self._types[TRUE_STATE] = JointState
            self.truth_topic = TRUE_STATE
        #: Every topic this monitor subscribes to (relative names, as in topics.py).
        self.watched = (*self._types, topics.DIAGNOSTICS)
        self._raw: Dict[str, List[Tuple[int, bytes]]] = {t: [] for t in self._types}
        self.foreign = {t: 0 for t in self._types}
        self._decoded = -1
        self.received = {t: 0 for t in (*self._types, topics.DIAGNOSTICS)}
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
        # The time master starts when its topics have all their subscribers.  Subscribing
        # to those last, once every other subscription of this monitor is matched,
        # makes sure no message of the run is published before the monitor can get it.
        self.gate = tuple(gate)
        self.subscriptions_by_topic = {
            t: self._subscribe(t) for t in (*self._types, topics.DIAGNOSTICS)
            if t not in self.gate}

    def _in_window(self, stamp: int) -> bool:
        lo, hi = self.window_ns
        # A realtime session's samples are all in the past when they are decoded.
        return lo <= stamp <= (time.time_ns() if hi is None else hi)

    def _subscribe(self, topic: str):
        if topic == topics.DIAGNOSTICS:
            return self.create_subscription(DiagnosticArray, topic, self._on_diag, self._qos)
        store = self._raw[topic]

        def on_message(data: bytes, info) -> None:
            # The middleware's reception time, not this callback's: erva run spins its
            # monitor between other work, and its figures must be the loop's.
            store.append((info.get('received_timestamp') or time.time_ns(), data))
            self.received[topic] += 1
        return self.create_subscription(self._types[topic], topic, on_message, self._qos,
                                        raw=True)

    def _on_diag(self, msg: DiagnosticArray) -> None:
        rx = time.time_ns()
        self.received[topics.DIAGNOSTICS] += 1
        for status in msg.status:
            name, level, text, values = parse_status(status)
            node = name.rsplit('/', 1)[-1]
            old = self.diag.get(node)
            if old is None or (old[0], old[1]) != (level, text):
                self.diag_events.append((rx, node, level, text))
            self.diag[node] = (level, text, values, rx)
            if values.get('finished') == 'true':
                self.finished_rx.setdefault(node, rx)

    def _decode(self) -> None:
        """Deserialize what arrived since the last call into the per-sample tables."""
        total = sum(len(v) for v in self._raw.values())
        if total == self._decoded:
            return
        self._decoded = total
        self.states.clear()
        self.state_rx.clear()
        self.commands.clear()

        def each(topic):
            seen = set()
            for rx, data in self._raw[topic]:
                msg = deserialize_message(data, self._types[topic])
                stamp = time_to_ns(msg.header.stamp)
                # The loop publishes each stamp once per topic, inside the session
                # (the NMPC's safe commands may repeat a stamp: kept, as commands).
                if not self._in_window(stamp) or (stamp in seen
                                                  and topic != topics.DAMPING_CMD):
                    foreign[topic] += 1
                    continue
                seen.add(stamp)
                yield rx, stamp, msg

        foreign = {t: 0 for t in self._types}

        for rx, stamp, msg in each(topics.STATE):
            self.states[stamp], self.state_rx[stamp] = _state(msg), rx
        if self.hil:
            self.truth = {stamp: _state(m) for _, stamp, m in each(self.truth_topic)}
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

    def diag_values(self, node: str) -> Dict[str, str]:
        """Return the newest diagnostic values of ``node`` (empty if none arrived)."""
        entry = self.diag.get(node)
        return {} if entry is None else entry[2]

    def diag_rx(self, node: str) -> int:
        """Return the arrival time (ns) of the newest diagnostics of ``node`` (0 if none)."""
        entry = self.diag.get(node)
        return 0 if entry is None else entry[3]

    def published(self) -> Dict[str, Optional[int]]:
        """Return the messages each node says it published per topic (None: not known)."""
        plant = self.diag_values('plant_sim_node')
        nmpc = self.diag_values('nmpc_node')
        road = self.diag_values('road_preview_node')
        loop = hil_summary.published(self.diag_values) if self.hil else {
            topics.STATE: value_int(plant.get('states')),
            topics.SPRUNG_ACCEL: value_int(plant.get('steps')),
            topics.GENERATOR: value_int(plant.get('steps'))}
        return {
            **loop,
            topics.ROAD_HEIGHT: value_int(road.get('samples_published')),
            topics.ROAD_PREVIEW: value_int(road.get('samples_published')),
            topics.DAMPING_CMD: (None if not nmpc else (value_int(nmpc.get('commands')) or 0)
                                 + (value_int(nmpc.get('safe_commands')) or 0)),
        }

    def dropped(self, published: Dict[str, Optional[int]]) -> Dict[str, Optional[int]]:
        """Return, per topic, the messages published but not received here."""
        self._decode()
        return {t: (max(0, n - self.received[t] + self.foreign.get(t, 0))
                    if n is not None else None)
                for t, n in published.items()}

    # -- summary -----------------------------------------------------------------------
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

    def summary(self, ts: float, n_steps: int, realtime: bool) -> Dict[str, Any]:
        """Return the run's figures (see module doc) for a run of ``n_steps`` periods ``ts``."""
        self._decode()
        plant = self.diag_values('plant_sim_node')
        nmpc = self.diag_values('nmpc_node')
        road = self.diag_values('road_preview_node')
        accel = [self.accel[s] for s in sorted(self.accel)][:n_steps]
        integrator = hil_summary.ECU if self.hil else 'plant_sim_node'
        harvested = value_float(self.diag_values(integrator).get('harvested_j'))
        duration = len(accel) * ts
        metrics = comfort_power(accel, harvested, duration) if accel else {}
        metrics.update({'harvested_j': harvested, 'samples': len(accel)})
        if len(self.state_rx) > 1:
            # Simulated time over the wall time between the first and the last state.
            rx = sorted(self.state_rx.values())
            span = (rx[-1] - rx[0]) * 1e-9
            metrics['realtime_factor'] = (len(rx) - 1) * ts / span if span > 0 else None

        cmds = self.commands
        scheduled = [c for c in cmds if c[0] in self.states]   # not the safe commands
        out: Dict[str, Any] = {'metrics': metrics}
        cmd: Dict[str, Any] = {'received': len(cmds), 'for_samples': len(scheduled)}
        if realtime and len(scheduled) > 1:
            rx = np.array([c[1] for c in scheduled], dtype=float) * 1e-9
            cmd['rate_hz'] = float((len(rx) - 1) / (rx[-1] - rx[0]))
            if not self.hil:   # the HIL loop has no plant node: the monitor's figures below
                # Measured where the commands are used: at the plant (its diagnostics).
                cmd['period_jitter_ms'] = _stats(plant, 'cmd_jitter_ms')
                cmd['state_to_command_ms'] = _stats(plant, 'loop_latency_ms')
            cmd['sample_to_command_ms'] = percentiles_ms(
                [(c[1] - c[0]) * 1e-9 for c in scheduled])
            # And as this monitor, one more subscriber, sees them.
            cmd['monitor'] = {
                'period_jitter_ms': percentiles_ms(np.abs(np.diff(rx) - ts)),
                'state_to_command_ms': percentiles_ms(
                    [(c[1] - self.state_rx[c[0]]) * 1e-9 for c in scheduled])}
        out['commands'] = cmd
        out['nmpc'] = {
            'controller': nmpc.get('controller'),
            'solve_ms': _stats(nmpc, 'solve_ms'),
            'latency_ms': _stats(nmpc, 'latency_ms'),
            'cmd_jitter_ms': _stats(nmpc, 'cmd_jitter_ms'),
            'tick_jitter_ms': _stats(nmpc, 'tick_jitter_ms'),
            **{k: value_int(nmpc.get(k)) for k in (
                'solves', 'commands', 'late', 'deadline_misses', 'state_timeouts',
                'safe_commands', 'missed_samples', 'superseded_states', 'out_of_order',
                'stale_previews', 'no_preview', 'rejected_state', 'rejected_preview',
                'controller_fallback_plan', 'controller_fallback_passive',
                'controller_failures', 'controller_late')}}
        # What each node's threads got from realtime_priority (live/realtime.py).
        out['scheduling'] = {node.replace(': bag recorder', ''): entry[2]['scheduling']
                             for node, entry in self.diag.items() if 'scheduling' in entry[2]}
        if self.hil:
            out['plant'] = hil_summary.plant_equivalents(self.diag_values)
            out['hil'] = hil_summary.hil_block(
                self.diag_values, self.states, self.truth, _stats, self.diag_events,
                self.finished_rx.get(hil_summary.ECU))
        else:
            out['plant'] = {k: value_int(plant.get(k)) for k in (
                'steps', 'u_from_command', 'u_from_plan', 'u_from_passive', 'late_commands',
                'road_gaps', 'lockstep_timeouts', 'rejected_road_height',
                'rejected_damping_cmd')}
            out['plant'].update({k: _stats(plant, k) for k in (
                'loop_latency_ms', 'cmd_jitter_ms', 'road_latency_ms', 'step_ms')})
        published = self.published()
        dropped = self.dropped(published)
        rejected = {'state': value_int(nmpc.get('rejected_state')),
                    'road/preview': value_int(nmpc.get('rejected_preview')),
                    'road/height': value_int(plant.get('rejected_road_height')),
                    'damping_cmd': out['plant'].get('rejected_damping_cmd'),
                    '/clock': value_int(road.get('rejected_clock'))}
        if self.hil:   # the ECU ignores absurd road heights without counting them
            del rejected['road/height']
        # Inputs dropped for a stamp not newer than the newest (stamps going back).
        rejected['out_of_order'] = ((value_int(nmpc.get('out_of_order')) or 0)
                                    + (value_int(plant.get('out_of_order_commands')) or 0))
        t0 = min(self.state_rx.values()) if self.state_rx else 0
        out['events'] = [{'t_s': round((rx - t0) * 1e-9, 3), 'node': node,
                          'level': LEVEL_NAMES.get(level, str(level)), 'message': text}
                         for rx, node, level, text in self.diag_events[:MAX_EVENTS]]
        out['messages'] = {'published': published, 'received': dict(self.received),
                           'foreign': dict(self.foreign),
                           'foreign_total': sum(self.foreign.values()),
                           'dropped': dropped,
                           'dropped_total': sum(v for v in dropped.values() if v),
                           'rejected': rejected,
                           'rejected_total': sum(v for v in rejected.values() if v)}
        return out


def _state(msg: JointState) -> np.ndarray:
    """Return x = [z_s, ż_s, z_us, ż_us(, z_d, ż_d)] of a state message."""
    x = np.empty(2 * len(msg.position))
    x[0::2], x[1::2] = msg.position, msg.velocity
    return x


def _stats(values: Dict[str, str], prefix: str) -> Dict[str, Any]:
    out = {k: value_float(values.get(f'{prefix}_{k}')) for k in ('p50', 'p99', 'max')}
    out['samples'] = value_int(values.get(f'{prefix}_samples'))
    return out


__all__ = ['MAX_EVENTS', 'Monitor']
