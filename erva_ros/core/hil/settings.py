"""Parameters of the HIL nodes and the simulated ECU: defaults and sections of ``config/hil.yaml``.

The tables of allowed values are core/settings/hil.py's, one per user, for the ROS
descriptors (nodes) and for the offline loaders here (``erva ecu-sim``, ``erva bench-hil``):

* ``ecu_bridge_node``: the bus, the DBC, timeouts, E2E tolerance and the generator
  hardware (:data:`erva_ros.core.settings.hil.HARDWARE_SPECS`).  The simulated ECU reads
  the hardware keys from this section too, so bridge and ECU share one calibration.
* ``state_estimator_node``: the EKF's noise (:data:`erva_ros.core.settings.hil.NOISE_SPECS`)
  and its discretisation bound.
* ``ecu_sim``: the simulated ECU's latch step and sensor noise.

Sections are written ``/**/<node>`` so that they apply in any namespace (``-r
__ns:=/erva``): rcl reads a bare ``<node>`` key as the node in the root namespace.

The sample time ``ts`` and the model kind come from the ``/**`` section (as in an
``erva run`` session file), default 0.02 s and ``erva``.
"""

from typing import Any, Dict, Optional

from erva_ros.core.model.hardware import GeneratorHardware, validate_hardware
from erva_ros.core.model.estimator import EstimatorNoise, validate_noise
from erva_ros.core.model.params import read_ros_params, ROS_BUILTINS
from erva_ros.core.settings.files import shipped_checked, shipped_config
from erva_ros.core.settings.hil import (BRIDGE_NODE, BRIDGE_SPECS, COMMAND_LINE_DEFAULTS,
                                        ECU_SIM_SECTION, ECU_SIM_SPECS, ESTIMATOR_NODE,
                                        ESTIMATOR_SPECS, HARDWARE_SPECS, NOISE_SPECS)
from erva_ros.core.settings.schemas import SCHEMAS
from erva_ros.core.settings.specs import check_all, unknown_parameters


def _shipped(node: str, specs: Dict[str, Any]) -> Dict[str, Any]:
    """Return the defaults of ``node``: its section of the shipped config/hil.yaml."""
    return shipped_checked(specs, 'hil.yaml', node)


#: Defaults: the shipped config/hil.yaml (and the bus and CAN trace, above).
BRIDGE_DEFAULTS: Dict[str, Any] = {'bus': COMMAND_LINE_DEFAULTS['bus'],
                                   'can_log': COMMAND_LINE_DEFAULTS['can_log'],
                                   **_shipped(BRIDGE_NODE, BRIDGE_SPECS)}
ESTIMATOR_DEFAULTS: Dict[str, Any] = _shipped(ESTIMATOR_NODE, ESTIMATOR_SPECS)
ECU_SIM_DEFAULTS: Dict[str, Any] = _shipped(ECU_SIM_SECTION, ECU_SIM_SPECS)


def default_hil_file() -> str:
    """Return the path of the shipped ``config/hil.yaml`` (source tree or installed share)."""
    return shipped_config('hil.yaml', 'pass --hil-config FILE')


def _section(path: Optional[str], node: str) -> Dict[str, Any]:
    """Return the ``ros__parameters`` of ``node`` in a params file ({} if it has none).

    Sections are matched as rcl matches them for a node in any namespace: ``/**/node``
    (what config/hil.yaml uses, so ``-r __ns:=/erva`` still finds them), ``/node`` or
    ``node``; ``/**`` is not read (the HIL keys are per node).
    """
    return read_ros_params(path or default_hil_file(), node, wildcard=False, required=False)


def _validated(values: Dict[str, Any], specs: Dict[str, Any], defaults: Dict[str, Any],
               source: str, node: str) -> Dict[str, Any]:
    """Return the section's values of ``specs`` checked; another key is a one-line error.

    Other keys ``node`` declares (its schema: the physical parameters, the live loop's)
    and ROS's own may be there; anything else is a typo, which was ignored before (the
    value kept its default): the error names the closest known key.
    """
    schema = SCHEMAS.get(node)
    known = {*specs, *ROS_BUILTINS, *(schema.specs() if schema else ())}
    unknown = set(values) - known
    if unknown:
        raise unknown_parameters(unknown, known - set(ROS_BUILTINS), source)
    return check_all(specs, {k: v for k, v in values.items() if k in specs}, source, defaults)


def load_bridge_section(path: Optional[str] = None) -> Dict[str, Any]:
    """Return the validated ``ecu_bridge_node`` values of a HIL params file."""
    src = path or default_hil_file()
    return _validated(_section(path, BRIDGE_NODE), BRIDGE_SPECS, BRIDGE_DEFAULTS, src,
                      BRIDGE_NODE)


def load_ecu_sim_section(path: Optional[str] = None) -> Dict[str, Any]:
    """Return the validated ``ecu_sim`` values of a HIL params file."""
    src = path or default_hil_file()
    return _validated(_section(path, ECU_SIM_SECTION), ECU_SIM_SPECS, ECU_SIM_DEFAULTS, src,
                      ECU_SIM_SECTION)


def load_estimator_section(path: Optional[str] = None) -> Dict[str, Any]:
    """Return the validated ``state_estimator_node`` values of a HIL params file."""
    src = path or default_hil_file()
    return _validated(_section(path, ESTIMATOR_NODE), ESTIMATOR_SPECS, ESTIMATOR_DEFAULTS,
                      src, ESTIMATOR_NODE)


def hardware_of(values: Dict[str, Any], source: str = '') -> GeneratorHardware:
    """Return the GeneratorHardware of a bridge section."""
    return validate_hardware({k: values[k] for k in HARDWARE_SPECS}, source)


def noise_of(values: Dict[str, Any], source: str = '') -> EstimatorNoise:
    """Return the EstimatorNoise of an estimator section."""
    return validate_noise({k: values[k] for k in NOISE_SPECS}, source)
