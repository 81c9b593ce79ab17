"""ros ring: the only code (with erva_ros/nodes) that imports rclpy or message packages."""
