"""Nonlinear MPC of the ERVA damping (paper §III.A, eqs. (12)-(14)): the controller.

:class:`NMPCController` runs ``no_preview``, ``preview`` (the paper's NMPC, N intervals
of Ts) and ``preview_long`` (N intervals of Ts, then ``long_steps`` coarse intervals of
``long_step_s``, the command held over each).  Each sample it builds the parameters of
its OCP (:mod:`erva_ros.core.controllers.ocp`: the road, the weights, the command delay),
picks the starts and calls its solver:

``sqp``    the real-time SQP (:mod:`erva_ros.core.controllers.sqp`), one CasADi Function;
``ipopt``  the converged reference (:mod:`erva_ros.core.controllers.reference`).

Road: ``preview`` and ``preview_long`` use the preview w(t_k + j·Ts) (with ``use_preview``,
switchable live); ``no_preview`` (and the others with ``use_preview`` false) the measured
height w(t_k) held over the horizon (``road_prediction: hold``) or 0 (``zero``): the road
is an OCP parameter, one compiled solver for both.

Live settings (:meth:`NMPCController.retune`, erva_ros/core/controllers/tuning.py): the
weights α1, α2 (OCP parameters), the input box (a parameter of the solver), the preview
switch, the fallback and the time budget change between two solves without a rebuild.

Starts: the warm start (the previous plan shifted by one sample, its last value
repeated), a constant-c_e0 plan, and the warm start with its first move at u_max or
u_min; the SQP iterates the best of them by its value in the NLP.

Command delay (``command_delay_s`` = d > 0): modelled in the OCP (its prefix interval
holds the acting command over [t_k, t_k + d]), never predicted outside as for other laws
(:mod:`erva_ros.core.controllers.delay`).  d is an OCP parameter:
:attr:`NMPCController.command_delay_s` may change between solves without a rebuild.

Memory: x_a(k−1) of the paper cost is the previous sample's acceleration (with the
command actually applied, also after a fallback, :meth:`Controller.compute`).
"""

import math
from typing import Tuple

import numpy as np

from erva_ros.core.model.codegen import BufferedCall
from erva_ros.core.controllers.base import Controller, SolveFailure
from erva_ros.core.controllers.delay import check_delay
from erva_ros.core.controllers.ocp import (build_ocp, OCPSpec, passive_tail,
                                           stable_rollout_substep, U_SCALE)
from erva_ros.core.controllers.reference import IpoptReference, RecordedProblem, reference_gap
from erva_ros.core.controllers.settings import ControllerSettings
from erva_ros.core.controllers.sqp import build_rti
from erva_ros.core.model.quarter_car import QuarterCarModel
from erva_ros.core.model.params import ParamError

#: Other starts the real-time SQP compares with the warm start (NMPCController._alternatives).
N_ALTERNATIVES = 3


def nmpc_blocks(settings: ControllerSettings, name: str) -> Tuple[int, ...]:
    """Return the interval lengths (in samples) of controller ``name``."""
    blocks = (1,) * settings.horizon
    if name == 'preview_long':
        m = int(round(settings.long_step_s / settings.ts))
        blocks += (m,) * settings.long_steps
    return blocks


class NMPCController(Controller):
    """Paper NMPC (``no_preview``/``preview``) and the long-horizon ``preview_long``."""

    def __init__(self, model: QuarterCarModel, settings: ControllerSettings,
                 warm_start: bool = True):
        name = settings.controller
        if name not in ('no_preview', 'preview', 'preview_long'):
            raise ParamError(f'NMPCController cannot run controller {name!r}')
        self.name = name
        self.settings = settings
        self.model = model
        params = model.params
        self.warm_start = bool(warm_start)
        self.blocks = nmpc_blocks(settings, name)
        self.cost = settings.long_cost if name == 'preview_long' else settings.cost
        self.c_e0_param = min(max(params.c_e0, settings.u_min), settings.u_max)
        s = settings
        # The passive tail values what lies beyond the horizon in the continuous cost's
        # own terms; the paper cost's jerk-like sum has no such continuation.
        tail = (passive_tail(self.model, self.c_e0_param)
                if s.terminal_cost == 'passive' and self.cost == 'continuous' else None)
        self.ocp = build_ocp(self.model, OCPSpec(
            s.ts, self.blocks, self.cost, s.u_min, s.u_max,
            terminal_weight=s.terminal_weight if name == 'preview_long' else 0.0,
            degree=s.collocation_degree,
            rollout_substep_s=stable_rollout_substep(self.model, s.u_max),
            delayed=s.command_delay_s > 0, tail=tail))
        self._command_delay_s = s.command_delay_s
        if s.solver == 'ipopt':
            self._solver = IpoptReference(self.ocp, s.ipopt_max_iter, s.ipopt_starts)
        else:
            # Called through fixed buffers (erva_ros/core/model/codegen.py): no DM conversions.
            self._solver = BufferedCall(build_rti(self.ocp, s.iteration_cap(name), s.sqp_tol,
                                                  s.codegen, N_ALTERNATIVES, s.hessian))
        budget = math.inf if s.solver == 'ipopt' else s.time_budget_s
        super().__init__(self.ocp.horizon, s.ts, s.u_min, s.u_max, params.c_e0, budget)
        self._block_start = np.cumsum((0,) + self.blocks[:-1])
        self._sprung_accel = BufferedCall(self.model.sprung_accel)
        # Per-sample arrays filled in place (the solve itself takes well under a ms).
        self._p = self.ocp.with_box(self.ocp.params(np.zeros(self.ocp.horizon + 1),
                                                    (s.alpha1, s.alpha2), s.command_delay_s,
                                                    self.c_e0), s.u_min, s.u_max)
        self._u_alt = np.empty((len(self.blocks), N_ALTERNATIVES))
        self._u_alt[:, 0] = self.c_e0 / U_SCALE
        #: Set to a list to keep every real-time solve (:class:`RecordedProblem`), to be
        #: judged by :meth:`reference_gap`.
        self.recorded_problems = None

    @property
    def command_delay_s(self) -> float:
        """Return the delay d (s) from the sample to the command acting, modelled in the OCP."""
        return self._command_delay_s

    @command_delay_s.setter
    def command_delay_s(self, delay_s: float) -> None:
        # d is an OCP parameter: a new d takes effect at the next solve, no rebuild.
        delay_s = check_delay(delay_s, self.ts)
        if delay_s > 0 and not self.ocp.delayed:
            raise ValueError('command delay: this NMPC was built without one (its OCP has no '
                             'delay prefix); build it with command_delay_s > 0')
        self._command_delay_s = delay_s

    def predict_delay(self, model, delay_s: float) -> None:
        """Predict x(t_k + d) outside the OCP, for an NMPC built without a delay."""
        if self.ocp.delayed:
            raise ValueError('command delay: this NMPC models it in its OCP already '
                             '(command_delay_s); predicting it as well would apply it twice')
        super().predict_delay(model, delay_s)

    def retune(self, settings: ControllerSettings) -> None:
        """Take the live settings for the next solve: weights, box, preview, fallback, budget."""
        super().retune(settings)
        self.settings = settings
        self._p[self.ocp.n_p:] = settings.u_min / U_SCALE, settings.u_max / U_SCALE
        if settings.solver == 'sqp':
            self.time_budget_s = settings.time_budget_s

    # -- memory -------------------------------------------------------------------------
    def _reset_law(self) -> None:
        self._prev_sample = None     # (x, u, w) of the previous sample, for x_a(k-1)
        self._pending = None         # (x, w) of the sample being computed
        self._warm = None            # previous solution (plan, z) for the warm start

    def _on_fallback(self, plan: np.ndarray) -> None:
        # Remember what is really applied (for x_a(k-1)); the old solution no longer fits.
        pending, self._pending = self._pending, None
        self._prev_sample = None if pending is None else (pending[0], float(plan[0]),
                                                          pending[1])
        self._warm = None

    # -- one sample -----------------------------------------------------------------------
    def road_prediction(self, preview: np.ndarray) -> np.ndarray:
        """Return the road heights the OCP uses: the preview, or the held measurement."""
        if self.name != 'no_preview' and self.settings.use_preview:
            return preview
        if self.settings.road_prediction == 'hold':
            return np.full(preview.size, preview[0])
        out = np.zeros(preview.size)
        out[0] = preview[0]
        return out

    def _a_prev(self, x: np.ndarray, w0: float) -> float:
        """Return x_a(k−1): the previous sample's acceleration (at start: with c_e0)."""
        if self._prev_sample is None:
            return self._sprung_accel(x, self.c_e0, w0)[0]
        xp, up, wp = self._prev_sample
        return self._sprung_accel(xp, up, wp)[0]

    def _guess_plan(self) -> np.ndarray:
        """Return the warm-start plan: the previous one shifted by a sample, else c_e0."""
        if self.warm_start and self._warm is not None:
            prev = self._warm
            return np.append(prev[1:], prev[-1])
        return np.full(self.horizon, self.c_e0)

    def _alternatives(self, u_guess: np.ndarray) -> np.ndarray:
        """Return the solver's other starts (scaled, one per column).

        Constant c_e0, and the warm start with its first move at u_max / u_min: the
        first sample's jerk term reacts to u_0 at once, so its optimum often sits at
        a bound.
        """
        alt = self._u_alt
        alt[:, 1] = alt[:, 2] = u_guess
        alt[0, 1], alt[0, 2] = self.u_max / U_SCALE, self.u_min / U_SCALE
        return alt

    def _compute(self, x, preview, t):
        self._pending = (x.copy(), float(preview[0]))
        w = self.road_prediction(preview)
        a_prev = self._a_prev(x, float(preview[0]))
        p = self._p
        p[:w.size] = w
        p[w.size:w.size + 2] = self.settings.alpha1, self.settings.alpha2
        if self.ocp.delayed:
            p[self.ocp.n_p - 2:self.ocp.n_p] = self.command_delay_s, self._acting / U_SCALE
        u_guess = self._guess_plan()[self._block_start] / U_SCALE
        u_alt = self._alternatives(u_guess)
        try:
            u_blocks, z, cost, iterations = self._solver(x, a_prev, u_guess, u_alt, p)
        except RuntimeError as exc:   # evaluation error inside CasADi, or no IPOPT start
            self._warm = None
            raise SolveFailure(f'solver error: {str(exc).splitlines()[0]}') from None
        u_blocks, z = np.asarray(u_blocks).ravel(), np.asarray(z).ravel()
        cost, iterations = float(cost), int(iterations)
        if self.recorded_problems is not None and self.settings.solver == 'sqp':
            self.recorded_problems.append(RecordedProblem(x.copy(), a_prev, u_guess,
                                                          u_alt.copy(), p.copy(),
                                                          u_blocks.copy(), cost))
        if not (np.all(np.isfinite(u_blocks)) and math.isfinite(cost)):
            self._warm = None
            raise SolveFailure(f'{self.settings.solver}: non-finite solution')
        plan = np.repeat(np.clip(u_blocks * U_SCALE, self.u_min, self.u_max), self.blocks)
        self._warm = plan
        if self.ocp.delayed:
            # x_a(k−1) of the next solve: its previous node is this solve's first one,
            # t_k + d, where u_k starts acting.
            w_d = np.interp(self.command_delay_s, [0.0, self.ts], w[:2])
            self._prev_sample = (self.ocp.nodes(z)[0], float(plan[0]), float(w_d))
        else:
            self._prev_sample = (x.copy(), float(plan[0]), float(preview[0]))
        self._pending = None
        return plan, iterations

    def reference_gap(self, problem: RecordedProblem) -> float:
        """Return a recorded real-time solve's objective gap to IPOPT converged (≥ 0).

        ``problem`` is an entry of :attr:`recorded_problems`; see
        :func:`erva_ros.core.controllers.reference.reference_gap`.
        """
        return reference_gap(self.ocp, problem, self.settings.ipopt_max_iter,
                             self.settings.codegen)


__all__ = ['N_ALTERNATIVES', 'NMPCController', 'nmpc_blocks']
