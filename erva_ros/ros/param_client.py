"""Another node's parameters over its rcl_interfaces services, as ``ros2 param`` reaches them.

:class:`RemoteParameters` wraps rclpy's :class:`~rclpy.parameter_client.AsyncParameterClient`
(the services ``<node>/list_parameters``, ``get_parameters``, ``describe_parameters``,
``set_parameters_atomically``): every call returns a future, which the caller completes
with its own executor (`erva param`), in its spin loop (`erva run --set`) or by waiting
from another thread while the node's executor spins (the Foxglove server).

A value given as text (a command line, ``1.0:alpha1=0.5``) is converted to the type the
remote node declared for it (:func:`value_of_text`): ``0`` sets a double parameter to 0.0,
where ``ros2 param set`` would send an integer and be refused.  A refused change comes
back with the node's reason; a read-only one also with the reason its descriptor gives
(:func:`refusal_of`).
"""

from dataclasses import dataclass
import os
import threading
import time
from typing import Any, Dict, List, Mapping, Optional, Sequence, Tuple

from rcl_interfaces.msg import ParameterDescriptor, ParameterType
from rclpy.parameter import Parameter, parameter_value_to_python
from rclpy.parameter_client import AsyncParameterClient
import yaml

from erva_ros.core.errors import CLIError
from erva_ros.core.settings.specs import closest_key
from erva_ros.ros.context import RosContext
from erva_ros.ros.foxglove_server import NODE_PARAMETER_SEP
from erva_ros.ros.parameters import READ_ONLY_NOTE

#: ParameterType values by name, and their names (as `ros2 param describe` prints them).
TYPE_NAMES = {ParameterType.PARAMETER_BOOL: 'boolean', ParameterType.PARAMETER_INTEGER: 'integer',
              ParameterType.PARAMETER_DOUBLE: 'double', ParameterType.PARAMETER_STRING: 'string',
              ParameterType.PARAMETER_BYTE_ARRAY: 'byte array',
              ParameterType.PARAMETER_BOOL_ARRAY: 'boolean array',
              ParameterType.PARAMETER_INTEGER_ARRAY: 'integer array',
              ParameterType.PARAMETER_DOUBLE_ARRAY: 'double array',
              ParameterType.PARAMETER_STRING_ARRAY: 'string array',
              ParameterType.PARAMETER_NOT_SET: 'not set'}
#: The prefix of rclpy's refusal of a read-only parameter.
READ_ONLY_REFUSAL = 'Trying to set a read-only parameter'


class ParameterTypeError(ValueError):
    """A text value that is not of the parameter's declared type."""


def value_of_text(text: str, type_: int) -> Any:
    """Return ``text`` as a Python value of ParameterType ``type_`` (ParameterTypeError if not)."""
    t = text.strip()
    try:
        if type_ == ParameterType.PARAMETER_BOOL:
            if t.lower() not in ('true', 'false'):
                raise ValueError
            return t.lower() == 'true'
        if type_ == ParameterType.PARAMETER_INTEGER:
            return int(t)
        if type_ == ParameterType.PARAMETER_DOUBLE:
            return float(t)
        if type_ == ParameterType.PARAMETER_STRING_ARRAY:
            value = yaml.safe_load(t)
            if not isinstance(value, list):
                raise ValueError
            return [str(v) for v in value]
    except ValueError:
        raise ParameterTypeError(f'{text!r} is not a {TYPE_NAMES.get(type_, type_)}') from None
    return text


def typed(value: Any, type_: int) -> Any:
    """Return ``value`` as the declared type: an int for a double parameter becomes a float."""
    if type_ == ParameterType.PARAMETER_DOUBLE and isinstance(value, int) \
            and not isinstance(value, bool):
        return float(value)
    return value


def to_message(name: str, value: Any):
    """Return the rcl_interfaces/Parameter of a Python value (its type from the value)."""
    return Parameter(name, value=value).to_parameter_msg()


def python_value(parameter_value) -> Any:
    """Return a ParameterValue message as a Python value (None: not set)."""
    return parameter_value_to_python(parameter_value)


def refusal_of(reason: str, described: Optional['Described'] = None) -> str:
    """Return a refusal's reason, with why the parameter is read-only where it says so.

    rclpy refuses a read-only parameter itself (``Trying to set a read-only parameter:
    NAME.``), before the node's callback; the why is in its descriptor's description.
    """
    if described is not None and described.read_only and reason.startswith(READ_ONLY_REFUSAL):
        at = described.description.find(READ_ONLY_NOTE)
        why = described.description[at:] if at >= 0 else 'read-only'
        return f'{reason.rstrip(".")}: {why}'
    return reason


class RemoteParameters:
    """The parameters of node ``remote`` (fully qualified name) through ``node``'s clients."""

    def __init__(self, node, remote: str):
        self.remote = remote
        self.client = AsyncParameterClient(node, remote)

    def ready(self) -> bool:
        """Return True once the remote node's parameter services are there."""
        return self.client.services_are_ready()

    def list(self):
        """Return a future of ListParameters.Response (every name)."""
        return self.client.list_parameters()

    def get(self, names: Sequence[str]):
        """Return a future of GetParameters.Response (``values`` in the order of ``names``)."""
        return self.client.get_parameters(list(names))

    def describe(self, names: Sequence[str]):
        """Return a future of DescribeParameters.Response (``descriptors``)."""
        return self.client.describe_parameters(list(names))

    def set(self, values: Mapping[str, Any]):
        """Return a future of SetParametersAtomically.Response: all of ``values`` or none.

        One request, one /parameter_events message, one check by the node.
        """
        return self.client.set_parameters_atomically(
            [to_message(name, value) for name, value in values.items()])

    def destroy(self) -> None:
        """Destroy the clients (the node lives on)."""
        node = self.client.node
        for attr, client in list(vars(self.client).items()):
            if attr.endswith('_client'):
                node.destroy_client(client)


@dataclass(frozen=True)
class Described:
    """A parameter's descriptor as plain data (what ``ros2 param describe`` prints)."""

    name: str
    type: str                   # TYPE_NAMES' name ('double', ...)
    type_id: int
    description: str
    read_only: bool
    constraints: str            # additional_constraints
    range: Optional[Tuple[float, float, float]] = None   # (from, to, step)

    @classmethod
    def of(cls, d: ParameterDescriptor) -> 'Described':
        """Return the plain form of a ParameterDescriptor message."""
        rng = None
        if d.floating_point_range:
            r = d.floating_point_range[0]
            rng = (r.from_value, r.to_value, r.step)
        elif d.integer_range:
            r = d.integer_range[0]
            rng = (r.from_value, r.to_value, r.step)
        return cls(d.name, TYPE_NAMES.get(d.type, str(d.type)), d.type, d.description,
                   d.read_only, d.additional_constraints, rng)


class ParameterTool:
    """`erva param`'s synchronous access: one private hidden node, spun until each answer.

    Every wait is bounded by ``timeout_s``; running out raises CLIError (exit 2) saying
    what did not answer.
    """

    def __init__(self, timeout_s: float):
        self.timeout_s = timeout_s
        self.ros = RosContext()
        # Hidden (leading underscore), as ros2cli's own nodes: graph tools leave it out.
        self.node = self.ros.create_node(f'_erva_param_{os.getpid()}')
        self._remotes: Dict[str, RemoteParameters] = {}

    def _spin_until(self, done, what: str) -> None:
        deadline = time.monotonic() + self.timeout_s
        while not done():
            left = deadline - time.monotonic()
            if left <= 0:
                raise CLIError(f'{what} did not answer within {self.timeout_s:g} s (is it '
                               'running, on this ROS_DOMAIN_ID? --timeout S waits longer)')
            self.ros.spin_once(min(left, 0.05))

    def answer(self, future, what: str):
        """Return the result of ``future`` once done."""
        self._spin_until(future.done, what)
        return future.result()

    def remote(self, name: str) -> RemoteParameters:
        """Return the parameters of node ``name`` once its services are there."""
        if name not in self._remotes:
            remote = RemoteParameters(self.node, name)
            self._spin_until(remote.ready, f'node {name}')
            self._remotes[name] = remote
        return self._remotes[name]

    def list(self, node: str) -> List[str]:
        """Return the names of ``node``'s parameters, sorted."""
        return sorted(self.answer(self.remote(node).list(), f'node {node}').result.names)

    def get(self, node: str, names: Sequence[str]) -> Dict[str, Any]:
        """Return {name: value} (None: not set, or not declared)."""
        got = self.answer(self.remote(node).get(names), f'node {node}')
        return {n: python_value(v) for n, v in zip(names, got.values)}

    def describe(self, node: str, names: Sequence[str]) -> List[Described]:
        """Return the descriptors of ``names``, in their order."""
        got = self.answer(self.remote(node).describe(names), f'node {node}')
        return [Described.of(d) for d in got.descriptors]

    def set(self, node: str, values: Mapping[str, Any]) -> Optional[str]:
        """Set ``values`` at once (text values take the declared type); return a refusal or None.

        Raises CLIError for a parameter the node does not have or a text not of its type.
        """
        declared = self.list(node)
        unknown = [n for n in values if n not in declared]
        if unknown:
            close = closest_key(unknown[0], declared)
            raise CLIError(f'node {node} has no parameter {unknown[0]!r}'
                           + (f'; did you mean {close!r}?' if close else ''))
        described = {d.name: d for d in self.describe(node, list(values))}
        typed_values = {}
        for name, value in values.items():
            type_id = described[name].type_id
            try:
                typed_values[name] = (value_of_text(value, type_id) if isinstance(value, str)
                                      and type_id != ParameterType.PARAMETER_STRING
                                      else typed(value, type_id))
            except ParameterTypeError as exc:
                raise CLIError(f'parameter {name!r} of {node}: {exc} '
                               f'({described[name].constraints or described[name].type})'
                               ) from None
        result = self.answer(self.remote(node).set(typed_values), f'node {node}').result
        reason = results_reason(result)
        if reason is None:
            return None
        first = next((d for d in described.values() if d.read_only), None)
        return refusal_of(reason, first)

    def nodes(self, namespace: str = '', settle_s: float = 0.5) -> List[str]:
        """Return the nodes with parameter services once discovery settled (``settle_s``).

        The graph is discovered, not known: it is taken as complete once it did not
        change for ``settle_s`` (bounded by the timeout).
        """
        found, since = None, time.monotonic()
        end = since + self.timeout_s
        while time.monotonic() < end:
            self.ros.spin_once(0.05)
            now = node_names_with_parameters(self.node, namespace)
            if now != found:
                found, since = now, time.monotonic()
            elif now and time.monotonic() - since >= settle_s:
                break
        return found or []

    def close(self) -> None:
        """Destroy the clients, the node and the context."""
        for remote in self._remotes.values():
            remote.destroy()
        self.ros.close()


def connection_graph(node, topic_types: Mapping[str, Any]):
    """Return (published, subscribed, services) of the graph: topic or service -> node names."""
    def ids(infos):
        return sorted({f'{i.node_namespace.rstrip("/")}/{i.node_name}' for i in infos})
    published = {t: ids(node.get_publishers_info_by_topic(t)) for t in topic_types}
    subscribed = {t: ids(node.get_subscriptions_info_by_topic(t)) for t in topic_types}
    services: Dict[str, List[str]] = {}
    for name, ns in node.get_node_names_and_namespaces():
        for service, _ in node.get_service_names_and_types_by_node(name, ns):
            services.setdefault(service, []).append(f'{ns.rstrip("/")}/{name}')
    return published, subscribed, services


class GraphParameters:
    """The parameters of the graph's nodes for another thread (the Foxglove server's).

    Implements :class:`erva_ros.ros.foxglove_server.ParameterSource`.  :meth:`refresh`
    (in the node's executor thread) makes the clients of nodes that appeared in
    ``namespace``; :meth:`get` and :meth:`set` (any other thread) wait, at most
    ``timeout_s`` each, on futures the executor completes.
    """

    def __init__(self, node, namespace: str, timeout_s: float = 2.0):
        self.node = node
        self.namespace = namespace
        self.timeout_s = timeout_s
        self._lock = threading.Lock()
        self._remotes: Dict[str, RemoteParameters] = {}

    def refresh(self) -> None:
        """Make clients for the nodes with parameter services (the executor's thread)."""
        for name in node_names_with_parameters(self.node, self.namespace):
            if name not in self._remotes:
                remote = RemoteParameters(self.node, name)
                with self._lock:
                    self._remotes[name] = remote

    def _wait(self, future):
        done = threading.Event()
        future.add_done_callback(lambda _: done.set())
        if not done.wait(self.timeout_s):
            return None
        return future.result()

    def _remote(self, name: str) -> Optional[RemoteParameters]:
        with self._lock:
            return self._remotes.get(name)

    def get(self, names: Sequence[str]) -> List[Tuple[str, Any]]:
        """Return (``node.parameter``, value) of ``names``, of every known node's if empty."""
        by_node: Dict[str, List[str]] = {}
        if names:
            for full in names:
                node, _, param = full.partition(NODE_PARAMETER_SEP)
                by_node.setdefault(node, []).append(param)
        else:
            with self._lock:
                nodes = list(self._remotes)
            for node in nodes:
                listed = self._wait(self._remotes[node].list())
                if listed is not None:
                    by_node[node] = sorted(listed.result.names)
        out = []
        for node, params in by_node.items():
            remote = self._remote(node)
            got = None if remote is None else self._wait(remote.get(params))
            if got is None:
                continue
            out += [(f'{node}{NODE_PARAMETER_SEP}{p}', python_value(v))
                    for p, v in zip(params, got.values)]
        return out

    def set(self, values: Sequence[Tuple[str, Any]]) -> List[str]:
        """Set ``values`` (``node.parameter``: value), each node's at once; return refusals."""
        by_node: Dict[str, Dict[str, Any]] = {}
        for full, value in values:
            node, _, param = full.partition(NODE_PARAMETER_SEP)
            by_node.setdefault(node, {})[param] = value
        errors = []
        for node, params in by_node.items():
            remote = self._remote(node)
            if remote is None:
                errors.append(f'{node}: no such node with parameter services')
                continue
            got = self._wait(remote.describe(list(params)))
            if got is None:
                errors.append(f'{node}: did not answer within {self.timeout_s:g} s')
                continue
            described = [Described.of(d) for d in got.descriptors]
            values_typed = {p: typed(v, d.type_id) for (p, v), d in zip(params.items(),
                                                                        described)}
            answer = self._wait(remote.set(values_typed))
            if answer is None:
                errors.append(f'{node}: did not answer within {self.timeout_s:g} s')
                continue
            reason = results_reason(answer.result)
            if reason is not None:
                first = next((d for d in described if d.read_only), None)
                errors.append(f'{node}: {refusal_of(reason, first)}')
        return errors


def node_names_with_parameters(node, namespace: str = '') -> List[str]:
    """Return the fully qualified nodes of the graph that offer get/list_parameters.

    Within ``namespace`` when given (and not ``node`` itself), sorted.
    """
    own = node.get_fully_qualified_name()
    out = []
    for name, ns in node.get_node_names_and_namespaces():
        fq = f'{ns.rstrip("/")}/{name}'
        if fq == own or (namespace and ns.rstrip('/') != namespace.rstrip('/')):
            continue
        services = {s for s, _ in node.get_service_names_and_types_by_node(name, ns)}
        if {f'{fq}/get_parameters', f'{fq}/list_parameters'} <= services:
            out.append(fq)
    return sorted(set(out))


def results_reason(results) -> Optional[str]:
    """Return the reason of a refused SetParameters(Atomically) response (None: accepted)."""
    results = results if isinstance(results, (list, tuple)) else [results]
    for r in results:
        if not r.successful:
            return r.reason or 'refused (no reason given)'
    return None


__all__ = ['TYPE_NAMES', 'READ_ONLY_REFUSAL', 'ParameterTypeError', 'value_of_text', 'typed',
           'to_message', 'python_value', 'refusal_of', 'RemoteParameters', 'Described',
           'ParameterTool', 'connection_graph', 'GraphParameters',
           'node_names_with_parameters', 'results_reason']
