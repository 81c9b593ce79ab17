"""Publish a bag's messages with their original timing, as ``ros2 bag play`` does (rclpy).

Messages are published in log-time (receive-time) order; message i goes out when
(log_i − log_0)/rate of wall time has passed since the start (never earlier; a busy
machine may make it later, and ``lateness_ms`` reports by how much each message was
out after its time), as raw CDR bytes (no re-serialisation), from one publisher per
topic that offers the QoS recorded for it (``erva_ros.ros.qos.playback_qos``) but keeps
the history of the live loop's writers (``publisher_history_s``, 10 s of the topic's
messages at the playback rate, where rosbag2 keeps 10 messages): a subscriber -- a
recorder of the replay -- may stall that long and still get every message.
``sink(topic, bytes, log time)`` receives each message too when given (`erva replay
--foxglove`).  ``clock_hz`` > 0 publishes the playback time (bag time) on /clock at that
rate, like ``ros2 bag play --clock``; a /clock recorded in the bag is then not replayed.

The what-if mode (erva_ros/session/whatif.py) does not publish: the road recorded at the
tyre drives a fresh offline closed loop with another controller, written as a new session.
"""

import math
import time
from typing import Callable, Dict, Iterable, List, Optional

from erva_ros.core import topics as contract

from erva_ros.ros import qos as ros_qos
from erva_ros.core.bag import BagError
from erva_ros.core.bag.reader import Bag
from erva_ros.core.metrics import percentiles_ms

SLEEP_SLICE_S = 0.05   # longest sleep between checks of the stop flag


class Player:
    """Replay ``bag`` through ``node``'s publishers (see module doc)."""

    def __init__(self, node, bag: Bag, rate: float = 1.0, topics: Optional[Iterable[str]] = None,
                 loop: bool = False, clock_hz: float = 0.0,
                 sink: Optional[Callable[[str, bytes, int], None]] = None):
        from erva_ros.ros.qos import playback_qos
        from erva_ros.ros.bag_messages import message_class
        from erva_ros.core.node_params import LIVE

        if not rate > 0:
            raise BagError(f'rate {rate} must be positive')
        self.node, self.bag, self.rate, self.loop = node, bag, float(rate), bool(loop)
        self.clock_hz = float(clock_hz or 0.0)
        self.sink = sink
        if topics:
            missing = sorted(set(topics) - set(bag.topics))
            if missing:
                raise BagError(f'topic(s) {", ".join(missing)} not in the bag; it has '
                               f'{", ".join(sorted(bag.topics))}')
            self.topics = sorted(set(topics))
        else:
            self.topics = sorted(bag.topics)
        if self.clock_hz > 0 and contract.CLOCK in self.topics:
            self.topics.remove(contract.CLOCK)
        if not self.topics:
            raise BagError(f'{bag.path}: nothing to play')
        self.publishers = {}
        history_s = LIVE.defaults()['publisher_history_s']
        for name in self.topics:
            info = bag.topics[name]
            qos = playback_qos(info.offered_qos)
            qos.depth = max(qos.depth, self._depth(info.count, history_s))
            self.publishers[name] = node.create_publisher(message_class(info.type), name, qos)
        self.clock_pub = None
        if self.clock_hz > 0:
            from rosgraph_msgs.msg import Clock
            # As deep as the data's history: a stalled subscriber gets every tick repaired.
            self.clock_pub = node.create_publisher(
                Clock, contract.CLOCK, ros_qos.publisher_qos(history_s, 1.0 / self.clock_hz))
        self.published: Dict[str, int] = {name: 0 for name in self.topics}
        self.clock_ticks = 0
        self.clock_ticks_this_pass = 0
        self.lateness_s: List[float] = []

    def _depth(self, count: int, history_s: float) -> int:
        """Return how many of a topic's ``count`` messages are played in ``history_s``."""
        span = self.bag.duration_s
        if span <= 0:
            return count
        return min(count, int(math.ceil(count * history_s * self.rate / span)))

    def wait_for_subscribers(self, timeout_s: float) -> bool:
        """Wait until every publisher has a matched subscription (or ``timeout_s``)."""
        end = time.monotonic() + timeout_s
        pubs = self._all_publishers()
        while time.monotonic() < end:
            if all(p.get_subscription_count() > 0 for p in pubs):
                return True
            time.sleep(0.02)
        return False

    def _publish_clock(self, bag_ns: int) -> None:
        from erva_ros.core.contract import encode_clock
        self.clock_pub.publish(encode_clock(bag_ns))
        self.clock_ticks += 1

    def _sleep_until(self, target: float, wall0: float, bag0: int,
                     should_stop: Callable[[], bool]) -> bool:
        """Sleep until monotonic ``target``, ticking /clock; return False if stopped."""
        clock_period = 1.0 / self.clock_hz if self.clock_pub is not None else None
        while True:
            if should_stop():
                return False
            now = time.monotonic()
            if clock_period is not None:
                due = wall0 + self.clock_ticks_this_pass * clock_period
                if due <= now:
                    self._publish_clock(bag0 + int((now - wall0) * self.rate * 1e9))
                    self.clock_ticks_this_pass += 1
                    continue
                wake = min(target, due)
            else:
                wake = target
            if wake <= now:
                return True
            time.sleep(min(wake - now, SLEEP_SLICE_S))

    def run(self, should_stop: Callable[[], bool] = lambda: False) -> Dict:
        """Play (once, or until stopped with ``loop``); return what was published."""
        passes = 0
        started = time.monotonic()
        while True:
            passes += 1
            wall0 = time.monotonic()
            bag0: Optional[int] = None
            self.clock_ticks_this_pass = 0
            for m in self.bag.messages(self.topics):
                if bag0 is None:
                    bag0 = m.log_time_ns
                target = wall0 + (m.log_time_ns - bag0) * 1e-9 / self.rate
                if not self._sleep_until(target, wall0, bag0, should_stop):
                    return self._stats(passes, started, stopped=True)
                self.publishers[m.topic].publish(m.data)
                if self.sink is not None:
                    self.sink(m.topic, m.data, m.log_time_ns)
                # Measured once the message is out: its source timestamp then lies in
                # [target, target + lateness], a bound a subscriber can check.
                self.lateness_s.append(time.monotonic() - target)
                self.published[m.topic] += 1
            if not self.loop or should_stop() or bag0 is None:
                return self._stats(passes, started, stopped=should_stop())

    def finish(self, timeout_s: float = 5.0) -> bool:
        """Wait until subscribers acknowledged everything (reliable QoS); return success."""
        from rclpy.duration import Duration
        return all(p.wait_for_all_acked(Duration(seconds=timeout_s))
                   for p in self._all_publishers())

    def _all_publishers(self) -> list:
        """Return the topics' publishers and /clock's (ticks count as much as messages)."""
        return list(self.publishers.values()) + ([self.clock_pub] if self.clock_pub else [])

    def _stats(self, passes: int, started: float, stopped: bool) -> Dict:
        return {'bag': self.bag.path, 'rate': self.rate, 'passes': passes,
                'stopped': stopped, 'wall_s': time.monotonic() - started,
                'published': dict(self.published), 'total': sum(self.published.values()),
                'clock_ticks': self.clock_ticks,
                'lateness_ms': percentiles_ms(self.lateness_s)}


__all__ = ['Player']
