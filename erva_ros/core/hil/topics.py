"""Topics of the HIL loop, relative to the ``/erva`` namespace (as in erva_ros/core/topics.py).

Published by ``ecu_bridge_node`` from the ECU's CAN frames; every stamp is the CAN
receive time of the first frame of the ECU cycle (so all five share one stamp).

====================  ===========================  ========================================
topic                 type                         content (SI units)
====================  ===========================  ========================================
ecu/damping_applied   sensor_msgs/JointState       name [c_e, c_e_mean]: position = the
                                                   c_e the ECU applies now / its mean over
                                                   the cycle (Ns/m), from its status frame
ecu/sprung_accel      geometry_msgs/AccelStamped   accel.linear.z = measured z_s'' (m/s^2)
ecu/suspension        sensor_msgs/JointState       name [suspension]: position = measured
                                                   deflection z_s - z_us (m)
ecu/generator         sensor_msgs/JointState       name [generator]: velocity = v_gen =
                                                   l * phi' (m/s), effort = kappa * i (N);
                                                   P = effort * velocity (W), as GENERATOR
ecu/measurements      sensor_msgs/JointState       the whole ECU cycle in one message, once
                                                   its frames are in (the estimator's
                                                   input): name [c_e, c_e_mean,
                                                   sprung_accel, suspension,
                                                   generator_speed, f_gen], position = the
                                                   values above, the rotor speed phi' as
                                                   the ECU measures it (Ns/m, Ns/m, m/s^2,
                                                   m, rad/s, N); a lost frame's values are
                                                   NaN (published with the next cycle's
                                                   first frame or after Ts/2)
/diagnostics          diagnostic_msgs/Diagnostic-  bridge: command link, CAN bus, ECU
                      Array                        heartbeat (counters, latency)
====================  ===========================  ========================================

Published by ``erva ecu-sim`` (simulation only, ground truth): ``sprung_accel`` and
``generator`` exactly as plant_sim_node does (so `erva run` metrics are unchanged) and
``ecu_sim/state`` (a JointState like ``state``: the true state, to judge the estimator).
``state`` itself comes from ``state_estimator_node`` in HIL mode.
"""

from erva_ros.core.namespace import NAMESPACE

ECU_SPRUNG_ACCEL = 'ecu/sprung_accel'
ECU_SUSPENSION = 'ecu/suspension'
ECU_GENERATOR = 'ecu/generator'
ECU_DAMPING_APPLIED = 'ecu/damping_applied'
ECU_MEASUREMENTS = 'ecu/measurements'
TRUE_STATE = 'ecu_sim/state'

SUSPENSION_JOINT = 'suspension'
APPLIED_JOINTS = ('c_e', 'c_e_mean')
#: ``ecu/measurements`` names (position[i], SI units as in the table), by CAN frame: the
#: values of one frame are all present or all NaN (frame lost).
MEASUREMENT_NAMES = ('c_e', 'c_e_mean', 'sprung_accel', 'suspension', 'generator_speed',
                     'f_gen')
MEASUREMENT_CHANNELS = {'status': (0, 1), 'chassis': (2, 3), 'generator': (4, 5)}

#: ROS type names of the HIL topics, fully qualified under NAMESPACE (for recorders).
TOPIC_TYPES = {
    f'{NAMESPACE}/{ECU_SPRUNG_ACCEL}': 'geometry_msgs/msg/AccelStamped',
    f'{NAMESPACE}/{ECU_SUSPENSION}': 'sensor_msgs/msg/JointState',
    f'{NAMESPACE}/{ECU_GENERATOR}': 'sensor_msgs/msg/JointState',
    f'{NAMESPACE}/{ECU_DAMPING_APPLIED}': 'sensor_msgs/msg/JointState',
    f'{NAMESPACE}/{ECU_MEASUREMENTS}': 'sensor_msgs/msg/JointState',
    f'{NAMESPACE}/{TRUE_STATE}': 'sensor_msgs/msg/JointState',
}

#: The HIL topics a session recorder should add to the contract's (relative names).
RECORD_TOPICS = (ECU_DAMPING_APPLIED, ECU_SPRUNG_ACCEL, ECU_SUSPENSION, ECU_GENERATOR,
                 ECU_MEASUREMENTS, TRUE_STATE)
