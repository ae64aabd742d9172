"""rosbag2 recordings and message <-> array conversion, without rclpy (via rosbags)."""
