"""The road node's core: which sample of the scenario goes out when, and what it holds.

For every sample t_k = k·Ts of the scenario (k = 0..duration/Ts) the road node publishes
the true height w(t_k) at the tyre and the preview w(t_k + j·Ts), j = 0..N, degraded by
the configured error model (:class:`erva_ros.core.road.preview.PreviewErrorModel`).  In real
time a wall-clock timer takes the newest due instant of a :class:`SampleGrid` (a timer
that fell behind skips samples, counted); in lock-step each ``/clock`` tick of the plant
asks for one sample (:meth:`RoadSource.on_clock`).
"""

from dataclasses import dataclass
from typing import Any, Mapping, Optional

import numpy as np

from erva_ros.core.loop.scenario import build_preview_model, build_road
from erva_ros.core.timing import SampleGrid
from erva_ros.core.loop.validation import MessageRejected
from erva_ros.core.reports import RoadReport
from erva_ros.core.wire import NS


@dataclass(frozen=True)
class RoadSample:
    """What goes out for sample k: its stamp, distance (m), height (m) and preview (m)."""

    k: int
    stamp_ns: int
    distance_m: float
    height_m: float
    preview: np.ndarray


class RoadSource:
    """The scenario's road samples and the road node's report (see the module doc)."""

    def __init__(self, cfg: Mapping[str, Any], report: RoadReport):
        self.cfg = cfg
        self.road = build_road(cfg)
        self.error_model = build_preview_model(cfg)
        self.ts = cfg['ts']
        self.ts_ns = int(round(self.ts * NS))
        self.n_samples = int(round(cfg['duration_s'] / self.ts)) + 1
        self.grid = SampleGrid(self.ts_ns, self.n_samples)    # real time's samples
        self.last_k = -1
        self.report = report
        report.mode, report.road, report.seed = cfg['mode'], self.road.name, cfg['seed']
        report.samples_total = self.n_samples
        report.preview_points = cfg['preview_steps'] + 1
        report.preview_error = ('perfect' if self.error_model.is_perfect else
                                f'snr={self.error_model.snr_db} dB '
                                f'delay={self.error_model.delay_s:g} s')

    @property
    def finished(self) -> bool:
        """Return True once the last sample went out."""
        return self.report.finished

    def sample(self, k: int, stamp_ns: int) -> RoadSample:
        """Return sample k stamped ``stamp_ns``, and count it published."""
        t_k = k * self.ts
        preview = self.road.preview(t_k, self.cfg['preview_steps'], self.ts)
        if not self.error_model.is_perfect:
            preview = self.error_model.apply(preview, t_k)
        self.last_k = k
        self.report.samples_published += 1
        if k >= self.n_samples - 1:
            self.report.finished = True
        return RoadSample(k, stamp_ns, self.road.distance(t_k), self.road.height(t_k), preview)

    def on_timer(self, now_ns: int) -> Optional[RoadSample]:
        """Real time: return the sample due at ``now_ns`` (None: none)."""
        k = self.grid.due(now_ns)
        self.report.samples_skipped = self.grid.skipped
        return None if k is None else self.sample(k, self.grid.stamp_ns(k))

    def on_clock(self, stamp_ns: int) -> Optional[RoadSample]:
        """Lock-step: return the sample of a /clock tick (MessageRejected: off grid, old)."""
        k, rest = divmod(stamp_ns, self.ts_ns)
        if rest != 0 or k <= self.last_k:
            why = 'off the Ts grid' if rest else 'not after the last sample'
            raise MessageRejected(f'/clock {stamp_ns} ns is {why}')
        if self.finished or k >= self.n_samples:
            self.report.finished = True
            return None
        return self.sample(k, stamp_ns)


__all__ = ['RoadSample', 'RoadSource']
