"""erva_ros: ROS 2 NMPC for an energy-regenerative vibration absorber (ERVA) quarter car."""

__version__ = '0.1.0'
