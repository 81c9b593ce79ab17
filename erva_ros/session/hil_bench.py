"""The live HIL benchmark behind `erva bench-hil`: the real loop, its latencies measured.

Processes (as `erva run --ecu virtual` starts them, :func:`hil_process_specs`):
``erva ecu-sim`` (plant + ECU on loopback UDP CAN), ``ecu_bridge_node`` and
``state_estimator_node``.  This process runs a driver node that stands in for the
road node and the NMPC: it publishes the road height at 50 Hz and answers every
``state`` with a ``damping_cmd`` at once (skyhook or passive law), so the loop

    driver → damping_cmd → bridge → CAN → ECU/plant → CAN → bridge → ecu/measurements
    → estimator → state → driver

runs at the ECU's 50 Hz.  Measured:

* by the nodes themselves (reported on /diagnostics, DDS receive time → done):
  bridge ROS→CAN (damping_cmd received → frame sent), bridge CAN→ROS (frame's kernel
  receive time → its topic published), estimator (``ecu/measurements``, one per ECU
  cycle, received → state published); and within each, the node's own processing (time inside its
  callbacks), the rest being time spent waiting to be scheduled;
* by the driver, from message stamps and DDS source timestamps: the estimator seen
  from outside (``ecu/measurements`` published → state published) and the
  whole sensor path (first CAN frame of the cycle received → state received);
* estimation error against the ECU's ground truth (``ecu_sim/state``).

:func:`run_core_bench` times the same stages' plain-Python cores without ROS.
"""

import os
import tempfile
import time
from typing import Dict, List, Optional

import numpy as np

from erva_ros.core import topics
from erva_ros.session.hil_processes import hil_process_specs
from erva_ros.session.processes import ChildProcess, stop_processes
from erva_ros.ros import qos as ros_qos
from erva_ros.core.metrics import percentiles_ms

#: Latency keys of the nodes' diagnostics (prefix of _p50/_p99/_max/_samples).
NODE_LATENCIES = {
    'bridge_ros_to_can': ('ecu_bridge_node: command', 'ros_to_can_ms'),
    'bridge_ros_to_can_processing': ('ecu_bridge_node: command', 'ros_to_can_proc_ms'),
    'bridge_can_to_ros': ('ecu_bridge_node: ecu', 'can_to_ros_ms'),
    'bridge_can_to_ros_processing': ('ecu_bridge_node: ecu', 'can_to_ros_proc_ms'),
    'estimator': ('state_estimator_node', 'latency_ms'),
    'estimator_processing': ('state_estimator_node', 'compute_ms'),
}


def run_live_bench(params_file: str, hil_file: Optional[str], duration_s: float,
                   law: str = 'skyhook', seed: int = 0, namespace: str = topics.NAMESPACE,
                   log=lambda s: None, startup_timeout_s: float = 30.0,
                   realtime_priority: int = 0) -> Dict:
    """Run the HIL loop for ``duration_s`` and return the measured figures (see module doc)."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.signals import SignalHandlerOptions

    from erva_ros.core.params import load_erva_params
    from erva_ros.core.roads import make_road

    params = load_erva_params(params_file)
    road = make_road('paper', duration_s + 30.0, seed=seed)
    env = dict(os.environ)
    env.setdefault('ROS_DOMAIN_ID', '0')
    # The driver below is the road source: the ECU takes the heights as they arrive.
    specs = hil_process_specs(params_file, namespace, duration_s, hil_file, env=env,
                              road='ros', realtime_priority=realtime_priority)
    logdir = tempfile.mkdtemp(prefix='erva_bench_hil_')
    context = rclpy.Context()
    rclpy.init(args=[], context=context, signal_handler_options=SignalHandlerOptions.NO)
    driver = _Driver(namespace, context, road, law, params)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(driver.node)
    procs: List[ChildProcess] = []
    errors: List[str] = []
    try:
        for spec in specs:
            procs.append(ChildProcess.start(spec, logdir))
        log(f'started {", ".join(s.name for s in specs)} (logs in {logdir})')
        t0 = time.monotonic()
        ecu = procs[0]
        while ecu.poll() is None:
            executor.spin_once(timeout_sec=0.01)
            dead = [s.name for s, p in zip(specs[1:], procs[1:]) if p.poll() is not None]
            if dead:
                errors.append(f'{", ".join(dead)} exited early (logs in {logdir})')
                break
            if driver.ready is None and time.monotonic() - t0 > startup_timeout_s:
                errors.append(f'the loop was not connected within {startup_timeout_s:g} s '
                              f'(logs in {logdir})')
                break
            if time.monotonic() - t0 > startup_timeout_s + duration_s + 30:
                errors.append('the ECU did not finish')
                break
        end = time.monotonic() + 1.2   # the nodes' last periodic diagnostics
        while time.monotonic() < end:
            executor.spin_once(timeout_sec=0.02)
    finally:
        stop_processes(procs, grace_s=10.0)
        executor.shutdown()
        driver.node.destroy_node()
        rclpy.try_shutdown(context=context)
    if procs and procs[0].poll() not in (0, None):
        errors.append(f'ecu-sim exited with {procs[0].poll()} (logs in {logdir})')
    result = driver.results()
    result['errors'] = errors
    result['duration_s'] = duration_s
    result['law'] = law
    result['logs'] = logdir
    return result


class _Driver:
    """Road + control-law stand-in and the outside observer of the loop."""

    WARMUP = 25   # cycles (0.5 s) not counted: discovery and first-call allocations

    def __init__(self, namespace, context, road, law, params):
        from diagnostic_msgs.msg import DiagnosticArray
        from geometry_msgs.msg import PointStamped
        from rclpy.node import Node
        from sensor_msgs.msg import JointState
        from trajectory_msgs.msg import JointTrajectory

        from erva_ros.core.hil import topics as hil_topics

        self.node = Node('bench_hil_driver', namespace=namespace, context=context)
        self.road, self.law, self.params = road, law, params
        qos = ros_qos.control_qos()
        self.pub_road = self.node.create_publisher(PointStamped, topics.ROAD_HEIGHT, qos)
        self.pub_cmd = self.node.create_publisher(JointTrajectory, topics.DAMPING_CMD, qos)
        self.node.create_subscription(JointState, topics.STATE, self._on_state, qos)
        self.node.create_subscription(JointState, hil_topics.TRUE_STATE, self._on_truth, qos)
        self.node.create_subscription(DiagnosticArray, topics.DIAGNOSTICS, self._on_diag, qos)
        # The estimator's input: one message per ECU cycle, after the cycle's frames.
        self.node.create_subscription(JointState, hil_topics.ECU_MEASUREMENTS, self._on_ecu,
                                      qos)
        self.t0 = time.time()
        self.ready = None
        self.node.create_timer(0.02, self._on_road_timer)
        self.states = 0
        self.est: Dict[int, np.ndarray] = {}
        self.truth: Dict[int, np.ndarray] = {}
        self.ecu_src: Dict[int, int] = {}       # stamp -> ecu/measurements source time
        self.state_src: Dict[int, int] = {}     # stamp -> source time of the state (ns)
        self.sensor_path: List[float] = []
        self.diag: Dict[str, Dict[str, str]] = {}

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
        from erva_ros.ros.msgs import road_height_msg
        if self.ready is None:
            if not self._graph_ready():
                return
            self.ready = time.monotonic()
            self.t0 = time.time()
        t = time.time()
        self.pub_road.publish(road_height_msg(int(t * 1e9), 0.0, self.road.height(t - self.t0)))

    def _on_ecu(self, msg, info):
        from erva_ros.ros.msgs import time_to_ns
        st = time_to_ns(msg.header.stamp)
        self.ecu_src[st] = max(self.ecu_src.get(st, 0), info['source_timestamp'])

    def _on_state(self, msg, info):
        from erva_ros.ros.msgs import damping_msg, parse_state
        now = time.time_ns()
        stamp, x = parse_state(msg, 'erva' if len(msg.name) == 3 else 'benchmark')
        if self.law == 'skyhook':
            u = 20000.0 if x[1] * (x[1] - x[3]) > 0 else 0.0
        else:
            u = self.params.c_e0
        self.pub_cmd.publish(damping_msg(stamp, [u] * 10, 20_000_000))
        self.states += 1
        self.est[stamp] = x
        if self.states > self.WARMUP:
            self.sensor_path.append((now - stamp) * 1e-9)
            self.state_src[stamp] = info['source_timestamp']

    def _on_truth(self, msg):
        from erva_ros.ros.msgs import parse_state
        stamp, x = parse_state(msg, 'erva' if len(msg.name) == 3 else 'benchmark')
        self.truth[stamp] = x

    def _on_diag(self, arr):
        from erva_ros.ros.diagnostics import parse_status
        for st in arr.status:
            name, level, message, values = parse_status(st)
            self.diag[name] = dict(values, _level=str(level), _message=message)

    def _node_stats(self, status_suffix: str, key: str) -> Dict:
        for name, values in self.diag.items():
            if name.endswith(status_suffix) and f'{key}_p99' in values:
                return {k: float(values[f'{key}_{k}']) for k in ('p50', 'p99', 'max', 'samples')}
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
        for name, values in self.diag.items():
            for k in ('bad_crc', 'skipped', 'repeated', 'wrong_length', 'command_timeouts',
                      'incomplete_cycles', 'incomplete', 'overruns', 'nis_mean',
                      'commands_received', 'frames_sent', 'safe_frames_sent'):
                if k in values:
                    counters[f'{name.rsplit("/", 1)[-1]}.{k}'] = values[k]
        out['counters'] = counters
        return _finite(out)


def _finite(obj):
    """Return ``obj`` with NaN / inf floats replaced by None (valid JSON)."""
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_finite(v) for v in obj]
    if isinstance(obj, float) and not np.isfinite(obj):
        return None
    return obj


def run_core_bench(samples: int = 2000) -> Dict:
    """Time the plain-Python cores alone (no ROS, no DDS): the CPU cost of each stage.

    * bridge ROS→CAN: :meth:`BridgeCore.submit` (clamp, duty, DBC encode, E2E, send on
      a loopback UDP bus);
    * bridge CAN→ROS: :meth:`BridgeCore.receive` of a frame waiting in the socket
      (read, E2E check, DBC decode);
    * estimator: one ECU cycle as state_estimator_node runs it: decode the serialized
      ``ecu/measurements``, the compiled EKF cycle (predict over Ts and update, one
      buffered call), encode the state message;
    * simulated ECU: ``prepare`` (the cycle integrated ahead: latch plan, one compiled
      call) and, at the sample instant, ``run_cycle`` (read, take the prepared step,
      sample, encode and send the three sensor frames): its own share of the loop.
    """
    import math

    from erva_ros.core.estimator import ExtendedKalmanFilter
    from erva_ros.core.hil.bridge import BridgeConfig, BridgeCore
    from erva_ros.core.hil.codec import Chassis, EcuCodec, Kind
    from erva_ros.core.hil.hardware import GeneratorHardware
    from erva_ros.core.hil.topics import MEASUREMENT_NAMES
    from erva_ros.core.hil.transport import free_udp_ports, open_bus
    from erva_ros.ros.cdr import decode_joint_state, JointStateEncoder
    from erva_ros.ros.msgs import state_joint_names
    from erva_ros.core.params import paper_params

    codec = EcuCodec()
    a, b = free_udp_ports(2)
    ecu = open_bus(f'udp:{b}:{a}')
    core = BridgeCore(codec, GeneratorHardware(), BridgeConfig(),
                      lambda: open_bus(f'udp:{a}:{b}'))
    core.open()
    tx = codec.sender(Kind.CHASSIS)
    params = paper_params()
    ekf = ExtendedKalmanFilter(params)
    measurements = JointStateEncoder(MEASUREMENT_NAMES)
    state = JointStateEncoder(state_joint_names('erva'))
    send, recv, est = [], [], []
    ecu_prepare, ecu_sample = _ecu_core_bench(samples, codec)
    try:
        for k in range(samples):
            c_e = 10000.0 + 5000.0 * math.sin(0.1 * k)
            t0 = time.perf_counter()
            core.submit([c_e] * 10)
            send.append(time.perf_counter() - t0)
            ecu.recv(1.0)
            ecu.send(codec.encode(Kind.CHASSIS, Chassis(0.1, 0.001), tx))
            time.sleep(0.0002)                   # the frame is in the socket
            t0 = time.perf_counter()
            frame = core.receive(1.0)
            recv.append(time.perf_counter() - t0)
            assert frame is not None
            data = measurements.encode(k * 20_000_000, (c_e, c_e, 0.1, 1e-3, 0.5, 40.0))
            t0 = time.perf_counter()
            _, _, y, _, _ = decode_joint_state(data)
            x, _ = ekf.cycle((y[2], y[3], y[4]), y[1], y[0], 1e-3, 1.1e-3)
            state.encode(k * 20_000_000, x[0::2].tolist(), x[1::2].tolist())
            est.append(time.perf_counter() - t0)
    finally:
        core.close()
        ecu.shutdown()
    return {'bridge_ros_to_can': percentiles_ms(send),
            'bridge_can_to_ros': percentiles_ms(recv),
            'estimator_cycle': percentiles_ms(est),
            'ecu_prepare': percentiles_ms(ecu_prepare),
            'ecu_sample_and_send': percentiles_ms(ecu_sample)}


def _ecu_core_bench(samples: int, codec):
    """Time the simulated ECU's ``prepare`` and ``run_cycle`` (a command every cycle)."""
    import math

    from erva_ros.core.hil.codec import Command, CommandMode, Kind
    from erva_ros.core.hil.ecu_sim import EcuSimConfig, EcuSimCore, SensorNoise
    from erva_ros.core.hil.hardware import GeneratorHardware
    from erva_ros.core.hil.transport import free_udp_ports, open_bus
    from erva_ros.core.params import paper_params

    hw = GeneratorHardware()
    a, b = free_udp_ports(2)
    bridge = open_bus(f'udp:{a}:{b}')
    ecu = EcuSimCore(paper_params(), hw, codec, lambda: open_bus(f'udp:{b}:{a}'),
                     lambda t: 1e-3 * math.sin(t), EcuSimConfig(), SensorNoise())
    tx = codec.sender(Kind.COMMAND)
    prepare, sample = [], []
    try:
        ecu.open()
        ecu.start(time.time())
        for k in range(samples):
            c_e = 10000.0 + 5000.0 * math.sin(0.1 * k)
            bridge.send(codec.encode(Kind.COMMAND, Command(hw.duty_from_c_e(c_e), c_e,
                                                           CommandMode.CONTROLLED), tx))
            time.sleep(0.0002)                   # the frame is in the socket
            t0 = time.perf_counter()
            ecu.prepare()
            prepare.append(time.perf_counter() - t0)
            t0 = time.perf_counter()
            ecu.run_cycle()
            sample.append(time.perf_counter() - t0)
            while bridge.recv(0.0) is not None:  # the sensor frames
                pass
    finally:
        ecu.close()
        bridge.shutdown()
    return prepare, sample
