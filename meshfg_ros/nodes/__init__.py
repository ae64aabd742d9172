"""rclpy nodes: the thin ROS 2 shell over meshfg_ros.core."""
