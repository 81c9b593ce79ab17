"""A private rclpy context for the session tools (`erva run`, `erva replay`, bench-hil).

The session and command layers never import rclpy themselves (docs/design.md): they
open a :class:`RosContext`, create or add their nodes through it, spin it, and close it.
The context installs no signal handlers -- the tool owns SIGINT/SIGTERM and decides how
to stop -- and runs one SingleThreadedExecutor (one process per node elsewhere; this
process's observer nodes share it).
"""

from typing import List, Optional


class RosContext:
    """An initialised rclpy context without signal handlers, and its executor."""

    def __init__(self):
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
