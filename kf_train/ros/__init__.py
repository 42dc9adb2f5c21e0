"""Floor 4, the ROS adapters: the only place that imports rclpy or message packages."""
