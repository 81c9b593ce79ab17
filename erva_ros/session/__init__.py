"""Sessions: `erva run`, its benchmarks and reports, built on erva_ros.core and erva_ros.ros.

No rclpy or message import here (test_rings): ROS work goes through erva_ros.ros
(:class:`~erva_ros.ros.context.RosContext`, :mod:`~erva_ros.ros.monitor`, ...).

* :mod:`~erva_ros.session.monitor` -- what the monitor observed, as the run's figures;
* :mod:`~erva_ros.session.hil_summary` -- its HIL figures (`erva run --ecu virtual`);
* :mod:`~erva_ros.session.orchestrator` -- `erva run`: one session, start to summary;
* :mod:`~erva_ros.session.run_config` -- its options validated, the session params file;
* :mod:`~erva_ros.session.processes` -- child processes: start, stop (every session tool);
* :mod:`~erva_ros.session.supervisor` -- the session's processes and phases;
* :mod:`~erva_ros.session.start_gate` -- when the loop may start (every reader matched);
* :mod:`~erva_ros.session.recording` -- the recorder process, its drain, the bag check;
* :mod:`~erva_ros.session.benchmark` -- `erva bench --live`.
"""
