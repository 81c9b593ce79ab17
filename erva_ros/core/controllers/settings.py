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

from erva_ros.core.model.params import ERVA_SPECS, ParamError, read_ros_params, ROS_BUILTINS
from erva_ros.core.settings.schemas import COMMAND_DELAY_SPEC, TS_SPEC
from erva_ros.core.settings.specs import Choice, Flag, Integer, Number, unknown_parameters

#: Control laws understood by make_controller (and `erva sim --controller`).
CONTROLLER_NAMES = ('passive', 'skyhook', 'no_preview', 'preview', 'preview_long')
#: Signals that make_controller also builds, for identification: they ignore the state
#: (erva_ros/core/controllers/excite.py), so the studies of control laws leave them out.
EXCITATION_NAMES = ('excite',)
#: Excitation signals of the ``excite`` controller.
EXCITE_SIGNALS = ('prbs', 'chirp')
#: Stage-cost variants of the NMPC (see erva_ros.core.controllers.ocp).
COST_KINDS = ('paper', 'continuous')
#: NMPC solvers: 'sqp' = real-time SQP (one CasADi Function), 'ipopt' = converged reference.
SOLVER_KINDS = ('sqp', 'ipopt')
#: Terminal costs of the continuous NMPC cost (erva_ros/core/controllers/ocp.py passive_tail).
TERMINAL_COSTS = ('passive', 'none')
#: Reduced Hessians of the real-time SQP (erva_ros/core/controllers/sqp.py).
HESSIANS = ('exact', 'gauss_newton')
#: codegen: auto = compile when a C compiler is on PATH (else run the CasADi VM).
CODEGEN_MODES = ('auto', 'on', 'off')
#: How the no-preview NMPC predicts the road: hold the last measured height, or zero.
ROAD_PREDICTIONS = ('hold', 'zero')
#: What follows a failed solve: the previous plan shifted while it lasts, then passive
#: c_e0 (plan), or passive c_e0 at once (passive).  erva_ros/core/controllers/base.py.
FALLBACKS = ('plan', 'passive')

#: Node name whose section of the params file holds the controller settings.
NODE_NAME = 'nmpc_node'

#: Numeric settings: allowed range, unit and meaning (reused for ROS descriptors).
NUMERIC_SPECS: Dict[str, Number] = {
    'horizon': Integer(1, 200, 'steps', 'prediction horizon N (paper: 10)'),
    'ts': TS_SPEC,
    'alpha1': Number(0.0, 1e6, '-', 'comfort weight alpha1 on chassis acceleration (eq. (12))',
                     live=True),
    'alpha2': Number(0.0, 1e6, '-', 'energy weight alpha2 on harvested power (eq. (12))',
                     live=True),
    'u_min': Number(0.0, 1e6, 'Ns/m', 'lower bound of the electrical damping c_e', live=True),
    'u_max': Number(0.0, 1e6, 'Ns/m', 'upper bound of the electrical damping c_e', lo_open=True,
                    live=True),
    'max_iter': Integer(1, 50, 'iterations', 'real-time SQP: most iterations per sample'),
    'sqp_tol': Number(0.0, 1.0, '-', 'real-time SQP: stop when an iteration is predicted to '
                      'gain less than this share of the objective', lo_open=False),
    'ipopt_max_iter': Integer(1, 100000, 'iterations', 'IPOPT iteration limit (reference)'),
    'ipopt_starts': Integer(1, 4, 'starts', 'IPOPT reference: converge from the warm start, '
                            '+ constant c_e0, + first move at u_max, + at u_min; keep the best'),
    'time_budget_s': Number(0.0, 10.0, 's', 'real-time SQP: a solve slower than this is '
                            'counted late (its plan is still used)', live=True),
    'command_delay_s': COMMAND_DELAY_SPEC,
    'collocation_degree': Integer(1, 6, '-', 'Radau collocation points per interval (model)'),
    'long_steps': Integer(0, 200, 'steps', 'preview_long: coarse intervals after the first N'),
    'long_step_s': Number(1e-3, 1.0, 's', 'preview_long: length of a coarse interval'),
    'long_max_iter': Integer(1, 50, 'iterations', 'preview_long: real-time SQP: most '
                             'iterations per sample (an iteration costs 3-4x preview\'s)'),
    'terminal_weight': Number(0.0, 1e6, '-', 'preview_long: weight of the terminal energy cost'),
    'excite_bit_s': Number(1e-3, 10.0, 's', 'excite, prbs: length of one bit (a multiple of '
                           'ts); flat spectrum to about 0.44 / excite_bit_s Hz'),
    'excite_seed': Integer(0, 2 ** 31 - 1, '-', 'excite, prbs: start of the sequence'),
    'excite_f0_hz': Number(0.0, 1e3, 'Hz', 'excite, chirp: start frequency', lo_open=True),
    'excite_f1_hz': Number(0.0, 1e3, 'Hz', 'excite, chirp: end frequency (< 1 / (2 ts))',
                           lo_open=True),
    'excite_sweep_s': Number(0.0, 3600.0, 's', 'excite, chirp: duration of one sweep '
                             '(repeated)', lo_open=True),
}
#: Settings that must be whole numbers.
INTEGER_KEYS = frozenset(k for k, spec in NUMERIC_SPECS.items() if isinstance(spec, Integer))
#: String settings and their allowed values.
CHOICE_SPECS: Dict[str, Choice] = {
    'controller': Choice(CONTROLLER_NAMES + EXCITATION_NAMES,
                         'control law, or excite (an identification signal)'),
    'excite_signal': Choice(EXCITE_SIGNALS, 'excite: the signal driving c_e over '
                            '[u_min, u_max]: prbs (pseudo-random binary) or chirp '
                            '(logarithmic sweep)'),
    'cost': Choice(COST_KINDS,
                   'NMPC stage cost: paper (discrete, eq. (14)) or continuous (eq. (12))'),
    'solver': Choice(SOLVER_KINDS,
                     'NMPC solver: sqp (real-time SQP) or ipopt (converged reference)'),
    'road_prediction': Choice(ROAD_PREDICTIONS,
                              'no_preview road model: hold last height or zero', live=True),
    'fallback': Choice(FALLBACKS, 'after a failed solve: the previous plan shifted while it '
                       'lasts, then the passive c_e0 (plan), or c_e0 at once (passive)',
                       live=True),
    'long_cost': Choice(COST_KINDS, 'stage cost of preview_long (paper or continuous)'),
    'terminal_cost': Choice(TERMINAL_COSTS, 'continuous cost: value of the state at the '
                            'horizon end as if the passive damping took over (passive) or '
                            'none (the paper\'s NMPC)'),
    'hessian': Choice(HESSIANS, 'real-time SQP Hessian: exact (Lagrangian) or gauss_newton '
                                '(comfort Gauss-Newton + exact economic term)'),
    'codegen': Choice(CODEGEN_MODES, 'compile the real-time solver\'s model functions to C '
                                     '(auto: when cc/gcc is on PATH; cached in '
                                     '~/.cache/erva_ros)'),
}
#: On/off settings.
FLAG_SPECS: Dict[str, Flag] = {
    'use_preview': Flag('NMPC preview and preview_long: plan on the road preview (false: the '
                        'road predicted as road_prediction says, as no_preview does)',
                        live=True),
}
#: Every setting's spec (erva_ros.core.settings.specs): the one table of allowed values.
SPECS: Dict[str, Any] = {**NUMERIC_SPECS, **CHOICE_SPECS, **FLAG_SPECS}


def _shipped_settings() -> Dict[str, Any]:
    """Return the shipped defaults: config/nmpc.yaml's nmpc_node, ts from config/live.yaml.

    ``ts`` is the loop's sample time, one value for every node (config/live.yaml ``/**``).
    """
    from erva_ros.core.settings.files import shipped_defaults
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
    from erva_ros.core.settings.files import shipped_config
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
