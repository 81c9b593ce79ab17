"""Serve a session's topics to Foxglove over its WebSocket protocol (the foxglove-sdk server).

Plain Python (no rclpy): the ROS subscriber (``nodes/foxglove_node.py``) and the bag
player (``erva replay --foxglove``) hand it each message's CDR bytes as they are on
DDS / in the bag, and it forwards them unchanged on a channel per topic with the
topic's ``ros2msg`` schema (the full text rosbag2 stores, :mod:`erva_ros.core.bag.schemas`),
so Foxglove decodes them as it decodes a bag, and one layout serves both.

A JSON channel ``<namespace>/session`` carries the session description (scenario,
controller, parameters, version: what the bag stores as its ``erva_session`` record);
it is sent again whenever a client subscribes to it.

Capabilities, as foxglove_bridge offers them: ``parameters`` (view and set the nodes'
parameters, named ``<node>.<parameter>``, e.g. ``/erva/nmpc_node.alpha1``; a
:class:`ParameterSource` maps them onto the nodes' parameter services, a refused change
comes back as an error status with the node's reason), ``connectionGraph`` (which node
publishes and subscribes which topic, which node offers which service:
:meth:`FoxgloveServer.publish_graph`) and ``time`` (the server's clock: a replay's log
time, the lock-step session's /clock).

Slow viewers: the SDK queues up to ``backlog`` messages per client and, when a client
does not read, drops that client's oldest ones (``log`` never waits).  The SDK does not
report how many (foxglove-sdk 0.30.3 discards the count), so :class:`FoxgloveServer`
counts, per client, the messages offered to it, and the overflow events the SDK logs
(throttled by the SDK to one per 30 s for the whole server).
"""

import ipaddress
import json
import logging
import socket
import threading
from typing import Any, Dict, List, Mapping, Optional, Sequence, Tuple

from erva_ros.core import topics
from erva_ros.core.bag.schemas import message_definition
from erva_ros.core.contract import CdrError, decode_parameter_event

DEFAULT_HOST = '127.0.0.1'
DEFAULT_PORT = 8765
DEFAULT_ADDRESS = f'{DEFAULT_HOST}:{DEFAULT_PORT}'
#: Messages the SDK queues per client before it drops that client's oldest (its default):
#: about 2.5 s of the live loop's ~400 messages per second.
DEFAULT_BACKLOG = 1024
#: Channel of the session description, relative to the namespace.
SESSION_TOPIC = 'session'
#: The SDK's WebSocket subprotocol (0.30.3 accepts only this one).
SUBPROTOCOL = 'foxglove.sdk.v1'
#: ``<node>.<parameter>``: how a node's parameter is named to clients (as foxglove_bridge).
NODE_PARAMETER_SEP = '.'
#: Logger of the SDK's "outbox for client ... full" line (Rust log target, via pyo3-log).
_OVERFLOW_LOGGER = 'foxglove.websocket.connected_client.send_lossy'
#: How long closing may wait for clients: the SDK's stop() waits on a client that does
#: not read (its Close frame cannot be sent); the process exit ends such a connection.
STOP_WAIT_S = 1.0


def sdk_missing() -> Optional[str]:
    """Return why the Foxglove server cannot run here (None when foxglove-sdk imports)."""
    try:
        import foxglove  # noqa: F401
    except ImportError as exc:
        return (f'the Foxglove server needs foxglove-sdk ({exc}); install it with '
                f'pip install "erva_ros[foxglove]"')
    return None


def parse_address(text: str) -> Tuple[str, int]:
    """Return (host, port) of ``[HOST:]PORT`` (``[::1]:8765`` for IPv6); raise ValueError."""
    text = str(text).strip()
    host, port = DEFAULT_HOST, text
    if text.startswith('['):
        inner, sep, rest = text[1:].partition(']')
        if not sep or not rest.startswith(':'):
            raise ValueError(f'{text!r}: write an IPv6 address as [ADDRESS]:PORT')
        host, port = inner, rest[1:]
    elif ':' in text:
        host, _, port = text.rpartition(':')
        if ':' in host:
            raise ValueError(f'{text!r}: write an IPv6 address as [ADDRESS]:PORT')
    if not host:
        raise ValueError(f'{text!r}: the host before ":" is empty')
    try:
        number = int(port)
    except ValueError:
        raise ValueError(f'{text!r}: port {port!r} is not a number') from None
    if not 0 <= number <= 65535:
        raise ValueError(f'{text!r}: port {number} is not in [0, 65535] (0: any free port)')
    return host, number


def is_loopback(host: str) -> bool:
    """Return True for localhost and loopback addresses (127.0.0.0/8, ::1)."""
    if host == 'localhost':
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def check_bindable(host: str, port: int) -> None:
    """Raise ValueError (one line) unless a server can listen on ``host:port`` now.

    Binds and closes a socket with SO_REUSEADDR, as the SDK's listener does, so a port
    in use or an address of no interface here is refused before anything starts.
    """
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
    except socket.gaierror as exc:
        raise ValueError(f'cannot resolve host {host!r} ({exc.strerror})') from None
    family, _, _, _, sockaddr = infos[0]
    with socket.socket(family, socket.SOCK_STREAM) as sock:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind(sockaddr)
            sock.listen(1)
        except OSError as exc:
            where = f'{host}:{port}'
            if exc.errno == 98:   # EADDRINUSE
                raise ValueError(f'cannot serve Foxglove on {where}: the port is in use '
                                 f'(choose another PORT, or 0 for any free one)') from None
            raise ValueError(f'cannot serve Foxglove on {where}: {exc.strerror}') from None


def url(host: str, port: int) -> str:
    """Return the ws:// URL a viewer opens for a server listening on host:port."""
    shown = f'[{host}]' if ':' in host else host
    if host in ('0.0.0.0', '::'):
        shown = socket.gethostname()
    return f'ws://{shown}:{port}'


class _Overflows(logging.Handler):
    """Count the SDK's "outbox full" log records (one per 30 s at most, SDK-throttled)."""

    def __init__(self):
        super().__init__(logging.INFO)
        self.events = 0

    def emit(self, record) -> None:
        self.events += 1


class ParameterSource:
    """Where the ``parameters`` capability gets and sets values (the ROS side implements it).

    Names are ``<node>.<parameter>``; values are Python values (None: not set).  Called
    from the SDK's threads.
    """

    def get(self, names: Sequence[str]) -> List[Tuple[str, Any]]:
        """Return (name, value) of ``names`` (empty: every parameter there is)."""
        raise NotImplementedError

    def set(self, values: Sequence[Tuple[str, Any]]) -> List[str]:
        """Set the values (all of a node's at once); return one line per refusal."""
        raise NotImplementedError


class FoxgloveServer:
    """A Foxglove WebSocket server forwarding CDR bytes per topic (see the module doc)."""

    def __init__(self, host: str = DEFAULT_HOST, port: int = DEFAULT_PORT, name: str = 'erva',
                 backlog: int = DEFAULT_BACKLOG, session: Optional[Mapping[str, str]] = None,
                 namespace: str = topics.NAMESPACE, with_time: bool = False,
                 parameters: Optional[ParameterSource] = None, graph: bool = False):
        import foxglove
        from foxglove.websocket import Capability

        self._foxglove = foxglove
        self._lock = threading.Lock()
        self.context = foxglove.Context()
        self.channels: Dict[str, object] = {}
        self._topic_of: Dict[int, str] = {}
        self.forwarded: Dict[str, int] = {}
        #: client id -> {'offered': messages logged while it was subscribed, 'topics': set}
        self.clients: Dict[int, Dict] = {}
        self._subscribers: Dict[str, set] = {}
        self.subscriptions = 0     # subscriptions made so far (by any client)
        self.overflows = _install_overflow_counter()
        self._overflows_at_start = self.overflows.events
        self.session = {str(k): str(v) for k, v in (session or {}).items()}
        self.session_topic = f'{namespace.rstrip("/")}/{SESSION_TOPIC}'
        self._session_channel = foxglove.Channel(self.session_topic, context=self.context)
        self._topic_of[self._session_channel.id()] = self.session_topic
        #: The parameters capability's source, and the names clients follow.
        self.parameters = parameters
        self._watched: set = set()
        #: Clients following the connection graph (the ROS side publishes it while > 0).
        self.graph_subscribers = 0
        capabilities = ([Capability.Time] if with_time else []) \
            + ([Capability.Parameters] if parameters is not None else []) \
            + ([Capability.ConnectionGraph] if graph else [])
        self.server = foxglove.start_server(
            name=name, host=host, port=port, context=self.context,
            server_listener=_Listener(self), supported_encodings=['cdr'],
            capabilities=capabilities, message_backlog_size=int(backlog))
        self.host, self.port = host, self.server.port
        self.url = url(host, self.port)

    # -- channels ----------------------------------------------------------------------------
    def add_topic(self, topic: str, type_name: str) -> None:
        """Advertise ``topic`` (a ROS type 'pkg/msg/Type') with its ros2msg schema."""
        if topic in self.channels:
            return
        encoding, text = message_definition(type_name)
        schema = self._foxglove.Schema(name=type_name, encoding=encoding,
                                       data=text.encode('utf-8'))
        channel = self._foxglove.Channel(topic, schema=schema, message_encoding='cdr',
                                         context=self.context)
        with self._lock:
            self.channels[topic] = channel
            self._topic_of[channel.id()] = topic
            self.forwarded[topic] = 0
            self._subscribers.setdefault(topic, set())

    def log(self, topic: str, data: bytes, log_time_ns: int) -> None:
        """Forward one message's CDR bytes (never waits: a slow client loses its oldest)."""
        channel = self.channels.get(topic)
        if channel is None:
            return
        channel.log(bytes(data), log_time=int(log_time_ns))
        with self._lock:
            self.forwarded[topic] += 1
            for client in self._subscribers[topic]:
                self.clients[client]['offered'] += 1

    def broadcast_time(self, time_ns: int) -> None:
        """Tell the clients the current (playback) time (servers made ``with_time``)."""
        self.server.broadcast_time(int(time_ns))

    def clear_session(self) -> None:
        """Make the clients start afresh (a replay that loops starts its times again)."""
        self.server.clear_session()

    def send_session(self) -> None:
        """Send the session description on its channel (again)."""
        if self.session:
            self._session_channel.log(json.dumps(self.session).encode('utf-8'))

    # -- parameters and the connection graph ---------------------------------------------
    def _parameter(self, name: str, value: Any):
        """Return a foxglove Parameter: floats typed Float64 (a whole 1.0 stays a double)."""
        from foxglove.websocket import Parameter, ParameterType
        if value is None:
            return Parameter(name)
        if isinstance(value, float):
            return Parameter(name, value=value, type=ParameterType.Float64)
        if isinstance(value, (list, tuple)) and value \
                and all(isinstance(v, float) for v in value):
            return Parameter(name, value=list(value), type=ParameterType.Float64Array)
        return Parameter(name, value=list(value) if isinstance(value, tuple) else value)

    def _get_parameters(self, names: Sequence[str]) -> list:
        return [self._parameter(n, v) for n, v in self.parameters.get(list(names))]

    def _set_parameters(self, parameters: Sequence) -> list:
        from foxglove import StatusLevel
        values = [(p.name, p.get_value()) for p in parameters]
        for line in self.parameters.set(values):
            self.server.publish_status(line, StatusLevel.Error)
        return self._get_parameters([n for n, _ in values])

    def parameter_event(self, data: bytes) -> None:
        """Take a /parameter_events message (CDR): its values to the clients following them."""
        try:
            event = decode_parameter_event(data)
        except CdrError:
            return
        self.parameters_changed({f'{event.node}{NODE_PARAMETER_SEP}{k}': v
                                 for k, v in {**event.new, **event.changed}.items()})

    def parameters_changed(self, changed: Mapping[str, Any]) -> None:
        """Send changed values (``<node>.<parameter>``) to the clients following them."""
        with self._lock:
            followed = [(n, v) for n, v in changed.items() if n in self._watched]
        if followed:
            self.server.publish_parameter_values([self._parameter(n, v) for n, v in followed])

    def publish_graph(self, published: Mapping[str, Sequence[str]],
                      subscribed: Mapping[str, Sequence[str]],
                      services: Mapping[str, Sequence[str]]) -> None:
        """Send the connection graph: topic -> publishing / subscribing nodes, service -> nodes.

        Not from an SDK callback (the SDK would deadlock): from the ROS side's own thread.
        """
        from foxglove import ConnectionGraph
        graph = ConnectionGraph()
        for topic, ids in published.items():
            graph.set_published_topic(topic, sorted(ids))
        for topic, ids in subscribed.items():
            graph.set_subscribed_topic(topic, sorted(ids))
        for service, ids in services.items():
            graph.set_advertised_service(service, sorted(ids))
        self.server.publish_connection_graph(graph)

    # -- client bookkeeping (called by the SDK's threads) --------------------------------------
    def _subscribed(self, client_id: int, channel_id: int) -> None:
        topic = self._topic_of.get(channel_id)
        with self._lock:
            entry = self.clients.setdefault(client_id, {'offered': 0, 'topics': set()})
            self.subscriptions += 1
            if topic is not None:
                entry['topics'].add(topic)
                self._subscribers.setdefault(topic, set()).add(client_id)
        if topic == self.session_topic:
            self.send_session()

    def _unsubscribed(self, client_id: int, channel_id: int) -> None:
        topic = self._topic_of.get(channel_id)
        with self._lock:
            entry = self.clients.get(client_id)
            if entry is not None and topic is not None:
                entry['topics'].discard(topic)
            self._subscribers.get(topic, set()).discard(client_id)

    def stats(self) -> Dict:
        """Return the counters: forwarded per topic, clients, offered per client, overflows."""
        with self._lock:
            return {'url': self.url, 'forwarded': dict(self.forwarded),
                    'forwarded_total': sum(self.forwarded.values()),
                    'clients_seen': len(self.clients),
                    'clients_subscribed': sum(1 for c in self.clients.values() if c['topics']),
                    'subscriptions': self.subscriptions,
                    'offered': {cid: c['offered'] for cid, c in self.clients.items()},
                    'overflow_events': self.overflows.events - self._overflows_at_start}

    def close(self) -> None:
        """Stop serving; waits at most STOP_WAIT_S for clients that do not read."""
        stopper = threading.Thread(target=self.server.stop, name='foxglove-stop', daemon=True)
        stopper.start()
        stopper.join(STOP_WAIT_S)


class ReplaySink:
    """Forward a bag's messages as the player publishes them (`erva replay --foxglove`).

    Log times are the recorded ones (so the plots match the bag's); the server's time
    follows them; a replay that starts again (``--loop``) clears the viewers' session.
    """

    def __init__(self, server: FoxgloveServer):
        self.server = server
        self._last = None

    def __call__(self, topic: str, data: bytes, log_time_ns: int) -> None:
        """Forward one message (the player's ``sink``)."""
        if self._last is not None and log_time_ns < self._last:
            self.server.clear_session()
            self.server.send_session()
        self._last = log_time_ns
        self.server.log(topic, data, log_time_ns)
        self.server.broadcast_time(log_time_ns)


class _Listener:
    """The SDK's ServerListener: subscriptions, parameters and the graph's followers."""

    def __init__(self, server: FoxgloveServer):
        self._server = server

    def on_subscribe(self, client, channel) -> None:
        self._server._subscribed(client.id, channel.id)

    def on_unsubscribe(self, client, channel) -> None:
        self._server._unsubscribed(client.id, channel.id)

    def on_get_parameters(self, client, param_names, request_id=None):
        return self._server._get_parameters(param_names)

    def on_set_parameters(self, client, parameters, request_id=None):
        return self._server._set_parameters(parameters)

    def on_parameters_subscribe(self, param_names) -> None:
        with self._server._lock:
            self._server._watched.update(param_names)

    def on_parameters_unsubscribe(self, param_names) -> None:
        with self._server._lock:
            self._server._watched.difference_update(param_names)

    def on_connection_graph_subscribe(self) -> None:
        self._server.graph_subscribers += 1

    def on_connection_graph_unsubscribe(self) -> None:
        self._server.graph_subscribers = max(0, self._server.graph_subscribers - 1)


_OVERFLOW_HANDLER: Optional[_Overflows] = None


def _install_overflow_counter() -> _Overflows:
    """Route the SDK's log to Python logging once: warnings shown, overflows counted."""
    global _OVERFLOW_HANDLER
    if _OVERFLOW_HANDLER is None:
        import foxglove
        _OVERFLOW_HANDLER = _Overflows()
        overflow = logging.getLogger(_OVERFLOW_LOGGER)
        overflow.addHandler(_OVERFLOW_HANDLER)
        overflow.setLevel(logging.INFO)
        overflow.propagate = False
        sdk = logging.getLogger('foxglove')
        if sdk.level == logging.NOTSET:
            sdk.setLevel(logging.WARNING)   # not each client's connect and disconnect
        foxglove.set_log_level('INFO')
    return _OVERFLOW_HANDLER


__all__ = ['FoxgloveServer', 'ParameterSource', 'ReplaySink', 'parse_address', 'check_bindable',
           'is_loopback', 'url',
           'sdk_missing', 'DEFAULT_ADDRESS', 'DEFAULT_HOST', 'DEFAULT_PORT', 'DEFAULT_BACKLOG',
           'SESSION_TOPIC', 'SUBPROTOCOL', 'NODE_PARAMETER_SEP']
