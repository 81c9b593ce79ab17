"""Declare node parameters with descriptors built from their specs, defaults from config/.

One source of truth for every allowed value: each parameter has a spec of
:mod:`erva_ros.core.specs` (``Number``, ``Integer``, ``Choice``, ``Flag``, ``Text``) --
the physical parameters :data:`erva_ros.core.params.ERVA_SPECS`, the controller
settings :data:`erva_ros.core.controllers.settings.SPECS`, the HIL tables of
:mod:`erva_ros.core.hil.settings`, and the live-system parameters :data:`LIVE_SPECS`
below.  Every default comes from the shipped ``config/*.yaml`` (:data:`LIVE_DEFAULTS`
is ``config/live.yaml``'s ``/**`` section).  :func:`declare` declares one parameter
read-only with a ParameterDescriptor (description, FloatingPointRange or IntegerRange,
allowed values as additional_constraints), so ``ros2 param describe`` shows the range.

Values come from rclpy's own ``--ros-args --params-file F -p name:=value`` handling.
Before a parameter is declared its override is checked with the spec's ``check``, the
same the offline tools and the session file use, so a bad value stops the node with
one :class:`~erva_ros.core.params.ParamError` line naming the key, the value and the
range.  A whole number given for a floating-point parameter (``alpha2: 1``) is accepted.
"""

from typing import Any, Dict, Sequence

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor

from erva_ros.core.config import shipped_defaults
from erva_ros.core.controllers.settings import ControllerSettings, SPECS, validate_settings
from erva_ros.core.loop.validation import StampWindow
from erva_ros.core.model import MODEL_KINDS
from erva_ros.core.params import ERVA_SPECS, ERVAParams, validate_erva
from erva_ros.core.roads import ISO_CLASSES, ROAD_KINDS
from erva_ros.core.specs import Choice, Flag, Integer, Number, Text
from erva_ros.ros.realtime import MAX_PRIORITY

MODES = ('realtime', 'lockstep')

#: The live nodes' parameters: what each may be (defaults: config/live.yaml).
LIVE_SPECS: Dict[str, Any] = {
    'mode': Choice(MODES, 'time base: realtime (wall clock) or lockstep (the plant publishes '
                   '/clock)'),
    'model': Choice(MODEL_KINDS, 'model: erva (nonlinear, eq. (11)) or benchmark (linear, '
                    'eq. (15))'),
    'ts': SPECS['ts'],
    'duration_s': Number(0.0, 86400.0, 's', 'scenario length: the road ends and the plant '
                         'stops', lo_open=True),
    'road': Choice(ROAD_KINDS[:-1], 'road profile (a recorded one: set road_file)'),
    'road_file': Text('recorded road: CSV file of time (s), height (m) rows; overrides road'),
    'seed': Integer(0, 1_000_000_000, '-', 'seed of the road noise and the preview error'),
    'road_class': Choice(tuple(ISO_CLASSES), 'ISO 8608 road class'),
    'speed_mps': Number(0.0, 100.0, 'm/s', 'vehicle speed (time to distance)', lo_open=True),
    'bump_height_m': Number(-0.5, 0.5, 'm', 'bump road: height of the cosine bump'),
    'bump_length_m': Number(0.0, 100.0, 'm', 'bump road: length of the bump', lo_open=True),
    'bump_start_s': Number(0.0, 86400.0, 's', 'bump road: time the tyre reaches the bump'),
    'preview_steps': Integer(1, 10000, 'steps',
                             'preview intervals N (N + 1 points from t_k on)'),
    'preview_noise': Flag('preview error: add noise at preview_snr_db'),
    'preview_snr_db': Number(-40.0, 200.0, 'dB', 'preview error: SNR of the added noise'),
    'preview_delay_s': Number(0.0, 10.0, 's', 'preview error: age of the preview estimate'),
    'command_timeout_s': Number(0.0, 60.0, 's', 'plant: age after which a command\'s plan is '
                                'not used (passive)'),
    'lockstep_timeout_s': Number(0.01, 3600.0, 's',
                                 'lock-step: wall time the plant waits for a command'),
    'state_timeout_periods': Integer(1, 1000, 'periods', 'NMPC: passive command + ERROR after '
                                     'this many periods without a state'),
    'wait_for_subscribers': Integer(0, 100, '-',
                                    'time master: subscribers each of its topics needs first'),
    'wait_for_reader': Text('time master: one subscriber of each of its topics must be the '
                            'node of this name (\'\': any)'),
    'start_delay_s': Number(0.0, 600.0, 's',
                            'time master: settling time before the first sample'),
    'diagnostics_period_s': Number(0.05, 3600.0, 's', 'period of the /diagnostics status'),
    'reject_log_period_s': Number(0.0, 3600.0, 's',
                                  'rejected messages are logged once per period'),
    'max_stamp_lead_s': Number(0.0, 3600.0, 's',
                               'inputs stamped further ahead of the node\'s clock are rejected '
                               '(clock skew between hosts; at least Ts)'),
    'max_stamp_age_s': Number(0.0, 86400.0, 's',
                              'inputs stamped longer ago than this are rejected as stale',
                              lo_open=True),
    'publisher_history_s': Number(0.0, 3600.0, 's',
                                  'history each loop publisher keeps for reliable repair: a '
                                  'subscriber (the recorder) may stall this long losing '
                                  'nothing', lo_open=True),
    'realtime_priority': Integer(0, MAX_PRIORITY, '-',
                                 'realtime mode: SCHED_FIFO priority of the node\'s threads, '
                                 '0 = normal scheduling (needs CAP_SYS_NICE, else a warning)'),
}
#: Defaults of the live parameters: the "/**" section of the shipped config/live.yaml.
LIVE_DEFAULTS: Dict[str, Any] = {key: LIVE_SPECS[key].check(key, value, 'config/live.yaml')
                                 for key, value in shipped_defaults('live.yaml').items()}


def _override(node, name: str):
    # rclpy keeps the --params-file / -p values here until a parameter is declared;
    # reading them first lets a bad value fail with our one-line message.
    param = getattr(node, '_parameter_overrides', {}).get(name)
    return None if param is None else param.value


def descriptor(name: str, spec) -> ParameterDescriptor:
    """Return the read-only ParameterDescriptor of a spec (what ``ros2 param describe`` shows)."""
    desc = ParameterDescriptor(name=name, read_only=True)
    if isinstance(spec, Number):
        desc.description = f'{spec.doc} ({spec.unit})'
        desc.additional_constraints = spec.describe()
        if isinstance(spec, Integer):
            desc.integer_range = [IntegerRange(from_value=int(spec.lo), to_value=int(spec.hi),
                                               step=1)]
        else:
            desc.floating_point_range = [FloatingPointRange(
                from_value=float(spec.lo), to_value=float(spec.hi), step=0.0)]
    elif isinstance(spec, Choice):
        desc.description = spec.doc
        desc.additional_constraints = spec.describe()
    else:
        desc.description = spec.doc
    return desc


def declare(node, name: str, spec, default: Any) -> Any:
    """Declare parameter ``name`` (its override, else ``default``); return the checked value.

    The value is checked by ``spec`` and converted to its type before it is declared, so
    the override itself is not applied a second time.
    """
    value = _override(node, name)
    value = spec.check(name, default if value is None else value)
    return node.declare_parameter(name, value, descriptor(name, spec),
                                  ignore_override=True).value


def declare_all(node, specs: Dict[str, Any], defaults: Dict[str, Any],
                names: Sequence[str] = ()) -> Dict[str, Any]:
    """Declare ``names`` (default: every key of ``defaults``) with their specs; their values."""
    return {name: declare(node, name, specs[name], defaults[name])
            for name in (names or defaults)}


def declare_live(node, names: Sequence[str]) -> Dict[str, Any]:
    """Declare the live parameters ``names`` (LIVE_SPECS, LIVE_DEFAULTS); return their values."""
    return declare_all(node, LIVE_SPECS, LIVE_DEFAULTS, names)


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
    """Declare the physical parameters (ERVA_SPECS; defaults config/erva_paper.yaml)."""
    return validate_erva(declare_all(node, ERVA_SPECS, shipped_defaults('erva_paper.yaml')))


def settings_defaults() -> Dict[str, Any]:
    """Return the controller settings' defaults: nmpc_node of the shipped config/nmpc.yaml."""
    return validate_settings(shipped_defaults('nmpc.yaml', 'nmpc_node'),
                             'config/nmpc.yaml').as_dict()


def declare_controller_settings(node, skip: Sequence[str] = ()) -> ControllerSettings:
    """Declare the controller settings (SPECS; defaults config/nmpc.yaml); return them."""
    defaults = settings_defaults()
    return validate_settings(declare_all(node, SPECS, defaults,
                                         [k for k in defaults if k not in skip]))


__all__ = ['MODES', 'LIVE_SPECS', 'LIVE_DEFAULTS', 'descriptor', 'declare', 'declare_all',
           'declare_live', 'declare_erva_params', 'settings_defaults',
           'declare_controller_settings', 'loop_priority', 'stamp_window']
