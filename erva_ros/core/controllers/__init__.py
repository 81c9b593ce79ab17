"""Controllers of the ERVA damping (no ROS inside): passive, skyhook, the NMPC and the bound.

Use :func:`make_controller` with a name from :data:`CONTROLLER_NAMES`:

==============  ==========================================================================
passive         u = c_e0 (paper's passive ERVA)
skyhook         on-off (Karnopp) skyhook on ż_s·(ż_s − ż_us), see skyhook.py
no_preview      NMPC (paper §III.A), road predicted by holding the measured height
preview         NMPC with the road preview over the horizon (paper §IV.B)
preview_long    NMPC with a longer, non-uniform horizon and move blocking (beyond the paper)
excite          not a control law: a PRBS or chirp of c_e for identification (excite.py)
==============  ==========================================================================

The clairvoyant bound (one OCP over the whole run) is not a causal controller; see
:mod:`erva_ros.core.controllers.clairvoyant`.
"""

from typing import Optional

from erva_ros.core.controllers.base import ControlResult, Controller, SolveFailure, STATUSES
from erva_ros.core.controllers.excite import ExciteController
from erva_ros.core.controllers.nmpc import NMPCController
from erva_ros.core.controllers.passive import PassiveController
from erva_ros.core.controllers.settings import ControllerSettings, load_controller_settings
from erva_ros.core.controllers.skyhook import SkyhookController
from erva_ros.core.settings.controller import CONTROLLER_NAMES, EXCITATION_NAMES
from erva_ros.core.model.quarter_car import QuarterCarModel
from erva_ros.core.model.params import ParamError


def make_controller(name: Optional[str], model: QuarterCarModel,
                    settings: Optional[ControllerSettings] = None) -> Controller:
    """Build the controller ``name`` (default settings.controller) on ``model``.

    Its live settings (:meth:`Controller.retune`: the fallback...) are those of ``settings``.
    """
    settings = settings or ControllerSettings()
    ctrl = _build(name, model, settings)
    ctrl.fallback = settings.fallback
    return ctrl


def _build(name: Optional[str], model: QuarterCarModel, settings: ControllerSettings
           ) -> Controller:
    name = name or settings.controller
    if name not in CONTROLLER_NAMES + EXCITATION_NAMES:
        raise ParamError(f'unknown controller {name!r}; choose one of '
                         f'{", ".join(CONTROLLER_NAMES + EXCITATION_NAMES)}')
    common = dict(horizon=settings.horizon, ts=settings.ts, u_min=settings.u_min,
                  u_max=settings.u_max, c_e0=model.params.c_e0)
    # The command delay (settings.command_delay_s) is applied here, once per law.
    if name == 'passive':
        return PassiveController(**common)   # constant: nothing to compensate
    if name == 'excite':
        return ExciteController(**common, signal=settings.excite_signal,   # open loop
                                bit_s=settings.excite_bit_s, seed=settings.excite_seed,
                                f0_hz=settings.excite_f0_hz, f1_hz=settings.excite_f1_hz,
                                sweep_s=settings.excite_sweep_s)
    if name != 'skyhook':
        # models the delay in its OCP
        return NMPCController(model, settings.with_(controller=name))
    ctrl = SkyhookController(**common)
    if settings.command_delay_s > 0:         # predicted outside the law
        ctrl.predict_delay(model, settings.command_delay_s)
    return ctrl


__all__ = ['ControlResult', 'Controller', 'SolveFailure', 'STATUSES', 'CONTROLLER_NAMES',
           'EXCITATION_NAMES',
           'ControllerSettings', 'load_controller_settings', 'make_controller']
