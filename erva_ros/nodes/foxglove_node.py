"""foxglove_node: serve the running session's topics to Foxglove (WebSocket, no ROS install).

A subscriber like recorder_node, in its own process at normal (niced) priority: it
takes every topic of the live contract -- the ``/erva`` topics resolved against this
node's namespace, ``/diagnostics``, ``/clock`` -- as raw CDR (QoS
``ros_qos.control_qos``, as the publishers offer it) and forwards the bytes unchanged
through :class:`~erva_ros.ros.foxglove_server.FoxgloveServer`: one Foxglove channel per
topic with its ``ros2msg`` schema, log time = reception time as in the bag (node time
under ``use_sim_time``).  Topics whose type the contract does not name are subscribed
once a publisher shows their type.  A client that does not read loses its own oldest
messages; nothing here waits for a client, and the loop's nodes never wait for this one.

Parameters: config/session.yaml (``host``, ``port``, ``topics``, ``session_metadata``,
``message_backlog_size``, ``diagnostics_period_s``, ``nice``; ``ros2 param describe``).

As foxglove_bridge, it offers the ``parameters`` capability (view and set every
parameter of the namespace's nodes, ``/erva/nmpc_node.alpha1``, through their parameter
services: a live one changes at the node's next sample, a refused change comes back with
the node's reason as an error status; values followed by a client are updated from
/parameter_events) and the ``connectionGraph`` (publishers and subscribers of each topic,
the nodes offering each service).  ``/clock`` is served once a publisher of it appears
(lock-step: the plant's), never in real time; under ``use_sim_time`` the server's time
follows it (the ``time`` capability).

Logs ``serving ws://HOST:PORT`` once listening (`erva run --foxglove` waits for it).  An
address that cannot be bound ends it with one line and exit status 2.  Its report on
/diagnostics counts the messages received and forwarded, the clients, the messages
offered to each, and the SDK's queue overflows (WARN).
"""

import functools
import json
import os
import sys
import time
from typing import Dict, List, Optional

from erva_ros.core import topics as contract
from erva_ros.core.contract import decode_clock
from erva_ros.core.levels import OK, WARN
from erva_ros.core.model.params import ParamError
from erva_ros.core.reports import FoxgloveReport
from erva_ros.ros import foxglove_server as fg
from erva_ros.ros import qos as ros_qos
from erva_ros.ros.bag_messages import message_class
from erva_ros.ros.loop_node import LoopNode
from erva_ros.ros.param_client import connection_graph, GraphParameters
from erva_ros.ros.runtime import run_node

DISCOVERY_PERIOD_S = 0.5
#: Reader history per topic: the server takes each message at once; this only bridges
#: a stall of this process (2 s of a 50 Hz topic) without the publishers noticing.
DEPTH = 100
#: Topics served only once a publisher of them appears (as foxglove_bridge serves what
#: the graph has): /clock exists in lock-step only.
ON_DEMAND = (contract.CLOCK,)


class FoxgloveNode(LoopNode):
    """Forward the session's topics to Foxglove clients; see the module doc."""

    NAME = 'foxglove_server'
    REPORT = FoxgloveReport

    def __init__(self):
        super().__init__(self.NAME, 'foxglove server', namespace=contract.NAMESPACE)
        self.report.node += ': foxglove server'
        p = self.p
        missing = fg.sdk_missing()
        if missing:
            raise ParamError(missing)
        try:
            session = json.loads(p['session_metadata'] or '{}')
        except ValueError as exc:
            raise ParamError(f'parameter session_metadata is not JSON ({exc})') from None
        if not isinstance(session, dict):
            raise ParamError('parameter session_metadata must be a JSON object')
        if p['nice']:
            os.nice(p['nice'])   # before the server's threads start: they inherit it
        self._use_sim_time = bool(self.get_parameter('use_sim_time').value)
        self.parameters = GraphParameters(self, self.get_namespace())
        try:
            fg.check_bindable(p['host'], p['port'])
            self.server = fg.FoxgloveServer(
                p['host'], p['port'], name=f'erva {self.get_namespace()}',
                backlog=p['message_backlog_size'], session=session,
                namespace=self.get_namespace(), with_time=self._use_sim_time,
                parameters=self.parameters, graph=True)
        except (ValueError, RuntimeError) as exc:
            raise ParamError(str(exc)) from None
        self._subs: Dict[str, object] = {}
        self._pending: List[str] = []
        self._graph = None          # the connection graph last sent
        self._clock_topic = self.resolve_topic_name(contract.CLOCK)
        for name in p['topics']:
            topic = self.resolve_topic_name(name)
            type_name = contract.type_of(name, self.get_namespace())
            if type_name is None or name in ON_DEMAND:
                self._pending.append(topic)
            else:
                self._subscribe(topic, type_name)
        # Parameter changes, for the clients that follow values (served or not).
        self._events = self.create_subscription(
            message_class(contract.ROS_TOPIC_TYPES[contract.PARAMETER_EVENTS]),
            contract.PARAMETER_EVENTS, self.server.parameter_event,
            ros_qos.control_qos(DEPTH), raw=True)
        self.report.url = self.server.url
        self.status.set(OK, f'serving {self.server.url}')
        self.status_timer()
        self._discovery = self.create_timer(DISCOVERY_PERIOD_S, self._discover)
        # The line `erva run --foxglove` waits for.
        self.get_logger().info(f'serving {self.server.url} ({len(self._subs)} topics'
                               + (f', {len(self._pending)} awaiting a publisher'
                                  if self._pending else '') + ')')

    def _subscribe(self, topic: str, type_name: str) -> None:
        self.server.add_topic(topic, type_name)
        self._subs[topic] = self.create_subscription(
            message_class(type_name), topic, functools.partial(self._on_message, topic),
            ros_qos.control_qos(DEPTH), raw=True)

    def _discover(self) -> None:
        """Follow the graph: topics that got a publisher, nodes with parameters, the graph."""
        graph = dict(self.get_topic_names_and_types())
        for topic in [t for t in self._pending if t in graph
                      and (t != self._clock_topic or self.count_publishers(t))]:
            self._pending.remove(topic)
            try:
                self._subscribe(topic, graph[topic][0])
            except Exception as exc:  # noqa: BLE001 -- a type not installed here
                self.get_logger().warning(f'not serving {topic}: {exc}')
        self.parameters.refresh()
        if self.server.graph_subscribers:       # (as foxglove_bridge: nodes by full name)
            now = connection_graph(self, graph)
            if now != self._graph:
                self.server.publish_graph(*now)
                self._graph = now

    def _on_message(self, topic: str, data: bytes, info: dict) -> None:
        self.report.received += 1
        if self._use_sim_time:
            log_time = self.now_ns()
        else:
            log_time = info.get('received_timestamp') or time.time_ns()
        self.server.log(topic, data, log_time)
        if topic == self._clock_topic and self._use_sim_time:    # the server time: the loop
            self.server.broadcast_time(decode_clock(data))

    def refresh_report(self) -> None:
        s, r = self.server.stats(), self.report
        r.forwarded, r.clients_seen = s['forwarded_total'], s['clients_seen']
        r.clients_subscribed, r.overflow_events = s['clients_subscribed'], s['overflow_events']
        r.topics, r.awaiting_publisher = len(self._subs), len(self._pending)
        r.offered = {f'client{cid}': n for cid, n in sorted(s['offered'].items())}

    def on_status_timer(self, busy_window_s: float) -> None:
        if self.server.stats()['overflow_events']:
            self.status.set(WARN, f'serving {self.server.url}; a client did not keep up '
                                  f'and lost messages (the loop did not)')
        super().on_status_timer(busy_window_s)

    def destroy_node(self) -> Optional[bool]:
        """Stop the server (not waiting long for clients that do not read), then the node."""
        server: Optional[fg.FoxgloveServer] = getattr(self, 'server', None)
        if server is not None:
            s = server.stats()
            # Printed, not logged: at shutdown the context (and /rosout) may be gone.
            print(f'{self.NAME}: forwarded {s["forwarded_total"]} of {self.report.received} '
                  f'messages received; {s["clients_seen"]} client(s), offered {s["offered"]}, '
                  f'{s["overflow_events"]} queue overflow event(s)', file=sys.stderr, flush=True)
            server.close()
        return super().destroy_node()


def main(args=None) -> int:
    """Run foxglove_node until shutdown."""
    return run_node(FoxgloveNode, args)


if __name__ == '__main__':
    sys.exit(main())
