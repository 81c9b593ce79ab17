"""Hardware-in-the-loop: the NMPC on a vehicle ECU over CAN, a simulated ECU, plain-Python cores.

=====================  ============================================================
module                 role
=====================  ============================================================
``e2e``                AUTOSAR E2E profile 1 style CRC-8 + alive counter, checks
``codec``              the DBC (config/erva_ecu.dbc) with cantools: frames ↔ values
``transport``          bus selection: SocketCAN, python-can virtual, loopback UDP
``bridge``             bridge core joining the four units below
``bus_link``           the bridge's CAN bus: open, send, loss and retry
``command_watchdog``   commands → frames at Ts: plan while late, safe command
``ecu_cycles``         ECU frames → cycles (incomplete ones too), ECU heartbeat
``bridge_diagnostics`` the bridge's statuses: command link, CAN bus, ECU
``ecu_sim``            simulated ECU core on erva_ros.core.model.plant.PlantSimulator
``road_buffer``        w(t) from time-stamped road samples
``evaluation``         offline closed loop on estimated vs true state
``settings``           parameter tables of config/hil.yaml
=====================  ============================================================

The ROS adapters are erva_ros/nodes/ecu_bridge_node.py and state_estimator_node.py,
the estimator core erva_ros/core/model/estimator.py, the commands `erva ecu-sim` and
`erva bench-hil`.
"""
