"""Recorder benchmark: added control-loop latency and sustained recording throughput.

1. Latency: a synthetic plant (:mod:`erva_ros.ros.traffic` ``contract --echo``) publishes
   the whole contract at 50 Hz and an echo controller answers every state at once; the
   plant measures state stamp → command receipt.  While this loop runs, recorder_node
   is started and stopped in alternating windows (off, on, off, on, ...), and each
   latency sample is classed by whether the recorder was recording at its stamp --
   alternation cancels the drift of a shared machine's background load.  The
   difference is what recording adds to the control loop (CPU and DDS fan-out; the
   recorder is a separate process).
2. Throughput: the whole contract (8 topics) is published at a multiple of the live
   rate, and a flood publisher sends states on one topic at the given rates (0 = as
   fast as it can); the bag's count against the published count gives the rate the
   recorder sustained and what it lost.  The flood has the contract's reliable
   keep-last-10 QoS, so one topic at 1 kHz leaves the recorder 10 ms of slack; the
   contract traffic keeps 10 s of samples per writer, as the live loop's writers do
   (``publisher_history_s``), so it loses only what a recorder cannot catch up with.

Processes are started with the caller's ROS_DOMAIN_ID and local-only discovery.
"""

import json
import os
import shutil
import tempfile
import time
from typing import Callable, Dict, List, Optional, Sequence

from erva_ros.core.bag import BagError
from erva_ros.core.bag.reader import open_bag
from erva_ros.core.bag.session import recorder_ros_args
from erva_ros.core.metrics import percentiles_ms
from erva_ros.session.processes import ChildProcess, child_env, module_argv
from erva_ros.session.run.run_config import STARTUP_TIMEOUT_S


def _spawn(args: Sequence[str]) -> ChildProcess:
    """Start ``python -m args...``, its stdout and stderr captured."""
    return ChildProcess(args[0], module_argv(*args), child_env(), capture=True)


def _stop(proc: Optional[ChildProcess], timeout: float = 15.0) -> str:
    """Stop ``proc`` (SIGINT first) and return its output ('' for None)."""
    if proc is None:
        return ''
    proc.stop(grace_s=timeout)
    return proc.output()


def _finish(proc: ChildProcess, timeout: float) -> str:
    """Let ``proc`` end by itself within ``timeout`` (else stop it); return its output."""
    proc.stop(grace_s=timeout, first=None)
    return proc.output()


def _last_json(text: str) -> Dict:
    for line in reversed(text.strip().splitlines()):
        if line.startswith('{'):
            return json.loads(line)
    raise BagError('benchmark helper printed no result')


#: Extra recorder parameters of every benchmark run (e.g. ['nice:=0']).
RECORDER_PARAMS: List[str] = []


def start_recorder(bag_dir: str, topics: Optional[List[str]] = None) -> ChildProcess:
    """Start recorder_node on ``bag_dir``; return its process once it is recording."""
    extra = [arg for p in RECORDER_PARAMS for arg in ('-p', p)]
    proc = _spawn(['erva_ros.nodes.recorder_node',
                   *recorder_ros_args(bag_dir, {'scenario': 'bench'}, topics=topics), *extra])
    end = time.monotonic() + STARTUP_TIMEOUT_S
    while not os.path.exists(bag_dir):
        if proc.poll() is not None:
            proc.wait(1.0)
            raise BagError(f'recorder_node exited: {proc.errors().strip()[-300:]}')
        if time.monotonic() > end:
            proc.stop()
            raise BagError(f'recorder_node did not start recording within '
                           f'{STARTUP_TIMEOUT_S:g} s')
        time.sleep(0.05)
    return proc


def echo_loop(window_s: float, pairs: int, work: str,
              progress: Callable[[str], None] = lambda s: None) -> Dict:
    """Return latencies (s) of the echo loop without and with the recorder (alternating)."""
    echo = _spawn(['erva_ros.ros.traffic', 'echo'])
    # Runs until stopped (SIGINT) after the last window.
    plant = _spawn(['erva_ros.ros.traffic', 'contract', '--echo', '--duration', '86400',
                    '--subscribers', '0', '--ack-timeout', '1'])
    on: List[tuple] = []
    recorder = None
    try:
        time.sleep(4.0)       # discovery and the first samples
        for i in range(pairs):
            progress(f'window {2 * i + 1}/{2 * pairs}: recorder off, {window_s:g} s')
            time.sleep(window_s)
            progress(f'window {2 * i + 2}/{2 * pairs}: recorder on, {window_s:g} s')
            bag = os.path.join(work, f'echo{i}')
            recorder = start_recorder(bag)
            began = time.time_ns() + int(2e9)     # subscribed within 2 s of start
            time.sleep(window_s)
            ended = time.time_ns() - int(0.5e9)
            _stop(recorder)
            recorder = None
            on.append((began, ended))
            time.sleep(1.0)   # the recorder's exit settles before the next off window
        result = _last_json(_stop(plant, timeout=60))
    finally:
        _stop(recorder)
        _stop(echo)
        _stop(plant, timeout=1.0)
    if 'error' in result:
        raise BagError(f'benchmark plant: {result["error"]}')
    stamps = result['stamps_ns']
    first, last = on[0][0] - int(window_s * 1e9), on[-1][1]

    def recording(t):
        return any(a <= t <= b for a, b in on)

    def settled(t):   # away from the recorder's start and exit
        return all(not (b < t < b + int(1.5e9)) and not (a - int(2.5e9) < t < a)
                   for a, b in on)
    out = {'published': result['published']}
    for key in ('latency_s', 'publish_latency_s'):
        out[key] = {
            'with': [x for t, x in zip(stamps, result[key]) if recording(t)],
            'without': [x for t, x in zip(stamps, result[key])
                        if first <= t <= last and not recording(t) and settled(t)]}
    return out


def _traffic_into_recorder(bag_dir: str, role: List[str], topics: Optional[List[str]] = None
                           ) -> Dict:
    """Record ``bag_dir`` while ``erva_ros.ros.traffic ROLE...`` runs; return its result."""
    recorder = start_recorder(bag_dir, topics=topics)
    try:
        duration_s = float(role[role.index('--duration') + 1])
        result = _last_json(_finish(_spawn(['erva_ros.ros.traffic', *role]), duration_s + 120))
        if 'error' in result:
            raise BagError(f'benchmark traffic ({role[0]}): {result["error"]}')
        time.sleep(0.5)
    finally:
        _stop(recorder, timeout=60)
    return result


def flood(rate_hz: float, duration_s: float, bag_dir: str) -> Dict:
    """Flood the recorder with states; return published/recorded counts and rates."""
    result = _traffic_into_recorder(bag_dir, ['flood', '--duration', str(duration_s),
                                              '--rate', str(rate_hz)], topics=['state'])
    published = sum(result['published'].values())
    recorded = open_bag(bag_dir).message_count
    return {'requested_hz': rate_hz or None, 'published': published, 'recorded': recorded,
            'lost': published - recorded, 'duration_s': result['duration_s'],
            'published_per_s': published / result['duration_s'],
            'recorded_per_s': recorded / result['duration_s']}


def contract_rate(rate_hz: float, duration_s: float, bag_dir: str) -> Dict:
    """Publish the contract at ``rate_hz`` to the recorder; return published/recorded."""
    result = _traffic_into_recorder(bag_dir, ['contract', '--rate', str(rate_hz),
                                              '--duration', str(duration_s)])
    bag = open_bag(bag_dir)
    published = sum(result['published'].values())
    recorded = sum(bag.topics[t].count if t in bag.topics else 0 for t in result['published'])
    own = sum(1 for m in bag.messages(['/diagnostics']) if b': bag recorder' in m.data)
    recorded -= own
    return {'rate_hz': rate_hz, 'published': published, 'recorded': recorded,
            'lost': published - recorded, 'duration_s': result['duration_s'],
            'recorded_per_s': recorded / result['duration_s']}


def run(window_s: float = 10.0, pairs: int = 3, flood_rates: Sequence[float] = (1000.0, 0.0),
        flood_s: float = 4.0, contract_rates: Sequence[float] = (250.0, 500.0, 1000.0),
        progress: Callable[[str], None] = lambda s: None) -> Dict:
    """Run the benchmark (see module doc); return its figures."""
    work = tempfile.mkdtemp(prefix='erva_bench_')
    try:
        progress(f'echo loop, recorder off/on in {2 * pairs} windows of {window_s:g} s')
        loop = echo_loop(window_s, pairs, work, progress)
        out = {'windows': {'seconds': window_s, 'pairs': pairs},
               'echo_published': loop['published'], 'flood': []}
        # 'command': state stamp -> the echo controller publishes the command (what the
        # live system calls state -> command latency); 'round_trip': -> the plant has it.
        for name, key in (('command', 'publish_latency_s'), ('round_trip', 'latency_s')):
            b = percentiles_ms(loop[key]['without'])
            r = percentiles_ms(loop[key]['with'])
            out[name] = {'without_recorder_ms': b, 'with_recorder_ms': r,
                         'added_ms': {k: r[k] - b[k] for k in ('p50', 'p99', 'max')}}
        out['contract'] = []
        for i, rate in enumerate(contract_rates):
            progress(f'throughput, the contract at {rate:g} Hz, {flood_s:g} s')
            out['contract'].append(contract_rate(rate, flood_s,
                                                 os.path.join(work, f'contract{i}')))
        for i, rate in enumerate(flood_rates):
            progress(f'throughput, {"max" if not rate else f"{rate:g} msg/s"}, {flood_s:g} s')
            out['flood'].append(flood(rate, flood_s, os.path.join(work, f'flood{i}')))
        lossless = [f['recorded_per_s'] for f in out['flood'] + out['contract']
                    if f['lost'] == 0]
        out['sustained_msgs_per_s'] = max(lossless) if lossless else None
        return out
    finally:
        shutil.rmtree(work, ignore_errors=True)


__all__ = ['run', 'echo_loop', 'flood', 'contract_rate', 'start_recorder']
