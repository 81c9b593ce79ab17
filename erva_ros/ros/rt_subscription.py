"""A subscription served by its own thread straight from an rcl wait set, not the executor.

rclpy's SingleThreadedExecutor (Jazzy, rclpy 7.1) rebuilds its wait set and walks its
Python task machinery on every wake-up: measured here, 0.3–0.6 ms between the DDS
receive time of a message and its callback, longer than the callback itself.  For the
one message per cycle that is on the HIL loop's critical path (the bridge's
``damping_cmd``, the estimator's ``ecu/measurements``) that is the whole latency budget.

:class:`RealtimeSubscription` takes that message in a dedicated thread that blocks in
``rcl_wait`` on a wait set of just this subscription and a stop guard condition (the GIL
is released while it waits), and calls the callback with ``(msg, info)`` as the executor
would.  An optional ``idle()`` runs in the same thread at a time the callback arms
(:attr:`RealtimeSubscription.idle_at`) if no message came first: the estimator warms its
caches there, just before the next cycle is due.

The subscription lives on a helper node ``<node>_rt`` of the same context and namespace
(one DDS participant per context: it costs no discovery), which no executor spins, so no
message is ever taken twice.  The topic is resolved by the owning node, so its remapping
rules (``-r damping_cmd:=...``, node-specific ones included) apply as to any of its
topics; the graph shows the subscriber as ``<node>_rt``.  The thread inherits the
process's scheduling (SCHED_FIFO, erva_ros/ros/realtime.py, applies to every thread).
"""

import threading
import time
from typing import Any, Callable, Optional

from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.node import Node
from rclpy.parameter import Parameter

#: Longest single wait (s): how soon a stop is noticed even if its wake-up were missed.
MAX_WAIT_S = 0.25


class RealtimeSubscription:
    """Take ``msg_type`` messages of ``topic`` in a dedicated thread (see module doc)."""

    def __init__(self, node: Node, msg_type: Any, topic: str, qos,
                 callback: Callable[[Any, dict], None],
                 idle: Optional[Callable[[], None]] = None, raw: bool = False):
        """Subscribe now; call :meth:`start` to begin taking messages.

        ``raw``: the callback gets the serialized CDR bytes instead of a message object
        (decode what is needed with erva_ros/core/contract.py: much cheaper).

        ``idle()`` runs once in this thread when the monotonic time reaches
        :attr:`idle_at` (s, time.monotonic; None = not armed) with no message waiting;
        the callback re-arms it.  An exception in ``callback`` or ``idle`` shuts the
        context down (the node's spin ends) and :meth:`destroy` re-raises it.
        """
        self._owner = node
        self._callback = callback
        self._idle = idle
        self.idle_at: Optional[float] = None
        self._helper = Node(
            f'{node.get_name()}_rt', namespace=node.get_namespace(), context=node.context,
            use_global_arguments=False, enable_rosout=False, start_parameter_services=False,
            parameter_overrides=[Parameter('start_type_description_service', value=False)])
        self.topic = node.resolve_topic_name(topic)
        self._sub = self._helper.create_subscription(msg_type, self.topic, _never, qos,
                                                     raw=raw)
        self._wake = self._helper.create_guard_condition(_never)
        self._stop = threading.Event()
        self._error: Optional[BaseException] = None
        self._thread = threading.Thread(target=self._run, name=f'rt:{self.topic}',
                                        daemon=True)

    def start(self) -> None:
        self._thread.start()

    def _run(self) -> None:
        context = self._owner.context
        wait_set = _rclpy.WaitSet(1, 1, 0, 0, 0, 0, context.handle)
        sub, wake = self._sub, self._wake
        try:
            with sub.handle, wake.handle:
                while not self._stop.is_set() and context.ok():
                    wait_set.clear_entities()
                    wait_set.add_subscription(sub.handle)
                    wait_set.add_guard_condition(wake.handle)
                    wait_s = MAX_WAIT_S
                    if self.idle_at is not None:
                        wait_s = min(wait_s, max(self.idle_at - time.monotonic(), 0.0))
                    wait_set.wait(int(wait_s * 1e9))
                    if self._stop.is_set():
                        break
                    if wait_set.get_ready_entities('subscription'):
                        taken = sub.handle.take_message(sub.msg_type, sub.raw)
                        if taken is not None:
                            self._callback(*taken)
                    elif self.idle_at is not None and time.monotonic() >= self.idle_at:
                        self.idle_at = None
                        self._idle()
        except BaseException as exc:  # noqa: B902 -- handed to destroy(), not swallowed
            if context.ok() and not self._stop.is_set():
                # As an exception in an executor callback would: the node stops (its spin
                # ends) and destroy() re-raises it, so the process exits with the error.
                self._error = exc
                self._owner.get_logger().fatal(
                    f'{self._thread.name}: {type(exc).__name__}: {exc}; stopping the node')
                context.try_shutdown()

    @property
    def alive(self) -> bool:
        return self._thread.is_alive()

    def destroy(self) -> None:
        """Stop the thread, destroy the helper node; re-raise a callback's exception."""
        self._stop.set()
        try:
            self._wake.trigger()
        except Exception:  # context already shut down: the wait returns by itself
            pass
        if self._thread.is_alive():
            self._thread.join(timeout=2 * MAX_WAIT_S + 1.0)
        self._helper.destroy_node()
        if self._error is not None:
            raise self._error


def _never(*_args) -> None:
    """Do nothing: the callback of entities no executor serves (never called)."""


__all__ = ['RealtimeSubscription', 'MAX_WAIT_S']
