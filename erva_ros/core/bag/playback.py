"""What a bag player plays and when: topic selection, start offset, rate and pauses (no ROS).

The player (``erva_ros.ros.replay.Player``, `erva bag play` / `erva replay`) keeps the
rules of ``ros2 bag play`` (rosbag2 Jazzy):

* topics: ``--topics`` and ``--regex`` together choose (either one selects a topic; the
  regex must match the whole name, as rosbag2's MCAP reader does); ``--exclude-topics``
  and ``--exclude-regex`` then remove; nothing chosen means every topic;
* ``--start-offset S``: playback starts S seconds after the bag's first message (of any
  topic); earlier messages are not played, and a later one goes out after its distance
  from that point (the playback clock starts there, as rosbag2's does);
* ``--playback-duration S``: messages more than S seconds after that point are not played;
* pauses: the playback clock stops (a /clock publisher keeps publishing the frozen time)
  and no message goes out until it resumes; the schedule then continues where it stopped.

Unlike ``ros2 bag play``, the player never loses silently (:class:`Reach`): it says how
many subscribers each topic had matched when it started, warns when a topic had none,
and at the end counts the messages that went out before a topic's last subscriber
matched -- those a late subscriber (a recorder started after the player) cannot have.
"""

from dataclasses import asdict, dataclass
import re
from typing import Dict, Iterable, List, Mapping, Optional, Sequence

from erva_ros.core.bag import BagError


def compile_regex(pattern: str, option: str) -> Optional['re.Pattern']:
    """Return the compiled ``pattern`` (None for ''); BagError naming ``option`` if invalid."""
    if not pattern:
        return None
    try:
        return re.compile(pattern)
    except re.error as exc:
        raise BagError(f'{option} {pattern!r} is not a regular expression ({exc})') from None


def select_topics(available: Iterable[str], topics: Sequence[str] = (), regex: str = '',
                  exclude_topics: Sequence[str] = (), exclude_regex: str = '') -> List[str]:
    """Return the topics of ``available`` to play, sorted (rules in the module doc).

    A topic named in ``topics`` or ``exclude_topics`` that ``available`` lacks is an error
    naming what the bag has; a selection that leaves nothing is an error too.
    """
    available = sorted(set(available))
    named = set(topics or ()) | set(exclude_topics or ())
    missing = sorted(named - set(available))
    if missing:
        raise BagError(f'topic(s) {", ".join(missing)} not in the bag; it has '
                       f'{", ".join(available)}')
    include = compile_regex(regex, '--regex')
    exclude = compile_regex(exclude_regex, '--exclude-regex')
    chosen = [t for t in available
              if (not topics and include is None) or t in set(topics or ())
              or (include is not None and include.fullmatch(t))]
    chosen = [t for t in chosen if t not in set(exclude_topics or ())
              and not (exclude is not None and exclude.fullmatch(t))]
    if not chosen:
        raise BagError('the topic selection leaves nothing to play')
    return chosen


class PlaybackClock:
    """Bag time as a function of monotonic wall time: a rate, a start point, pauses.

    ``bag_ns(now)`` is the playback time at wall time ``now``; ``due(bag_ns)`` is the wall
    time at which a message of that bag time goes out (None while paused).
    """

    def __init__(self, bag_start_ns: int, rate: float, now: float, paused: bool = False):
        if not rate > 0:
            raise BagError(f'rate {rate} must be positive')
        self.rate = float(rate)
        self._bag_anchor = int(bag_start_ns)
        self._wall_anchor = float(now)
        self.paused = bool(paused)
        self.paused_s = 0.0
        self._paused_at: Optional[float] = now if paused else None

    def restart(self, bag_start_ns: int, now: float) -> None:
        """Start a new pass (``--loop``) at ``bag_start_ns``, keeping the pause state."""
        self._bag_anchor = int(bag_start_ns)
        self._wall_anchor = float(now)

    def bag_ns(self, now: float) -> int:
        """Return the playback time (bag ns) at wall time ``now`` (frozen while paused)."""
        if self.paused:
            return self._bag_anchor
        return self._bag_anchor + int(round((now - self._wall_anchor) * self.rate * 1e9))

    def due(self, bag_ns: int) -> Optional[float]:
        """Return the wall time of bag time ``bag_ns`` on the schedule; None while paused."""
        if self.paused:
            return None
        return self._wall_anchor + (bag_ns - self._bag_anchor) * 1e-9 / self.rate

    def pause(self, now: float) -> bool:
        """Stop the playback clock at ``now``; return whether it was running."""
        if self.paused:
            return False
        self._bag_anchor = self.bag_ns(now)
        self.paused, self._paused_at = True, now
        return True

    def resume(self, now: float) -> bool:
        """Run the playback clock again from ``now``; return whether it was paused."""
        if not self.paused:
            return False
        self._wall_anchor = float(now)
        self.paused_s += now - self._paused_at
        self.paused, self._paused_at = False, None
        return True


@dataclass
class TopicReach:
    """Whom one topic's messages reached: its publisher's matched subscribers over time."""

    at_start: int = 0           # subscribers matched when playing started
    most: int = 0               # the most matched at any message
    published: int = 0
    unmatched: int = 0          # published while no subscriber was matched
    before_last_match: int = 0  # published before the count first reached ``most``


class Reach:
    """Per topic, the subscribers a player's publisher had matched at each message.

    A reliable, volatile publisher delivers a message only to the subscribers it has
    matched when it publishes: a subscriber that matches later never gets it.  So what
    went out before the last subscriber matched is what a late one missed.
    """

    def __init__(self, topics: Iterable[str]):
        self.topics: Dict[str, TopicReach] = {t: TopicReach() for t in topics}

    def start(self, matched: Mapping[str, int]) -> None:
        """Take each topic's matched subscribers when playing starts."""
        for topic, n in matched.items():
            r = self.topics[topic]
            r.at_start = r.most = int(n)

    def publish(self, topic: str, matched: int) -> None:
        """Count one message of ``topic`` published while ``matched`` subscribers were."""
        r = self.topics[topic]
        if matched > r.most:
            r.most, r.before_last_match = matched, r.published
        r.unmatched += matched == 0
        r.published += 1

    @property
    def published(self) -> Dict[str, int]:
        """Return the messages published per topic."""
        return {t: r.published for t, r in self.topics.items()}

    def start_lines(self) -> List[str]:
        """Return the subscribers matched per topic at the start; a WARN if a topic had none."""
        counts = ', '.join(f'{t} {r.at_start}' for t, r in self.topics.items())
        out = [f'subscribers matched at the start: {counts}']
        alone = [t for t, r in self.topics.items() if r.at_start == 0]
        if alone:
            which = (f'any of the {len(alone)} topics' if len(alone) == len(self.topics) else
                     f'{_some(alone)} ({len(alone)} of {len(self.topics)} topics)')
            out.append(f'WARN no subscriber matched {which}: their messages reach no one '
                       'until one matches (--wait-for-subscribers S waits up to S s for '
                       'every topic)')
        return out

    def end_line(self) -> Optional[str]:
        """Return a WARN line on what went out unmatched or before a late match (or None)."""
        rs = self.topics
        missed = {t: max(r.unmatched, r.before_last_match) for t, r in rs.items()}
        if not any(missed.values()):
            return None
        total = sum(r.published for r in rs.values())
        unmatched = sum(r.unmatched for r in rs.values())
        late = sum(r.before_last_match for r in rs.values())
        parts = ([f'{unmatched} went out with no subscriber matched'] if unmatched else []) + \
            ([f'{late} before the last subscriber of their topic matched']
             if late and late != unmatched else [])
        if late:
            parts[-1] += '; a subscriber that matched late does not have them'
        per_topic = _some([f'{t} {n} of {rs[t].published}' for t, n in missed.items() if n])
        return f'WARN of {total} messages, {", ".join(parts)} ({per_topic})'

    def as_dict(self) -> Dict[str, Dict[str, int]]:
        """Return {topic: TopicReach as a dict}."""
        return {t: asdict(r) for t, r in self.topics.items()}


def _some(items: Sequence[str], most: int = 4) -> str:
    """Return up to ``most`` of ``items`` joined, with how many more."""
    shown = ', '.join(items[:most])
    return shown + (f', and {len(items) - most} more' if len(items) > most else '')


__all__ = ['compile_regex', 'select_topics', 'PlaybackClock', 'Reach', 'TopicReach']
