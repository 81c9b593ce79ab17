"""QoS of the loop's topics (rclpy profiles), and the player's from a recorded profile.

The topic names and types are erva_ros/core/topics.py; the recorded profiles' dict form
(rosbag2's YAML) is erva_ros/core/bag/qos.py.  Everything that builds an rclpy
``QoSProfile`` is here.
"""

import math
from typing import Dict, Sequence

from rclpy.duration import Duration, Infinite
from rclpy.qos import (DurabilityPolicy, HistoryPolicy, LivelinessPolicy, QoSProfile,
                       ReliabilityPolicy)

from erva_ros.core.bag.qos import INFINITE, PLAYBACK_DEPTH


def control_qos(depth: int = 10):
    """Return the control topics' QoS: reliable, volatile, keep-last ``depth``.

    Reliable so that nothing published is silently lost (the recorder's counts must
    equal the publishers'); a subscriber's depth 10 absorbs a 200 ms stall at 50 Hz
    (a controller wants the newest sample, not a backlog).
    """
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth,
                      reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.VOLATILE)


def diagnostics_qos():
    """Return the QoS of a node's /diagnostics publisher: :func:`control_qos`, keep-last 100.

    A status comes about twice a second: 100 of them (~50 s) let reliable delivery repair
    a stalled recorder, as :func:`publisher_qos` does for the data.
    """
    return control_qos(100)


def publisher_depth(history_s: float, ts: float) -> int:
    """Return the keep-last depth that holds ``history_s`` of samples every ``ts`` (>= 10)."""
    return max(10, int(math.ceil(history_s / ts - 1e-9)))


def publisher_qos(history_s: float, ts: float):
    """Return a loop publisher's QoS: :func:`control_qos` keeping ``history_s`` of samples.

    A reliable writer repairs what a subscriber missed only from its own history: with
    keep-last 10, a recorder that stalls longer than the transports buffer (~1.5 s
    measured) loses those samples for good.  A deeper history costs the writer memory,
    not latency: a keep-last writer never waits for a slow reader.
    """
    return control_qos(publisher_depth(history_s, ts))


def playback_qos(profiles: Sequence[Dict]):
    """Return the rclpy QoS a player offers for a topic recorded with ``profiles``."""
    default = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=PLAYBACK_DEPTH,
                         reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.VOLATILE)
    if not profiles:
        return default
    keys = ('reliability', 'durability', 'deadline', 'liveliness', 'liveliness_lease_duration')
    if any(p.get(k) != profiles[0].get(k) for p in profiles for k in keys):
        return default

    def policy(enum, value, fallback):
        try:
            member = enum[str(value).upper()] if isinstance(value, str) else enum(int(value))
        except (KeyError, ValueError):
            return fallback
        return fallback if member.name in ('UNKNOWN', 'BEST_AVAILABLE') else member

    def duration(value):
        if not isinstance(value, dict):
            return Duration(nanoseconds=0)  # rmw default
        if value == INFINITE:
            return Infinite
        return Duration(seconds=int(value.get('sec', 0)), nanoseconds=int(value.get('nsec', 0)))

    p = profiles[0]
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST, depth=PLAYBACK_DEPTH,
        reliability=policy(ReliabilityPolicy, p.get('reliability'), default.reliability),
        durability=policy(DurabilityPolicy, p.get('durability'), default.durability),
        deadline=duration(p.get('deadline')),
        lifespan=duration(p.get('lifespan')),
        liveliness=policy(LivelinessPolicy, p.get('liveliness'), LivelinessPolicy.AUTOMATIC),
        liveliness_lease_duration=duration(p.get('liveliness_lease_duration')),
        avoid_ros_namespace_conventions=bool(p.get('avoid_ros_namespace_conventions', False)))


__all__ = ['control_qos', 'diagnostics_qos', 'publisher_depth', 'publisher_qos', 'playback_qos']
