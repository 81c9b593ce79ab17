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

import math
import os
import tempfile
import time
from typing import Dict, List, Optional

from erva_ros.core import topics
from erva_ros.core.contract import (decode_measurements, encode_state,
                                    MEASUREMENTS_ENCODER as measurements)
from erva_ros.core.model.hardware import GeneratorHardware
from erva_ros.core.metrics import percentiles_ms
from erva_ros.core.model.estimator import ExtendedKalmanFilter
from erva_ros.core.model.params import load_erva_params, paper_params
from erva_ros.core.model.quarter_car import make_model
from erva_ros.core.road.profiles import make_road
from erva_ros.ros.context import RosContext
from erva_ros.session.hil.hil_processes import hil_process_specs
from erva_ros.session.processes import ChildProcess, stop_processes
from erva_ros.session.run.report import jsonable
from erva_ros.session.run.run_config import STARTUP_TIMEOUT_S


def run_live_bench(params_file: str, hil_file: Optional[str], duration_s: float,
                   law: str = 'skyhook', seed: int = 0, namespace: str = topics.NAMESPACE,
                   log=lambda s: None, startup_timeout_s: float = STARTUP_TIMEOUT_S,
                   realtime_priority: int = 0) -> Dict:
    """Run the HIL loop for ``duration_s`` and return the measured figures (see module doc)."""
    from erva_ros.ros.hil_bench_driver import HilBenchDriver

    params = load_erva_params(params_file)
    road = make_road('paper', duration_s + 30.0, seed=seed)
    env = dict(os.environ)
    env.setdefault('ROS_DOMAIN_ID', '0')
    # The driver below is the road source: the ECU takes the heights as they arrive.
    specs = hil_process_specs(params_file, namespace, duration_s, hil_file, env=env,
                              road='ros', realtime_priority=realtime_priority)
    logdir = tempfile.mkdtemp(prefix='erva_bench_hil_')
    ros = RosContext()
    driver = HilBenchDriver(namespace, ros.context, road, law, params)
    ros.add(driver.node)
    procs: List[ChildProcess] = []
    errors: List[str] = []
    try:
        for spec in specs:
            procs.append(ChildProcess.start(spec, logdir))
        log(f'started {", ".join(s.name for s in specs)} (logs in {logdir})')
        t0 = time.monotonic()
        ecu = procs[0]
        while ecu.poll() is None:
            ros.spin_once(0.01)
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
            ros.spin_once(0.02)
    finally:
        stop_processes(procs, grace_s=10.0)
        ros.close()
    if procs and procs[0].poll() not in (0, None):
        errors.append(f'ecu-sim exited with {procs[0].poll()} (logs in {logdir})')
    result = jsonable(driver.results())
    result['errors'] = errors
    result['duration_s'] = duration_s
    result['law'] = law
    result['logs'] = logdir
    return result


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
    from erva_ros.core.hil.bridge import BridgeConfig, BridgeCore
    from erva_ros.core.hil.codec import Chassis, EcuCodec, Kind
    from erva_ros.core.hil.transport import free_udp_ports, open_bus

    codec = EcuCodec()
    a, b = free_udp_ports(2)
    ecu = open_bus(f'udp:{b}:{a}')
    core = BridgeCore(codec, GeneratorHardware(), BridgeConfig(),
                      lambda: open_bus(f'udp:{a}:{b}'))
    core.open()
    tx = codec.sender(Kind.CHASSIS)
    model = make_model(paper_params())
    ekf = ExtendedKalmanFilter(model)
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
            m = decode_measurements(data)
            x, _ = ekf.cycle(m.sensors, m.c_e_mean, m.c_e, 1e-3, 1.1e-3)
            encode_state(k * 20_000_000, x, model.joints)
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
    from erva_ros.core.hil.codec import Command, CommandMode, Kind
    from erva_ros.core.hil.ecu_sim import EcuSimConfig, EcuSimCore, SensorNoise
    from erva_ros.core.hil.transport import free_udp_ports, open_bus

    hw = GeneratorHardware()
    a, b = free_udp_ports(2)
    bridge = open_bus(f'udp:{a}:{b}')
    ecu = EcuSimCore(make_model(paper_params()), hw, codec, lambda: open_bus(f'udp:{b}:{a}'),
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
