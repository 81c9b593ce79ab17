"""Helpers of the tests that run `erva run` as a user does (a process, its stderr, its bag)."""

import json
import os
import re
import signal
import subprocess
import sys
import time

from conftest import REPO, ros_env


def start_run(*args, env=None):
    """Start ``erva run ARGS`` in its own session, stdout and stderr piped (``env``: added)."""
    return subprocess.Popen([sys.executable, '-m', 'erva_ros.cli', 'run', *map(str, args)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=ros_env(env), cwd=REPO, start_new_session=True)


def wait_connected(proc, timeout=120.0, lines=None):
    """Read erva run's stderr until it is connected; return {node: pid} it reported.

    The lines read go to ``lines`` (a list) if given.
    """
    pids = {}
    lines = [] if lines is None else lines
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        line = proc.stderr.readline()
        if not line:
            break
        lines.append(line)
        pids.update({n: int(p) for n, p in re.findall(r'(\w+_node) \(pid (\d+)\)', line)})
        if 'connected in' in line:
            return pids
    raise AssertionError('erva run did not connect:\n' + ''.join(lines))


class SampleWatch:
    """Count the loop's samples in this process (rclpy, own context).

    For tests that act *during* a run: waiting for samples, not for a time, puts the
    action inside the run on any machine.  By default it counts /erva/sprung_accel, which
    the start does not wait for: a real-time run lasts long enough for it to match.  A
    lock-step run may end within a second: ``state_reader=True`` counts /erva/state
    instead, as a reader the run waits for (``erva run --extra-readers 1``), so no sample
    goes by before it is matched.
    """

    def __init__(self, state_reader=False):
        import rclpy
        from geometry_msgs.msg import AccelStamped
        from rclpy.executors import SingleThreadedExecutor
        from sensor_msgs.msg import JointState

        from erva_ros.core import topics
        from erva_ros.ros import qos as ros_qos
        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.node = rclpy.create_node('sample_watch', context=self.context)
        self.samples = 0
        msg_type, topic = ((JointState, topics.STATE) if state_reader
                           else (AccelStamped, topics.SPRUNG_ACCEL))
        self.node.create_subscription(msg_type, f'{topics.NAMESPACE}/{topic}',
                                      self._on_sample, ros_qos.control_qos())
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)

    def _on_sample(self, _msg):
        self.samples += 1

    def wait(self, n, timeout=120.0, proc=None):
        """Spin until ``n`` samples came (generous ``timeout``); fail if they did not.

        With ``proc`` (the `erva run` process, stderr piped) the wait ends as soon as it
        exits, and a failure shows what it printed.
        """
        self.spin_until(lambda: self.samples >= n, lambda: f'the loop ran {self.samples} of '
                        f'{n} samples', timeout, proc)

    def spin_until(self, done, what, timeout=120.0, proc=None):
        """Spin until ``done()``; else fail with ``what()`` (and ``proc``'s output, see wait)."""
        end = time.monotonic() + timeout
        while not done() and time.monotonic() < end and (proc is None or proc.poll() is None):
            self.executor.spin_once(timeout_sec=0.05)
        if done():
            return
        if proc is not None:
            if proc.poll() is None:
                proc.kill()
            proc.wait()
            raise AssertionError(f'{what()}; erva run exited {proc.returncode}:\n'
                                 f'{proc.stderr.read()}')
        raise AssertionError(what())

    def close(self):
        import rclpy
        self.executor.shutdown()
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)


def run_acting_on(node, after_samples, act, *args):
    """Run ``erva run ARGS --json``; call ``act(pid of node)`` ``after_samples`` into the run.

    "Into the run" counts the loop's samples (SampleWatch), not the test's wall time, so
    a busy machine cannot move the action out of the run.  Return (exit code, summary,
    stderr, {node: pid}).
    """
    watch = SampleWatch()
    proc = start_run(*args, '--json')
    try:
        pids = wait_connected(proc)
        watch.wait(after_samples, proc=proc)
        act(pids[node])
        out, err = proc.communicate(timeout=240)
    finally:
        watch.close()
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    return proc.returncode, json.loads(out), err, pids


def run_with_node_stopped(node, tmp_path, duration, stop_after_s, stop_for_s, *args):
    """Run erva run (recording, JSON); SIGSTOP ``node`` ``stop_after_s`` into the run.

    Return (exit code, summary, stderr).
    """
    def stop(pid):
        os.kill(pid, signal.SIGSTOP)
        try:
            time.sleep(stop_for_s)
        finally:
            os.kill(pid, signal.SIGCONT)
    return run_acting_on(node, int(round(stop_after_s / 0.02)), stop, '--duration', duration,
                         '--record', tmp_path, *args)[:3]


def run_with_node_killed(node, after_samples, *args):
    """Run ``erva run ARGS --json``; SIGKILL ``node`` ``after_samples`` into the run."""
    return run_acting_on(node, after_samples, lambda pid: os.kill(pid, signal.SIGKILL), *args)


def bag_counts(bag_dir, decode=False):
    """Return the messages per topic of a bag (all its files), read with the mcap package."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory
    mcaps = [f for f in os.listdir(bag_dir) if f.endswith('.mcap')]
    assert mcaps, os.listdir(bag_dir)
    counts = {}
    for name in mcaps:
        with open(os.path.join(bag_dir, name), 'rb') as fh:
            if decode:
                reader = make_reader(fh, decoder_factories=[DecoderFactory()])
                for _, channel, _, decoded in reader.iter_decoded_messages():
                    counts[channel.topic] = counts.get(channel.topic, 0) + 1
                    assert decoded is not None
            else:
                for _, channel, _ in make_reader(fh).iter_messages():
                    counts[channel.topic] = counts.get(channel.topic, 0) + 1
    return counts


def bag_messages(bag_dir, topics):
    """Return (topic, log time ns, header stamp ns) of a bag's messages on ``topics``.

    Read and decoded with the mcap and mcap-ros2 packages, in log-time order.
    """
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory
    out = []
    for name in sorted(f for f in os.listdir(bag_dir) if f.endswith('.mcap')):
        with open(os.path.join(bag_dir, name), 'rb') as fh:
            reader = make_reader(fh, decoder_factories=[DecoderFactory()])
            for _, channel, message, decoded in reader.iter_decoded_messages(topics=topics):
                stamp = decoded.header.stamp
                out.append((channel.topic, message.log_time,
                            stamp.sec * 1_000_000_000 + stamp.nanosec))
    return sorted(out, key=lambda m: m[1])
