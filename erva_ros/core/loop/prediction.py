"""What the controller's plan predicts: the states and outputs over the horizon.

For the command of sample t_k the NMPC publishes, beside it, the trajectory its plan
implies on the shared model (core/model.py): from the measured x(t_k), with the
command acting before t_k + d, then plan[j] from t_{k+j} + d, and the road the preview
gave.  :class:`Predictor` returns the states x(t_{k+j}) and the chassis acceleration
and harvested power at t_{k+j}, j = 0..N (the outputs with the damping acting at that
instant, as the plant publishes them): what a report compares with what then happened.

It integrates with the plant's own RK4 (``PLANT_SUBSTEP_S``), so for a converged solve
it equals the OCP's collocation trajectory to the integrators' accuracy; for a fallback
(the shifted plan) it is what that plan implies.  One CasADi call per sample.
"""

from dataclasses import dataclass
import math

import casadi as ca
import numpy as np

from erva_ros.core.model import PLANT_SUBSTEP_S


@dataclass(frozen=True)
class Prediction:
    """The plan's trajectory at t_{k+j}, j = 0..N: states, z̈_s (m/s²), power (W)."""

    states: np.ndarray          # (N + 1, nx)
    sprung_accel: np.ndarray    # (N + 1,)
    power: np.ndarray           # (N + 1,)


class Predictor:
    """Roll a plan out on the model over N periods Ts with the command delay d."""

    def __init__(self, model, ts: float, horizon: int, delay_s: float = 0.0):
        self.model, self.horizon = model, int(horizon)
        nx, n = model.nx, self.horizon
        x0, acting = ca.SX.sym('x0', nx), ca.SX.sym('acting')
        plan, w = ca.SX.sym('plan', n), ca.SX.sym('w', n + 1)
        pieces = [(d, model.rk4_step(d, max(1, math.ceil(d / PLANT_SUBSTEP_S - 1e-9))))
                  for d in ((delay_s, ts - delay_s) if delay_s > 0 else (ts,))]
        xs, accs, pows, x = [x0], [], [], x0
        for j in range(n + 1):
            before = acting if j == 0 else plan[j - 1]   # acting at t_{k+j}
            acc, pw = model.outputs(x, before if delay_s > 0 else plan[min(j, n - 1)], w[j])
            accs.append(acc)
            pows.append(pw)
            if j == n:
                break
            t = 0.0
            for (dt, step), u in zip(pieces, (before, plan[j]) if delay_s > 0 else (plan[j],)):
                wa = w[j] + (w[j + 1] - w[j]) * t / ts
                wb = w[j] + (w[j + 1] - w[j]) * (t + dt) / ts
                x = step(x, u, wa, wb)
                t += dt
            xs.append(x)
        self._fn = ca.Function('predict', [x0, acting, plan, w],
                               [ca.horzcat(*xs).T, ca.vertcat(*accs), ca.vertcat(*pows)])

    def __call__(self, x0, acting: float, plan, preview) -> Prediction:
        """Return the trajectory of ``plan`` (N values) from ``x0`` on ``preview`` (N + 1)."""
        n = self.horizon
        states, acc, pw = self._fn(np.asarray(x0, dtype=float), float(acting),
                                   np.asarray(plan, dtype=float)[:n],
                                   np.asarray(preview, dtype=float)[:n + 1])
        return Prediction(np.asarray(states), np.asarray(acc).ravel(), np.asarray(pw).ravel())


__all__ = ['Prediction', 'Predictor']
