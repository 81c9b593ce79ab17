"""Loop logic of the live nodes without ROS: scheduling, holds, timing, validation."""
