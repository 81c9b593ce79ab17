"""A private rclpy context for the session tools (`erva run`, `erva replay`, bench-hil).

The session and command layers never import rclpy themselves (docs/design.md): they
open a :class:`RosContext`, create or add their nodes through it, spin it, and close it.
The context installs no signal handlers -- the tool owns SIGINT/SIGTERM and decides how
to stop -- and runs one SingleThreadedExecutor (one process per node elsewhere; this
process's observer nodes share it).
"""

import os
from typing import List, Mapping, Optional

from erva_ros.core.errors import CLIError

#: Fast DDS maps domain d to UDP ports 7400 + 250·d + offsets: 232 is the largest that fits.
DOMAIN_ID_MAX = 232


def check_domain_id(environ: Optional[Mapping[str, str]] = None) -> None:
    """Raise CLIError unless $ROS_DOMAIN_ID is unset, empty or an integer 0..232.

    rcl and Fast DDS report a bad one as a port error deep in start-up; this says what
    is wrong before any node or recording starts.
    """
    text = (os.environ if environ is None else environ).get('ROS_DOMAIN_ID', '').strip()
    if text and not (text.isdigit() and int(text) <= DOMAIN_ID_MAX):
        raise CLIError(f'ROS_DOMAIN_ID={text!r} is not a ROS domain: an integer 0..'
                       f'{DOMAIN_ID_MAX} (Fast DDS maps it to UDP ports; 0..101 stay clear '
                       'of Linux\'s ephemeral ports)')


class RosContext:
    """An initialised rclpy context without signal handlers, and its executor."""

    def __init__(self):
        check_domain_id()
        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.signals import SignalHandlerOptions
        self.context = rclpy.Context()
        rclpy.init(args=[], context=self.context,
                   signal_handler_options=SignalHandlerOptions.NO)
        self.executor = SingleThreadedExecutor(context=self.context)
        self._nodes: List[object] = []

    def create_node(self, name: str, namespace: Optional[str] = None):
        """Return a new node in this context, spun by its executor."""
        import rclpy
        node = rclpy.create_node(name, namespace=namespace or '', context=self.context)
        return self.add(node)

    def add(self, node):
        """Spin ``node`` (created with ``context=self.context``) with the executor."""
        self.executor.add_node(node)
        self._nodes.append(node)
        return node

    def spin_once(self, timeout_s: float) -> None:
        """Run at most one ready callback, waiting up to ``timeout_s``."""
        self.executor.spin_once(timeout_sec=timeout_s)

    def close(self) -> None:
        """Stop the executor, destroy the nodes and shut the context down (idempotent)."""
        import rclpy
        self.executor.shutdown()
        while self._nodes:
            self._nodes.pop().destroy_node()
        rclpy.try_shutdown(context=self.context)


def absolute_namespace(namespace: str) -> str:
    """Return ``namespace`` made absolute; ValueError (rcl's first line) if ROS refuses it."""
    from rclpy.exceptions import InvalidNamespaceException
    from rclpy.validate_namespace import validate_namespace
    absolute = namespace if namespace.startswith('/') else '/' + namespace
    try:
        validate_namespace(absolute)
    except InvalidNamespaceException as exc:
        raise ValueError(str(exc).splitlines()[0].rstrip(':')) from None
    return absolute


__all__ = ['RosContext', 'absolute_namespace']
