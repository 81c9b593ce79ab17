"""state_estimator_node: the NMPC's state ``/erva/state`` from the ECU's sensors (HIL mode).

A thin rclpy adapter around :class:`erva_ros.core.estimator.ExtendedKalmanFilter` (the shared
CasADi model, paper eq. (11)).  It subscribes to ``ecu/measurements``, the one message
ecu_bridge_node publishes per ECU cycle (stamp t_k; c_e applied and cycle-mean c_e,
sprung acceleration, deflection, rotor speed, generator force), plus ``road/height`` (the road
at the tyre, buffered and interpolated).  One callback per cycle: the prediction from
t_{k-1} with the ECU's cycle-mean c_e and the road w(t_{k-1}) → w(t_k), the correction
with the measurements present (a lost CAN frame's values are NaN: that channel is left
out, the cycle counted ``incomplete``; a lost status frame holds the last applied c_e),
and the estimate published on ``state`` with stamp t_k; predict and update are one
compiled CasADi call (:meth:`ExtendedKalmanFilter.cycle`).  ``ecu/measurements`` is taken
by its own thread straight from its wait set, not by the executor
(:class:`~erva_ros.ros.rt_subscription.RealtimeSubscription`, subscriber node
``state_estimator_node_rt``), and 4 ms before the next cycle is due that thread runs the
cycle's computation once on scratch copies, so the real one finds the CPU caches warm
(cold, after ~Ts asleep, it costs ~4x).  A malformed message (names, sizes), an absurd
value or a NaN that is not a whole channel is rejected and counted, and never reaches
the filter.  (The per-frame topics ``ecu/sprung_accel`` etc. are for users and the
recorder; the estimator does not listen to them.)
With ``stamp_on_road_grid`` (`erva run --ecu virtual` sets it) a cycle's stamp is the
road's sample instant t_k at most 3Ts/4 before (Ts/4 after) its CAN receive time: the
simulated ECU samples on that grid and sends at once, and the NMPC pairs each state with
the road preview of
the same t_k; the status then also reports the loop's chain from t_k
(``sample_to_measurements_ms``, ``sample_to_state_ms``).  The ECU sends at t_k as the
road node publishes w(t_k), which the prediction needs: a cycle whose road sample is not
there yet waits for it up to Ts/4 (``road_waits``; ``road_extrapolated`` if in vain).
Before the first road sample there is no grid: such a cycle waits the same, and is not
published if in vain (``before_road``).
``/diagnostics`` reports counters, the mean normalised innovation squared (≈ 3 when
the noise model fits) and the latency this node adds (``ecu/measurements`` received →
state published, p50/p99/max in ms) with, inside it, its own processing (compute_ms).
"""

import gc
import itertools
import math
import threading
import time
from typing import Optional, Tuple

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PointStamped
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from sensor_msgs.msg import JointState

from erva_ros.core import topics
from erva_ros.ros import qos as ros_qos
from erva_ros.core.estimator import ExtendedKalmanFilter
from erva_ros.core.hil import topics as hil_topics
from erva_ros.core.hil.latency import LatencyStats
from erva_ros.core.hil.road_buffer import RoadBuffer
from erva_ros.core.hil.settings import (COMMAND_LINE_DEFAULTS, ESTIMATOR_DEFAULTS,
                                        ESTIMATOR_SPECS, noise_of, ROAD_GRID_SPEC, TS_SPEC)
from erva_ros.ros import diagnostics as diag
from erva_ros.ros.cdr import CdrError, decode_joint_state, JointStateEncoder
from erva_ros.ros.msgs import NS, state_joint_names, time_to_ns
from erva_ros.ros.parameters import (declare, declare_all, declare_erva_params, declare_live,
                                     LIVE_DEFAULTS, LIVE_SPECS, loop_priority)
from erva_ros.ros.rt_subscription import RealtimeSubscription
from erva_ros.ros.runtime import run_node

#: Plausibility bounds of the measurements (absurd beyond: rejected, counted); speed is
#: the rotor speed phi' = v_gen / l (rad/s), applied the c_e's (Ns/m, >= 0), force in N.
LIMITS = {'accel': 100.0, 'deflection': 0.5, 'speed': 1e3, 'applied': 1e6, 'force': 1e6}
#: On the road grid, how long a cycle waits for its road sample w(t_k) (periods).
ROAD_WAIT_PERIODS = 0.25
#: Cache warming runs this long before the next ECU cycle is due (s).
WARM_LEAD_S = 0.004
_WARM_Y = (0.0, 0.0, 0.0)
_NAMES = list(hil_topics.MEASUREMENT_NAMES)
_CHANNELS = tuple(hil_topics.MEASUREMENT_CHANNELS.values())


def parse_measurements(data: bytes) -> Optional[Tuple[int, Tuple[float, ...]]]:
    """Return (stamp ns, (c_e, c_e_mean, accel, deflection, rotor speed)) of a message.

    ``data`` is a serialized ``ecu/measurements`` JointState.
    NaN marks a lost frame's values; None if the message is malformed (CDR, names,
    sizes), a value is absurd (beyond :data:`LIMITS`, infinite) or a frame's values are
    only partly NaN.
    """
    try:
        stamp, names, position, velocity, effort = decode_joint_state(data)
    except CdrError:
        return None
    if names != _NAMES or len(position) != len(_NAMES) or velocity or effort:
        return None
    v = position
    for channel in _CHANNELS:
        nans = sum(math.isnan(v[i]) for i in channel)
        if 0 < nans < len(channel):
            return None
    c_e, c_e_mean, accel, defl, speed, force = v
    if not all(math.isnan(x) or ok for x, ok in (
            (c_e, 0 <= c_e <= LIMITS['applied']),
            (c_e_mean, 0 <= c_e_mean <= LIMITS['applied']),
            (accel, abs(accel) <= LIMITS['accel']), (defl, abs(defl) <= LIMITS['deflection']),
            (speed, abs(speed) <= LIMITS['speed']), (force, abs(force) <= LIMITS['force']))):
        return None
    return stamp, (c_e, c_e_mean, accel, defl, speed)


class StateEstimatorNode(Node):
    """Estimate the quarter car's state from the ECU's measurements with an EKF."""

    def __init__(self):
        super().__init__('state_estimator_node')
        self.params = declare_erva_params(self)
        self.ts = declare(self, 'ts', TS_SPEC, LIVE_DEFAULTS['ts'])
        self.kind = declare(self, 'model', LIVE_SPECS['model'], LIVE_DEFAULTS['model'])
        # SCHED_FIFO once started (run_node, live/realtime.py): the node is on the loop.
        live = declare_live(self, ('realtime_priority', 'publisher_history_s'))
        self.realtime_priority = loop_priority(live)
        cfg = declare_all(self, ESTIMATOR_SPECS, ESTIMATOR_DEFAULTS)
        self.cfg = cfg
        self.on_road_grid = declare(self, 'stamp_on_road_grid', ROAD_GRID_SPEC,
                                    COMMAND_LINE_DEFAULTS['stamp_on_road_grid'])
        self.grid_ns: Optional[int] = None  # a road sample instant: the grid's phase
        self.ekf = ExtendedKalmanFilter(self.params, self.kind, self.ts, noise_of(cfg),
                                        u_max=cfg['u_max'])
        self.ts_ns = int(round(self.ts * NS))
        self.road = RoadBuffer(max_extrapolation_s=self.ts)
        self.last_ns: Optional[int] = None  # stamp of the last published estimate
        self.u_now = self.params.c_e0       # damping applied at the last stamp (Ns/m)
        self.count = dict.fromkeys(('updates', 'incomplete', 'gaps', 'restarts',
                                    'late_or_repeated', 'rejected', 'no_road',
                                    'road_waits', 'road_extrapolated', 'before_road'), 0)
        self.nis_sum = 0.0
        self.latency = LatencyStats()       # ecu/measurements received -> state published
        self.compute = LatencyStats()       # time spent in that callback
        self.lag_meas = LatencyStats()      # sample instant -> ecu/measurements received
        self.lag_state = LatencyStats()     # sample instant -> state published
        self.status_level, self.status_text = diag.WARN, 'waiting for ECU measurements'

        qos = ros_qos.control_qos()
        self.pub_state = diag.CountedPublisher(self.create_publisher(
            JointState, topics.STATE,
            ros_qos.publisher_qos(live['publisher_history_s'], self.ts)))
        self.counted_publishers = [self.pub_state]
        self._status_seq = itertools.count(1)
        self.pub_diag = self.create_publisher(DiagnosticArray, topics.DIAGNOSTICS,
                                              ros_qos.diagnostics_qos())
        # The road (executor thread) and the measurements (their own thread) share the
        # filter's inputs and counters: one lock (re-entrant: a cycle may publish
        # diagnostics).
        self.lock = threading.RLock()
        self.road_arrived = threading.Condition(self.lock)
        # ecu/measurements is on the loop's critical path: taken by its own thread, not
        # the executor (erva_ros/ros/rt_subscription.py; ~0.5 ms less per cycle).  That
        # thread also warms the caches WARM_LEAD_S before the next cycle is due: it runs
        # the cycle's computation once on scratch copies (armed by every cycle, so it
        # follows the ECU's phase).
        self.meas_sub = RealtimeSubscription(self, JointState, hil_topics.ECU_MEASUREMENTS,
                                             qos, self._on_measurements, idle=self._warm,
                                             raw=True)
        self.state_encoder = JointStateEncoder(state_joint_names(self.kind))
        self.warm_after_s = max(self.ts - WARM_LEAD_S, 0.5 * self.ts)
        self.create_subscription(PointStamped, topics.ROAD_HEIGHT, self._on_road, qos)
        steady = Clock(clock_type=ClockType.STEADY_TIME)
        self.create_timer(cfg['diagnostics_period_s'], self._publish_diagnostics, clock=steady)
        # Start-up objects (CasADi functions, messages, rclpy) are never garbage: keep the
        # collector from scanning them, so a collection cannot stall a cycle for ms.
        gc.freeze()
        self.meas_sub.start()
        self.get_logger().info(
            f'EKF on the {self.kind} model, Ts = {self.ts:g} s, {self.ekf.substeps} RK4 '
            f'sub-steps (stable to c_e = {cfg["u_max"]:g} Ns/m), noise {noise_of(cfg)}')

    # -- inputs --------------------------------------------------------------------------
    def _on_road(self, msg: PointStamped) -> None:
        w = float(msg.point.z)
        stamp = time_to_ns(msg.header.stamp)
        with self.lock:
            if not abs(w) <= 1.0:
                self.count['rejected'] += 1
                return
            if self.on_road_grid and self.grid_ns is None:
                self.grid_ns = stamp
            self.road.add(stamp / NS, w)
            self.road_arrived.notify_all()

    def _on_measurements(self, data: bytes, info) -> None:
        t0 = time.perf_counter()
        with self.lock:
            self._measurement(data, info, t0)

    def _measurement(self, data: bytes, info, t0: float) -> None:
        parsed = parse_measurements(data)
        if parsed is None:
            self.count['rejected'] += 1
            return
        stamp, y = parsed
        if (self.on_road_grid and self.grid_ns is None
                and not self._wait_for_road(lambda: self.grid_ns is not None)):
            # No grid yet: a state stamped off it would make the NMPC take the wrong
            # grid and refuse every later state (seen with the loop split across hosts,
            # where the ECU's first frames beat the first road height). Not published.
            self.count['before_road'] += 1
            return
        stamp = self._stamp(stamp)
        if self.last_ns is not None and stamp <= self.last_ns:
            self.count['late_or_repeated'] += 1
            return
        if self.grid_ns is not None and not self._road_at(stamp):
            self._wait_for_road(lambda: self._road_at(stamp))
        if any(math.isnan(v) for v in y):   # a CAN frame of the cycle was lost
            self.count['incomplete'] += 1
        u_now, u_mean, accel, deflection, speed = y
        if math.isnan(u_now):               # status frame lost: the last c_e held
            u_now = u_mean = self.u_now
        self.nis_sum += self._step(stamp, u_now, u_mean, (accel, deflection, speed))
        self._publish(stamp)
        done = time.time_ns()
        self.latency.add((done - info['received_timestamp']) * 1e-9)
        self.compute.add(time.perf_counter() - t0)
        if self.grid_ns is not None:        # stamps are sample instants: the loop's chain
            self.lag_meas.add((info['received_timestamp'] - stamp) * 1e-9)
            self.lag_state.add((done - stamp) * 1e-9)
        self.meas_sub.idle_at = time.monotonic() + self.warm_after_s

    def _warm(self) -> None:
        """Run a cycle's computation on scratch copies, so the due one finds warm caches.

        After ~Ts asleep, with the other processes of the loop on the same cores, this
        node's code and data are out of the CPU caches: the cycle then costs several
        times its warm time (measured: the compiled EKF cycle 0.4 ms instead of 0.1 ms).
        """
        with self.lock:
            ekf = self.ekf
            x, p, k = ekf.x, ekf.P, ekf.k
            ekf.cycle(_WARM_Y, self.u_now, self.u_now, 0.0, 0.0)
            self._state_bytes(self.last_ns or 0)
            ekf.x, ekf.P, ekf.k = x, p, k

    def _stamp(self, stamp: int) -> int:
        """Return the cycle stamp (ns) of an ECU message stamped ``stamp`` (ns).

        See ``stamp_on_road_grid``: the road sample instant in the window [−Ts/4, 3Ts/4)
        around the CAN receive time.  The ECU samples on that grid and sends at once, so
        its frames arrive a fraction of a millisecond after the instant; the quarter
        period before it keeps the pairing right when the ECU gateway's clock is a little
        behind the road's host (docs/hil.md: tolerated offsets).  The first cycle comes
        when the ECU has just started on the first road sample, on a busy machine up to
        a period late: the instant before it, but not before the first road sample.
        """
        if self.grid_ns is None:
            return stamp
        if self.last_ns is None:
            return max(stamp - (stamp - self.grid_ns) % self.ts_ns, self.grid_ns)
        return stamp - ((stamp - self.grid_ns + self.ts_ns // 4) % self.ts_ns
                        - self.ts_ns // 4)

    def _wait_for_road(self, arrived) -> bool:
        """Wait (lock released) up to ROAD_WAIT_PERIODS until ``arrived()``; counted.

        The ECU samples and sends at t_k as the road node publishes w(t_k) (it starts on
        the first road height it receives): its measurement may come first, and the
        prediction needs w(t_k) -- and the first cycle the grid of the first sample.
        """
        self.count['road_waits'] += 1
        return self.road_arrived.wait_for(arrived, ROAD_WAIT_PERIODS * self.ts)

    def _road_at(self, stamp_ns: int) -> bool:
        """Return True once the road sample of ``stamp_ns`` (or a later one) arrived."""
        latest = self.road.latest
        return latest is not None and latest[0] >= stamp_ns / NS - 1e-6

    # -- the filter ----------------------------------------------------------------------
    def _step(self, stamp_ns: int, u_now: float, u_mean: float, y) -> float:
        """Predict from the last estimate to ``stamp_ns`` and correct with y; return NIS.

        y is in erva_ros.core.estimator.MEASUREMENTS order, NaN = missing.
        """
        t1 = stamp_ns / NS
        if len(self.road) == 0:
            self.count['no_road'] += 1
        elif self.road.latest[0] < t1 - 1e-6:   # w(t_k) not here yet: extrapolated
            self.count['road_extrapolated'] += 1
        w1 = self.road.height(t1)
        steps = 0 if self.last_ns is None else max(
            1, int(round((stamp_ns - self.last_ns) / self.ts_ns)))
        if steps == 1:                      # every cycle: one compiled call
            _, nis = self.ekf.cycle(y, u_mean, u_now, self.road.height(self.last_ns / NS), w1)
            self.u_now = u_now
            return nis
        if steps == 0 or steps > self.cfg['max_gap_periods']:
            if steps:
                self.count['restarts'] += 1
            self.ekf.reset()
        else:
            self.count['gaps'] += 1
            t0 = self.last_ns / NS
            for i in range(steps):          # over a gap: the last applied damping held
                self.ekf.predict(u_mean if i == steps - 1 else self.u_now,
                                 self.road.height(t0 + i * self.ts),
                                 self.road.height(t0 + (i + 1) * self.ts))
        self.u_now = u_now
        return self.ekf.update(y, u_now, w1).nis

    def _publish(self, stamp_ns: int) -> None:
        self.pub_state.publish(self._state_bytes(stamp_ns))
        self.count['updates'] += 1
        self.last_ns = stamp_ns
        if self.status_level != diag.OK:
            self.status_level, self.status_text = diag.OK, 'estimating'
            self._publish_diagnostics()

    def _state_bytes(self, stamp_ns: int) -> bytes:
        """Return the estimate serialized as erva_ros.ros.msgs.state_msg's JointState."""
        x = self.ekf.x
        return self.state_encoder.encode(stamp_ns, x[0::2].tolist(), x[1::2].tolist())

    # -- diagnostics ---------------------------------------------------------------------
    def _publish_diagnostics(self) -> None:
        # Only the snapshot holds the lock: the statistics and the message are built
        # outside it, so a long run's percentiles never delay a cycle's filter step.
        with self.lock:
            values = dict(self.count)
            values['nis_mean'] = self.nis_sum / max(self.count['updates'], 1)
            std = self.ekf.std()
            level, text = self.status_level, self.status_text
        values['scheduling'] = getattr(self, 'scheduling', 'off')
        values.update(diag.flatten('latency_ms', self.latency.summary()))
        values.update(diag.flatten('compute_ms', self.compute.summary()))
        values.update(diag.flatten('sample_to_measurements_ms', self.lag_meas.summary()))
        values.update(diag.flatten('sample_to_state_ms', self.lag_state.summary()))
        for name, s in zip(self.ekf.model.state_names, std):
            values[f'std_{name}'] = float(s)
        if values['no_road'] and level == diag.OK:
            level, text = diag.WARN, 'no road height received: assuming w = 0'
        if values['before_road'] and not values['updates']:
            level, text = diag.WARN, 'no road height yet: measurements off its grid not used'
        values.update(diag.publisher_values(self.counted_publishers))
        values['status_seq'] = next(self._status_seq)
        self.pub_diag.publish(diag.array_msg(self.get_clock().now().nanoseconds, [
            diag.status_msg(self.get_fully_qualified_name(), level, text, values,
                            f'ekf:{self.kind}')]))

    def publish_status(self) -> None:
        """Publish the status now (the final counts, on shutdown: runtime.run_node)."""
        self._publish_diagnostics()

    def destroy_node(self):
        try:
            self.meas_sub.destroy()
        finally:
            super().destroy_node()


def main(args=None):
    return run_node('state_estimator_node', StateEstimatorNode, args)


if __name__ == '__main__':
    raise SystemExit(main())
