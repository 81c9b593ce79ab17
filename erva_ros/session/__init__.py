"""The live system's ROS 2 plumbing, shared by the nodes, `erva run` and `erva bench --live`.

Plain helpers around rclpy, kept out of the node files so the nodes stay thin:

* :mod:`~erva_ros.ros.msgs` -- numpy <-> common_interfaces messages (topics.py contract);
* :mod:`~erva_ros.core.loop.validation` -- NaN/inf/absurd values rejected, counted, logged at a
  limited rate, before anything reaches a controller or the plant;
* :mod:`~erva_ros.ros.diagnostics` -- diagnostic_msgs/DiagnosticArray of a node's status;
* :mod:`~erva_ros.ros.parameters` -- parameters declared with descriptors and ranges from
  the Spec tables, one-line errors on bad values;
* :mod:`~erva_ros.core.loop.command_hold` -- the plant's command/plan/passive hold (no ROS);
* :mod:`~erva_ros.core.loop.timing` -- grid alignment and timing statistics;
* :mod:`~erva_ros.ros.runtime` -- the main() idiom of every node;
* :mod:`~erva_ros.session.monitor` -- the in-process monitor node of `erva run`;
* :mod:`~erva_ros.session.hil_summary` -- its HIL figures (`erva run --ecu virtual`);
* :mod:`~erva_ros.session.orchestrator` -- `erva run`: one session, start to summary;
* :mod:`~erva_ros.session.run_config` -- its options validated, the session params file;
* :mod:`~erva_ros.session.processes` -- child processes: start, stop (every session tool);
* :mod:`~erva_ros.session.supervisor` -- the session's processes and phases;
* :mod:`~erva_ros.session.start_gate` -- when the loop may start (every reader matched);
* :mod:`~erva_ros.session.recording` -- the recorder process, its drain, the bag check;
* :mod:`~erva_ros.session.benchmark` -- `erva bench --live`.
"""
