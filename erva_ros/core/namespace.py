"""The loop's ROS namespace: a leaf, named by both topic tables (topics.py, hil/topics.py)."""

NAMESPACE = '/erva'

__all__ = ['NAMESPACE']
