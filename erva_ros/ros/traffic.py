"""Synthetic traffic of the live contract, for the recorder's tests and benchmark (rclpy).

Roles (``python -m erva_ros.ros.traffic ROLE --help``):

``contract``  publishes all eight topics of ``erva_ros.core.topics`` at their live rates --
              the six /erva topics and /clock at ``--rate`` (50 Hz), /diagnostics as
              three nodes do (three messages a second) -- and prints, as one JSON
              line, how many messages it published on each topic.  With ``--echo`` it
              leaves /erva/damping_cmd to an echo node and measures the state →
              command round trip (the plant's view of control-loop latency).
``echo``      answers every state with a damping command stamped with the state's
              stamp, at once (a zero-time controller).
``flood``     publishes states as fast as it can (or at ``--rate``) for a throughput run.

Every publisher waits until ``--subscribers`` readers have matched before the first
message and for all of them to acknowledge the last, so that counts are exact.  The
contract's writers keep ``--history`` seconds of samples, as the live loop's do
(``publisher_history_s``): a reader (the recorder) may stall that long and still get
every message; a keep-last-10 writer would drop what a stalled reader had not yet
acknowledged, and still report everything acknowledged.  The flood keeps the contract
QoS's keep-last 10 (the throughput benchmark measures what a reader sustains with it).
"""

import argparse
import json
import math
import signal
import sys
import time
from typing import Dict, List

import rclpy
from rclpy.duration import Duration
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions

from erva_ros.core import topics as contract
from erva_ros.core import contract as wire
from erva_ros.core.levels import OK
from erva_ros.core.settings.schemas import LIVE
from erva_ros.ros import qos as ros_qos

HORIZON = 10


def _wait_matched(publishers: Dict, timeout_s: float) -> bool:
    """Wait until each publisher (key) has its number (value) of matched readers."""
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if all(p.get_subscription_count() >= n for p, n in publishers.items()):
            return True
        time.sleep(0.02)
    return False


def _wait_acked(publishers: List, timeout_s: float = 5.0) -> bool:
    return all(p.wait_for_all_acked(Duration(seconds=timeout_s)) for p in publishers)


class ContractTraffic(Node):
    """Publish the contract's topics at their rates (see module doc)."""

    def __init__(self, rate_hz: float, echo: bool, clock: bool, history_s: float):
        super().__init__('contract_traffic', namespace=contract.NAMESPACE)
        from diagnostic_msgs.msg import DiagnosticArray
        from geometry_msgs.msg import AccelStamped, PointStamped
        from rosgraph_msgs.msg import Clock
        from sensor_msgs.msg import JointState
        from trajectory_msgs.msg import JointTrajectory
        self.ts = 1.0 / rate_hz
        self.ts_ns = wire.s_to_ns(self.ts)
        qos = ros_qos.publisher_qos(history_s, self.ts)
        self.echo = echo
        self.pubs = {
            contract.STATE: self.create_publisher(JointState, contract.STATE, qos),
            contract.SPRUNG_ACCEL: self.create_publisher(AccelStamped, contract.SPRUNG_ACCEL,
                                                         qos),
            contract.GENERATOR: self.create_publisher(JointState, contract.GENERATOR, qos),
            contract.ROAD_HEIGHT: self.create_publisher(PointStamped, contract.ROAD_HEIGHT, qos),
            contract.ROAD_PREVIEW: self.create_publisher(JointTrajectory, contract.ROAD_PREVIEW,
                                                         qos),
            contract.DIAGNOSTICS: self.create_publisher(DiagnosticArray, contract.DIAGNOSTICS,
                                                        qos),
        }
        if not echo:
            self.pubs[contract.DAMPING_CMD] = self.create_publisher(
                JointTrajectory, contract.DAMPING_CMD, qos)
        if clock:
            self.pubs[contract.CLOCK] = self.create_publisher(Clock, contract.CLOCK, qos)
        self.counts: Dict[str, int] = {self.pubs[k].topic_name: 0 for k in self.pubs}
        self.latency_s: List[float] = []           # state stamp -> command received here
        self.publish_latency_s: List[float] = []   # state stamp -> command published (echo)
        self.latency_stamps_ns: List[int] = []
        self.k = 0
        if echo:
            self.create_subscription(JointTrajectory, contract.DAMPING_CMD, self._on_cmd,
                                     ros_qos.control_qos(), raw=True)

    def _publish(self, key: str, msg) -> None:
        pub = self.pubs[key]
        pub.publish(msg)
        self.counts[pub.topic_name] += 1

    def tick(self) -> None:
        """Publish one control period's messages (and the diagnostics once a second)."""
        t = self.k * self.ts
        w = 1e-3 * math.sin(2 * math.pi * 1.7 * t)
        now = time.time_ns()
        if contract.CLOCK in self.pubs:
            self._publish(contract.CLOCK, wire.encode_clock(now))
        self._publish(contract.ROAD_HEIGHT, wire.encode_road_height(now, 20.0 * t, w))
        self._publish(contract.ROAD_PREVIEW, wire.encode_preview(
            now, [1e-3 * math.sin(2 * math.pi * 1.7 * (t + i * self.ts))
                  for i in range(HORIZON + 1)], self.ts_ns))
        self._publish(contract.SPRUNG_ACCEL, wire.encode_accel(now, 3.0 * w))
        self._publish(contract.GENERATOR, wire.encode_generator(now, 0.1 * w, 0.02, 1e4))
        # The state goes last, so that in the echo loop the command's round trip does
        # not wait for this node's other publications.
        state_ns = time.time_ns()
        self._publish(contract.STATE, wire.encode_state(
            state_ns, [w, 0.01, 0.5 * w, 0.02, 0.1 * w, 0.03], contract.STATE_JOINTS))
        if not self.echo:
            self._publish(contract.DAMPING_CMD,
                          wire.encode_command(state_ns, [1e4] * HORIZON, self.ts_ns))
        per_second = max(1, int(round(1.0 / self.ts)))
        if self.k % per_second == 0:
            for node in ('plant_sim_node', 'road_preview_node', 'nmpc_node'):
                self._publish(contract.DIAGNOSTICS, wire.encode_diagnostics(now, [wire.Status(
                    f'{node}: traffic', OK, 'synthetic', 'erva', {'k': str(self.k)})]))
        self.k += 1

    def _on_cmd(self, data: bytes, info) -> None:
        now = time.time_ns()
        stamp = wire.decode_command(data).stamp_ns
        self.latency_s.append((now - stamp) * 1e-9)
        self.publish_latency_s.append(((info.get('source_timestamp') or now) - stamp) * 1e-9)
        self.latency_stamps_ns.append(stamp)


class Echo(Node):
    """Answer each state with a damping command carrying the state's stamp."""

    def __init__(self):
        super().__init__('echo_controller', namespace=contract.NAMESPACE)
        from sensor_msgs.msg import JointState
        from trajectory_msgs.msg import JointTrajectory
        qos = ros_qos.control_qos()
        self.pub = self.create_publisher(JointTrajectory, contract.DAMPING_CMD, qos)
        self.create_subscription(JointState, contract.STATE, self._on_state, qos, raw=True)
        self.count = 0

    def _on_state(self, data: bytes) -> None:
        stamp = wire.decode_state(data).stamp_ns
        self.pub.publish(wire.encode_command(stamp, [1e4] * HORIZON, 20_000_000))
        self.count += 1


def _stop_flag():
    flag = {'stop': False}

    def handler(*_):
        flag['stop'] = True
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, handler)
    return flag


def _contract(args) -> int:
    node = ContractTraffic(args.rate, args.echo, not args.no_clock, args.history)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    flag = _stop_flag()
    pubs = list(node.pubs.values())
    need = {p: args.subscribers for p in pubs}
    if args.echo:
        need[node.pubs[contract.STATE]] += 1
    if not _wait_matched(need, args.wait):
        print(json.dumps({'error': 'subscribers did not match'}), flush=True)
        return 3
    if args.echo:  # the echo node's command publisher must reach us too
        end = time.monotonic() + args.wait
        while node.count_publishers(contract.NAMESPACE + '/' + contract.DAMPING_CMD) < 1 \
                and time.monotonic() < end:
            executor.spin_once(timeout_sec=0.02)
        time.sleep(0.5)
    n = int(round(args.duration * args.rate))
    start = time.monotonic()
    for k in range(n):
        node.tick()
        target = start + (k + 1) * node.ts
        while not flag['stop']:
            left = target - time.monotonic()
            if left <= 0:
                break
            executor.spin_once(timeout_sec=min(left, 0.005))
        if flag['stop']:
            break
    elapsed = time.monotonic() - start
    end = time.monotonic() + 0.2
    while time.monotonic() < end:  # the last commands of the echo loop
        executor.spin_once(timeout_sec=0.01)
    acked = _wait_acked(pubs, args.ack_timeout)
    out = {'published': node.counts, 'acked': acked, 'duration_s': elapsed}
    if args.echo:
        out['latency_s'] = node.latency_s
        out['publish_latency_s'] = node.publish_latency_s
        out['stamps_ns'] = node.latency_stamps_ns
    print(json.dumps(out), flush=True)
    node.destroy_node()
    return 0


def _echo(args) -> int:
    node = Echo()
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    flag = _stop_flag()
    while not flag['stop']:
        executor.spin_once(timeout_sec=0.1)
    print(json.dumps({'answered': node.count}), flush=True)
    node.destroy_node()
    return 0


def _flood(args) -> int:
    from sensor_msgs.msg import JointState
    node = Node('flood', namespace=contract.NAMESPACE)
    pub = node.create_publisher(JointState, contract.STATE, ros_qos.control_qos())
    flag = _stop_flag()
    if not _wait_matched({pub: args.subscribers}, args.wait):
        print(json.dumps({'error': 'subscribers did not match'}), flush=True)
        return 3
    count = 0
    start = time.monotonic()
    end = start + args.duration
    period = 1.0 / args.rate if args.rate > 0 else 0.0
    while not flag['stop']:
        now = time.monotonic()
        if now >= end:
            break
        if period and now < start + count * period:
            time.sleep(min(start + count * period - now, 0.001))
            continue
        pub.publish(wire.encode_state(time.time_ns(), [0.0] * 6, contract.STATE_JOINTS))
        count += 1
    elapsed = time.monotonic() - start
    acked = _wait_acked([pub], 10.0)
    print(json.dumps({'published': {pub.topic_name: count}, 'acked': acked,
                      'duration_s': elapsed}), flush=True)
    node.destroy_node()
    return 0


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog='python -m erva_ros.ros.traffic',
                                     description=__doc__.split('\n\n')[0])
    sub = parser.add_subparsers(dest='role', required=True)
    p = sub.add_parser('contract', help='all contract topics at their live rates')
    p.add_argument('--duration', type=float, default=10.0, help='seconds (default 10)')
    p.add_argument('--rate', type=float, default=50.0, help='control rate, Hz (default 50)')
    p.add_argument('--echo', action='store_true', help='let an echo node publish commands '
                   'and measure the state -> command round trip')
    p.add_argument('--no-clock', action='store_true', help='do not publish /clock')
    p.add_argument('--subscribers', type=int, default=1,
                   help='readers to wait for on every topic (default 1; with --echo the '
                        'echo node comes on top on the state topic)')
    p.add_argument('--wait', type=float, default=20.0, help='seconds to wait for them')
    p.add_argument('--ack-timeout', type=float, default=5.0,
                   help='seconds to wait for acknowledgements at the end (per topic)')
    p.add_argument('--history', type=float, default=LIVE.defaults()['publisher_history_s'],
                   help='seconds of samples each writer keeps for a stalled reader '
                        '(default: the live loop\'s publisher_history_s, 10)')
    sub.add_parser('echo', help='answer states with commands')
    p = sub.add_parser('flood', help='states as fast as possible')
    p.add_argument('--duration', type=float, default=5.0)
    p.add_argument('--rate', type=float, default=0.0, help='Hz; 0 = as fast as possible')
    p.add_argument('--subscribers', type=int, default=1)
    p.add_argument('--wait', type=float, default=20.0)
    args = parser.parse_args(argv)
    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    try:
        return {'contract': _contract, 'echo': _echo, 'flood': _flood}[args.role](args)
    except (KeyboardInterrupt, ExternalShutdownException):
        return 130
    finally:
        rclpy.try_shutdown()


if __name__ == '__main__':
    sys.exit(main())
