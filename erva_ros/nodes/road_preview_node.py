"""road_preview_node: the road under the wheel and its preview over the NMPC horizon.

Owns the seeded road of :mod:`erva_ros.core.roads` (paper road, ISO 8608, bump, sine,
or a recorded CSV profile) built by :func:`erva_ros.core.loop.scenario.build_road`, and
publishes for every sample t_k = k·Ts of the scenario (k = 0..duration/Ts):

* ``road/preview``: w(t_k + j·Ts), j = 0..N, degraded by the configured preview
  error model (:class:`erva_ros.core.preview.PreviewErrorModel`), for the controller;
* ``road/height``: the true w(t_k) at the tyre, for the plant.

The height is published first: the plant's step is on the path to the state,
while the controller needs the preview only once that state arrives.

Modes: ``realtime`` -- a wall-clock timer at 1/Ts, started once both topics have
``wait_for_subscribers`` subscribers (one of them ``wait_for_reader``'s, see
:mod:`erva_ros.ros.time_master`) plus ``start_delay_s``; it is the time base of
the live run.  ``lockstep`` -- one sample per ``/clock`` message from the plant.
"""

import time

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PointStamped
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rosgraph_msgs.msg import Clock as ClockMsg
from trajectory_msgs.msg import JointTrajectory

from erva_ros.core import topics
from erva_ros.ros import qos as ros_qos
from erva_ros.ros import diagnostics as diag
from erva_ros.ros.msgs import preview_msg, road_height_msg, s_to_ns, time_to_ns
from erva_ros.ros.parameters import declare_live, loop_priority
from erva_ros.ros.runtime import run_node
from erva_ros.ros.time_master import readers_ready, Settling
from erva_ros.core.loop.scenario import build_preview_model, build_road
from erva_ros.core.loop.timing import SampleGrid
from erva_ros.core.loop.validation import Rejections

LIVE_PARAMETERS = ('mode', 'ts', 'duration_s', 'road', 'road_file', 'seed', 'road_class',
                   'speed_mps', 'bump_height_m', 'bump_length_m', 'bump_start_s',
                   'preview_steps', 'preview_noise', 'preview_snr_db', 'preview_delay_s',
                   'wait_for_subscribers', 'wait_for_reader', 'start_delay_s',
                   'diagnostics_period_s', 'reject_log_period_s', 'publisher_history_s',
                   'realtime_priority')


class RoadPreviewNode(Node):
    """Publish the road height and its preview for every sample of the scenario."""

    def __init__(self):
        super().__init__('road_preview_node')
        cfg = declare_live(self, LIVE_PARAMETERS)
        self.realtime_priority = loop_priority(cfg)    # applied by run_node once started
        self.cfg = cfg
        self.road = build_road(cfg)
        self.error_model = build_preview_model(cfg)
        self.ts = cfg['ts']
        self.ts_ns = s_to_ns(self.ts)
        self.n_samples = int(round(cfg['duration_s'] / self.ts)) + 1
        self.last_k = -1
        self.published = 0
        self.grid = SampleGrid(self.ts_ns, self.n_samples)    # realtime mode's samples
        self.finished = False
        self.steady = Clock(clock_type=ClockType.STEADY_TIME)
        self._settling = Settling(cfg['start_delay_s'])
        self._sample_timer = None
        self._start_timer = None
        self.rejections = Rejections(self.get_logger().warning, time.monotonic,
                                     cfg['reject_log_period_s'])

        qos = ros_qos.control_qos()
        if cfg['mode'] == 'lockstep':
            # Subscribed before the publishers exist: the plant waits for them to appear.
            self.create_subscription(ClockMsg, topics.CLOCK, self._on_clock, qos)
        pub_qos = ros_qos.publisher_qos(cfg['publisher_history_s'], self.ts)
        self.pub_preview = diag.CountedPublisher(
            self.create_publisher(JointTrajectory, topics.ROAD_PREVIEW, pub_qos))
        self.pub_height = diag.CountedPublisher(
            self.create_publisher(PointStamped, topics.ROAD_HEIGHT, pub_qos))
        self.pub_diag = self.create_publisher(DiagnosticArray, topics.DIAGNOSTICS,
                                              ros_qos.diagnostics_qos())
        self.status = diag.StatusReporter(
            self.get_fully_qualified_name(), f'road:{self.road.name}', self.pub_diag.publish,
            lambda: self.get_clock().now().nanoseconds, self._diag_values,
            publishers=[self.pub_height, self.pub_preview])
        self.create_timer(cfg['diagnostics_period_s'],
                          lambda: self.status.on_timer(2 * self.ts), clock=self.steady)
        if cfg['mode'] == 'realtime':
            self._start_timer = self.create_timer(0.01, self._on_start_timer, clock=self.steady)
            self.status.set(diag.OK, 'waiting for subscribers')
        else:
            self.status.set(diag.OK, 'waiting for /clock')
        self.get_logger().info(
            f'road {self.road.name}, {self.n_samples} samples of {self.ts:g} s, preview '
            f'{cfg["preview_steps"]} steps, error model '
            f'{"perfect" if self.error_model.is_perfect else self.error_model}')

    def _publish_sample(self, k: int, stamp_ns: int) -> None:
        """Publish the preview and the height of sample k (t_k = k·Ts) stamped ``stamp_ns``."""
        t_k = k * self.ts
        # Height first: the plant's step is on the critical path to the state; the
        # controller waits for the preview of the state's sample if it comes second.
        self.pub_height.publish(road_height_msg(stamp_ns, self.road.distance(t_k),
                                                self.road.height(t_k)))
        preview = self.road.preview(t_k, self.cfg['preview_steps'], self.ts)
        if not self.error_model.is_perfect:
            preview = self.error_model.apply(preview, t_k)
        self.pub_preview.publish(preview_msg(stamp_ns, preview, self.ts_ns))
        self.last_k = k
        self.published += 1
        self.status.after_sample()

    def _finish(self) -> None:
        self.finished = True
        if self._sample_timer is not None:
            self._sample_timer.cancel()
        self.status.set(diag.OK, f'finished: {self.published} samples published')

    # -- realtime ----------------------------------------------------------------------
    def _on_start_timer(self) -> None:
        ready = readers_ready(self, (self.pub_height, self.pub_preview), self.cfg)
        if not self._settling.held(ready, time.monotonic()):
            return
        self._start_timer.cancel()
        # rcl timers fire at creation + m·period without drift; the grid is anchored at the
        # first firing's scheduled instant (below), so no sample is stamped ahead of its time.
        self._sample_timer = self.create_timer(self.ts, self._on_sample_timer)
        self.status.set(diag.OK, 'running')

    def _on_sample_timer(self) -> None:
        now = self.get_clock().now().nanoseconds
        if self.grid.start_ns is None:
            # The grid starts at this firing's scheduled instant (the next one minus a
            # period): later firings are never before their own scheduled instant.
            now -= self.ts_ns - self._sample_timer.time_until_next_call()
        k = self.grid.due(now)
        if k is None:
            return
        self._publish_sample(k, self.grid.stamp_ns(k))
        if self.grid.done:
            self._finish()

    # -- lock-step ---------------------------------------------------------------------
    def _on_clock(self, msg: ClockMsg) -> None:
        stamp = time_to_ns(msg.clock)
        k, rest = divmod(stamp, self.ts_ns)
        if rest != 0 or k <= self.last_k:
            why = 'off the Ts grid' if rest else 'not after the last sample'
            self.rejections.reject(topics.CLOCK, f'/clock {stamp} ns is {why}')
            return
        if self.finished or k >= self.n_samples:
            if not self.finished:
                self._finish()
            return
        if self.last_k < 0:
            self.status.set(diag.OK, 'running')
        self._publish_sample(k, stamp)
        if k == self.n_samples - 1:
            self._finish()

    def _diag_values(self):
        return {'mode': self.cfg['mode'], 'road': self.road.name, 'seed': self.cfg['seed'],
                'samples_published': self.published, 'samples_total': self.n_samples,
                'samples_skipped': self.grid.skipped,
                'preview_points': self.cfg['preview_steps'] + 1,
                'preview_error': 'perfect' if self.error_model.is_perfect else
                f'snr={self.error_model.snr_db} dB delay={self.error_model.delay_s:g} s',
                'finished': self.finished, 'scheduling': getattr(self, 'scheduling', 'off'),
                'rejected_clock': self.rejections.counts.get(topics.CLOCK, 0)}


def main(args=None) -> int:
    """Run road_preview_node until shutdown."""
    return run_node('road_preview_node', RoadPreviewNode, args)


if __name__ == '__main__':
    import sys
    sys.exit(main())
