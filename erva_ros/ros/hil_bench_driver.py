"""The driver node of `erva bench-hil` (session/bench/hil_bench.py): road and law stand-in.

It publishes the road height at 50 Hz once the HIL loop is discovered, answers every
``state`` with a ``damping_cmd`` at once (skyhook or passive), and observes the loop from
outside: DDS source timestamps, the ECU's true state, the nodes' diagnostics.
:meth:`HilBenchDriver.results` returns the figures (NaN where nothing was measured).
"""

import time
from typing import Dict, List

import numpy as np

from erva_ros.core import contract, topics
from erva_ros.core.hil import topics as hil_topics
from erva_ros.core.metrics import percentiles_ms
from erva_ros.core.reports import NodeReport, report_from_status
from erva_ros.core.settings.loop import command_delay_ns
from erva_ros.core.settings.schemas import LIVE
from erva_ros.core.wire import header_stamp_ns
from erva_ros.ros import qos as ros_qos

#: Latencies of the nodes' reports: (status name suffix, Timing field).
NODE_LATENCIES = {
    'bridge_ros_to_can': ('ecu_bridge_node: command', 'ros_to_can_ms'),
    'bridge_ros_to_can_processing': ('ecu_bridge_node: command', 'ros_to_can_proc_ms'),
    'bridge_can_to_ros': ('ecu_bridge_node: ecu', 'can_to_ros_ms'),
    'bridge_can_to_ros_processing': ('ecu_bridge_node: ecu', 'can_to_ros_proc_ms'),
    'estimator': ('state_estimator_node', 'latency_ms'),
    'estimator_processing': ('state_estimator_node', 'compute_ms'),
}


class HilBenchDriver:
    """Road + control-law stand-in and the outside observer of the loop."""

    WARMUP = 25   # cycles (0.5 s) not counted: discovery and first-call allocations

    def __init__(self, namespace, context, road, law, params):
        from diagnostic_msgs.msg import DiagnosticArray
        from geometry_msgs.msg import PointStamped
        from rclpy.node import Node
        from sensor_msgs.msg import JointState
        from trajectory_msgs.msg import JointTrajectory

        self.node = Node('bench_hil_driver', namespace=namespace, context=context)
        self.road, self.law, self.params = road, law, params
        # The loop's command delay, as the bridge's params give it: commands say when they act.
        self.delay_ns = command_delay_ns(LIVE.defaults()['command_delay_s'])
        qos = ros_qos.control_qos()
        self.pub_road = self.node.create_publisher(PointStamped, topics.ROAD_HEIGHT, qos)
        self.pub_cmd = self.node.create_publisher(JointTrajectory, topics.DAMPING_CMD, qos)
        self.node.create_subscription(JointState, topics.STATE, self._on_state, qos, raw=True)
        self.node.create_subscription(JointState, hil_topics.TRUE_STATE, self._on_truth, qos,
                                      raw=True)
        self.node.create_subscription(DiagnosticArray, topics.DIAGNOSTICS, self._on_diag, qos,
                                      raw=True)
        # The estimator's input: one message per ECU cycle, after the cycle's frames.
        self.node.create_subscription(JointState, hil_topics.ECU_MEASUREMENTS, self._on_ecu,
                                      qos, raw=True)
        self.t0 = time.time()
        self.ready = None
        self.node.create_timer(0.02, self._on_road_timer)
        self.states = 0
        self.est: Dict[int, np.ndarray] = {}
        self.truth: Dict[int, np.ndarray] = {}
        self.ecu_src: Dict[int, int] = {}       # stamp -> ecu/measurements source time
        self.state_src: Dict[int, int] = {}     # stamp -> source time of the state (ns)
        self.sensor_path: List[float] = []
        self.reports: Dict[str, NodeReport] = {}

    def _graph_ready(self) -> bool:
        # The ECU starts its run at the first road sample: hold the road back until the
        # whole loop is discovered, so the run measures the loop, not DDS discovery.
        n = self.node
        ns = n.get_namespace().rstrip('/')
        return (n.count_publishers(f'{ns}/state') >= 1
                and n.count_subscribers(f'{ns}/damping_cmd') >= 1
                and n.count_subscribers(f'{ns}/road/height') >= 2
                and n.count_publishers(f'{ns}/ecu/measurements') >= 1
                and n.count_subscribers(f'{ns}/ecu/measurements') >= 2
                and n.count_publishers(f'{ns}/ecu_sim/state') >= 1)

    def _on_road_timer(self):
        if self.ready is None:
            if not self._graph_ready():
                return
            self.ready = time.monotonic()
            self.t0 = time.time()
        t = time.time()
        self.pub_road.publish(contract.encode_road_height(int(t * 1e9), 0.0,
                                                          self.road.height(t - self.t0)))

    def _on_ecu(self, data, info):
        st = header_stamp_ns(data)
        self.ecu_src[st] = max(self.ecu_src.get(st, 0), info['source_timestamp'])

    def _on_state(self, data, info):
        now = time.time_ns()
        row = contract.decode_state(data)
        stamp, x = row.stamp_ns, row.x
        if self.law == 'skyhook':
            u = 20000.0 if x[1] * (x[1] - x[3]) > 0 else 0.0
        else:
            u = self.params.c_e0
        self.pub_cmd.publish(contract.encode_command(stamp, [u] * 10, 20_000_000,
                                                     self.delay_ns))
        self.states += 1
        self.est[stamp] = x
        if self.states > self.WARMUP:
            self.sensor_path.append((now - stamp) * 1e-9)
            self.state_src[stamp] = info['source_timestamp']

    def _on_truth(self, data):
        row = contract.decode_state(data)
        self.truth[row.stamp_ns] = row.x

    def _on_diag(self, data):
        for status in contract.decode_diagnostics(data)[1]:
            self.reports[status.name] = report_from_status(status)

    def _node_stats(self, status_suffix: str, key: str) -> Dict:
        for name, report in self.reports.items():
            if name.endswith(status_suffix) and hasattr(report, key):
                return getattr(report, key).as_dict()
        return {'p50': float('nan'), 'p99': float('nan'), 'max': float('nan'), 'samples': 0}

    def results(self) -> Dict:
        out = {'latency_ms': {k: self._node_stats(*v) for k, v in NODE_LATENCIES.items()}}
        outside = [(src - self.ecu_src[st]) * 1e-9 for st, src in self.state_src.items()
                   if st in self.ecu_src]
        out['latency_ms']['estimator_seen_outside'] = percentiles_ms(outside)
        out['latency_ms']['sensor_to_state'] = percentiles_ms(self.sensor_path)
        out['states'] = self.states
        # Estimate vs truth: the estimate's stamp is the CAN receive time of the cycle,
        # after the ECU's sample time and less than a period later.
        if self.truth and self.est:
            ts = np.array(sorted(self.truth))
            xs = np.array([self.truth[t] for t in ts])
            errs, truth = [], []
            for stamp, x in sorted(self.est.items())[self.WARMUP:]:
                i = int(np.searchsorted(ts, stamp, side='right')) - 1
                if i >= 0 and stamp - ts[i] < 20_000_000:
                    errs.append(x - xs[i])
                    truth.append(xs[i])
            if errs:
                e, tr = np.array(errs), np.array(truth)
                names = ('z_s', 'zdot_s', 'z_us', 'zdot_us', 'z_d', 'zdot_d')[:e.shape[1]]
                out['estimation_rms'] = dict(zip(names, np.sqrt((e ** 2).mean(0)).tolist()))
                out['state_rms'] = dict(zip(names, np.sqrt((tr ** 2).mean(0)).tolist()))
                out['matched'] = len(errs)
        counters = {}
        for name, report in self.reports.items():
            for k in ('bad_crc', 'skipped', 'repeated', 'wrong_length', 'command_timeouts',
                      'incomplete_cycles', 'incomplete', 'overruns', 'nis_mean',
                      'commands_received', 'frames_sent', 'safe_frames_sent'):
                if hasattr(report, k):
                    counters[f'{name.rsplit("/", 1)[-1]}.{k}'] = getattr(report, k)
        out['counters'] = counters
        return out


__all__ = ['NODE_LATENCIES', 'HilBenchDriver']
