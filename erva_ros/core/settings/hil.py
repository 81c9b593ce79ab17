"""The HIL nodes' and the simulated ECU's parameter tables (defaults: config/hil.yaml).

* ``ecu_bridge_node``: the bus, the DBC, timeouts, E2E tolerance and the generator
  hardware (:data:`HARDWARE_SPECS`).  The simulated ECU reads the hardware keys from this
  section too, so bridge and ECU share one calibration.
* ``state_estimator_node``: the EKF's noise (:data:`NOISE_SPECS`) and its discretisation
  bound.
* ``ecu_sim``: the simulated ECU's latch step and sensor noise.

Their users: core/hil/settings.py (the sections loaded and checked), core/model/hardware.py
(``GeneratorHardware``), core/model/estimator.py (``EstimatorNoise``), schemas.py.
"""

from typing import Any, Dict

from erva_ros.core.settings.specs import Flag, Integer, Number, Text

#: The generator and its PWM load switch (core/model/hardware.py).
HARDWARE_SPECS: Dict[str, Number] = {
    'kappa_n_per_a': Number(0.0, 1e5, 'N/A', 'generator force constant kappa = kappabar / l '
                            '(paper eq. (10)); c_e = kappa^2 / R', lo_open=True),
    'r_internal_ohm': Number(0.0, 1e3, 'Ohm', 'generator winding resistance R_int'),
    'r_switch_ohm': Number(0.0, 1e3, 'Ohm', 'load resistance while the PWM switch is on R_sw'),
    'duty_min': Number(0.0, 1.0, '-', 'lowest PWM duty the ECU accepts (0 = open circuit)'),
    'duty_max': Number(0.0, 1.0, '-', 'highest PWM duty the ECU accepts', lo_open=True),
}

#: The EKF's noise model (core/model/estimator.py).
NOISE_SPECS: Dict[str, Number] = {
    'q_accel_s': Number(0.0, 1e3, 'm/s^2', 'process noise: unmodelled sprung-mass acceleration'),
    'q_accel_us': Number(0.0, 1e4, 'm/s^2',
                         'process noise: unmodelled unsprung acceleration (incl. road error)'),
    'q_accel_d': Number(0.0, 1e3, 'm/s^2', 'process noise: unmodelled rotor (z_d) acceleration'),
    'r_sprung_accel': Number(0.0, 1e2, 'm/s^2', 'accelerometer noise std', lo_open=True),
    'r_deflection': Number(0.0, 1.0, 'm', 'deflection sensor noise std', lo_open=True),
    'r_speed': Number(0.0, 1e2, 'rad/s', 'generator speed noise std', lo_open=True),
    'p0_position': Number(0.0, 1.0, 'm', 'initial position uncertainty (std)', lo_open=True),
    'p0_velocity': Number(0.0, 10.0, 'm/s', 'initial velocity uncertainty (std)', lo_open=True),
}

BRIDGE_NODE = 'ecu_bridge_node'
ESTIMATOR_NODE = 'state_estimator_node'
ECU_SIM_SECTION = 'ecu_sim'


BRIDGE_SPECS: Dict[str, Any] = {
    'bus': Text('CAN bus: socketcan:IFACE (vehicle), udp:LOCAL_PORT:PEER_PORT (loopback to '
                '`erva ecu-sim`) or virtual:NAME (in-process)'),
    'dbc_file': Text('DBC file of the ECU messages (empty: the shipped config/erva_ecu.dbc)'),
    'can_log': Text('CAN trace of the bridge\'s bus, both directions: FILE.blf or FILE.asc '
                    '(python-can writers, epoch-second timestamps); empty: none'),
    'command_timeout_periods': Integer(1, 1000, 'periods', 'no fresh damping command for '
                                       'this many periods -> safe passive command + ERROR'),
    'sensor_timeout_periods': Integer(1, 1000, 'periods', 'no valid ECU frame for this many '
                                      'periods -> ECU silent ERROR'),
    'bus_retry_s': Number(0.01, 60.0, 's', 'time between attempts to re-open a lost CAN bus'),
    'max_delta_counter': Integer(1, 14, '-', 'largest alive-counter step accepted '
                                 '(1: a frame after a lost frame is dropped)'),
    'diagnostics_period_s': Number(0.05, 3600.0, 's', 'period of the /diagnostics status'),
    **HARDWARE_SPECS,
}
ESTIMATOR_SPECS: Dict[str, Any] = {
    **NOISE_SPECS,
    'u_max': Number(1.0, 1e6, 'Ns/m', 'largest c_e the discrete model must stay stable at '
                    '(sets the RK4 sub-steps)'),
    'max_gap_periods': Integer(1, 10000, 'periods', 'a gap in the measurements longer than '
                               'this restarts the filter'),
    'diagnostics_period_s': Number(0.05, 3600.0, 's', 'period of the /diagnostics status'),
}
ECU_SIM_SPECS: Dict[str, Any] = {
    'latch_s': Number(1e-4, 0.02, 's', 'command latch and plant step of the simulated ECU'),
    'noise_sprung_accel': Number(0.0, 100.0, 'm/s^2', 'accelerometer noise std'),
    'noise_deflection': Number(0.0, 1.0, 'm', 'deflection sensor noise std'),
    'noise_speed': Number(0.0, 100.0, 'rad/s', 'generator speed noise std'),
    'noise_current': Number(0.0, 100.0, 'A', 'generator current noise std'),
    'noise_voltage': Number(0.0, 1000.0, 'V', 'back-emf noise std'),
    'seed': Integer(0, 2 ** 31 - 1, '-', 'seed of the sensor noise'),
}


#: Parameters set on the command line only: rcl lets a /**/<node> key of a params file win
#: over ``-p name:=value``, so they have no key in config/hil.yaml and their defaults are here.
COMMAND_LINE_DEFAULTS: Dict[str, Any] = {'bus': 'socketcan:can0', 'can_log': '',
                                         'stamp_on_road_grid': False}
#: estimator node: stamp each cycle on the road grid (`erva run --ecu virtual` sets it).
ROAD_GRID_SPEC = Flag('stamp each ECU cycle with the road sample instant in [-Ts/4, 3Ts/4) '
                      'around its CAN receive time (an ECU sampling on the road grid and '
                      'sending at once)')
#: The parameters of COMMAND_LINE_DEFAULTS that are in no other table.
COMMAND_LINE_SPECS: Dict[str, Any] = {'stamp_on_road_grid': ROAD_GRID_SPEC}
