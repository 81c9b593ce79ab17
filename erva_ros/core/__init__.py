"""core ring: plain Python (no rclpy, no message packages)."""
