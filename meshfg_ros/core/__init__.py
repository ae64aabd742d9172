"""ROS-free core, in layers that import only downwards: geometry and solvers at the bottom, then
inputs, physics and estimation, with the scheduler (when each step runs) on top. Never imports
rclpy."""
