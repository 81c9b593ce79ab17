"""The skeleton every erva node is built on: written once, so a node file holds only its wiring.

:class:`LoopNode` owns what each node needs besides its own core:

* its parameters, declared from its schema (:data:`erva_ros.core.node_params.SCHEMAS`,
  the node's name is the key) with descriptors: ``self.p``;
* its typed report (:mod:`erva_ros.core.reports`) and the :class:`StatusReporter` that
  publishes it on ``/diagnostics``: ``self.report``, ``self.status``;
* counted publishers (``published`` per topic in the report: the session's loss
  accounting) and raw subscriptions whose callbacks get the CDR bytes and the
  middleware's reception time (the message families of :mod:`erva_ros.core.contract`
  decode them);
* the steady clock for its timers, the input rejections (counted, logged at a limited
  rate), its real-time priority (applied by :func:`erva_ros.ros.runtime.run_node` once
  the node is built) and the one shutdown protocol (:meth:`stop`).

Hooks a node may override: :meth:`refresh_report` (bring the report's figures up to date
before a status goes out), :meth:`started` (after the priority is set, e.g. start
threads) and :meth:`stop` (the shutdown protocol; the recorder finishes its bag there).
"""

import time
from typing import Callable, List, Optional, Type

from diagnostic_msgs.msg import DiagnosticArray
from rclpy.clock import Clock, ClockType
from rclpy.duration import Duration
from rclpy.node import Node

from erva_ros.core import topics
from erva_ros.core.loop.status import StatusReporter
from erva_ros.core.loop.validation import Rejections, StampWindow
from erva_ros.core.reports import NodeReport
from erva_ros.ros import qos as ros_qos
from erva_ros.ros.parameters import declare_node_parameters

#: The spin loop and the acknowledgement wait wake at least this often (s).
SLICE_S = 0.1


class CountedPublisher:
    """A publisher that counts what it published, for the session's loss accounting."""

    def __init__(self, publisher):
        self.publisher = publisher
        self.topic = publisher.topic_name
        self.count = 0

    def publish(self, msg) -> None:
        """Publish ``msg`` (a message or its CDR bytes) and count it."""
        self.publisher.publish(msg)
        self.count += 1

    def get_subscription_count(self) -> int:
        """Return the subscriptions this writer has matched."""
        return self.publisher.get_subscription_count()


class LoopNode(Node):
    """An erva node: parameters, report, status, clocks, publishers, shutdown (module doc)."""

    #: The node's report type.
    REPORT: Type[NodeReport] = NodeReport

    def __init__(self, name: str, hardware_id: str = '', namespace: Optional[str] = None):
        super().__init__(name, **({'namespace': namespace} if namespace else {}))
        self.p = declare_node_parameters(self, name)
        self.steady = Clock(clock_type=ClockType.STEADY_TIME)
        self.scheduling = 'off'
        self.report = self.REPORT(node=self.get_fully_qualified_name(), hardware_id=hardware_id,
                                  session=self.p.get('session_id', ''))
        self.pub_diag = self.create_publisher(DiagnosticArray, topics.DIAGNOSTICS,
                                              ros_qos.diagnostics_qos())
        self.status = StatusReporter(self.report, self.pub_diag.publish, self.now_ns,
                                     self._refresh)
        self.rejections = Rejections(self.get_logger().warning, time.monotonic,
                                     self.p.get('reject_log_period_s', 1.0))
        #: SCHED_FIFO priority run_node gives the node's threads once it is built: the
        #: loop's in real time; 0 in lock-step, which runs flat out and would starve the
        #: other processes at real-time priority.
        self.realtime_priority = (self.p.get('realtime_priority', 0)
                                  if self.p.get('mode', 'realtime') == 'realtime' else 0)

    # -- building blocks ---------------------------------------------------------------
    def now_ns(self) -> int:
        """Return the node's clock (ns): wall time, or simulated time under use_sim_time."""
        return self.get_clock().now().nanoseconds

    def publisher(self, msg_type, topic: str, qos=None) -> CountedPublisher:
        """Return a counted publisher of a loop topic (history: ``publisher_history_s``)."""
        if qos is None:
            qos = ros_qos.publisher_qos(self.p['publisher_history_s'], self.p['ts'])
        pub = CountedPublisher(self.create_publisher(msg_type, topic, qos))
        self.status.publishers.append(pub)
        return pub

    def subscribe(self, msg_type, topic: str, callback: Callable[[bytes, int], None],
                  qos=None):
        """Subscribe raw: ``callback(data, rx_ns)`` with the middleware's reception time."""
        def on_message(data: bytes, info) -> None:
            callback(data, info.get('received_timestamp') or time.time_ns())
        return self.create_subscription(msg_type, topic, on_message,
                                        qos or ros_qos.control_qos(), raw=True)

    def status_timer(self, busy_window_s: float = 0.0, period_s: Optional[float] = None):
        """Publish the status every ``diagnostics_period_s`` (see StatusReporter.on_timer)."""
        period = period_s or self.p['diagnostics_period_s']
        return self.create_timer(period, lambda: self.on_status_timer(busy_window_s),
                                 clock=self.steady)

    def on_status_timer(self, busy_window_s: float) -> None:
        """Publish the status when due (a node may check its health here first)."""
        self.status.on_timer(busy_window_s)

    def stamp_window(self, lockstep: bool = False) -> StampWindow:
        """Return the node's input stamp window (``max_stamp_lead_s``, ``max_stamp_age_s``).

        In lock-step the node's clock is /clock, which may reach a node after the sample
        it stamps: two periods more lead are allowed there.
        """
        lead = self.p['max_stamp_lead_s'] + (2 * self.p['ts'] if lockstep else 0.0)
        return StampWindow(int(round(lead * 1e9)), int(round(self.p['max_stamp_age_s'] * 1e9)))

    def reject(self, topic: str, why: str) -> None:
        """Count and (at a limited rate) log a rejected input message."""
        self.rejections.reject(topic, why)

    def rejected(self, topic: str) -> int:
        """Return how many messages of ``topic`` were rejected."""
        return self.rejections.counts.get(topic, 0)

    # -- hooks -------------------------------------------------------------------------
    def _refresh(self) -> None:
        self.report.scheduling = self.scheduling
        self.refresh_report()

    def refresh_report(self) -> None:
        """Bring the report's figures up to date (called before each status goes out)."""

    def started(self) -> None:
        """Start what runs once the node is built and its priority set (its threads)."""

    def stop(self, stopping: Callable[[], bool], limit_s: float) -> int:
        """Stop: publish the final status, then wait until all of it is delivered.

        Publishes the report with ``final`` set (its final counts), then waits, bounded
        by ``limit_s`` and in short slices (``stopping()`` true: a second signal, stop
        waiting), until every subscriber acknowledged what this node's counted
        publishers and status wrote.  Returns the process's exit status.
        """
        self.status.publish(final=True)
        self.acked = wait_for_acks([p.publisher for p in self.status.publishers]
                                   + [self.pub_diag], stopping, limit_s)
        return 0


def wait_for_acks(publishers: List, stopping: Callable[[], bool], limit_s: float) -> bool:
    """Return True once every subscriber of ``publishers`` acknowledged all they wrote.

    False after ``limit_s`` or once ``stopping()`` (a second signal) is true.
    """
    deadline = time.monotonic() + limit_s
    for pub in publishers:
        while not stopping():
            left = deadline - time.monotonic()
            if left <= 0:
                return False
            if pub.wait_for_all_acked(Duration(nanoseconds=int(min(left, SLICE_S) * 1e9))):
                break
        else:
            return False
    return True


__all__ = ['SLICE_S', 'CountedPublisher', 'LoopNode', 'wait_for_acks']
