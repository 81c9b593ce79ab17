"""The stages of one `erva run`, timed from the moment the command started (``--timing``).

:class:`Timeline` keeps when each stage of the session process ended, in seconds since
the `erva` process started (:func:`erva_ros.core.startup.process_age_s`: the
interpreter's start and the imports count too); :func:`node_stages` adds what each node
process reports of its own bring-up (``NodeReport.startup``: imported, initialised,
constructed, configuring, configured, activated, in seconds since *its* process started, which
`erva run` started at a known instant).  A benchmark, never a test's assertion
(docs/live_figures.md, "Bring-up").
"""

import time
from typing import Dict, List, Mapping, Optional

from erva_ros.core.startup import process_start_monotonic

#: A node's stages as it reports them, in order, with the label printed for each.
NODE_STAGES = (('imported', 'python + imports'), ('initialised', 'rclpy init'),
               ('constructed', 'node + parameters'), ('configuring', 'asked to configure'),
               ('configured', 'configure'), ('activated', 'activate'))


class Timeline:
    """When each stage of a session ended, in s since the command started."""

    def __init__(self, t0: Optional[float] = None):
        #: The command's start on time.monotonic()'s clock.
        self.t0 = process_start_monotonic() if t0 is None else t0
        self.stages: Dict[str, float] = {}
        #: When each child process was started (s since the command started).
        self.spawned: Dict[str, float] = {}

    def now(self) -> float:
        """Return the seconds since the command started."""
        return time.monotonic() - self.t0

    def mark(self, stage: str) -> float:
        """Record that ``stage`` ended now (the first time only); return its time."""
        return self.stages.setdefault(stage, round(self.now(), 3))

    def spawn(self, name: str) -> None:
        """Record that process ``name`` was started now."""
        self.spawned[name] = round(self.now(), 3)

    def get(self, stage: str) -> Optional[float]:
        """Return when ``stage`` ended (None: it did not)."""
        return self.stages.get(stage)

    def as_dict(self, reports: Mapping[str, object] = ()) -> Dict[str, object]:
        """Return the stages and each node's (for the JSON summary), in s since the command."""
        return {'stages': dict(self.stages), 'nodes': node_stages(self.spawned, reports)}

    def lines(self, nodes: Mapping[str, Mapping[str, float]] = ()) -> List[str]:
        """Return the stage table as text: time since the command, and since the stage before.

        ``nodes``: each node's stages (:func:`node_stages`, the summary's
        ``timing.nodes``).
        """
        out = ['stages, s since the command started (+ since the stage before):']
        last = 0.0
        for stage, t in sorted(self.stages.items(), key=lambda kv: kv[1]):
            out.append(f'  {t:7.3f}  (+{t - last:6.3f})  {stage}')
            last = t
        for name, stages in nodes.items():
            parts, prev = [], None
            for key, label in (('started', 'started at'),) + NODE_STAGES:
                if key in stages:
                    t = stages[key]
                    parts.append(f'{label} {t:.3f}' if prev is None
                                 else f'{label} +{t - prev:.3f}')
                    prev = t
            out.append(f'  {name}: ' + ', '.join(parts))
        return out


def node_stages(spawned: Mapping[str, float], reports: Mapping[str, object]
                ) -> Dict[str, Dict[str, float]]:
    """Return each started node's stages in s since the command started.

    ``reports`` maps a node's short name (as in ``spawned``) to its newest report; a
    node's own stage times count from its process start, which is when it was spawned.
    """
    out: Dict[str, Dict[str, float]] = {}
    for name, t0 in spawned.items():
        stages = {'started': t0}
        report = reports.get(name)
        for key, _ in NODE_STAGES:
            value = (getattr(report, 'startup', None) or {}).get(key)
            if value is not None:
                stages[key] = round(t0 + value, 3)
        out[name] = stages
    return out


__all__ = ['NODE_STAGES', 'Timeline', 'node_stages']
