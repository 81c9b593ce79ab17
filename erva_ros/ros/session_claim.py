"""Where `erva run` claims its namespace, and hears the claims of other sessions.

One reliable, transient-local, keep-last-1 topic per namespace
(:data:`erva_ros.core.topics.SESSION_CLAIM`): a session that joins the domain later gets
the newest claim of every session already there as soon as discovery matches it, with
no period to wait for.  The claims are DiagnosticArrays of one
:class:`~erva_ros.core.reports.SessionClaim` each; who wins is decided by the session
(:class:`erva_ros.session.run.start_gate.Contest`).
"""

from typing import Callable

from diagnostic_msgs.msg import DiagnosticArray
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from erva_ros.core import topics


class ClaimChannel:
    """Publish this session's claim; hand every claim heard (CDR bytes) to ``on_claim``."""

    def __init__(self, node, namespace: str, on_claim: Callable[[bytes], None]):
        self.node = node
        self.topic = f'{namespace.rstrip("/")}/{topics.SESSION_CLAIM}'
        qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                         reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self.publisher = node.create_publisher(DiagnosticArray, self.topic, qos)
        self.subscription = node.create_subscription(
            DiagnosticArray, self.topic, lambda data, info: on_claim(data), qos, raw=True)

    def publish(self, data: bytes) -> None:
        """Publish (or renew) this session's claim."""
        self.publisher.publish(data)

    def others(self) -> int:
        """Return how many other claimants are in the graph now (their claims' writers)."""
        return max(0, self.node.count_publishers(self.topic) - 1)


__all__ = ['ClaimChannel']
