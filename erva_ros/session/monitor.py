"""The session monitor: what `erva run` observed, turned into its summary.

:mod:`erva_ros.ros.monitor` receives and decodes (the ROS side); this module adds what
the session makes of it: the messages each node says it published (the plant's, or in
HIL mode the ECU's and the estimator's, :mod:`~erva_ros.session.hil_summary`), whether
all of them arrived, and the run's figures (:mod:`~erva_ros.session.monitor_figures`).
"""

from typing import Any, Dict, Optional

from erva_ros.core import topics
from erva_ros.ros import monitor as ros_monitor
from erva_ros.ros.diagnostics import value_int
from erva_ros.session import hil_summary, monitor_figures


class _SessionFigures:
    """What the session reads from an :class:`~erva_ros.ros.monitor.Observations`."""

    def published(self) -> Dict[str, Optional[int]]:
        """Return the messages each node says it published per topic (None: not known)."""
        plant = self.diag_values('plant_sim_node')
        nmpc = self.diag_values('nmpc_node')
        road = self.diag_values('road_preview_node')
        loop = hil_summary.published(self.diag_values) if self.hil else {
            topics.STATE: value_int(plant.get('states')),
            topics.SPRUNG_ACCEL: value_int(plant.get('steps')),
            topics.GENERATOR: value_int(plant.get('steps'))}
        return {
            **loop,
            topics.ROAD_HEIGHT: value_int(road.get('samples_published')),
            topics.ROAD_PREVIEW: value_int(road.get('samples_published')),
            topics.DAMPING_CMD: (None if not nmpc else (value_int(nmpc.get('commands')) or 0)
                                 + (value_int(nmpc.get('safe_commands')) or 0)),
        }

    def all_received(self) -> bool:
        """Return True once every node's final counters arrived and nothing is missing."""
        published = self.published()
        return (all(v is not None for v in published.values())
                and not any(self.dropped(published).values()))

    def summary(self, ts: float, n_steps: int, realtime: bool) -> Dict[str, Any]:
        """Return the run's figures for a run of ``n_steps`` periods ``ts``."""
        self._decode()
        return monitor_figures.summary(self, ts, n_steps, realtime)


class Observations(_SessionFigures, ros_monitor.Observations):
    """A session's observations without a node (synthetic input, tests)."""


class Monitor(_SessionFigures, ros_monitor.Monitor):
    """The in-process node of `erva run`, with the session's figures."""


__all__ = ['Observations', 'Monitor']
