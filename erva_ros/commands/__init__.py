"""Subcommands of the ``erva`` tool, one module each (see :mod:`erva_ros.cli`)."""
