"""Controller interface shared by the offline closed loop and the ROS 2 nmpc_node.

A controller maps the measured state x(t_k) and the road preview
w(t_k + k·Ts), k = 0..N, to the damping command u_k = c_e (Ns/m) applied from t_k
on (paper §III.A).  :meth:`Controller.compute` wraps the concrete law with the
safety net every controller shares:

* non-finite state or preview → the measurement is rejected (``nan_rejections``);
* the law raises, reports failure or returns NaN → fall back to the previous plan
  shifted by one step (``fallback_plan``), and when that plan is used up, to the
  passive damping c_e0 (``fallback_passive``);
  (``fallback: passive``: the passive damping at once, no previous plan);
* a valid solution that took longer than ``time_budget_s`` is still used (status
  ``late``, counted): it is the freshest answer there is -- the previous plan shifted
  was computed from an older state, and replacing a late answer by it did the damage
  under load, not the lateness.  Whether a newer state has arrived meanwhile is for the
  caller to know (the node); the plant's command hold then uses the plan's next point;
* the command is always clipped into the input box [u_min, u_max].

:meth:`Controller.retune` takes the live settings (erva_ros/core/controllers/tuning.py:
the box, the fallback; the NMPC's weights, preview switch and budget too) between two
samples, without a rebuild.
"""

from abc import ABC, abstractmethod
from dataclasses import dataclass, field
import math
import time
from typing import Dict, Optional

import numpy as np

from erva_ros.core.controllers.delay import DelayCompensation

#: Values of :attr:`ControlResult.status`.
STATUSES = ('ok', 'late', 'fallback_plan', 'fallback_passive')


@dataclass
class ControlResult:
    """One controller decision at sample time t_k."""

    damping_cmd: float          # Ns/m, u_k, always inside [u_min, u_max]
    plan: np.ndarray            # shape (N,): planned u_k .. u_{k+N-1}, plan[0] == damping_cmd
    status: str                 # one of STATUSES
    solve_time_s: float         # wall time spent in compute(), s
    iterations: int = 0         # solver iterations (0 for explicit laws)
    reason: str = ''            # why a fallback happened ('' when status == 'ok')
    predicted: Optional[dict] = field(default=None, repr=False)  # optional solver extras


class SolveFailure(RuntimeError):
    """The concrete law could not produce a usable command (caught by compute())."""


class Controller(ABC):
    """Base class: horizon N, sample time Ts, input box, fallbacks and their counters."""

    #: Short name used by make_controller, `erva sim --controller` and diagnostics.
    name = 'controller'
    #: After a failed solve: 'plan' (the previous plan shifted, then c_e0) or 'passive'.
    fallback = 'plan'

    def __init__(self, horizon: int, ts: float, u_min: float, u_max: float,
                 c_e0: float, time_budget_s: float = math.inf):
        if not 0 <= u_min < u_max:
            raise ValueError(f'need 0 <= u_min < u_max, got [{u_min}, {u_max}]')
        self.horizon = int(horizon)
        self.ts = float(ts)
        self.u_min = float(u_min)
        self.u_max = float(u_max)
        # The passive fallback must itself be admissible.
        self.c_e0 = float(min(max(c_e0, self.u_min), self.u_max))
        self.time_budget_s = float(time_budget_s)
        self._counters: Dict[str, int] = {}
        #: The command delay predicted outside the law (erva_ros/core/controllers/delay.py),
        #: or None.
        self.delay = None
        self.reset()

    def retune(self, settings) -> None:
        """Take the live settings of ``settings`` (ControllerSettings) for the next compute().

        The input box and the fallback; laws with more live settings extend this.  The
        settings are checked first (erva_ros/core/controllers/tuning.py ``retuned``): the
        box keeps the passive damping c_e0 inside.
        """
        self.u_min, self.u_max = float(settings.u_min), float(settings.u_max)
        self.fallback = settings.fallback

    def predict_delay(self, model, delay_s: float) -> None:
        """Plan from x(t_k + ``delay_s``) predicted with ``model``: the command acts that late."""
        self.delay = DelayCompensation(model, self.ts, delay_s)

    # -- the interface -----------------------------------------------------------------
    def reset(self) -> None:
        """Forget the previous plan and warm start and zero the counters."""
        self._prev_plan: Optional[np.ndarray] = None
        self._prev_age = 0
        self._acting = self.c_e0     # the last command returned: acting until the next
        self._counters = {'steps': 0, 'ok': 0, 'late': 0, 'fallback_plan': 0,
                          'fallback_passive': 0, 'failures': 0, 'nan_rejections': 0}
        self._reset_law()

    @property
    def counters(self) -> Dict[str, int]:
        """Return a copy of the step, status and failure counters."""
        return dict(self._counters)

    def compute(self, x: np.ndarray, preview: np.ndarray, t: float) -> ControlResult:
        """Return the damping command for state ``x`` (m, m/s) and road ``preview`` (m).

        ``preview`` holds w(t + k·Ts) for k = 0..N; laws without preview use preview[0].
        """
        t0 = time.perf_counter()
        self._counters['steps'] += 1
        x = np.asarray(x, dtype=float).ravel()
        preview = np.asarray(preview, dtype=float).ravel()
        iterations = 0
        reason = ''
        plan = None
        if preview.size < self.horizon + 1:
            raise ValueError(f'{self.name}: preview needs {self.horizon + 1} road heights, '
                             f'got {preview.size}')
        if not (np.all(np.isfinite(x)) and np.all(np.isfinite(preview[:self.horizon + 1]))):
            self._counters['nan_rejections'] += 1
            reason = 'non-finite state or preview'
        else:
            preview = preview[:self.horizon + 1]
            try:
                if self.delay is not None:
                    x, preview, t = self._compensate(x, preview, t)
                plan, iterations = self._compute(x, preview, float(t))
                plan = np.asarray(plan, dtype=float).ravel()
                if plan.shape != (self.horizon,) or not np.all(np.isfinite(plan)):
                    self._counters['nan_rejections'] += 1
                    reason = 'non-finite or malformed plan'
                    plan = None
            except SolveFailure as exc:
                self._counters['failures'] += 1
                reason = str(exc) or 'solver failure'
                plan = None
        elapsed = time.perf_counter() - t0
        if plan is not None:
            status = 'ok'
            if elapsed > self.time_budget_s:
                status = 'late'
                reason = (f'solve took {elapsed * 1e3:.2f} ms > budget '
                          f'{self.time_budget_s * 1e3:g} ms')
            plan = np.clip(plan, self.u_min, self.u_max)
            self._prev_plan, self._prev_age = plan, 0
        else:
            status, plan = self._fallback_plan()
            self._on_fallback(plan)
        self._counters[status] += 1
        self._acting = float(plan[0])
        return ControlResult(float(plan[0]), plan, status, time.perf_counter() - t0,
                             int(iterations), reason)

    def _compensate(self, x, preview, t):
        """Return (x, preview, t) moved to when the command acts; SolveFailure if not finite."""
        try:
            x, preview = self.delay(x, self._acting, preview)
        except RuntimeError as exc:   # evaluation error inside CasADi
            raise SolveFailure(f'delay compensation: {str(exc).splitlines()[0]}') from None
        if not np.all(np.isfinite(x)):
            raise SolveFailure('delay compensation: non-finite predicted state')
        return x, preview, t + self.delay.delay_s

    # -- for subclasses ----------------------------------------------------------------
    @abstractmethod
    def _compute(self, x: np.ndarray, preview: np.ndarray, t: float):
        """Return (plan of N commands in Ns/m, iterations); raise SolveFailure on failure."""

    def _reset_law(self) -> None:
        """Reset law-specific memory (warm starts); called by reset()."""

    def _on_fallback(self, plan: np.ndarray) -> None:
        """Let a law see the command actually applied after a fallback (e.g. warm start)."""

    def _fallback_plan(self):
        """Return (status, plan): the previous plan shifted one step, else passive c_e0."""
        prev = self._prev_plan
        if self.fallback == 'plan' and prev is not None and self._prev_age + 1 < prev.size:
            self._prev_age += 1
            rest = prev[self._prev_age:]
            plan = np.concatenate([rest, np.full(prev.size - rest.size, self.c_e0)])
            return 'fallback_plan', np.clip(plan, self.u_min, self.u_max)
        self._prev_plan = None
        return 'fallback_passive', np.full(self.horizon, self.c_e0)
