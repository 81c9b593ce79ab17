"""On-off skyhook (Karnopp) law adapted to the ERVA's generator damping.

Classic two-state skyhook for a semi-active damper: the damper should push the body
towards the "sky" (opposite its absolute velocity ż_s).  A damper between body and
wheel can only do so when the body velocity and the suspension velocity have the
same sign, ż_s·(ż_s − ż_us) > 0; then the damping is set high, otherwise low:

    u = u_max  if ż_s·(ż_s − ż_us) > 0,   else u_min.

The ERVA's generator is not directly between body and wheel (it damps the rotor
relative to the screw, v_gen = ż_d − (ż_s − ż_us)), so this is the standard law
applied unchanged to the device's damping input, as a semi-active baseline; it
needs no model and no preview (only the measured state).  Groundhook is not used.
"""

import numpy as np

from erva_ros.core.controllers.base import Controller


class SkyhookController(Controller):
    """Two-state skyhook: u_max when ż_s·(ż_s − ż_us) > 0, else u_min; plan holds it."""

    name = 'skyhook'

    def _compute(self, x, preview, t):
        body_vel, susp_vel = x[1], x[1] - x[3]
        u = self.u_max if body_vel * susp_vel > 0 else self.u_min
        return np.full(self.horizon, u), 0
