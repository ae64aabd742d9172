"""Topic names of meshfg_ros recordings (absolute, in the /meshfg namespace of the nodes)."""

# Inputs: what the sensors and the robot give, plus the initial mesh and scenario metadata.
POINTS_TOPIC = "/meshfg/points"                      # sensor_msgs/PointCloud2
TOOL_POSE_TOPIC = "/meshfg/tool_pose"                # geometry_msgs/PoseStamped
INITIAL_MESH_TOPIC = "/meshfg/initial_mesh"          # meshfg_msgs/TetraMesh, step 0
CAMERA_POSE_TOPIC = "/meshfg/camera_pose"            # geometry_msgs/PoseStamped
SCENARIO_TOPIC = "/meshfg/scenario"                  # std_msgs/String, JSON metadata of a synthetic scene
REMOVE_ELEMENTS_TOPIC = "/meshfg/remove_elements"    # std_msgs/UInt32MultiArray: element slots a cut removes
# Ground truth of synthetic recordings.
GROUND_TRUTH_TOPIC = "/meshfg/ground_truth"          # meshfg_msgs/TetraMesh per step
# Outputs of the estimator and simulator (live nodes and offline replay).
ESTIMATED_MESH_TOPIC = "/meshfg/estimated_mesh"      # meshfg_msgs/TetraMesh
PREDICTED_MESH_TOPIC = "/meshfg/predicted_mesh"      # meshfg_msgs/TetraMesh
MARKERS_TOPIC = "/meshfg/markers"                    # visualization_msgs/MarkerArray
STATUS_TOPIC = "/meshfg/status"                      # meshfg_msgs/EstimatorStatus
BODY_ACCELERATION_TOPIC = "/meshfg/body_acceleration"  # geometry_msgs/Vector3Stamped, m/s^2 (core/physics/body_load.py)
# Offline replay only.
SIMULATION_ONLY_MESH_TOPIC = "/meshfg/simulation_only_mesh"  # open-loop simulator, meshfg_msgs/TetraMesh
COST_HISTORY_TOPIC = "/meshfg/cost_history"          # std_msgs/Float64MultiArray: LM cost per iteration
