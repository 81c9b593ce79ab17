"""Passive ERVA: constant electrical damping u = c_e0 (paper §IV.A, Table I)."""

import numpy as np

from erva_ros.core.controllers.base import Controller


class PassiveController(Controller):
    """Hold u = c_e0 (clipped into the box); the paper's passive baseline."""

    name = 'passive'

    def _compute(self, x, preview, t):
        return np.full(self.horizon, self.c_e0), 0
