"""Declare node parameters with descriptors and ranges built from the Spec tables.

One source of truth for every allowed value: the physical parameters use
:data:`erva_ros.core.params.ERVA_SPECS`, the controller settings the tables of
:mod:`erva_ros.core.controllers.settings`, and the live-system parameters
:data:`LIVE_NUMERIC` / :data:`LIVE_CHOICES` below.  Each parameter is declared
read-only with a ParameterDescriptor (description, FloatingPointRange or
IntegerRange, allowed values as additional_constraints), so ``ros2 param describe``
shows the range.

Values come from rclpy's own ``--ros-args --params-file F -p name:=value`` handling.
Before a parameter is declared its override is checked with the same
``check_number`` the offline tools use, so a bad value stops the node with one
:class:`~erva_ros.core.params.ParamError` line naming the key, the value and the range.
A whole number given for a floating-point parameter (``alpha2: 1``) is accepted.
"""

from typing import Any, Dict, Sequence

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor

from erva_ros.core.controllers.settings import (CHOICE_SPECS, ControllerSettings, DEFAULTS,
                                                INTEGER_KEYS, NUMERIC_SPECS, validate_settings)
from erva_ros.ros.realtime import DEFAULT_PRIORITY, MAX_PRIORITY
from erva_ros.core.loop.validation import StampWindow
from erva_ros.core.model import MODEL_KINDS
from erva_ros.core.params import (check_number, ERVA_SPECS, ERVAParams, PAPER_VALUES, ParamError,
                                  Spec, validate_erva)
from erva_ros.core.roads import ISO_CLASSES, ROAD_KINDS

MODES = ('realtime', 'lockstep')

#: Numeric parameters of the live nodes: allowed range, unit and meaning.
LIVE_NUMERIC: Dict[str, Spec] = {
    'ts': NUMERIC_SPECS['ts'],
    'duration_s': Spec(0.0, 86400.0, 's', 'scenario length: the road ends and the plant stops',
                       lo_open=True),
    'seed': Spec(0, 1_000_000_000, '-', 'seed of the road noise and the preview error'),
    'speed_mps': Spec(0.0, 100.0, 'm/s', 'vehicle speed (time to distance)', lo_open=True),
    'bump_height_m': Spec(-0.5, 0.5, 'm', 'bump road: height of the cosine bump'),
    'bump_length_m': Spec(0.0, 100.0, 'm', 'bump road: length of the bump', lo_open=True),
    'bump_start_s': Spec(0.0, 86400.0, 's', 'bump road: time the tyre reaches the bump'),
    'preview_steps': Spec(1, 10000, 'steps', 'preview intervals N (N + 1 points from t_k on)'),
    'preview_snr_db': Spec(-40.0, 200.0, 'dB', 'preview error: SNR of the added noise'),
    'preview_delay_s': Spec(0.0, 10.0, 's', 'preview error: age of the preview estimate'),
    'command_timeout_s': Spec(0.0, 60.0, 's',
                              'plant: age after which a command\'s plan is not used (passive)'),
    'lockstep_timeout_s': Spec(0.01, 3600.0, 's',
                               'lock-step: wall time the plant waits for a command'),
    'state_timeout_periods': Spec(1, 1000, 'periods',
                                  'NMPC: passive command + ERROR after this many periods '
                                  'without a state'),
    'wait_for_subscribers': Spec(0, 100, '-',
                                 'time master: subscribers each of its topics needs first'),
    'start_delay_s': Spec(0.0, 600.0, 's', 'time master: settling time before the first sample'),
    'diagnostics_period_s': Spec(0.05, 3600.0, 's', 'period of the /diagnostics status'),
    'reject_log_period_s': Spec(0.0, 3600.0, 's', 'rejected messages are logged once per period'),
    'max_stamp_lead_s': Spec(0.0, 3600.0, 's',
                             'inputs stamped further ahead of the node\'s clock are rejected '
                             '(clock skew between hosts; at least Ts)'),
    'max_stamp_age_s': Spec(0.0, 86400.0, 's',
                            'inputs stamped longer ago than this are rejected as stale',
                            lo_open=True),
    'publisher_history_s': Spec(0.0, 3600.0, 's',
                                'history each loop publisher keeps for reliable repair: a '
                                'subscriber (the recorder) may stall this long losing nothing',
                                lo_open=True),
    'realtime_priority': Spec(0, MAX_PRIORITY, '-',
                              'realtime mode: SCHED_FIFO priority of the node\'s threads, '
                              '0 = normal scheduling (needs CAP_SYS_NICE, else a warning)'),
}
#: Live parameters that are whole numbers.
LIVE_INTEGERS = frozenset({'seed', 'preview_steps', 'state_timeout_periods',
                           'wait_for_subscribers', 'realtime_priority'})
#: String parameters of the live nodes with a fixed set of values.
LIVE_CHOICES: Dict[str, tuple] = {
    'mode': (MODES, 'time base: realtime (wall clock) or lockstep (the plant publishes /clock)'),
    'model': (MODEL_KINDS, 'model: erva (nonlinear, eq. (11)) or benchmark (linear, eq. (15))'),
    'road': (ROAD_KINDS[:-1], 'road profile (a recorded one: set road_file)'),
    'road_class': (tuple(ISO_CLASSES), 'ISO 8608 road class'),
}
#: Defaults of the live parameters (config/live.yaml holds the same values).
LIVE_DEFAULTS: Dict[str, Any] = {
    'mode': 'realtime', 'model': 'erva', 'ts': 0.02, 'duration_s': 4.0,
    'road': 'paper', 'road_file': '', 'seed': 0, 'road_class': 'C', 'speed_mps': 20.0,
    'bump_height_m': 0.01, 'bump_length_m': 0.5, 'bump_start_s': 1.0,
    'preview_steps': 10, 'preview_noise': False, 'preview_snr_db': 20.0,
    'preview_delay_s': 0.0, 'command_timeout_s': 0.2, 'lockstep_timeout_s': 5.0,
    'state_timeout_periods': 3, 'wait_for_subscribers': 1, 'start_delay_s': 0.5,
    'diagnostics_period_s': 0.5, 'reject_log_period_s': 1.0, 'realtime_priority': DEFAULT_PRIORITY,
    'max_stamp_lead_s': 0.05, 'max_stamp_age_s': 1.0, 'publisher_history_s': 10.0,
}
#: Descriptions of the live parameters that are neither numbers nor choices.
LIVE_OTHER = {
    'road_file': 'recorded road: CSV file of time (s), height (m) rows; overrides road',
    'preview_noise': 'preview error: add noise at preview_snr_db',
}


def _override(node, name: str):
    # rclpy keeps the --params-file / -p values here until a parameter is declared;
    # reading them first lets a bad value fail with our one-line message.
    param = getattr(node, '_parameter_overrides', {}).get(name)
    return None if param is None else param.value


def _declare(node, name: str, value: Any, descriptor: ParameterDescriptor) -> Any:
    # ``value`` is the override (or default) already checked and converted to the
    # declared type, so the override itself is not applied a second time.
    descriptor.name = name
    descriptor.read_only = True
    return node.declare_parameter(name, value, descriptor, ignore_override=True).value


def declare_number(node, name: str, default: float, spec: Spec, integer: bool = False):
    """Declare a numeric parameter with a range descriptor; return its validated value."""
    value = _override(node, name)
    if value is None:
        value = default
    if integer:
        if isinstance(value, float) and value.is_integer():
            value = int(value)
        if isinstance(value, bool) or not isinstance(value, int):
            raise ParamError(f'parameter {name!r} must be an integer in {spec.describe()} '
                             f'({spec.doc}), got {type(value).__name__} {value!r}')
        check_number(name, value, spec)
        desc = ParameterDescriptor(
            description=f'{spec.doc} ({spec.unit})', additional_constraints=spec.describe(),
            integer_range=[IntegerRange(from_value=int(spec.lo), to_value=int(spec.hi),
                                        step=1)])
        return int(_declare(node, name, int(value), desc))
    value = check_number(name, value, spec)
    desc = ParameterDescriptor(
        description=f'{spec.doc} ({spec.unit})', additional_constraints=spec.describe(),
        floating_point_range=[FloatingPointRange(from_value=float(spec.lo),
                                                 to_value=float(spec.hi), step=0.0)])
    return float(_declare(node, name, float(value), desc))


def declare_choice(node, name: str, default: str, choices: Sequence[str], doc: str) -> str:
    """Declare a string parameter that must be one of ``choices``; return its value."""
    value = _override(node, name)
    if value is None:
        value = default
    if not isinstance(value, str) or value not in choices:
        raise ParamError(f'parameter {name!r} = {value!r} is not allowed; '
                         f'choose one of {", ".join(choices)} ({doc})')
    desc = ParameterDescriptor(description=doc,
                               additional_constraints=f'one of {", ".join(choices)}')
    return _declare(node, name, value, desc)


def declare_string(node, name: str, default: str, doc: str) -> str:
    """Declare a free string parameter; return its value."""
    value = _override(node, name)
    if value is None:
        value = default
    if not isinstance(value, str):
        raise ParamError(f'parameter {name!r} must be a string ({doc}), got {value!r}')
    return _declare(node, name, value, ParameterDescriptor(description=doc))


def declare_bool(node, name: str, default: bool, doc: str) -> bool:
    """Declare a boolean parameter; return its value."""
    value = _override(node, name)
    if value is None:
        value = default
    if not isinstance(value, bool):
        raise ParamError(f'parameter {name!r} must be true or false ({doc}), got {value!r}')
    return bool(_declare(node, name, value, ParameterDescriptor(description=doc)))


def declare_live(node, names: Sequence[str]) -> Dict[str, Any]:
    """Declare the live parameters ``names`` (tables above); return their values."""
    out: Dict[str, Any] = {}
    for name in names:
        default = LIVE_DEFAULTS[name]
        if name in LIVE_NUMERIC:
            out[name] = declare_number(node, name, default, LIVE_NUMERIC[name],
                                       integer=name in LIVE_INTEGERS)
        elif name in LIVE_CHOICES:
            choices, doc = LIVE_CHOICES[name]
            out[name] = declare_choice(node, name, default, choices, doc)
        elif isinstance(default, bool):
            out[name] = declare_bool(node, name, default, LIVE_OTHER[name])
        else:
            out[name] = declare_string(node, name, default, LIVE_OTHER[name])
    return out


def loop_priority(cfg: Dict[str, Any]) -> int:
    """Return the SCHED_FIFO priority a loop node asks for (live/realtime.py).

    ``realtime_priority`` in realtime mode; 0 in lock-step, which runs flat out and
    would starve the other processes at real-time priority.
    """
    return cfg['realtime_priority'] if cfg.get('mode', 'realtime') == 'realtime' else 0


def stamp_window(cfg: Dict[str, Any], ts: float, lockstep: bool = False) -> StampWindow:
    """Return the input stamp window of a node from its live parameters.

    In lock-step the node's clock is /clock, which may reach a node after the sample it
    stamps: two periods more lead are allowed there.
    """
    lead = cfg['max_stamp_lead_s'] + (2 * ts if lockstep else 0.0)
    return StampWindow(int(round(lead * 1e9)), int(round(cfg['max_stamp_age_s'] * 1e9)))


def declare_erva_params(node) -> ERVAParams:
    """Declare the physical parameters (paper Table I, ERVA_SPECS); return ERVAParams."""
    values = {key: declare_number(node, key, PAPER_VALUES[key], spec)
              for key, spec in ERVA_SPECS.items()}
    return validate_erva(values)


def declare_controller_settings(node, skip: Sequence[str] = ()) -> ControllerSettings:
    """Declare the controller settings (tables of controllers/settings.py); return them."""
    values: Dict[str, Any] = {}
    for key, default in DEFAULTS.items():
        if key in skip:
            continue
        if key in CHOICE_SPECS:
            choices, doc = CHOICE_SPECS[key]
            values[key] = declare_choice(node, key, default, choices, doc)
        else:
            values[key] = declare_number(node, key, default, NUMERIC_SPECS[key],
                                         integer=key in INTEGER_KEYS)
    return validate_settings(values)


__all__ = ['MODES', 'LIVE_NUMERIC', 'LIVE_INTEGERS', 'LIVE_CHOICES', 'LIVE_DEFAULTS',
           'LIVE_OTHER', 'declare_number', 'declare_choice', 'declare_string', 'declare_bool',
           'declare_live', 'declare_erva_params', 'declare_controller_settings',
           'stamp_window']
