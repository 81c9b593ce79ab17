"""The session monitor node of `erva run`: it observes every topic of the run.

It subscribes to the live topics and ``/diagnostics`` exactly as any other subscriber
would (same QoS), takes every message raw (CDR bytes, with the middleware's reception
time) and hands it to a store -- :class:`erva_ros.session.run.observations.Observations`,
which decodes and judges it.  The node costs the loop as little CPU as possible while it
runs: nothing is decoded here.
"""

import time
from typing import Protocol, Sequence

from diagnostic_msgs.msg import DiagnosticArray
from rclpy.node import Node

from erva_ros.core import topics
from erva_ros.core.hil.topics import TOPIC_TYPES
from erva_ros.ros import qos as ros_qos
from erva_ros.ros.bag_messages import message_class


class Sink(Protocol):
    """Where the monitor hands what it takes (an Observations store)."""

    watched: Sequence[str]

    def add(self, topic: str, rx_ns: int, data: bytes) -> None:
        """Keep a data topic's message."""

    def add_diagnostics(self, data: bytes, rx_ns: int) -> None:
        """Keep a DiagnosticArray."""


class Monitor(Node):
    """Take every message of a session raw, with its arrival time, into ``sink``.

    The time master starts when its topics have all their subscribers.  Subscribing to
    the ``gate`` topics last, once every other subscription is matched
    (:meth:`connect`), makes sure no message of the run is published before the monitor
    can get it.
    """

    def __init__(self, sink: Sink, namespace: str = topics.NAMESPACE,
                 name: str = topics.MONITOR_NODE, context=None,
                 gate: Sequence[str] = (topics.ROAD_HEIGHT, topics.ROAD_PREVIEW)):
        super().__init__(name, namespace=namespace, context=context,
                         start_parameter_services=False)
        self.sink = sink
        self._qos = ros_qos.control_qos(depth=1000)   # a stalled erva run loses nothing
        self.gate = tuple(gate)
        self.subscriptions_by_topic = {t: self._subscribe(t) for t in sink.watched
                                       if t not in self.gate}

    def _subscribe(self, topic: str):
        if topic == topics.DIAGNOSTICS:
            def on_status(data: bytes, info) -> None:
                self.sink.add_diagnostics(data, info.get('received_timestamp')
                                          or time.time_ns())
            return self.create_subscription(DiagnosticArray, topic, on_status, self._qos,
                                            raw=True)

        def on_message(data: bytes, info) -> None:
            # The middleware's reception time, not this callback's: erva run spins its
            # monitor between other work, and its figures must be the loop's.
            self.sink.add(topic, info.get('received_timestamp') or time.time_ns(), data)
        type_name = topics.TOPIC_TYPES.get(f'{topics.NAMESPACE}/{topic}')
        if type_name is None:
            type_name = TOPIC_TYPES[f'{topics.NAMESPACE}/{topic}']
        return self.create_subscription(message_class(type_name), topic, on_message,
                                        self._qos, raw=True)

    def connect(self, n_diagnostics: int) -> bool:
        """Return True once every subscription is matched to a publisher (call repeatedly).

        Opens the gate topics once the others are matched; ``n_diagnostics`` is the
        number of nodes publishing /diagnostics.
        """
        def matched(topic):
            sub = self.subscriptions_by_topic.get(topic)
            need = n_diagnostics if topic == topics.DIAGNOSTICS else 1
            return sub is not None and sub.get_publisher_count() >= need

        others = [t for t in self.sink.watched if t not in self.gate]
        if not all(matched(t) for t in others):
            return False
        for t in self.gate:
            if t not in self.subscriptions_by_topic:
                self.subscriptions_by_topic[t] = self._subscribe(t)
        return all(matched(t) for t in self.gate)


__all__ = ['Sink', 'Monitor']
