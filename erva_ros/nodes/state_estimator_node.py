"""state_estimator_node: the NMPC's state ``/erva/state`` from the ECU's sensors (HIL mode).

A thin rclpy adapter around :class:`erva_ros.estimator.ExtendedKalmanFilter` (the shared
CasADi model, paper eq. (11)).  It subscribes to what ecu_bridge_node publishes for
each ECU cycle -- ``ecu/damping_applied``, ``ecu/sprung_accel``, ``ecu/suspension``
and ``ecu/generator``, all with the same stamp t_k -- plus ``road/height`` (the road at
the tyre, buffered and interpolated).  The work is spread over the cycle's messages so
the last one costs little: the damping message (the ECU sends it first) triggers the
prediction from t_{k-1} with the ECU's cycle-mean c_e and the road w(t_{k-1}) → w(t_k)
and the output linearisation; each measurement is then applied the moment it
arrives (sequential scalar updates, equal to the batch update); the estimate is
published on ``state`` with stamp t_k once all three are in.  A cycle that stays
incomplete (a CAN frame was lost) is published with what it has when the next cycle
starts, or after Ts/2 at the latest check (once per Ts).
``/diagnostics`` reports counters, the mean normalised innovation squared (≈ 3 when
the noise model fits) and the latency this node adds (last message of a cycle
received → state published, p50/p99/max in ms).
"""

import gc
import time
from typing import Dict, Optional

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import AccelStamped, PointStamped
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from sensor_msgs.msg import JointState

from erva_ros import topics
from erva_ros.estimator import ExtendedKalmanFilter
from erva_ros.hil import topics as hil_topics
from erva_ros.hil.latency import LatencyStats
from erva_ros.hil.road_buffer import RoadBuffer
from erva_ros.hil.settings import (ESTIMATOR_DEFAULTS, ESTIMATOR_NUMERIC, INTEGER_KEYS,
                                   noise_of, TS_SPEC)
from erva_ros.live import diagnostics as diag
from erva_ros.live.msgs import NS, state_msg, time_to_ns
from erva_ros.live.parameters import (declare_choice, declare_erva_params, declare_number,
                                      LIVE_CHOICES)
from erva_ros.live.runtime import run_node

#: Measurement rows of the EKF (erva_ros.estimator.MEASUREMENTS) fed by each topic.
ROWS = {'accel': 0, 'deflection': 1, 'speed': 2}
#: Plausibility bounds of the measurements (absurd beyond: rejected, counted).
LIMITS = {'accel': 100.0, 'deflection': 0.5, 'speed': 1e3, 'applied': 1e6}


class _Cycle:
    """Measurements of one ECU cycle (one stamp) as they arrive."""

    def __init__(self, stamp_ns: int):
        self.stamp_ns = stamp_ns
        self.started = time.monotonic()
        self.begun = False                  # predicted to this stamp, output linearised
        self.waiting: Dict[str, float] = {}  # measurements that came before the damping
        self.used = set()
        self.nis = 0.0
        self.cpu = 0.0                      # s spent in this cycle's callbacks


class StateEstimatorNode(Node):
    """Estimate the quarter car's state from the ECU's measurements with an EKF."""

    def __init__(self):
        super().__init__('state_estimator_node')
        self.params = declare_erva_params(self)
        self.ts = declare_number(self, 'ts', 0.02, TS_SPEC)
        choices, doc = LIVE_CHOICES['model']
        self.kind = declare_choice(self, 'model', 'erva', choices, doc)
        cfg = {key: declare_number(self, key, default, ESTIMATOR_NUMERIC[key],
                                   integer=key in INTEGER_KEYS)
               for key, default in ESTIMATOR_DEFAULTS.items()}
        self.cfg = cfg
        self.ekf = ExtendedKalmanFilter(self.params, self.kind, self.ts, noise_of(cfg),
                                        u_max=cfg['u_max'])
        self.ts_ns = int(round(self.ts * NS))
        self.road = RoadBuffer(max_extrapolation_s=self.ts)
        self.cycle: Optional[_Cycle] = None
        self.last_ns: Optional[int] = None  # stamp of the last published estimate
        self.u_now = self.params.c_e0       # damping applied at the last stamp (Ns/m)
        self.count = dict.fromkeys(('updates', 'incomplete', 'gaps', 'restarts',
                                    'late_or_repeated', 'rejected', 'no_road'), 0)
        self.nis_sum = 0.0
        self.latency = LatencyStats()       # last message of a cycle received -> published
        self.compute = LatencyStats()       # time spent in the cycle's callbacks
        self.status_level, self.status_text = diag.WARN, 'waiting for ECU measurements'

        qos = topics.control_qos()
        self.pub_state = self.create_publisher(JointState, topics.STATE, qos)
        self.pub_diag = self.create_publisher(DiagnosticArray, topics.DIAGNOSTICS, qos)
        # Created in the order the ECU sends (status first): when several are ready at
        # once the executor takes them in this order, so the prediction comes first.
        self.create_subscription(JointState, hil_topics.ECU_DAMPING_APPLIED, self._on_applied,
                                 qos)
        self.create_subscription(AccelStamped, hil_topics.ECU_SPRUNG_ACCEL, self._on_accel,
                                 qos)
        self.create_subscription(JointState, hil_topics.ECU_SUSPENSION, self._on_suspension,
                                 qos)
        self.create_subscription(JointState, hil_topics.ECU_GENERATOR, self._on_generator, qos)
        self.create_subscription(PointStamped, topics.ROAD_HEIGHT, self._on_road, qos)
        steady = Clock(clock_type=ClockType.STEADY_TIME)
        self.create_timer(self.ts, self._on_timer, clock=steady)
        self.create_timer(cfg['diagnostics_period_s'], self._publish_diagnostics, clock=steady)
        # Start-up objects (CasADi functions, messages, rclpy) are never garbage: keep the
        # collector from scanning them, so a collection cannot stall a cycle for ms.
        gc.freeze()
        self.get_logger().info(
            f'EKF on the {self.kind} model, Ts = {self.ts:g} s, {self.ekf.substeps} RK4 '
            f'sub-steps (stable to c_e = {cfg["u_max"]:g} Ns/m), noise {noise_of(cfg)}')

    # -- inputs --------------------------------------------------------------------------
    def _on_road(self, msg: PointStamped) -> None:
        w = float(msg.point.z)
        if not abs(w) <= 1.0:
            self.count['rejected'] += 1
            return
        self.road.add(time_to_ns(msg.header.stamp) / NS, w)

    def _on_accel(self, msg: AccelStamped, info) -> None:
        self._on_measurement('accel', msg, msg.accel.linear.z, info)

    def _on_suspension(self, msg: JointState, info) -> None:
        if list(msg.name) != [hil_topics.SUSPENSION_JOINT] or len(msg.position) != 1:
            self.count['rejected'] += 1
            return
        self._on_measurement('deflection', msg, msg.position[0], info)

    def _on_generator(self, msg: JointState, info) -> None:
        if list(msg.name) != [topics.GENERATOR_JOINT] or len(msg.velocity) != 1:
            self.count['rejected'] += 1
            return
        # Measured as rotor speed phi' = v_gen / l (the EKF's y_3).
        self._on_measurement('speed', msg, msg.velocity[0] / self.params.l, info)

    def _on_applied(self, msg: JointState, info) -> None:
        if list(msg.name) != list(hil_topics.APPLIED_JOINTS) or len(msg.position) != 2:
            self.count['rejected'] += 1
            return
        u_now, u_mean = float(msg.position[0]), float(msg.position[1])
        if not (0 <= u_now <= LIMITS['applied'] and 0 <= u_mean <= LIMITS['applied']):
            self.count['rejected'] += 1
            return
        t0 = time.perf_counter()
        cyc = self._cycle_for(time_to_ns(msg.header.stamp))
        if cyc is not None and not cyc.begun:
            self._begin(cyc, u_now, u_mean)
            self._maybe_publish(cyc, info, t0)

    def _on_measurement(self, part: str, msg, value: float, info) -> None:
        value = float(value)
        if not abs(value) <= LIMITS[part]:           # also NaN
            self.count['rejected'] += 1
            return
        t0 = time.perf_counter()
        cyc = self._cycle_for(time_to_ns(msg.header.stamp))
        if cyc is None:
            return
        if cyc.begun:
            self._correct(cyc, part, value)
            self._maybe_publish(cyc, info, t0)
        else:
            cyc.waiting[part] = value
            cyc.cpu += time.perf_counter() - t0

    # -- the filter ----------------------------------------------------------------------
    def _cycle_for(self, stamp: int) -> Optional[_Cycle]:
        """Return the cycle of ``stamp``; finish an older unfinished one first."""
        if (self.last_ns is not None and stamp <= self.last_ns) or (
                self.cycle is not None and stamp < self.cycle.stamp_ns):
            self.count['late_or_repeated'] += 1
            return None
        if self.cycle is not None and stamp != self.cycle.stamp_ns:
            self._finish(self.cycle)
        if self.cycle is None:
            self.cycle = _Cycle(stamp)
        return self.cycle

    def _begin(self, cyc: _Cycle, u_now: float, u_mean: float) -> None:
        """Predict from the last estimate to the cycle's stamp; linearise the outputs."""
        t = cyc.stamp_ns / NS
        if len(self.road) == 0:
            self.count['no_road'] += 1
        if self.last_ns is None:
            self.ekf.reset()
        else:
            steps = max(1, int(round((cyc.stamp_ns - self.last_ns) / self.ts_ns)))
            if steps > self.cfg['max_gap_periods']:
                self.count['restarts'] += 1
                self.ekf.reset()
            else:
                if steps > 1:
                    self.count['gaps'] += 1
                t0 = self.last_ns / NS
                for i in range(steps):      # over a gap: the last applied damping held
                    self.ekf.predict(u_mean if i == steps - 1 else self.u_now,
                                     self.road.height(t0 + i * self.ts),
                                     self.road.height(t0 + (i + 1) * self.ts))
        self.ekf.linearize_output(u_now, self.road.height(t))
        self.u_now = u_now
        cyc.begun = True
        for part, value in cyc.waiting.items():
            self._correct(cyc, part, value)
        cyc.waiting.clear()

    def _correct(self, cyc: _Cycle, part: str, value: float) -> None:
        if part in cyc.used:
            return
        _, nis = self.ekf.correct(ROWS[part], value)
        cyc.nis += nis
        cyc.used.add(part)

    def _maybe_publish(self, cyc: _Cycle, info, t0: float) -> None:
        if cyc.begun and len(cyc.used) == len(ROWS):
            self._publish(cyc)
            self.latency.add((time.time_ns() - info['received_timestamp']) * 1e-9)
            self.compute.add(cyc.cpu + time.perf_counter() - t0)
        else:
            cyc.cpu += time.perf_counter() - t0

    def _finish(self, cyc: _Cycle) -> None:
        """Publish a cycle that will not complete (a frame was lost) with what it has."""
        self.count['incomplete'] += 1
        if not cyc.begun:
            self._begin(cyc, self.u_now, self.u_now)
        self._publish(cyc)

    def _publish(self, cyc: _Cycle) -> None:
        self.pub_state.publish(state_msg(cyc.stamp_ns, self.ekf.x, self.kind))
        self.nis_sum += cyc.nis
        self.count['updates'] += 1
        self.last_ns = cyc.stamp_ns
        self.cycle = None
        if self.status_level != diag.OK:
            self.status_level, self.status_text = diag.OK, 'estimating'
            self._publish_diagnostics()

    def _on_timer(self) -> None:
        # A cycle still incomplete after Ts/2 lost a frame: do not make the NMPC wait (a
        # new cycle finishes it too; this timer, once per Ts, is the backstop).
        if self.cycle is not None and time.monotonic() - self.cycle.started > self.ts / 2:
            self._finish(self.cycle)

    # -- diagnostics ---------------------------------------------------------------------
    def _publish_diagnostics(self) -> None:
        values = dict(self.count)
        n = max(self.count['updates'], 1)
        values['nis_mean'] = self.nis_sum / n
        values.update(diag.flatten('latency_ms', self.latency.summary()))
        values.update(diag.flatten('compute_ms', self.compute.summary()))
        std = self.ekf.std()
        for name, s in zip(self.ekf.model.state_names, std):
            values[f'std_{name}'] = float(s)
        level, text = self.status_level, self.status_text
        if self.count['no_road'] and level == diag.OK:
            level, text = diag.WARN, 'no road height received: assuming w = 0'
        arr = DiagnosticArray()
        arr.header.stamp = self.get_clock().now().to_msg()
        arr.status = [diag.status_msg(self.get_fully_qualified_name(), level, text, values,
                                      f'ekf:{self.kind}')]
        self.pub_diag.publish(arr)


def main(args=None):
    return run_node('state_estimator_node', StateEstimatorNode, args)


if __name__ == '__main__':
    raise SystemExit(main())
