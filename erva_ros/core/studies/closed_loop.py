"""Offline closed loop (no ROS): controller + plant simulator + road, one control period a step.

Per-step semantics (the live lock-step mode reproduces them exactly):

    plant = PlantSimulator(model, ts)          # the plant's model (the controller has its own)
    for k in range(n):  t_k = k·Ts,  w_k = road.height(t_k)
        preview = error_model(road.preview(t_k, N, Ts))      # or the perfect preview
        if before_sample is not None:
            before_sample(k)
        cpu0 = time.thread_time_ns()
        res = controller.compute(plant.x, preview, t_k)
        solve_cpu[k] = (time.thread_time_ns() - cpu0) * 1e-9
        s = plant.sample(res.damping_cmd, w_k)             # z̈_s(t_k), P(t_k) with u_k
        plant.step(res.damping_cmd, w_k, road.height((k + 1)·Ts))   # not t_k + Ts: last bit
    metrics = comfort_power(accels, plant.harvested_j, n·Ts)

With ``actuation_delay_s`` = d > 0 the plant is an actuator behind a delay (as the ECU in
HIL mode): u_k acts on [t_k + d, t_{k+1} + d), the previous command (c_e0 before the
first) until then, and z̈_s(t_k), P(t_k) are sampled with that previous command.  The
controller's ``command_delay_s`` setting compensates it (erva_ros/core/controllers/delay.py).
"""

from dataclasses import dataclass, field
import time
from typing import Callable, Dict, List, Optional

import numpy as np

from erva_ros.core.controllers.base import Controller
from erva_ros.core.metrics import comfort_power, evaluation_objective, percentiles_ms
from erva_ros.core.model.quarter_car import QuarterCarModel
from erva_ros.core.model.plant import PlantSimulator
from erva_ros.core.road.preview import PreviewErrorModel
from erva_ros.core.road.profiles import Road


@dataclass
class ClosedLoopResult:
    """Time series (one row per sample t_k) and metrics of one closed-loop run."""

    controller: str
    road: str
    ts: float
    t: np.ndarray               # s, (n,)
    x: np.ndarray               # states at t_k, (n, nx)
    u: np.ndarray               # Ns/m, command u_k (acts on [t_k + d, t_{k+1} + d), d = delay)
    w: np.ndarray               # m, road height at t_k
    sprung_accel: np.ndarray    # m/s², z̈_s(t_k)
    power: np.ndarray           # W, instantaneous harvested power at t_k
    harvested_j: float          # J, integrated by the plant over the run
    solve_time_s: np.ndarray    # s, controller.compute wall time per step
    iterations: np.ndarray      # solver iterations per step
    status: List[str]           # ControlResult.status per step
    counters: Dict[str, int]    # controller.counters at the end
    wall_time_s: float          # s, wall time of the whole loop
    plans: Optional[np.ndarray] = None   # (n, N) planned commands, if kept
    x_final: Optional[np.ndarray] = None  # state at t_n
    accel_sq_int: float = float('nan')    # m²/s³, ∫ z̈_s² dt over the run (plant, exact)
    metrics: Dict = field(default_factory=dict)
    # s, the thread's CPU time in compute() per step: the wall time minus the slices other
    # tasks took on a shared core (a loaded machine's wall time says more about the load)
    solve_cpu_s: Optional[np.ndarray] = None

    @property
    def duration_s(self) -> float:
        """Return the simulated time n·Ts (s)."""
        return self.t.size * self.ts


def simulate_closed_loop(model: QuarterCarModel, controller: Controller, road: Road,
                         duration_s: float, ts: Optional[float] = None,
                         preview_model: Optional[PreviewErrorModel] = None,
                         keep_plans: bool = False,
                         progress: Optional[Callable[[int, int], None]] = None,
                         actuation_delay_s: float = 0.0,
                         before_sample: Optional[Callable[[int], None]] = None
                         ) -> ClosedLoopResult:
    """Run ``controller`` on ``model``'s plant over ``road`` for ``duration_s`` (module doc).

    ``ts`` defaults to the controller's; the controller is reset first.
    ``before_sample(k)`` runs before the controller computes sample k: a sample boundary,
    where live settings change (`erva sim --set`, core/controllers/tuning.py).
    """
    ts = controller.ts if ts is None else float(ts)
    n = int(round(duration_s / ts))
    if n < 1:
        raise ValueError(f'duration {duration_s} s is shorter than one sample of {ts} s')
    big_n = controller.horizon
    controller.reset()
    plant = PlantSimulator(model, ts)
    t = ts * np.arange(n)
    xs = np.empty((n, plant.model.nx))
    u = np.empty(n)
    w = road.height(t)
    acc = np.empty(n)
    pw = np.empty(n)
    solve = np.empty(n)
    solve_cpu = np.empty(n)
    iters = np.zeros(n, dtype=int)
    status: List[str] = []
    plans = np.empty((n, big_n)) if keep_plans else None
    delay = float(actuation_delay_s)
    if not 0.0 <= delay < ts:
        raise ValueError(f'actuation delay must be in [0, Ts = {ts:g} s), got {delay:g} s')
    acting = controller.c_e0          # delayed actuator: the command acting at t_k
    wall0 = time.perf_counter()
    for k in range(n):
        t_k = k * ts
        w_k = road.height(t_k)
        preview = road.preview(t_k, big_n, ts)
        if preview_model is not None:
            preview = preview_model.apply(preview, t_k)
        if before_sample is not None:
            before_sample(k)
        cpu0 = time.thread_time_ns()
        res = controller.compute(plant.x, preview, t_k)
        solve_cpu[k] = (time.thread_time_ns() - cpu0) * 1e-9
        s = plant.sample(acting if delay else res.damping_cmd, w_k)
        xs[k] = s.x
        u[k] = res.damping_cmd
        acc[k] = s.sprung_accel
        pw[k] = s.power_w
        solve[k] = res.solve_time_s
        iters[k] = res.iterations
        status.append(res.status)
        if plans is not None:
            plans[k] = res.plan
        # the road at t_{k+1} = (k + 1)·Ts, the next sample's instant as the live loop
        # stamps it (t_k + Ts can differ from it in the last bit)
        w_next = road.height((k + 1) * ts)
        if delay:
            plant.step_delayed(acting, res.damping_cmd, delay, w_k, w_next)
            acting = res.damping_cmd
        else:
            plant.step(res.damping_cmd, w_k, w_next)
        if progress is not None:
            progress(k + 1, n)
    wall = time.perf_counter() - wall0
    result = ClosedLoopResult(controller.name, road.name, ts, t, xs, u, w, acc, pw,
                              plant.harvested_j, solve, iters, status, controller.counters,
                              wall, plans, plant.x.copy(), plant.accel_sq_int,
                              solve_cpu_s=solve_cpu)
    result.metrics = closed_loop_metrics(result)
    return result


def closed_loop_metrics(r: ClosedLoopResult) -> Dict:
    """Return comfort/power (metrics.comfort_power), solve-time percentiles and fallbacks."""
    m = dict(comfort_power(r.sprung_accel, r.harvested_j, r.duration_s))
    # Comfort between the samples too: z̈_s jumps where the command switches (at the
    # samples), and a cost sampled there can trade the instants in between.
    m['acc_rms_continuous'] = (float(np.sqrt(r.accel_sq_int / r.duration_s))
                               if np.isfinite(r.accel_sq_int) else None)
    m['solve_ms'] = percentiles_ms(r.solve_time_s)
    if r.solve_cpu_s is not None:
        m['solve_cpu_ms'] = percentiles_ms(r.solve_cpu_s)
    m['iterations_mean'] = float(np.mean(r.iterations)) if r.iterations.size else 0.0
    m['fallbacks'] = {k: int(r.counters.get(k, 0))
                      for k in ('fallback_plan', 'fallback_passive', 'failures',
                                'nan_rejections', 'late')}
    m['realtime_factor'] = float(r.duration_s / r.wall_time_s) if r.wall_time_s > 0 else None
    return m


def closed_loop_cost(r: ClosedLoopResult, alpha1: float, alpha2: float,
                     cost: str = 'paper') -> float:
    """Return the NMPC stage cost summed along the closed loop (for suboptimality).

    ``paper``: Σ_k α1/Ts²·(a_k − a_{k−1})² − α2·P_k (a_{−1} = a_0);
    ``continuous``: (α1·∫ z̈_s² dt − α2·E_h)/Ts, both integrated by the plant -- what
    the continuous stage cost predicts, between the samples too.
    """
    a = r.sprung_accel
    if cost == 'paper':
        jerk = np.diff(a, prepend=a[0])
        return float(np.sum(alpha1 / r.ts ** 2 * jerk ** 2 - alpha2 * r.power))
    return float((alpha1 * r.accel_sq_int - alpha2 * r.harvested_j) / r.ts)


__all__ = ['ClosedLoopResult', 'simulate_closed_loop', 'closed_loop_metrics', 'closed_loop_cost',
           'evaluation_objective']
