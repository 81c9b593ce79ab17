"""Sessions: `erva run`, its benchmarks and reports, built on erva_ros.core and erva_ros.ros.

No rclpy or message import here (test_rings): ROS work goes through erva_ros.ros
(:class:`~erva_ros.ros.context.RosContext`, :mod:`~erva_ros.ros.monitor`, ...).

* :mod:`~erva_ros.session.run.orchestrator` -- `erva run`: one session, start to summary;
* :mod:`~erva_ros.session.run.run_config` -- its options;
* :mod:`~erva_ros.session.run.session_file` -- the options validated, the session id, the
  session params file; :mod:`~erva_ros.session.run.session_dirs` -- where it is kept;
* :mod:`~erva_ros.session.processes` -- child processes: start, stop (every session tool);
* :mod:`~erva_ros.session.run.supervisor` -- the session's processes and phases;
* :mod:`~erva_ros.session.run.start_gate` -- another session here? when the loop may start;
* :mod:`~erva_ros.session.run.recording` -- the recorder process and its drain;
* :mod:`~erva_ros.session.run.accounting` -- who must be matched, was anything lost (the bag);
* :mod:`~erva_ros.session.run.observations` -- what the monitor observed, as the run's figures
  (:mod:`~erva_ros.session.run.monitor_figures`, :mod:`~erva_ros.session.run.hil_summary`,
  :mod:`~erva_ros.session.run.verdict`);
* :mod:`~erva_ros.session.bench.benchmark` -- `erva bench --live`.
"""
