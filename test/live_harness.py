"""Test helpers (no tests here): start one real node process; play the rest of the loop.

:class:`Harness` is an ordinary rclpy node (own context, same QoS as the nodes) that
publishes what the node under test subscribes to, on the Ts grid of wall time, and
records everything the node publishes with its arrival time.  It stands in for loop
nodes, so it runs at their priority (SCHED_FIFO 20, where the kernel permits it, as the
node under test does): a busy machine then delays it no more than the loop itself.
"""

import contextlib
import os
import signal
import subprocess
import sys
import time

import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import AccelStamped, PointStamped
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from sensor_msgs.msg import JointState
from trajectory_msgs.msg import JointTrajectory

from erva_ros.core import contract, topics
from erva_ros.core.reports import report_from_status
from erva_ros.ros import qos as ros_qos

from conftest import REPO, ros_env

#: Priority of the loop nodes (config/live.yaml realtime_priority), taken by the harness.
LOOP_PRIORITY = 20
TS = 0.02
TS_NS = 20_000_000
PAPER = os.path.join(REPO, 'config', 'erva_paper.yaml')


def start_node(name, namespace, log_path, *params):
    """Start erva_ros.nodes.<name> in ``namespace`` with ``-p`` params; output to a file."""
    argv = [sys.executable, '-m', f'erva_ros.nodes.{name}', '--ros-args',
            '-r', f'__ns:={namespace}', '--params-file', PAPER]
    for p in params:
        argv += ['-p', p]
    log = open(log_path, 'w')
    proc = subprocess.Popen(argv, stdout=log, stderr=subprocess.STDOUT, env=ros_env(),
                            cwd=REPO, start_new_session=True)
    proc.log_path = log_path
    proc.log_file = log
    return proc


def stop_node(proc, sig=signal.SIGINT, timeout=60.0):
    """Stop a node process with ``sig``; return its exit status (killed if it hangs)."""
    if proc.poll() is None:
        os.killpg(proc.pid, sig)
    try:
        return proc.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
        return None
    finally:
        proc.log_file.close()


@contextlib.contextmanager
def cleaned_up(proc, harness):
    """Close ``harness`` and stop the node ``proc`` however the block ends."""
    try:
        yield
    finally:
        harness.close()
        if proc.poll() is None:
            stop_node(proc)


class Harness:
    """An in-process node that plays the road, the plant or the controller for a test."""

    def __init__(self, namespace):
        self.ctx = rclpy.Context()
        rclpy.init(args=[], context=self.ctx)
        self.node = Node('test_harness', namespace=namespace, context=self.ctx)
        # Every thread of this process, DDS's too (they exist now); undone by close().
        self.realtime = _set_scheduling(os.SCHED_FIFO, LOOP_PRIORITY)
        self.ns = namespace
        self.executor = SingleThreadedExecutor(context=self.ctx)
        self.executor.add_node(self.node)
        qos = ros_qos.control_qos(depth=100)
        n = self.node
        self.pub_state = n.create_publisher(JointState, topics.STATE, qos)
        self.pub_preview = n.create_publisher(JointTrajectory, topics.ROAD_PREVIEW, qos)
        self.pub_height = n.create_publisher(PointStamped, topics.ROAD_HEIGHT, qos)
        self.pub_cmd = n.create_publisher(JointTrajectory, topics.DAMPING_CMD, qos)
        self.commands = []     # (stamp_ns, rx_ns, plan)
        self.states = []       # (stamp_ns, x)
        self.generator = []    # (stamp_ns, displacement, velocity, effort)
        self.accel = []        # (stamp_ns, accel)
        self.diag = []         # (rx_ns, node, level, message, report)
        self.on_state = None

        def sub(msg_type, topic, callback):
            return n.create_subscription(msg_type, topic, callback, qos, raw=True)
        self.sub_cmd = sub(JointTrajectory, topics.DAMPING_CMD, self._cmd)
        self.sub_state = sub(JointState, topics.STATE, self._state)
        self.sub_gen = sub(JointState, topics.GENERATOR, self._gen)
        sub(AccelStamped, topics.SPRUNG_ACCEL, self._accel)
        sub(DiagnosticArray, topics.DIAGNOSTICS, self._diag)

    def _cmd(self, data):
        cmd = contract.decode_command(data)
        self.commands.append((cmd.stamp_ns, time.time_ns(), cmd.plan))

    def _state(self, data):
        row = contract.decode_state(data)
        self.states.append((row.stamp_ns, row.x))
        if self.on_state is not None:
            self.on_state(row.stamp_ns, row.x)

    def _gen(self, data):
        g = contract.decode_generator(data)
        self.generator.append((g.stamp_ns, g.position, g.velocity, g.effort))

    def _accel(self, data):
        a = contract.decode_accel(data)
        self.accel.append((a.stamp_ns, a.sprung_accel))

    def _diag(self, data):
        for status in contract.decode_diagnostics(data)[1]:
            if status.name.startswith(self.ns + '/'):
                self.diag.append((time.time_ns(), status.name.rsplit('/', 1)[-1],
                                  status.level, status.message, report_from_status(status)))

    def spin_until(self, condition, timeout):
        """Spin until ``condition()`` holds; return whether it did within ``timeout`` s."""
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if condition():
                return True
            self.executor.spin_once(timeout_sec=0.01)
        return condition()

    def run_ticks(self, start_ns, k0, k1, on_tick):
        """Call ``on_tick(k, stamp_ns)`` at wall time start + k·Ts for k in [k0, k1), spinning."""
        for k in range(k0, k1):
            due = start_ns + k * TS_NS
            while time.time_ns() < due:
                wait = min(0.002, (due - time.time_ns()) * 1e-9)
                self.executor.spin_once(timeout_sec=max(0.0, wait))
            on_tick(k, due)
        return start_ns + k1 * TS_NS

    def wait_matched(self, pubs, subs, timeout=120.0):
        """Spin until both ends of each publisher and subscription are matched.

        This side is asked directly; the node under test's writers report the readers
        they matched in their report (``subscribers``): a message it published before its
        writer matched ours would never reach the harness.  (A reliable writer of the
        harness repairs what a reader got before it matched.)
        """
        def node_sees_us():
            if not self.diag:
                return False
            report = self.diag[-1][4]
            return all(report.subscribers.get(s.topic_name, 1) >= 1 for s in subs)
        ok = self.spin_until(lambda: all(p.get_subscription_count() >= 1 for p in pubs)
                             and all(s.get_publisher_count() >= 1 for s in subs)
                             and node_sees_us(), timeout)
        assert ok, 'the node under test did not come up'

    def wait_for_diag(self, node, condition, timeout=120.0):
        """Spin until the newest report of ``node`` satisfies ``condition``.

        Returns that report (the caller asserts on it: a timeout leaves the last seen).
        ``condition`` is only asked once the node has reported.
        """
        self.spin_until(lambda: self.last_diag(node) is not None
                        and condition(self.last_diag(node)), timeout)
        return self.last_diag(node)

    def spin_for(self, seconds):
        """Spin for ``seconds`` of wall time."""
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            self.executor.spin_once(timeout_sec=0.005)

    def last_diag(self, node):
        """Return the newest report of ``node`` (None before its first)."""
        for entry in reversed(self.diag):
            if entry[1] == node:
                return entry[4]
        return None

    def close(self):
        self.executor.shutdown()
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.ctx)
        if self.realtime:
            _set_scheduling(os.SCHED_OTHER, 0)


def _set_scheduling(policy, priority):
    """Set every thread of this process to ``policy``; return False if not permitted."""
    try:
        for tid in os.listdir('/proc/self/task'):
            try:
                os.sched_setscheduler(int(tid), policy, os.sched_param(priority))
            except ProcessLookupError:
                continue        # ended since the listing
    except PermissionError:     # no CAP_SYS_NICE: the nodes run at normal priority too
        return False
    return True
