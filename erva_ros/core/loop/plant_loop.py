"""plant_sim_node's core: step the quarter car one period per road sample, with the right u_k.

The plant's state x_k at t_k is published when the road sample w(t_k) arrives; the
command for t_k comes back from the NMPC, and when w(t_{k+1}) arrives the plant
integrates [t_k, t_{k+1}) (the road linear in between), then publishes x_{k+1} and the
chassis acceleration and generator outputs at t_k.

Commands act at a fixed instant (logical execution time): with the loop's command
delay d > 0 the command u_k acts from t_k + d, so [t_k, t_k + d) is integrated with
the one acting before, [t_k + d, t_{k+1}) with u_k -- as ``erva sim
--actuation-delay d``; d = 0 is the paper's loop (u_k from t_k).  u_k is chosen by
:class:`~erva_ros.core.loop.command_hold.CommandHold` (its doc is the late rule): the
command stamped t_k received by t_k + d, else the newest plan received in time, else
passive c_e0, each counted.  With d = 0 a command counts until w(t_{k+1}) arrives.

Lock-step: the plant publishes ``/clock``; after the state at t_k it waits for the
command stamped t_k (or ``lockstep_timeout_s`` of wall time), then asks for the next
sample -- the same instants, deterministic, and equal to `erva sim`.  No ROS inside:
:class:`PlantLoop` returns what to publish (:class:`Step`) and the status.
"""

from dataclasses import dataclass
from typing import Any, List, Mapping, Optional, Tuple

import numpy as np

from erva_ros.core.levels import ERROR, OK, WARN
from erva_ros.core.loop.command_hold import CommandHold
from erva_ros.core.timing import DurationStats, PeriodStats
from erva_ros.core.loop.validation import MessageRejected
from erva_ros.core.model.quarter_car import QuarterCarModel
from erva_ros.core.model.plant import PlantSimulator
from erva_ros.core.reports import PlantReport, Timing
from erva_ros.core.settings.loop import command_delay_ns
from erva_ros.core.wire import NS


@dataclass(frozen=True)
class Step:
    """What one plant step publishes: x_{k+1} at t_{k+1}, and the outputs at t_k."""

    t_k: int                  # ns
    u_k: float                # Ns/m, acting from t_k + d
    u_at_t_k: float           # Ns/m, acting at t_k (u_k if d = 0, else the one before)
    sprung_accel: float       # m/s², at t_k
    generator: Tuple[float, float]     # position (m), v_gen (m/s) at t_k
    x_next: np.ndarray        # the state at t_{k+1} = t_k + Ts
    decision: Optional[Tuple[int, str]] = None   # the status of u_k, if decided now


class PlantLoop:
    """The plant's samples, commands and report (see the module doc)."""

    def __init__(self, model: QuarterCarModel, cfg: Mapping[str, Any], report: PlantReport):
        params = model.params
        self.model = model
        self.ts = cfg['ts']
        self.ts_ns = int(round(self.ts * NS))
        self.lockstep = cfg['mode'] == 'lockstep'
        self.delay_s = float(cfg['command_delay_s'])
        self.delay_ns = command_delay_ns(self.delay_s)
        if not self.delay_ns < self.ts_ns:
            raise ValueError(f'command_delay_s = {self.delay_s:g} s must be below ts = '
                             f'{self.ts:g} s')
        self.n_steps = int(round(cfg['duration_s'] / self.ts))
        self.plant = PlantSimulator(model, self.ts)
        self.plant.prepare_delay(self.delay_s)
        self.hold = CommandHold(self.ts_ns, params.c_e0,
                                int(round(cfg['command_timeout_s'] * NS)))
        self.k: Optional[int] = None     # index of the current sample (state x_k published)
        self.t_ns: Optional[int] = None  # stamp of sample k (ns)
        self.w_k = 0.0                   # road height at t_k (m)
        self.u_k: Optional[float] = None  # damping decided for [t_k + d, t_{k+1} + d) (Ns/m)
        self.acting = params.c_e0        # the damping acting at t_k (before t_k + d)
        self.sample = None               # plant outputs at t_k with u_k
        self.report = report
        report.mode, report.model, report.steps_total = cfg['mode'], model.kind, self.n_steps
        report.command_delay_ms = self.delay_s * 1e3
        self.late_on_arrival = 0             # commands for an already integrated sample
        self.road_latency = DurationStats()   # road sample time -> height received
        self.step_time = DurationStats()      # height received -> state published
        self.loop_latency = DurationStats()   # state published -> its command received
        self.cmd_period = PeriodStats(self.ts)   # command arrivals |Δt - Ts|
        self.arrival = DurationStats()        # sample t_k -> its command received

    @property
    def finished(self) -> bool:
        """Return True once the scenario's last step is done."""
        return self.report.finished

    # -- road samples drive the plant ---------------------------------------------------
    def on_height(self, stamp: int, w: float) -> List[Step]:
        """Take w(t) stamped ``stamp``: the first starts the plant; later ones step it.

        Returns the steps to publish (a skipped road sample: the road linear across the
        gap, counted); MessageRejected for a stamp not after the current sample or off
        its Ts grid.
        """
        if self.k is None:
            self.k, self.t_ns, self.w_k = 0, stamp, w
            return []
        steps, rest = divmod(stamp - self.t_ns, self.ts_ns)
        if steps <= 0 or rest != 0:
            why = 'not after' if steps <= 0 else 'off the Ts grid of'
            raise MessageRejected(f'stamp {stamp} ns is {why} the current sample '
                                  f'{self.t_ns} ns')
        if steps > 1:
            self.report.road_gaps += 1
        w0, out = self.w_k, []
        for i in range(1, steps + 1):
            out.append(self._advance(w0 + (w - w0) * i / steps))
            if self.finished:
                break
        return out

    def _advance(self, w_next: float) -> Step:
        """Step the plant from t_k to t_{k+1}."""
        decision = self.decide() if self.u_k is None else None
        t_k, u_k, sample, u_at_t_k = self.t_ns, self.u_k, self.sample, self._u_at_t_k()
        if self.delay_ns:
            self.plant.step_delayed(self.acting, u_k, self.delay_s, self.w_k, w_next)
            self.acting = u_k
        else:
            self.plant.step(u_k, self.w_k, w_next)
        self.k += 1
        self.t_ns += self.ts_ns
        self.w_k, self.u_k, self.sample = w_next, None, None
        position, v_gen, _ = self.plant.generator(sample.x, u_at_t_k)
        if self.k >= self.n_steps:
            self.report.finished = True
        return Step(t_k, u_k, u_at_t_k, sample.sprung_accel, (position, v_gen),
                    np.array(self.plant.x, dtype=float), decision)

    def _u_at_t_k(self) -> float:
        """Return the damping acting at the sample instant t_k itself."""
        return self.acting if self.delay_ns else self.u_k

    def decide(self) -> Tuple[int, str]:
        """Fix u_k (acting from t_k + d) from the command, its plan or passive c_e0.

        Realtime with d > 0 only commands received by t_k + d count (the late rule,
        command_hold.py); returns the status that says where u_k came from.
        """
        deadline = (self.t_ns + self.delay_ns
                    if self.delay_ns and not self.lockstep else None)
        # Passive damping is an outage (ERROR) only once a command has acted: before that
        # (the start, or a first command late for its t_k + d) there is no plan to use up.
        started = self.hold.counts['command'] + self.hold.counts['plan'] > 0
        self.u_k, source = self.hold.select(self.t_ns, deadline)
        self.sample = self.plant.sample(self._u_at_t_k(), self.w_k)
        if source == 'command':
            return OK, 'running'
        if source == 'plan':
            return WARN, 'command late: applying the previous plan'
        if self.hold.stamp_ns is None:
            return WARN, 'no command yet: passive damping c_e0'
        if not started:
            return WARN, 'first command late (after t_k + d): passive damping c_e0'
        return ERROR, 'no command and plan used up: passive damping c_e0'

    # -- commands ----------------------------------------------------------------------
    def on_command(self, stamp: int, plan: np.ndarray, rx_ns: int = 0) -> bool:
        """Take a command received at ``rx_ns`` (wall ns; realtime).

        Returns True if it is the one lock-step waits for (u_k open).
        """
        if self.t_ns is not None and (stamp < self.t_ns
                                      or (stamp == self.t_ns and self.u_k is not None
                                          and not self.lockstep)):
            self.late_on_arrival += 1     # its u_k is already decided
        elif not self.lockstep and stamp == self.t_ns:
            self.arrival.add((rx_ns - stamp) * 1e-9)
        self.hold.update(stamp, plan, rx_ns)
        return (self.lockstep and self.k is not None and not self.finished
                and self.u_k is None and stamp == self.t_ns)

    def fill(self) -> None:
        """Bring the report's figures up to date."""
        r = self.report
        r.steps = self.k or 0
        r.sim_time_s = 0.0 if self.k is None else self.k * self.ts
        r.harvested_j = self.plant.harvested_j
        r.acc_rms_continuous = self.plant.acc_rms_continuous()
        r.u_from_command = self.hold.counts['command']
        r.u_from_plan = self.hold.counts['plan']
        r.u_from_passive = self.hold.counts['passive']
        r.out_of_order_commands = self.hold.out_of_order
        r.late_commands = self.late_on_arrival + self.hold.late
        r.command_arrival_ms = Timing.of(self.arrival.summary())
        r.arrival_p999_ms = self.arrival.quantile(0.999) * 1e3
        r.road_latency_ms = Timing.of(self.road_latency.summary())
        r.step_ms = Timing.of(self.step_time.summary())
        r.loop_latency_ms = Timing.of(self.loop_latency.summary())
        r.cmd_jitter_ms = Timing.of(self.cmd_period.jitter.summary())


__all__ = ['Step', 'PlantLoop']
