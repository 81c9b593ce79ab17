"""Status levels of ``/diagnostics`` (diagnostic_msgs/DiagnosticStatus), defined once.

The plain-Python cores that judge their own health (the HIL bridge) and the ROS side
that publishes and reads the statuses (erva_ros/core/reports.py, the nodes) use
these values; the message package itself is not imported here (core ring).
"""

OK = 0
WARN = 1
ERROR = 2
STALE = 3
LEVEL_NAMES = {OK: 'OK', WARN: 'WARN', ERROR: 'ERROR', STALE: 'STALE'}

__all__ = ['OK', 'WARN', 'ERROR', 'STALE', 'LEVEL_NAMES']
