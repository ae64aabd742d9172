"""Launch the meshfg_ros live pipeline (needs a ROS 2 install with launch_ros).

    ros2 launch meshfg_ros meshfg.launch.py [namespace:=meshfg] [params_file:=FILE]
        [single_process:=false] [bag:=RECORDING rate:=1.0] [use_sim_time:=false]

Starts simulation_node and estimator_node (or meshfg_stack with single_process:=true) in
`namespace` with `params_file` (default: the installed config/meshfg.yaml), and, if `bag` is
given, bag_player on that recording (set use_sim_time:=true to run the nodes on its /clock).
"""

from launch_ros.actions import Node
from launch_ros.descriptions import ParameterValue
from launch_ros.substitutions import FindPackageShare

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.conditions import IfCondition, UnlessCondition
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution, PythonExpression

PACKAGE = "meshfg_ros"


def generate_launch_description() -> LaunchDescription:
    namespace = LaunchConfiguration("namespace")
    params_file = LaunchConfiguration("params_file")
    single_process = LaunchConfiguration("single_process")
    bag = LaunchConfiguration("bag")
    rate = LaunchConfiguration("rate")
    use_sim_time = ParameterValue(LaunchConfiguration("use_sim_time"), value_type=bool)
    parameters = [params_file, {"use_sim_time": use_sim_time}]

    def pipeline_node(executable: str, condition) -> Node:
        return Node(package=PACKAGE, executable=executable, namespace=namespace, parameters=parameters,
                    condition=condition, output="screen")

    return LaunchDescription([
        DeclareLaunchArgument("namespace", default_value="meshfg", description="Namespace of the nodes' topics."),
        DeclareLaunchArgument("params_file",
                              default_value=PathJoinSubstitution([FindPackageShare(PACKAGE), "config", "meshfg.yaml"]),
                              description="ROS 2 parameters file of the nodes."),
        DeclareLaunchArgument("single_process", default_value="false",
                              description="Run both nodes in one process (meshfg_stack)."),
        DeclareLaunchArgument("bag", default_value="", description="Recording to play (empty: none)."),
        DeclareLaunchArgument("rate", default_value="1.0", description="Playback speed of the recording."),
        DeclareLaunchArgument("use_sim_time", default_value="false", description="Run the nodes on /clock."),
        pipeline_node("simulation_node", UnlessCondition(single_process)),
        pipeline_node("estimator_node", UnlessCondition(single_process)),
        pipeline_node("meshfg_stack", IfCondition(single_process)),
        Node(package=PACKAGE, executable="bag_player", arguments=[bag, "--rate", rate],
             condition=IfCondition(PythonExpression(["'", bag, "' != ''"])), output="screen"),
    ])
