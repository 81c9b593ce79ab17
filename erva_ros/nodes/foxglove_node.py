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

Parameters (read at start-up):

========================  ==========  ====================================================
``host``                  string      address to listen on (default 127.0.0.1; anything
                                      else exposes the session to that network)
``port``                  int         TCP port (default 8765; 0 = any free port)
``topics``                string[]    topics to serve; relative names resolve against the
                                      node namespace (default: the whole contract)
``session_metadata``      string      JSON object sent on ``<ns>/session``
``message_backlog_size``  int         messages queued per client before its oldest are
                                      dropped (default 1024)
``diagnostics_period_s``  double (s)  period of this node's status on /diagnostics
``nice``                  int         CPU niceness added to this process (default 10)
========================  ==========  ====================================================

Logs ``serving ws://HOST:PORT`` once listening (`erva run --foxglove` waits for it).  An
address that cannot be bound ends it with one line and exit status 2.  Its status on
/diagnostics (``<name>: foxglove server``) counts the messages received and forwarded,
the clients, the messages offered to each, and the SDK's queue overflows (WARN).
"""

import functools
import json
import os
import sys
import time
from typing import Dict, List, Optional

from rclpy.node import Node
from rcl_interfaces.msg import ParameterDescriptor, ParameterType

from diagnostic_msgs.msg import DiagnosticArray

from erva_ros.core import topics as contract
from erva_ros.ros import qos as ros_qos
from erva_ros.ros.bag_messages import message_class
from erva_ros.ros import diagnostics as diag
from erva_ros.ros import foxglove_server as fg
from erva_ros.ros.runtime import run_node
from erva_ros.nodes.recorder_node import _range, CONTRACT_TYPES, DEFAULT_TOPICS
from erva_ros.core.params import ParamError

NODE_NAME = 'foxglove_server'
DISCOVERY_PERIOD_S = 0.5
#: Reader history per topic: the server takes each message at once; this only bridges
#: a stall of this process (2 s of a 50 Hz topic) without the publishers noticing.
DEPTH = 100


#: Parameters: name -> (default, type, description, range); see the module doc.
PARAMETERS = {
    'host': (fg.DEFAULT_HOST, ParameterType.PARAMETER_STRING,
             'address to listen on (loopback by default)', {}),
    'port': (fg.DEFAULT_PORT, ParameterType.PARAMETER_INTEGER,
             'TCP port to listen on (0: any free port)', _range(0, 65535, integer=True)),
    'topics': (list(DEFAULT_TOPICS), ParameterType.PARAMETER_STRING_ARRAY,
               'topics to serve; relative names resolve against the node namespace', {}),
    'session_metadata': ('{}', ParameterType.PARAMETER_STRING,
                         'JSON object sent on <namespace>/session', {}),
    'message_backlog_size': (fg.DEFAULT_BACKLOG, ParameterType.PARAMETER_INTEGER,
                             'messages queued per client before its oldest are dropped',
                             _range(16, 1_000_000, integer=True)),
    'diagnostics_period_s': (1.0, ParameterType.PARAMETER_DOUBLE,
                             'period of the status on /diagnostics (s)', _range(0.1, 60.0)),
    'nice': (10, ParameterType.PARAMETER_INTEGER,
             'CPU niceness added to this process, so the control loop goes first',
             _range(0, 19, integer=True)),
}


class FoxgloveNode(Node):
    """Forward the session's topics to Foxglove clients; see the module doc."""

    def __init__(self):
        super().__init__(NODE_NAME, namespace=contract.NAMESPACE)
        p = {name: self.declare_parameter(name, default, ParameterDescriptor(
                 name=name, type=ptype, description=doc, read_only=True, **rng)).value
             for name, (default, ptype, doc, rng) in PARAMETERS.items()}
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
        try:
            fg.check_bindable(p['host'], p['port'])
            self.server = fg.FoxgloveServer(
                p['host'], p['port'], name=f'erva {self.get_namespace()}',
                backlog=p['message_backlog_size'], session=session,
                namespace=self.get_namespace())
        except (ValueError, RuntimeError) as exc:
            raise ParamError(str(exc)) from None
        self._use_sim_time = bool(self.get_parameter('use_sim_time').value)
        self.received = 0
        self._subs: Dict[str, object] = {}
        self._pending: List[str] = []
        for name in p['topics']:
            topic = self.resolve_topic_name(name)
            type_name = CONTRACT_TYPES.get(name) or contract.TOPIC_TYPES.get(topic)
            if type_name is None:
                self._pending.append(topic)
            else:
                self._subscribe(topic, type_name)
        # (``pub_diag``: what run_node waits on, acknowledged, when the node stops.)
        self.pub_diag = self.create_publisher(DiagnosticArray, contract.DIAGNOSTICS,
                                              ros_qos.diagnostics_qos())
        self.status = diag.StatusReporter(
            f'{self.get_fully_qualified_name()}{fg.STATUS_SUFFIX}', 'foxglove',
            self.pub_diag.publish, lambda: self.get_clock().now().nanoseconds,
            self._values)
        self.status.set(diag.OK, f'serving {self.server.url}')
        self.create_timer(p['diagnostics_period_s'], self._on_timer)
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
        """Subscribe to the requested topics of unknown type once the graph shows it."""
        if not self._pending:
            self._discovery.cancel()
            return
        graph = dict(self.get_topic_names_and_types())
        for topic in [t for t in self._pending if t in graph]:
            self._pending.remove(topic)
            try:
                self._subscribe(topic, graph[topic][0])
            except Exception as exc:  # noqa: BLE001 -- a type not installed here
                self.get_logger().warning(f'not serving {topic}: {exc}')

    def _on_message(self, topic: str, data: bytes, info: dict) -> None:
        self.received += 1
        if self._use_sim_time:
            log_time = self.get_clock().now().nanoseconds
        else:
            log_time = info.get('received_timestamp') or time.time_ns()
        self.server.log(topic, data, log_time)

    def _values(self) -> Dict[str, object]:
        s = self.server.stats()
        values = {'url': s['url'], 'received': self.received,
                  'forwarded': s['forwarded_total'], 'clients_seen': s['clients_seen'],
                  'clients_subscribed': s['clients_subscribed'],
                  'overflow_events': s['overflow_events'],
                  'topics': len(self._subs), 'awaiting_publisher': len(self._pending)}
        values.update({f'offered:client{cid}': n for cid, n in sorted(s['offered'].items())})
        return values

    def _on_timer(self) -> None:
        if self.server.stats()['overflow_events']:
            self.status.set(diag.WARN, f'serving {self.server.url}; a client did not keep up '
                                       f'and lost messages (the loop did not)')
        self.status.on_timer(0.0)

    def destroy_node(self) -> Optional[bool]:
        """Stop the server (not waiting long for clients that do not read), then the node."""
        server: Optional[fg.FoxgloveServer] = getattr(self, 'server', None)
        if server is not None:
            s = server.stats()
            # Printed, not logged: at shutdown the context (and /rosout) may be gone.
            print(f'{NODE_NAME}: forwarded {s["forwarded_total"]} of {self.received} '
                  f'messages received; {s["clients_seen"]} client(s), offered {s["offered"]}, '
                  f'{s["overflow_events"]} queue overflow event(s)', file=sys.stderr, flush=True)
            server.close()
        return super().destroy_node()


def main(args=None) -> int:
    """Run foxglove_node until shutdown."""
    return run_node('foxglove_node', FoxgloveNode, args)


if __name__ == '__main__':
    sys.exit(main())
