"""When a time master may start: road_preview_node in real time, plant_sim_node in lock-step.

Each of its topics needs ``wait_for_subscribers`` matched readers and, when
``wait_for_reader`` names a node (`erva run` names its monitor), a reader of that very
node: counting alone lets any other reader -- a ``ros2 topic echo`` started before the
run -- stand in for the monitor, which then misses the first samples.  Once that holds
for ``start_delay_s`` without a break (:class:`Settling`), sample 0 may go out.
"""

from typing import Mapping, Sequence


def readers_ready(node, publishers: Sequence, cfg: Mapping) -> bool:
    """Return True once every publisher (a CountedPublisher) has the readers it waits for."""
    need, name = cfg['wait_for_subscribers'], cfg['wait_for_reader']
    for pub in publishers:
        if pub.get_subscription_count() < need:
            return False
        if name and not any(info.node_name == name
                            for info in node.get_subscriptions_info_by_topic(pub.topic)):
            return False
    return True


class Settling:
    """True once a condition has held for ``delay_s`` without a break (the start's settling)."""

    def __init__(self, delay_s: float):
        self.delay_s = delay_s
        self._since = None

    def held(self, ready: bool, now: float) -> bool:
        """Return True if ``ready`` has been true since at least ``now - delay_s``."""
        if not ready:
            self._since = None
            return False
        if self._since is None:
            self._since = now
        return now - self._since >= self.delay_s


__all__ = ['readers_ready', 'Settling']
