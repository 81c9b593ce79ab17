"""Validated controller settings, loaded from ``config/nmpc.yaml`` (a ROS 2 params file).

The file's ``nmpc_node: ros__parameters:`` section (merged over ``/**``, as
``--params-file`` does) configures every controller.  The tables below are the
single source of the allowed values: :func:`load_controller_settings` validates with
them and the ROS 2 ``nmpc_node`` builds its ParameterDescriptors from them.

Input box (not stated in the paper): u = c_e ∈ [0, 20] kNs/m by
default.  0 is the open circuit (duty cycle 0, R → ∞); 20 kNs/m = 2·c_e0 puts the
paper's passive damping in the middle of the box.  The NMPC's prediction model is
stable over the whole box: it is Radau IIA collocation (L-stable), see ocp.py.
"""

from dataclasses import asdict, dataclass, fields, replace
from typing import Any, Dict, Mapping, Optional, Tuple

from erva_ros.core.model.params import ParamError, read_ros_params, ROS_BUILTINS
from erva_ros.core.settings.erva import ERVA_SPECS
from erva_ros.core.settings.controller import (CHOICE_SPECS, CONTROLLER_NAMES, COST_KINDS,
                                               EXCITATION_NAMES, EXCITE_SIGNALS, FALLBACKS,
                                               FLAG_SPECS, INTEGER_KEYS, NODE_NAME, NUMERIC_SPECS,
                                               ROAD_PREDICTIONS, SOLVER_KINDS, SPECS)
from erva_ros.core.settings.files import shipped_config, shipped_defaults
from erva_ros.core.settings.specs import unknown_parameters


def _shipped_settings() -> Dict[str, Any]:
    """Return the shipped defaults: config/nmpc.yaml's nmpc_node, ts from config/live.yaml.

    ``ts`` is the loop's sample time, one value for every node (config/live.yaml ``/**``).
    """
    values = dict(shipped_defaults('nmpc.yaml', NODE_NAME))
    values['ts'] = shipped_defaults('live.yaml')['ts']
    return {k: SPECS[k].check(k, v, 'config/nmpc.yaml') for k, v in values.items()}


_SHIPPED = _shipped_settings()


@dataclass(frozen=True)
class ControllerSettings:
    """Controller configuration (SI units); defaults: config/nmpc.yaml as shipped (and ts)."""

    controller: str = _SHIPPED['controller']
    horizon: int = _SHIPPED['horizon']
    ts: float = _SHIPPED['ts']
    alpha1: float = _SHIPPED['alpha1']
    alpha2: float = _SHIPPED['alpha2']
    u_min: float = _SHIPPED['u_min']
    u_max: float = _SHIPPED['u_max']
    cost: str = _SHIPPED['cost']
    solver: str = _SHIPPED['solver']
    max_iter: int = _SHIPPED['max_iter']
    sqp_tol: float = _SHIPPED['sqp_tol']
    hessian: str = _SHIPPED['hessian']
    terminal_cost: str = _SHIPPED['terminal_cost']
    ipopt_max_iter: int = _SHIPPED['ipopt_max_iter']
    ipopt_starts: int = _SHIPPED['ipopt_starts']
    time_budget_s: float = _SHIPPED['time_budget_s']
    # Offline the paper's ideal loop (the command acts at its sample); the live loop's d
    # is config/live.yaml's, one value for the OCP, the plant and the ECU.
    command_delay_s: float = 0.0
    collocation_degree: int = _SHIPPED['collocation_degree']
    road_prediction: str = _SHIPPED['road_prediction']
    use_preview: bool = _SHIPPED['use_preview']
    fallback: str = _SHIPPED['fallback']
    long_steps: int = _SHIPPED['long_steps']
    long_step_s: float = _SHIPPED['long_step_s']
    long_max_iter: int = _SHIPPED['long_max_iter']
    terminal_weight: float = _SHIPPED['terminal_weight']
    long_cost: str = _SHIPPED['long_cost']
    codegen: str = _SHIPPED['codegen']
    excite_signal: str = _SHIPPED['excite_signal']
    excite_bit_s: float = _SHIPPED['excite_bit_s']
    excite_seed: int = _SHIPPED['excite_seed']
    excite_f0_hz: float = _SHIPPED['excite_f0_hz']
    excite_f1_hz: float = _SHIPPED['excite_f1_hz']
    excite_sweep_s: float = _SHIPPED['excite_sweep_s']

    @property
    def weights(self) -> Tuple[float, float]:
        """Return (alpha1, alpha2)."""
        return (self.alpha1, self.alpha2)

    def iteration_cap(self, controller: str) -> int:
        """Return the real-time SQP's most iterations per sample for ``controller``."""
        return self.long_max_iter if controller == 'preview_long' else self.max_iter

    def with_(self, **kw: Any) -> 'ControllerSettings':
        """Return a validated copy with some values replaced."""
        return validate_settings(dict(asdict(self), **kw), source='override')

    def as_dict(self) -> Dict[str, Any]:
        """Return the settings as a plain dict (ROS parameter names)."""
        return asdict(self)


#: Default value of every setting (for ROS declare_parameter).
DEFAULTS: Dict[str, Any] = asdict(ControllerSettings())


def describe(key: str) -> str:
    """Return the allowed values of ``key`` as text (for --help and descriptors)."""
    return SPECS[key].allowed()


def _check(key: str, value: Any, source: str) -> Any:
    if key == 'codegen' and isinstance(value, bool):
        value = 'on' if value else 'off'   # YAML 1.1 reads a bare on/off as a boolean
    return SPECS[key].check(key, value, source)


def validate_settings(values: Mapping[str, Any], source: str = '') -> ControllerSettings:
    """Validate a mapping of settings (missing keys take defaults); raise ParamError."""
    where = f'{source}: ' if source else ''
    known = {f.name for f in fields(ControllerSettings)}
    # Physical parameters and ROS's own may share the file; anything else is a typo.
    unknown = set(values) - known - set(ERVA_SPECS) - set(ROS_BUILTINS)
    if unknown:
        raise unknown_parameters(unknown, known, source)
    out: Dict[str, Any] = {key: _check(key, value, source)
                           for key, value in values.items() if key in known}
    s = replace(ControllerSettings(), **out)
    if not s.u_min < s.u_max:
        raise ParamError(f'{where}parameter \'u_max\' = {s.u_max:g} must exceed '
                         f'u_min = {s.u_min:g} Ns/m')
    if not s.command_delay_s < s.ts:
        raise ParamError(f'{where}parameter \'command_delay_s\' = {s.command_delay_s:g} must '
                         f'be below ts = {s.ts:g} s')
    ratio = s.long_step_s / s.ts
    if s.long_steps and abs(ratio - round(ratio)) > 1e-6:
        raise ParamError(f'{where}parameter \'long_step_s\' = {s.long_step_s:g} must be a whole '
                         f'multiple of ts = {s.ts:g} s')
    ratio = s.excite_bit_s / s.ts
    if abs(ratio - round(ratio)) > 1e-6:
        raise ParamError(f'{where}parameter \'excite_bit_s\' = {s.excite_bit_s:g} must be a '
                         f'whole multiple of ts = {s.ts:g} s')
    if not s.excite_f0_hz < s.excite_f1_hz < 0.5 / s.ts:
        raise ParamError(f'{where}parameters \'excite_f0_hz\' = {s.excite_f0_hz:g} and '
                         f'\'excite_f1_hz\' = {s.excite_f1_hz:g} must satisfy f0 < f1 < '
                         f'1 / (2 ts) = {0.5 / s.ts:g} Hz')
    if s.alpha1 == 0 and s.alpha2 == 0 and s.controller in ('no_preview', 'preview',
                                                            'preview_long'):
        raise ParamError(f'{where}parameters \'alpha1\' and \'alpha2\' are both 0; '
                         'the NMPC needs a nonzero weight')
    return s


def default_settings_file() -> str:
    """Return the path of the shipped config/nmpc.yaml (source tree or installed share)."""
    return shipped_config('nmpc.yaml', 'pass a settings file')


def with_linked_iteration_cap(overrides: Dict[str, Any]) -> Dict[str, Any]:
    """Return ``overrides`` where a given ``max_iter`` also sets ``long_max_iter``.

    One rule for every command line: ``--max-iter`` caps each NMPC, preview_long too.
    """
    k = overrides.get('max_iter')
    return overrides if k is None else dict(overrides, long_max_iter=k)


def load_controller_settings(path: Optional[str] = None,
                             overrides: Optional[Mapping[str, Any]] = None
                             ) -> ControllerSettings:
    """Load ``nmpc_node`` settings from ``path`` (default config/nmpc.yaml), then overrides.

    ``overrides`` (e.g. from command-line options) win over the file; ``None`` values in
    it are ignored.  Raises :class:`~erva_ros.core.model.params.ParamError` with one line.
    """
    path = path or default_settings_file()
    values = dict(read_ros_params(path, NODE_NAME))
    # ts is the loop's (config/live.yaml): an older settings file may still name it.
    s = validate_settings(values, source=path)
    if overrides:
        extra = {k: v for k, v in overrides.items() if v is not None}
        s = validate_settings(dict(asdict(s), **extra), source='override')
    return s


__all__ = ['CONTROLLER_NAMES', 'EXCITATION_NAMES', 'EXCITE_SIGNALS', 'COST_KINDS',
           'SOLVER_KINDS', 'ROAD_PREDICTIONS', 'FALLBACKS', 'NODE_NAME',
           'NUMERIC_SPECS', 'INTEGER_KEYS', 'CHOICE_SPECS', 'FLAG_SPECS', 'SPECS', 'DEFAULTS',
           'ControllerSettings',
           'describe', 'validate_settings', 'load_controller_settings',
           'with_linked_iteration_cap',
           'default_settings_file']
