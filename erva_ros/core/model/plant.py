"""Plant simulator core (no ROS): the ERVA or benchmark quarter car advanced one control period.

Used by the offline closed loop (``erva sim``), the plant-simulator node and the
simulated ECU, so every user integrates the same way:

* the damping command u_k is held over [t_k, t_k + Ts) (zero-order hold),
* the road moves linearly between its samples w(t_k) and w(t_k + Ts),
* RK4 with sub-steps of at most :data:`~erva_ros.core.model.quarter_car.PLANT_SUBSTEP_S` (0.5 ms),
* harvested energy is integrated exactly along (see ``QuarterCarModel.plant_step``);
* ``codegen`` as the NMPC's (core/model/codegen.py): the step compiled to C when a compiler
  is on PATH -- the same operations, so results agree to rounding.
"""

from dataclasses import dataclass
from functools import lru_cache
import math
from typing import Optional, Sequence

import casadi as ca
import numpy as np

from erva_ros.core.model.codegen import BufferedCall, compile_for
from erva_ros.core.model.quarter_car import PLANT_SUBSTEP_S, QuarterCarModel


@dataclass
class PlantSample:
    """Measured outputs at one sample time t_k (SI units)."""

    t: float                 # s
    x: np.ndarray            # state at t_k
    road_height: float       # m, w(t_k)
    damping_cmd: float       # Ns/m, u applied from t_k on
    sprung_accel: float      # m/s², z̈_s(t_k) with u_k applied (paper x_a = ẋ_2)
    power_w: float           # W, instantaneous harvested power at t_k
    harvested_j: float       # J, energy harvested since the start


@dataclass(frozen=True)
class ProfileStep:
    """One period integrated by :meth:`PlantSimulator.integrate_profile`, not yet applied."""

    x: np.ndarray            # state at the end of the period
    harvested_j: float       # J harvested over the period
    accel_sq_int: float      # ∫ z̈_s² dt over the period (m²/s³)


class PlantSimulator:
    """Integrates the quarter car by whole control periods with the command held."""

    def __init__(self, model: QuarterCarModel, ts: float = 0.02,
                 substep: float = PLANT_SUBSTEP_S, x0: Optional[np.ndarray] = None,
                 codegen: str = 'auto'):
        if not ts > 0:
            raise ValueError(f'sample time ts must be > 0, got {ts}')
        self.model = model
        self.params = model.params
        self.ts = float(ts)
        self.substep = float(substep)
        self.substeps = max(1, int(math.ceil(self.ts / substep - 1e-9)))
        self._step = self.model.plant_step(self.ts, self.substeps)
        # The same arithmetic in C: 2x faster than CasADi's VM; called through fixed
        # buffers (erva_ros/core/model/codegen.py BufferedCall): the DM conversions cost more.
        self._step, = compile_for(codegen, [self._step], 'the plant')
        self._step = BufferedCall(self._step)
        self._outputs = BufferedCall(self.model.outputs)
        #: (x, u) -> (position, v_gen, power): the model's generator outputs, for every
        #: publisher of the ``generator`` topic (QuarterCarModel.generator, buffered).
        self.generator = BufferedCall(self.model.generator)
        self._split = None   # (delay, the two partial steps) of step_delayed
        self._profile = None  # (pieces, compiled period) of integrate_profile
        self._codegen = codegen
        self.reset(x0)

    def reset(self, x0: Optional[np.ndarray] = None, t0: float = 0.0) -> None:
        self.x = self.model.zero_state() if x0 is None else np.array(x0, dtype=float)
        if self.x.shape != (self.model.nx,):
            raise ValueError(f'x0 must have {self.model.nx} states, got shape {self.x.shape}')
        self.t = float(t0)
        self.k = 0
        self.harvested_j = 0.0
        #: ∫ z̈_s² dt since reset (m²/s³): the continuous-time comfort measure.
        self.accel_sq_int = 0.0

    def acc_rms_continuous(self) -> float:
        """Return sqrt(∫ z̈_s² dt / T) over the periods taken since reset (0 before any)."""
        return math.sqrt(self.accel_sq_int / (self.k * self.ts)) if self.k else 0.0

    def sample(self, u: float, w: float) -> PlantSample:
        """Return the outputs now if command ``u`` is applied with road height ``w``."""
        acc, pw = self._outputs(self.x, u, w)
        return PlantSample(self.t, self.x.copy(), float(w), float(u), float(acc), float(pw),
                           self.harvested_j)

    def step(self, u: float, w0: float, w1: float) -> np.ndarray:
        """Advance one period Ts with u held and the road moving from w0 to w1."""
        xn, e, a2 = self._step(self.x, u, w0, w1)
        self.x = np.asarray(xn).ravel()
        self.harvested_j += float(e)
        self.accel_sq_int += a2
        self.k += 1
        self.t = self.k * self.ts
        return self.x

    def step_delayed(self, u_old: float, u_new: float, delay_s: float, w0: float,
                     w1: float) -> np.ndarray:
        """Advance one period Ts in which the new command acts only after ``delay_s``.

        u_old on [t, t + delay_s), u_new on [t + delay_s, t + Ts); the road linear from
        w0 to w1 throughout.  An actuator behind a delay, as the ECU in HIL mode.
        """
        if delay_s <= 0:
            return self.step(u_new, w0, w1)
        first, second = self._split_steps(float(delay_s))
        wd = w0 + (w1 - w0) * delay_s / self.ts
        xd, e1, a1 = first(self.x, u_old, w0, wd)
        xn, e2, a2 = second(xd, u_new, wd, w1)
        self.x = np.asarray(xn).ravel()
        self.harvested_j += e1 + e2
        self.accel_sq_int += a1 + a2
        self.k += 1
        self.t = self.k * self.ts
        return self.x

    def integrate_profile(self, us: Sequence[float], ws: Sequence[float]) -> ProfileStep:
        """Return one period Ts from the current state with a command profile; no step taken.

        us[j] is held on the j-th of ``len(us)`` equal sub-intervals and the road moves
        linearly from ws[j] to ws[j + 1] on it (``len(ws) == len(us) + 1``): an actuator
        that latches new commands at sub-interval boundaries, as the simulated ECU's.
        One compiled call for the whole period; :meth:`apply` takes the step, so a
        caller can integrate ahead and again when the profile changes.
        """
        n = len(us)
        if self._profile is None or self._profile[0] != n:
            if n < 1 or len(ws) != n + 1:
                raise ValueError(f'need len(ws) == len(us) + 1 >= 2, got {len(ws)} and {n}')
            fn = _profile_function(self.model, self.ts / n,
                                   max(1, math.ceil(self.ts / n / self.substep - 1e-9)), n)
            fn, = compile_for(self._codegen, [fn], 'the plant')
            self._profile = (n, BufferedCall(fn))
        x, e, a2 = self._profile[1](self.x, us, ws)
        return ProfileStep(x, e, a2)

    def apply(self, step: ProfileStep) -> np.ndarray:
        """Advance one period Ts to the end of an :meth:`integrate_profile` result."""
        self.x = np.array(step.x, dtype=float)
        self.harvested_j += step.harvested_j
        self.accel_sq_int += step.accel_sq_int
        self.k += 1
        self.t = self.k * self.ts
        return self.x

    def prepare_delay(self, delay_s: float) -> None:
        """Build (and call once) :meth:`step_delayed`'s pieces for ``delay_s`` now.

        A live plant must not pay their construction (~30 ms) in its first period: the
        commands of the samples behind it would all be late.
        """
        if delay_s > 0:
            for piece in self._split_steps(float(delay_s)):
                piece(self.x, 0.0, 0.0, 0.0)

    def _split_steps(self, delay_s: float):
        if not delay_s < self.ts:
            raise ValueError(f'actuation delay {delay_s:g} s must be below Ts = {self.ts:g} s')
        if self._split is None or self._split[0] != delay_s:
            steps = []
            for dt in (delay_s, self.ts - delay_s):
                n = max(1, math.ceil(dt / self.substep - 1e-9))
                steps.append(BufferedCall(self.model.plant_step(dt, n)))
            self._split = (delay_s, steps)
        return self._split[1]


@lru_cache(maxsize=16)
def _profile_function(model, dt: float, substeps: int, n: int) -> ca.Function:
    """(x, u[n], w[n+1]) -> (x⁺, E_h, ∫z̈_s²) over n pieces of ``dt``: a loop, not unrolled."""
    step = model.plant_step(dt, substeps)
    nx = model.nx
    z, uw = ca.SX.sym('z', nx + 2), ca.SX.sym('uw', 3)
    xn, e, a2 = step(z[:nx], uw[0], uw[1], uw[2])
    piece = ca.Function('piece', [z, uw], [ca.vertcat(xn, z[nx] + e, z[nx + 1] + a2)])
    loop = piece.mapaccum('pieces', n)
    x, u, w = ca.MX.sym('x', nx), ca.MX.sym('u', n), ca.MX.sym('w', n + 1)
    zs = loop(ca.vertcat(x, 0, 0), ca.vertcat(u.T, w[:n].T, w[1:].T))
    end = zs[:, n - 1]
    return ca.Function(f'plant_profile_{model.kind}_{n}', [x, u, w],
                       [end[:nx], end[nx], end[nx + 1]], ['x', 'u', 'w'],
                       ['xn', 'harvested_j', 'accel_sq_int'])
