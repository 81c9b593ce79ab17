"""What the controller's plan predicts: the states and outputs over the horizon.

For the command of sample t_k the NMPC publishes, beside it, the trajectory its plan
implies on the shared model (core/model/quarter_car.py): from x(t_k), with the damping acting
before t_k + d (``acting``: what the earlier commands left in force), then plan[j] on
[t_{k+j} + d, t_{k+j+1} + d), and the road the preview gave, linear between its
samples w(t_k + j·Ts).  :class:`Predictor` returns the states x(t_{k+j}) and the chassis
acceleration and harvested power at t_{k+j}, j = 0..N, with the damping acting at that
instant (as the plant publishes them; at t_{k+N} the plan's last value, held).

It integrates exactly as :class:`~erva_ros.core.model.plant.PlantSimulator` does (RK4 with
sub-steps of at most ``PLANT_SUBSTEP_S``, the period split at d), so with the plan
applied and the same road it reproduces the plant to rounding; for a converged solve
it is the OCP's own trajectory to the integrators' accuracy, for a fallback what the
shifted plan implies.  One compiled CasADi call per sample (``mapaccum`` over the
periods, ``codegen`` as the NMPC's).

:class:`PlanPredictor` is nmpc_node's part: it keeps the commands published (for
``acting``) and returns the ``prediction`` of a sample.  :func:`prediction_errors` is the
report's: each prediction against what then happened, h steps ahead.
"""

from dataclasses import dataclass
from functools import lru_cache
import math
from typing import Dict, Mapping, Optional, Sequence, Tuple

import casadi as ca
import numpy as np

from erva_ros.core.model.codegen import BufferedCall, compile_for
from erva_ros.core.model.quarter_car import PLANT_SUBSTEP_S

#: The outputs after the states in each point of a ``prediction`` message.
OUTPUT_NAMES = ('sprung_accel', 'power')


def prediction_joint_names(state_names: Sequence[str]) -> Tuple[str, ...]:
    """Return the joint names of a ``prediction`` message: the states, z̈_s and P."""
    return tuple(state_names) + OUTPUT_NAMES


@dataclass(frozen=True)
class Prediction:
    """The plan's trajectory at t_{k+j}, j = 0..N: states, z̈_s (m/s²), power (W)."""

    states: np.ndarray          # (N + 1, nx)
    sprung_accel: np.ndarray    # (N + 1,)
    power: np.ndarray           # (N + 1,)

    def table(self) -> np.ndarray:
        """Return the (N + 1, nx + 2) rows [x, z̈_s, P] a ``prediction`` message carries."""
        return np.column_stack([self.states, self.sprung_accel, self.power])


def _pieces(ts: float, delay_s: float):
    """Return the (duration, sub-steps) the plant integrates one period in."""
    spans = (delay_s, ts - delay_s) if delay_s > 0 else (ts,)
    return [(dt, max(1, math.ceil(dt / PLANT_SUBSTEP_S - 1e-9))) for dt in spans]


@lru_cache(maxsize=16)
def _function(model, ts: float, horizon: int, delay_s: float) -> ca.Function:
    """(x0, acting, plan[N], w[N+1]) -> (states (N+1) x nx, z̈_s[N+1], P[N+1])."""
    nx, n = model.nx, horizon
    x, p = ca.SX.sym('x', nx), ca.SX.sym('p', 4)    # p = [u before t + d, u after, w0, w1]
    u_before, u_after, w0, w1 = p[0], p[1], p[2], p[3]
    t, xn = 0.0, x
    for (dt, substeps), u in zip(_pieces(ts, delay_s),
                                 (u_before, u_after) if delay_s > 0 else (u_after,)):
        wa, wb = w0 + (w1 - w0) * t / ts, w0 + (w1 - w0) * (t + dt) / ts
        xn = model.rk4_step(dt, substeps)(xn, u, wa, wb)
        t += dt
    u_now = u_before if delay_s > 0 else u_after        # the damping acting at t itself
    acc, pw = model.outputs(x, u_now, w0)
    period = ca.Function('period', [x, p], [xn, ca.vertcat(acc, pw)])
    roll = period.mapaccum('roll', n)
    x0, acting = ca.MX.sym('x0', nx), ca.MX.sym('acting')
    plan, w = ca.MX.sym('plan', n), ca.MX.sym('w', n + 1)
    before = ca.vertcat(acting, plan[:n - 1])            # acting at t_{k+j}, j = 0..N-1
    xs, outs = roll(x0, ca.vertcat(before.T, plan.T, w[:n].T, w[1:].T))
    acc_n, pw_n = model.outputs(xs[:, n - 1], plan[n - 1], w[n])
    states = ca.horzcat(x0, xs)
    return ca.Function(f'predict_{model.kind}_{n}', [x0, acting, plan, w],
                       [states.T, ca.horzcat(outs[0, :], acc_n).T,
                        ca.horzcat(outs[1, :], pw_n).T],
                       ['x0', 'acting', 'plan', 'w'], ['states', 'sprung_accel', 'power'])


class Predictor:
    """Roll a plan out on the model over N periods Ts with the command delay d."""

    def __init__(self, model, ts: float, horizon: int, delay_s: float = 0.0,
                 codegen: str = 'off'):
        if not 0 <= delay_s < ts:
            raise ValueError(f'command delay {delay_s:g} s must be in [0, Ts = {ts:g} s)')
        if horizon < 1:
            raise ValueError(f'horizon must be >= 1, got {horizon}')
        self.model, self.horizon = model, int(horizon)
        fn, = compile_for(codegen, [_function(model, float(ts), self.horizon,
                                              float(delay_s))], 'the predictor')
        self._fn = BufferedCall(fn)

    def __call__(self, x0, acting: float, plan, preview) -> Prediction:
        """Return the trajectory of ``plan`` (N values) from ``x0`` on ``preview`` (N + 1)."""
        n = self.horizon
        plan, preview = np.asarray(plan, dtype=float), np.asarray(preview, dtype=float)
        if plan.size < n or preview.size < n + 1:
            raise ValueError(f'need {n} plan values and {n + 1} preview heights, got '
                             f'{plan.size} and {preview.size}')
        states, acc, pw = self._fn(np.asarray(x0, dtype=float), float(acting), plan[:n],
                                   preview[:n + 1])
        return Prediction(np.asarray(states).reshape(n + 1, -1), np.ravel(acc), np.ravel(pw))


class PlanPredictor:
    """nmpc_node's predictions: the commands published so far and each sample's trajectory.

    ``acting`` at t_k is what the plant applies on [t_{k-1} + d, t_k + d): the newest
    command before t_k, its plan entry for t_{k-1}, else passive c_e0 (the late rule of
    core/loop/command_hold.py, assuming every command arrived in time).
    """

    def __init__(self, model, ts: float, horizon: int, delay_s: float, c_e0: float,
                 codegen: str = 'off'):
        self.predict = Predictor(model, ts, horizon, delay_s, codegen)
        self.ts_ns = int(round(ts * 1e9))
        self.c_e0 = float(c_e0)
        self.names = prediction_joint_names(model.state_names)
        self._last: Optional[Tuple[int, np.ndarray]] = None   # (stamp, plan) published

    def commanded(self, stamp_ns: int, plan) -> None:
        """Take a command as published (stamp t_m, plan[j] acting from t_{m+j} + d)."""
        if self._last is None or stamp_ns > self._last[0]:
            self._last = (int(stamp_ns), np.asarray(plan, dtype=float))

    def acting(self, stamp_ns: int) -> float:
        """Return the damping acting at t_k = ``stamp_ns``, before its own command acts."""
        last = self._last
        if last is None or last[0] >= stamp_ns:
            return self.c_e0
        j = int(round((stamp_ns - last[0]) / self.ts_ns)) - 1
        return float(last[1][j]) if j < last[1].size else self.c_e0

    def sample(self, stamp_ns: int, x, plan, preview) -> Prediction:
        """Return sample t_k's prediction, then record its command (``plan``) as published."""
        out = self.predict(x, self.acting(stamp_ns), plan, preview)
        self.commanded(stamp_ns, plan)
        return out


def prediction_steps(horizon: int) -> Tuple[int, ...]:
    """Return the steps ahead a report compares: 1, 5 and N (those within the horizon)."""
    return tuple(sorted({h for h in (1, 5, horizon) if 1 <= h <= horizon}))


def prediction_errors(stamps_ns: Sequence[int], tables: Sequence[np.ndarray],
                      names: Sequence[str], ts_ns: int,
                      actual: Mapping[str, Tuple[np.ndarray, np.ndarray]],
                      steps: Optional[Sequence[int]] = None) -> Dict[int, Dict[str, Dict]]:
    """Return, per step h ahead, the error predicted − actual of each signal in ``actual``.

    ``tables[i]`` (rows j = 0..N, one column per name) was predicted at ``stamps_ns[i]``;
    ``actual[name]`` = (stamps ns, values) of what happened.  A prediction counts at h
    when a sample is stamped exactly t_k + h·Ts.  Per signal: ``rms``, ``max`` (of |e|)
    and ``samples`` (0: no match, rms and max NaN).
    """
    horizon = min((len(t) for t in tables), default=1) - 1
    steps = prediction_steps(horizon) if steps is None else tuple(steps)
    index = {name: {int(t): v for t, v in zip(*series)} for name, series in actual.items()}
    out: Dict[int, Dict[str, Dict]] = {}
    for h in steps:
        out[h] = {}
        for name, at in index.items():
            col = list(names).index(name)
            e = np.array([table[h, col] - at[t + h * ts_ns]
                          for t, table in zip(stamps_ns, tables)
                          if h < len(table) and t + h * ts_ns in at], dtype=float)
            out[h][name] = {'rms': float(np.sqrt(np.mean(e ** 2))) if e.size else math.nan,
                            'max': float(np.max(np.abs(e))) if e.size else math.nan,
                            'samples': int(e.size)}
    return out


__all__ = ['OUTPUT_NAMES', 'prediction_joint_names', 'Prediction', 'Predictor',
           'PlanPredictor', 'prediction_steps', 'prediction_errors']
