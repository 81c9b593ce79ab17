"""road_preview_node: the road under the wheel and its preview over the NMPC horizon.

A thin adapter around :class:`erva_ros.core.loop.road_source.RoadSource` (paper road,
ISO 8608, bump, sine, or a recorded CSV profile), publishing for every sample t_k:

* ``road/height``: the true w(t_k) at the tyre, for the plant -- first, as the plant's
  step is on the critical path to the state;
* ``road/preview``: w(t_k + j·Ts), j = 0..N, for the controller.

Modes: ``realtime`` -- a wall-clock timer at 1/Ts, started once both topics have
``wait_for_subscribers`` subscribers (one of them ``wait_for_reader``'s, see
:mod:`erva_ros.ros.time_master`) plus ``start_delay_s`` once active; it is the time
base of the live run (deactivated, it skips the samples meanwhile, counted).
``lockstep`` -- one sample per ``/clock`` message from the plant.

``source`` ``map`` (docs/road.md): ``road/height`` stays the simulated world's road (for
the ECU simulator only), and the preview comes from ``map_file`` instead
(:class:`erva_ros.core.loop.road_loop.MapPreviewLoop`): one per ``road/estimate``, stamped as
it, at the odometry position corrected by profile matching; ``road/alignment`` carries
the correction.  Fallbacks (off the map, gaps, no match) are counted in the report.
"""

import time

from geometry_msgs.msg import PointStamped, PoseWithCovarianceStamped
from rosgraph_msgs.msg import Clock as ClockMsg
from trajectory_msgs.msg import JointTrajectory

from erva_ros.core import contract, topics
from erva_ros.core.levels import OK
from erva_ros.core.loop.road_source import RoadSample, RoadSource
from erva_ros.core.timing import next_grid_delay_ns
from erva_ros.core.loop.validation import MessageRejected
from erva_ros.core.reports import RoadReport
from erva_ros.ros.loop_node import LoopNode
from erva_ros.ros.runtime import run_node
from erva_ros.ros.time_master import readers_ready, Settling


class RoadPreviewNode(LoopNode):
    """Publish the road height and its preview for every sample of the scenario."""

    NAME = 'road_preview_node'
    REPORT = RoadReport

    def configure(self) -> None:
        self.source = RoadSource(self.p, self.report)
        self.report.hardware_id = f'road:{self.source.road.name}'
        self._settling = Settling(self.p['start_delay_s'])
        self._sample_timer = self._align_timer = None
        self._finished = False
        if self.p['mode'] == 'lockstep':
            # Subscribed before the publishers exist: the plant waits for them to appear.
            self.subscribe(ClockMsg, topics.CLOCK, self._on_clock)
        self.map = None
        if self.p['source'] == 'map':
            # Imported only here: the map preview brings the road EKF, the vehicle loop
            # and the CAN codec, ~40 % of this node's start-up (docs/live_figures.md, Bring-up).
            from erva_ros.core.loop.road_loop import MapPreviewLoop
            self.map = MapPreviewLoop(self.p, self.report)
        self.pub_preview = self.publisher(JointTrajectory, topics.ROAD_PREVIEW)
        self.pub_height = self.publisher(PointStamped, topics.ROAD_HEIGHT)
        if self.map is not None:
            self.pub_alignment = self.publisher(PointStamped, topics.ROAD_ALIGNMENT)
            self.subscribe(PoseWithCovarianceStamped, topics.ROAD_ESTIMATE, self._on_estimate)
        self.status_timer(2 * self.source.ts)
        if self.p['mode'] == 'realtime':
            self._start_timer = self.timer(0.01, self._on_start_timer, clock=self.steady)
        model = self.source.error_model
        self.get_logger().info(
            f'road {self.source.road.name}, {self.source.n_samples} samples of '
            f'{self.source.ts:g} s, preview {self.p["preview_steps"]} steps from '
            + (f'the map {self.p["map_file"]}' if self.map else
               f'the road, error model {"perfect" if model.is_perfect else model}'))

    def activate(self) -> None:
        if self.p['mode'] == 'lockstep':
            self.status.set(OK, 'waiting for /clock')
        elif self._sample_timer is None:
            self.status.set(OK, 'waiting for subscribers')

    def _publish(self, s: RoadSample) -> None:
        self.pub_height.publish(contract.encode_road_height(s.stamp_ns, s.distance_m,
                                                            s.height_m))
        if self.map is None:
            self.pub_preview.publish(contract.encode_preview(s.stamp_ns, s.preview,
                                                             self.source.ts_ns))
        if self.source.finished:
            self._finish()
        self.status.after_sample()

    def _finish(self) -> None:
        if self._sample_timer is not None:
            self._sample_timer.cancel()
        self._finished = True
        self.status.set(OK, f'finished: {self.report.samples_published} samples published')

    def _on_estimate(self, data: bytes, rx_ns: int) -> None:
        try:
            est = contract.decode_road_estimate(data, strict=True)
            res = self.map.on_estimate(est)
        except MessageRejected as exc:
            self.reject(topics.ROAD_ESTIMATE, str(exc))
            self.report.rejected_estimate = self.rejected(topics.ROAD_ESTIMATE)
            return
        self.pub_preview.publish(contract.encode_preview(est.stamp_ns, res.heights,
                                                         self.source.ts_ns))
        self.pub_alignment.publish(contract.encode_alignment(
            est.stamp_ns, res.offset_m, res.offset_std_m, res.correlation))

    # -- realtime ----------------------------------------------------------------------
    def _on_start_timer(self) -> None:
        ready = readers_ready(self, (self.pub_height, self.pub_preview), self.p)
        if not self._settling.held(ready, time.monotonic()):
            return
        self._start_timer.cancel()
        # The samples fall on k·Ts of the clock, as a real ECU's cycles do (docs/hil.md §8:
        # the cycle number is round(t / Ts)): the simulated ECU samples on this grid, and
        # an estimator without the road stamps its cycles on it.  So the sample timer is
        # made at the next such instant (at least 1 ms ahead).
        delay = next_grid_delay_ns(self.now_ns(), 0, self.source.ts_ns)
        if delay < 1_000_000:
            delay += self.source.ts_ns
        self._align_timer = self.timer(delay * 1e-9, self._on_grid_instant)

    def _on_grid_instant(self) -> None:
        self._align_timer.cancel()
        # rcl timers fire at creation + m·period without drift; the grid is anchored at the
        # first firing's instant on k·Ts (below), so no sample is stamped ahead of its time.
        self._sample_timer = self.timer(self.source.ts, self._on_sample_timer)
        self.status.set(OK, 'running')

    def _on_sample_timer(self) -> None:
        now = self.now_ns()
        if self.source.grid.start_ns is None:
            # The grid starts at this firing's scheduled instant (the next one minus a
            # period), made the k·Ts it was meant for (the timer was made a little after
            # it): later firings are never before their own instant.
            now -= self.source.ts_ns - self._sample_timer.time_until_next_call()
            now -= now % self.source.ts_ns
        sample = self.source.on_timer(now)
        if sample is not None:
            self._publish(sample)

    # -- lock-step ---------------------------------------------------------------------
    def _on_clock(self, data: bytes, rx_ns: int) -> None:
        try:
            first = self.source.last_k < 0
            sample = self.source.on_clock(contract.decode_clock(data))
        except MessageRejected as exc:
            self.reject(topics.CLOCK, str(exc))
            self.report.rejected_clock = self.rejected(topics.CLOCK)
            return
        if sample is None:
            if self.source.finished and not self._finished:
                self._finish()
            return
        if first:
            self.status.set(OK, 'running')
        self._publish(sample)


def main(args=None) -> int:
    """Run road_preview_node until shutdown."""
    return run_node(RoadPreviewNode, args)


if __name__ == '__main__':
    import sys
    sys.exit(main())
