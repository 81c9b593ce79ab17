"""Helpers of the recorder tests (no tests here): watch recorder_node's own status.

recorder_node reports on /diagnostics what it has written (``written``, and per topic
``count:<topic>``).  A test that stops it once that covers what was published -- as
`erva run` does -- needs no sleep: SIGINT then only has the messages in flight to take.
"""

import threading
import time

from erva_ros.core import topics as contract
from erva_ros.ros import qos as ros_qos


class SpinningNode:
    """An rclpy node in a context of its own, spun in a thread (the tests' subscribers)."""

    def __init__(self, name):
        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        self.context = rclpy.context.Context()
        rclpy.init(context=self.context)
        self.node = rclpy.create_node(name, context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.running = True
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.thread.start()

    def _spin(self):
        while self.running:
            self.executor.spin_once(timeout_sec=0.05)

    def close(self):
        import rclpy
        self.running = False
        self.thread.join()
        self.node.destroy_node()
        rclpy.shutdown(context=self.context)


class DiagnosticsWatcher(SpinningNode):
    """Collect /diagnostics statuses in this process (rclpy in a thread)."""

    def __init__(self):
        from diagnostic_msgs.msg import DiagnosticArray
        super().__init__('diag_watcher')
        self.statuses = []
        self.node.create_subscription(DiagnosticArray, contract.DIAGNOSTICS,
                                      lambda m: self.statuses.extend(m.status),
                                      ros_qos.control_qos())

    def values(self, name_part):
        """Return the key-values of each status so far whose name contains ``name_part``."""
        return [{kv.key: kv.value for kv in s.values} for s in list(self.statuses)
                if name_part in s.name]

    def wait(self, condition, timeout=60.0):
        """Wait until ``condition()`` holds (generous ``timeout``); return whether it did."""
        end = time.monotonic() + timeout
        while time.monotonic() < end and not condition():
            time.sleep(0.05)
        return condition()

    def errors(self, name_part):
        return [s for s in self.statuses
                if name_part in s.name and s.level == b'\x02' or
                (name_part in s.name and s.level == 2)]


def recorded_counts(watcher, name='recorder'):
    """Return {topic: messages written} of the newest status of recorder ``name``."""
    statuses = watcher.values(f'{name}: bag recorder')
    if not statuses:
        return {}
    return {k[len('count:'):]: int(v) for k, v in statuses[-1].items()
            if k.startswith('count:')}


def wait_recorded(watcher, published, name='recorder', timeout=120.0):
    """Wait until recorder ``name`` says it wrote ``published`` ({topic: n}) or more.

    More on /diagnostics: the recorder records its own statuses too.  Fails after a
    generous ``timeout`` with what it had written.
    """
    def done():
        counts = recorded_counts(watcher, name)
        return all(counts.get(topic, 0) >= n for topic, n in published.items())
    assert watcher.wait(done, timeout), (recorded_counts(watcher, name), published)
