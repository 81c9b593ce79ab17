"""Thin rclpy adapters around the plain-Python cores, one process per node."""
