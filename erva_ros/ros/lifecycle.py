"""Drive managed (lifecycle) nodes through their transitions, as `ros2 lifecycle set` does.

:class:`LifecycleDriver` calls each node's ``<node>/change_state`` service
(lifecycle_msgs/srv/ChangeState) from a node of the caller's, without blocking: the
caller spins its executor and polls.  `erva run` uses it to configure every loop node,
then activate them one by one in a fixed order (:mod:`erva_ros.session.run.supervisor`).
"""

from typing import Dict, Optional, Sequence, Tuple

from lifecycle_msgs.msg import Transition
from lifecycle_msgs.srv import ChangeState, GetState

#: The transitions by the names ``ros2 lifecycle set`` takes.
TRANSITIONS = {'configure': Transition.TRANSITION_CONFIGURE,
               'cleanup': Transition.TRANSITION_CLEANUP,
               'activate': Transition.TRANSITION_ACTIVATE,
               'deactivate': Transition.TRANSITION_DEACTIVATE}


class LifecycleDriver:
    """Request transitions of the nodes ``names`` in ``namespace`` (see the module doc)."""

    def __init__(self, node, names: Sequence[str], namespace: str):
        ns = namespace.rstrip('/')
        self.clients = {n: node.create_client(ChangeState, f'{ns}/{n}/change_state')
                        for n in names}
        self.state_clients = {n: node.create_client(GetState, f'{ns}/{n}/get_state')
                              for n in names}
        self._pending: Dict[str, Tuple[str, object]] = {}
        self._last: Dict[str, bool] = {}      # the newest answered request's success

    def ready(self, names: Optional[Sequence[str]] = None) -> bool:
        """Return True once the nodes' change_state services are there."""
        return all(self.clients[n].service_is_ready() for n in (names or self.clients))

    def request(self, name: str, transition: str) -> None:
        """Ask node ``name`` for ``transition`` (a key of :data:`TRANSITIONS`)."""
        req = ChangeState.Request()
        req.transition.id = TRANSITIONS[transition]
        self._last.pop(name, None)
        self._pending[name] = (transition, self.clients[name].call_async(req))

    def result(self, name: str) -> Optional[bool]:
        """Return the newest request's success, or None while it is still open."""
        if name not in self._pending:
            return self._last.get(name)
        _, future = self._pending[name]
        if not future.done():
            return None
        del self._pending[name]
        response = future.result()
        self._last[name] = bool(response is not None and response.success)
        return self._last[name]

    def pending(self) -> Sequence[str]:
        """Return the nodes with an open request."""
        return tuple(self._pending)


__all__ = ['TRANSITIONS', 'LifecycleDriver']
