"""meshfg_ros: factor-graph mesh state estimation of deforming soft tissue.

`meshfg_ros.core` is the ROS-free estimator (numpy/scipy/torch); `meshfg_ros.io` reads and
writes rosbag2 recordings without rclpy; `meshfg_ros.nodes` is the thin rclpy shell.
"""
