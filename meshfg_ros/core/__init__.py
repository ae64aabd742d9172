"""ROS-free core: mesh, FEM, simulator, factors, solver, metrics. Never imports rclpy."""
