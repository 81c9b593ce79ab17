"""`erva run`: one session, start to summary.

Its processes and phases (``orchestrator``, ``supervisor``), what it observed and the
summary (``observations``, ``monitor_stats``, ``monitor_figures``, ``verdict``, ``report``).
"""
