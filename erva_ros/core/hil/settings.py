"""Parameters of the HIL nodes and the simulated ECU: ranges, defaults, ``config/hil.yaml``.

One table per user, the single source of allowed values for the ROS descriptors
(nodes) and for the offline loaders (``erva ecu-sim``, ``erva bench-hil``):

* ``ecu_bridge_node``: the bus, the DBC, timeouts, E2E tolerance and the generator
  hardware (:data:`erva_ros.core.hil.hardware.HARDWARE_SPECS`).  The simulated ECU reads
  the hardware keys from this section too, so bridge and ECU share one calibration.
* ``state_estimator_node``: the EKF's noise (:data:`erva_ros.core.estimator.NOISE_SPECS`)
  and its discretisation bound.
* ``ecu_sim``: the simulated ECU's latch step and sensor noise.

Sections are written ``/**/<node>`` so that they apply in any namespace (``-r
__ns:=/erva``): rcl reads a bare ``<node>`` key as the node in the root namespace.

The sample time ``ts`` and the model kind come from the ``/**`` section (as in an
``erva run`` session file), default 0.02 s and ``erva``.
"""

from typing import Any, Dict, Optional

from erva_ros.core.estimator import EstimatorNoise, NOISE_SPECS, validate_noise
from erva_ros.core.hil.hardware import (DEFAULTS as HW_DEFAULTS, GeneratorHardware,
                                        HARDWARE_SPECS, validate_hardware)
from erva_ros.core.params import check_number, ParamError, read_ros_params, Spec

BRIDGE_NODE = 'ecu_bridge_node'
ESTIMATOR_NODE = 'state_estimator_node'
ECU_SIM_SECTION = 'ecu_sim'

TS_SPEC = Spec(1e-3, 1.0, 's', 'command / ECU cycle period Ts (paper: 0.02)')

BRIDGE_NUMERIC: Dict[str, Spec] = {
    'command_timeout_periods': Spec(1, 1000, 'periods', 'no fresh damping command for this '
                                    'many periods -> safe passive command + ERROR'),
    'sensor_timeout_periods': Spec(1, 1000, 'periods', 'no valid ECU frame for this many '
                                   'periods -> ECU silent ERROR'),
    'bus_retry_s': Spec(0.01, 60.0, 's', 'time between attempts to re-open a lost CAN bus'),
    'max_delta_counter': Spec(1, 14, '-', 'largest alive-counter step accepted '
                              '(1: a frame after a lost frame is dropped)'),
    'diagnostics_period_s': Spec(0.05, 3600.0, 's', 'period of the /diagnostics status'),
}
BRIDGE_NUMERIC.update(HARDWARE_SPECS)
BRIDGE_DEFAULTS: Dict[str, Any] = {
    'bus': 'socketcan:can0', 'dbc_file': '', 'command_timeout_periods': 3,
    'sensor_timeout_periods': 3, 'bus_retry_s': 0.5, 'max_delta_counter': 1,
    'diagnostics_period_s': 0.5}
BRIDGE_DEFAULTS.update(HW_DEFAULTS)
BRIDGE_STRINGS = {
    'bus': 'CAN bus: socketcan:IFACE (vehicle), udp:LOCAL_PORT:PEER_PORT (loopback to '
           '`erva ecu-sim`) or virtual:NAME (in-process)',
    'dbc_file': 'DBC file of the ECU messages (empty: the shipped config/erva_ecu.dbc)',
}

ESTIMATOR_NUMERIC: Dict[str, Spec] = dict(NOISE_SPECS)
ESTIMATOR_NUMERIC.update({
    'u_max': Spec(1.0, 1e6, 'Ns/m', 'largest c_e the discrete model must stay stable at '
                  '(sets the RK4 sub-steps)'),
    'max_gap_periods': Spec(1, 10000, 'periods', 'a gap in the measurements longer than this '
                            'restarts the filter'),
    'diagnostics_period_s': Spec(0.05, 3600.0, 's', 'period of the /diagnostics status'),
})
ESTIMATOR_DEFAULTS: Dict[str, Any] = dict(EstimatorNoise().as_dict())
ESTIMATOR_DEFAULTS.update({'u_max': 22800.0, 'max_gap_periods': 50,
                           'diagnostics_period_s': 0.5})

ECU_SIM_NUMERIC: Dict[str, Spec] = {
    'latch_s': Spec(1e-4, 0.02, 's', 'command latch and plant step of the simulated ECU'),
    'noise_sprung_accel': Spec(0.0, 100.0, 'm/s^2', 'accelerometer noise std'),
    'noise_deflection': Spec(0.0, 1.0, 'm', 'deflection sensor noise std'),
    'noise_speed': Spec(0.0, 100.0, 'rad/s', 'generator speed noise std'),
    'noise_current': Spec(0.0, 100.0, 'A', 'generator current noise std'),
    'noise_voltage': Spec(0.0, 1000.0, 'V', 'back-emf noise std'),
    'seed': Spec(0, 2 ** 31 - 1, '-', 'seed of the sensor noise'),
}
ECU_SIM_DEFAULTS: Dict[str, Any] = {
    'latch_s': 0.001, 'noise_sprung_accel': 0.02, 'noise_deflection': 1e-4,
    'noise_speed': 0.01, 'noise_current': 0.01, 'noise_voltage': 0.05, 'seed': 0}

INTEGER_KEYS = frozenset({'command_timeout_periods', 'sensor_timeout_periods',
                          'max_delta_counter', 'max_gap_periods', 'seed'})


def default_hil_file() -> str:
    """Return the path of the shipped ``config/hil.yaml`` (source tree or installed share)."""
    from erva_ros.core.config import shipped_config
    return shipped_config('hil.yaml', 'pass --hil-config FILE')


def check_value(key: str, value: Any, spec: Spec, source: str = '') -> Any:
    """Return a validated number (an int for INTEGER_KEYS); one-line ParamError otherwise."""
    if key in INTEGER_KEYS:
        if isinstance(value, float) and value.is_integer():
            value = int(value)
        if isinstance(value, bool) or not isinstance(value, int):
            where = f'{source}: ' if source else ''
            raise ParamError(f'{where}parameter {key!r} must be an integer in '
                             f'{spec.describe()} ({spec.doc}), got {value!r}')
        return int(check_number(key, value, spec, source))
    return check_number(key, value, spec, source)


def _section(path: Optional[str], node: str) -> Dict[str, Any]:
    """Return the ``ros__parameters`` of ``node`` in a params file ({} if it has none).

    Sections are matched as rcl matches them for a node in any namespace: ``/**/node``
    (what config/hil.yaml uses, so ``-r __ns:=/erva`` still finds them), ``/node`` or
    ``node``; ``/**`` is not read (the HIL keys are per node).
    """
    return read_ros_params(path or default_hil_file(), node, wildcard=False, required=False)


def _validated(values: Dict[str, Any], specs: Dict[str, Spec], defaults: Dict[str, Any],
               source: str) -> Dict[str, Any]:
    out = {}
    for key, default in defaults.items():
        v = values.get(key, default)
        if key in specs:
            out[key] = check_value(key, v, specs[key], source)
        elif not isinstance(v, str):
            raise ParamError(f'{source}: parameter {key!r} must be a string, got {v!r}')
        else:
            out[key] = v
    return out


def load_bridge_section(path: Optional[str] = None) -> Dict[str, Any]:
    """Return the validated ``ecu_bridge_node`` values of a HIL params file."""
    src = path or default_hil_file()
    return _validated(_section(path, BRIDGE_NODE), BRIDGE_NUMERIC, BRIDGE_DEFAULTS, src)


def load_ecu_sim_section(path: Optional[str] = None) -> Dict[str, Any]:
    """Return the validated ``ecu_sim`` values of a HIL params file."""
    src = path or default_hil_file()
    return _validated(_section(path, ECU_SIM_SECTION), ECU_SIM_NUMERIC, ECU_SIM_DEFAULTS, src)


def load_estimator_section(path: Optional[str] = None) -> Dict[str, Any]:
    """Return the validated ``state_estimator_node`` values of a HIL params file."""
    src = path or default_hil_file()
    return _validated(_section(path, ESTIMATOR_NODE), ESTIMATOR_NUMERIC, ESTIMATOR_DEFAULTS,
                      src)


def hardware_of(values: Dict[str, Any], source: str = '') -> GeneratorHardware:
    """Return the GeneratorHardware of a bridge section."""
    return validate_hardware({k: values[k] for k in HARDWARE_SPECS}, source)


def noise_of(values: Dict[str, Any], source: str = '') -> EstimatorNoise:
    """Return the EstimatorNoise of an estimator section."""
    return validate_noise({k: values[k] for k in NOISE_SPECS}, source)
