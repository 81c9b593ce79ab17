"""The command delay d: the command computed at t_k acts from t_k + d on.

The paper's NMPC (§III.A) plans u_k for [t_k, t_k + Ts) from x(t_k).  On a vehicle, and in
`erva run --ecu virtual`, the command reaches the generator a delay d after the sample
t_k (sensors → CAN → bridge → estimator → solve → CAN → ECU: ≈ 8 ms of the 20 ms period),
and the previous command acts until then.  Planned for t_k, the first move is then
applied too late throughout.  A known d (setting ``command_delay_s``, checked by
:func:`check_delay`) is applied once, by :func:`erva_ros.core.controllers.make_controller`:

* the NMPC models it in its OCP (erva_ros/core/controllers/ocp.py: a prefix interval
  [t_k, t_k + d] with the acting command), d a parameter of every solve;
* every other law is handed the state and the preview predicted d ahead
  (:class:`DelayCompensation`, :meth:`Controller.predict_delay`), which:

1. predicts x(t_k + d) from x(t_k) with the shared model (paper eq. (11), RK4 in steps
   of at most 0.5 ms, the plant's), the command now acting held, and the road linear
   from w(t_k) to w(t_k + d) (interpolated in the preview);
2. shifts the preview by d: w(t_k + d + j·Ts) by linear interpolation between preview
   samples, the last one held;
3. plans from there, so u_k is optimised for [t_k + d, t_{k+1} + d), when it acts.

The offline closed loop reproduces such a delay with ``actuation_delay_s``
(erva_ros/core/studies/closed_loop.py; `erva sim --actuation-delay`), so the compensation is
measured there too.
"""

import math
from typing import Tuple

import numpy as np

from erva_ros.core.model.codegen import BufferedCall
from erva_ros.core.model.quarter_car import PLANT_SUBSTEP_S, QuarterCarModel


def check_delay(delay_s: float, ts: float, positive: bool = False) -> float:
    """Return ``delay_s`` as a float if it lies in [0, ts) (``positive``: (0, ts)), else raise.

    ValueError names the range: a command must act before the next sample's does.
    """
    low_ok = delay_s > 0.0 if positive else delay_s >= 0.0
    if not (low_ok and delay_s < ts):
        raise ValueError(f'command delay must be in {"(" if positive else "["}0, Ts = {ts:g} s), '
                         f'got {delay_s:g} s')
    return float(delay_s)


class DelayCompensation:
    """Predict the state and the road preview ``delay_s`` ahead (see module doc)."""

    def __init__(self, model: QuarterCarModel, ts: float, delay_s: float):
        self.ts = float(ts)
        self.delay_s = check_delay(delay_s, ts, positive=True)
        substeps = max(1, math.ceil(self.delay_s / PLANT_SUBSTEP_S - 1e-9))
        self._step = BufferedCall(model.rk4_step(self.delay_s, substeps))

    def __call__(self, x: np.ndarray, u_acting: float, preview: np.ndarray
                 ) -> Tuple[np.ndarray, np.ndarray]:
        """Return (x(t_k + d), preview shifted by d) for x(t_k) and w(t_k + j·Ts), j = 0..N."""
        preview = np.asarray(preview, dtype=float)
        grid = self.ts * np.arange(preview.size)
        shifted = np.interp(grid + self.delay_s, grid, preview)   # holds past the end
        return self._step(x, u_acting, preview[0], shifted[0])[0], shifted


__all__ = ['DelayCompensation', 'check_delay']
