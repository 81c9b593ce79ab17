"""What a recording lacks, told by its publishers' sequence numbers (no ROS).

erva's recorder stores each message's ``publication_sequence_number`` (DDS numbers a
writer's samples 1, 2, 3, ...) as the MCAP message's ``sequence``.  A topic with one
publisher then shows what the recorder never got: a first recorded number above 1 is
what went out before the recorder matched that publisher (a late recorder), a hole in
the numbers a loss in between.  Where a topic has several publishers (their numbers
repeat) or a writer gives none (0), nothing can be told, and nothing is claimed.
"""

from dataclasses import dataclass
from typing import Dict, Iterable, Optional


@dataclass
class Missing:
    """One topic's messages missing from a recording, by its publisher's numbers."""

    recorded: int
    before_first: int     # numbers 1 .. first - 1: published before the recorder matched
    holes: int            # numbers between the first and the last that are not there

    @property
    def total(self) -> int:
        return self.before_first + self.holes


def missing_by_sequence(messages: Iterable) -> Dict[str, Optional[Missing]]:
    """Return, per topic of ``messages`` (``.topic``, ``.sequence``), what is missing.

    None for a topic whose numbers cannot tell (several publishers, or no numbers).
    """
    seen: Dict[str, set] = {}
    unknown = set()
    for m in messages:
        numbers = seen.setdefault(m.topic, set())
        if m.sequence <= 0 or m.sequence in numbers:
            unknown.add(m.topic)
        numbers.add(m.sequence)
    out: Dict[str, Optional[Missing]] = {}
    for topic, numbers in seen.items():
        if topic in unknown:
            out[topic] = None
            continue
        first, last = min(numbers), max(numbers)
        out[topic] = Missing(len(numbers), first - 1, last - first + 1 - len(numbers))
    return out


__all__ = ['Missing', 'missing_by_sequence']
