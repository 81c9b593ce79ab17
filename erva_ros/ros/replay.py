"""Publish a bag's messages with their original timing, as ``ros2 bag play`` does (rclpy).

Messages are published in log-time (receive-time) order; message i goes out when
(log_i − log_0)/rate of playback time has passed since the start (never earlier; a busy
machine may make it later, and ``lateness_ms`` reports by how much each message was
out after its time), as raw CDR bytes (no re-serialisation), from one publisher per
topic that offers the QoS recorded for it (``erva_ros.ros.qos.playback_qos``) but keeps
the history of the live loop's writers (``publisher_history_s``, 10 s of the topic's
messages at the playback rate, where rosbag2 keeps 10 messages): a subscriber -- a
recorder of the replay -- may stall that long and still get every message.
``sink(topic, bytes, log time)`` receives each message too when given (`erva replay
--foxglove`).  ``clock_hz`` > 0 publishes the playback time (bag time) on /clock at that
rate, like ``ros2 bag play --clock``; a /clock recorded in the bag is then not replayed.

Topic selection, ``start_offset_s`` (log_0 is then the bag's start plus the offset),
``playback_duration_s`` and pauses follow ``ros2 bag play``
(:mod:`erva_ros.core.bag.playback`).  :meth:`Player.pause`, :meth:`Player.resume` and
:meth:`Player.toggle_pause` may be called from a signal handler or another thread: they
only queue the request, which the playing loop applies (``on_pause`` is then told).
``remap`` publishes a recorded topic under another name.  Each message's publisher is
asked how many subscribers it has matched as it publishes (:class:`Reach`): ``on_start``
is told the counts when playing starts, and the stats count what went out before a
topic's last subscriber matched.

The what-if mode (erva_ros/session/bag/whatif.py) does not publish: the road recorded at the
tyre drives a fresh offline closed loop with another controller, written as a new session.
"""

import math
import queue
import time
from typing import Callable, Dict, Iterable, List, Mapping, Optional, Sequence

from erva_ros.core import topics as contract

from erva_ros.core.contract import encode_clock
from erva_ros.core.settings.schemas import LIVE
from erva_ros.ros import qos as ros_qos
from erva_ros.core.bag import BagError
from erva_ros.core.bag.playback import PlaybackClock, Reach, select_topics
from erva_ros.core.bag.reader import Bag
from erva_ros.core.metrics import percentiles_ms
from erva_ros.ros.bag_messages import message_class

SLEEP_SLICE_S = 0.05   # longest sleep between checks of the stop flag


class Player:
    """Replay ``bag`` through ``node``'s publishers (see module doc)."""

    def __init__(self, node, bag: Bag, rate: float = 1.0, topics: Optional[Iterable[str]] = None,
                 loop: bool = False, clock_hz: float = 0.0,
                 sink: Optional[Callable[[str, bytes, int], None]] = None,
                 start_offset_s: float = 0.0, playback_duration_s: Optional[float] = None,
                 start_paused: bool = False, regex: str = '',
                 exclude_topics: Sequence[str] = (), exclude_regex: str = '',
                 remap: Optional[Mapping[str, str]] = None):
        from erva_ros.ros.qos import playback_qos

        if not rate > 0:
            raise BagError(f'rate {rate} must be positive')
        if not start_offset_s >= 0:
            raise BagError(f'start offset {start_offset_s} s must be >= 0')
        self.node, self.bag, self.rate, self.loop = node, bag, float(rate), bool(loop)
        self.clock_hz = float(clock_hz or 0.0)
        self.sink = sink
        self.start_offset_s = float(start_offset_s)
        self.playback_duration_s = playback_duration_s
        self.start_paused = bool(start_paused)
        #: Called as on_pause(paused, messages published so far) when a pause or a
        #: resume takes effect (in the playing thread).
        self.on_pause: Optional[Callable[[bool, int], None]] = None
        #: Called as on_start(reach) once, when playing starts (the subscribers matched
        #: per topic then are in ``reach``).
        self.on_start: Optional[Callable[[Reach], None]] = None
        self._requests: 'queue.SimpleQueue[str]' = queue.SimpleQueue()
        self.topics = select_topics(bag.topics, list(topics or ()), regex,
                                    list(exclude_topics or ()), exclude_regex)
        if self.clock_hz > 0 and contract.CLOCK in self.topics:
            self.topics.remove(contract.CLOCK)
        if not self.topics:
            raise BagError(f'{bag.path}: nothing to play')
        self.remap = dict(remap or {})
        unknown = sorted(set(self.remap) - set(self.topics))
        if unknown:
            raise BagError(f'--remap {", ".join(unknown)}: not a played topic')
        self.publishers = {}
        history_s = LIVE.defaults()['publisher_history_s']
        for name in self.topics:
            info = bag.topics[name]
            qos = playback_qos(info.offered_qos)
            qos.depth = max(qos.depth, self._depth(info.count, history_s))
            self.publishers[name] = node.create_publisher(
                message_class(info.type), self.remap.get(name, name), qos)
        self.clock_pub = None
        if self.clock_hz > 0:
            from rosgraph_msgs.msg import Clock
            # As deep as the data's history: a stalled subscriber gets every tick repaired.
            self.clock_pub = node.create_publisher(
                Clock, contract.CLOCK, ros_qos.publisher_qos(history_s, 1.0 / self.clock_hz))
        self.reach = Reach(self.topics)
        self.clock_ticks = 0
        self.pauses = 0
        self.lateness_s: List[float] = []
        #: The playback time: bag time as a function of wall time, with its pauses.
        self.playback = PlaybackClock(0, self.rate, time.monotonic(), paused=self.start_paused)

    # -- pause and resume (safe from signal handlers and other threads) --------------------
    def pause(self) -> None:
        """Ask the playing loop to pause."""
        self._requests.put('pause')

    def resume(self) -> None:
        """Ask the playing loop to resume."""
        self._requests.put('resume')

    def toggle_pause(self) -> None:
        """Ask the playing loop to pause if it plays, to resume if it is paused."""
        self._requests.put('toggle')

    def _apply_requests(self, now: float) -> None:
        while True:
            try:
                request = self._requests.get_nowait()
            except queue.Empty:
                return
            if request == 'toggle':
                request = 'resume' if self.playback.paused else 'pause'
            changed = self.playback.pause(now) if request == 'pause' else self.playback.resume(now)
            if changed:
                self.pauses += request == 'pause'
                if self.on_pause is not None:
                    self.on_pause(self.playback.paused, sum(self.published.values()))

    @property
    def published(self) -> Dict[str, int]:
        """Return the messages published so far per topic."""
        return self.reach.published

    def matched(self) -> Dict[str, int]:
        """Return the subscribers each topic's publisher has matched now."""
        return {t: p.get_subscription_count() for t, p in self.publishers.items()}

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
        self.clock_pub.publish(encode_clock(bag_ns))
        self.clock_ticks += 1

    def _wait_until_due(self, bag_ns: int, should_stop: Callable[[], bool]) -> Optional[float]:
        """Wait until bag time ``bag_ns`` is due, ticking /clock, applying pauses.

        Return the wall time it fell due, or None if stopped.
        """
        period = 1.0 / self.clock_hz if self.clock_pub is not None else None
        while True:
            if should_stop():
                return None
            now = time.monotonic()
            self._apply_requests(now)
            if period is not None:
                tick = self._pass_wall0 + self._pass_ticks * period
                if tick <= now:   # ticks fallen due meanwhile go out at once
                    self._publish_clock(self.playback.bag_ns(now))
                    self._pass_ticks += 1
                    continue
            due = self.playback.due(bag_ns)
            if due is not None and due <= now:
                return due
            wake = [now + SLEEP_SLICE_S] + ([due] if due is not None else []) + \
                ([tick] if period is not None else [])
            time.sleep(max(0.0, min(wake) - now))

    def _window(self, first_log_ns: int):
        """Return (start, end) bag times of a pass whose first selected message is given."""
        if self.start_offset_s > 0:
            start = int(self.bag.start_ns) + int(round(self.start_offset_s * 1e9))
        else:
            start = first_log_ns
        end = None
        if self.playback_duration_s is not None and self.playback_duration_s >= 0:
            end = start + int(round(self.playback_duration_s * 1e9))
        return start, end

    def run(self, should_stop: Callable[[], bool] = lambda: False) -> Dict:
        """Play (once, or until stopped with ``loop``); return what was published."""
        passes = 0
        started = time.monotonic()
        self.reach.start(self.matched())
        if self.on_start is not None:
            self.on_start(self.reach)
        if self.start_paused and self.on_pause is not None:
            self.on_pause(True, 0)
        while True:
            passes += 1
            self._pass_wall0, self._pass_ticks = time.monotonic(), 0
            window = None
            played = 0
            for m in self.bag.messages(self.topics):
                if window is None:
                    window = self._window(m.log_time_ns)
                    self.playback.restart(window[0], time.monotonic())
                if m.log_time_ns < window[0]:
                    continue       # before --start-offset
                if window[1] is not None and m.log_time_ns > window[1]:
                    break          # after --playback-duration
                target = self._wait_until_due(m.log_time_ns, should_stop)
                if target is None:
                    return self._stats(passes, started, stopped=True)
                publisher = self.publishers[m.topic]
                matched = publisher.get_subscription_count()
                publisher.publish(m.data)
                self.reach.publish(m.topic, matched)
                if self.sink is not None:
                    self.sink(m.topic, m.data, m.log_time_ns)
                # Measured once the message is out: its source timestamp then lies in
                # [target, target + lateness], a bound a subscriber can check.
                self.lateness_s.append(time.monotonic() - target)
                played += 1
            if not self.loop or should_stop() or not played:
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
                'start_offset_s': self.start_offset_s, 'pauses': self.pauses,
                'paused_s': self.playback.paused_s, 'remap': dict(self.remap),
                'published': dict(self.published), 'total': sum(self.published.values()),
                'subscribers': self.reach.as_dict(),
                'clock_ticks': self.clock_ticks,
                'lateness_ms': percentiles_ms(self.lateness_s)}


__all__ = ['Player']
