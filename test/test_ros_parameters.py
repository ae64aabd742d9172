"""declare_parameters on rclpy nodes of this process: unknown overrides refused with the closest
name, integers taken for doubles, read-only and dynamic descriptors, and run-time sets validated,
applied to the node's values and handed to its callback (or refused with a reason)."""
import pytest
import rclpy
from rclpy.node import Node
from rclpy.parameter import Parameter

from meshfg_ros.parameters import ParameterError, node_parameters
from meshfg_ros.nodes.ros_parameters import declare_parameters


@pytest.fixture
def context():
    context = rclpy.Context()
    context.init()
    yield context
    context.try_shutdown()


def make_node(context, name, **overrides):
    return Node(name, context=context,
                parameter_overrides=[Parameter(key, value=value) for key, value in overrides.items()])


def test_an_unknown_override_is_refused_with_the_closest_name(context):
    node = make_node(context, "estimator_node", tool_radiuss=0.004)
    with pytest.raises(ParameterError, match=r"^unknown parameter tool_radiuss \(did you mean tool_radius\?\)$"):
        declare_parameters(node, "estimator_node")
    node.destroy_node()


def test_the_other_nodes_parameters_are_ignored_not_refused(context):
    node = make_node(context, "simulation_node", measurement_sigma=0.002, use_sim_time=True, density=900.0,
                     start_type_description_service=False)
    values = declare_parameters(node, "simulation_node")
    assert values["density"] == 900.0 and "measurement_sigma" not in values
    assert not node.has_parameter("measurement_sigma")
    rclpy_own = {"use_sim_time", "start_type_description_service"}
    assert set(node.list_parameters([], 0).names) - rclpy_own == {
        parameter.name for parameter in node_parameters("simulation_node")}
    node.destroy_node()


def test_integers_are_taken_for_doubles_and_empty_arrays_keep_their_type(context):
    node = make_node(context, "estimator_node", measurement_sigma=1, camera_pose=[0, 0, 0, 0, 0, 0, 1])
    values = declare_parameters(node, "estimator_node")
    assert values["measurement_sigma"] == 1.0 and type(values["measurement_sigma"]) is float
    assert values["camera_pose"] == (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)
    assert node.get_parameter("measurement_sigma").type_ == Parameter.Type.DOUBLE
    assert node.get_parameter("measurement_sigma").value == 1.0
    camera_pose = node.get_parameter("camera_pose")
    assert camera_pose.type_ == Parameter.Type.DOUBLE_ARRAY and list(camera_pose.value) == [0.0] * 6 + [1.0]
    simulation = make_node(context, "simulation_node")
    declare_parameters(simulation, "simulation_node")
    grasped = simulation.get_parameter("grasped_vertices")
    assert grasped.type_ == Parameter.Type.INTEGER_ARRAY and list(grasped.value) == []
    assert simulation.describe_parameter("grasped_vertices").read_only
    node.destroy_node()
    simulation.destroy_node()


def test_invalid_start_up_values_name_the_parameter(context):
    node = make_node(context, "estimator_node", window_size=2.5)
    with pytest.raises(ParameterError, match=r"^window_size must be an integer, got 2\.5$"):
        declare_parameters(node, "estimator_node")
    node.destroy_node()


def test_dynamic_parameters_are_validated_applied_and_handed_to_the_callback(context):
    node = make_node(context, "estimator_node")
    changes = []
    values = declare_parameters(node, "estimator_node", on_change=changes.append)
    descriptors = {p.name: node.describe_parameter(p.name) for p in node_parameters("estimator_node")}
    assert {name for name, descriptor in descriptors.items() if not descriptor.read_only} == {
        "measurement_sigma", "simulation_sigma", "temporal_sigma", "robust_scale", "gating_distance", "marker_std_max"}

    def set_one(name, value):
        return node.set_parameters([Parameter(name, value=value)])[0]

    assert set_one("measurement_sigma", 0.002).successful
    assert set_one("marker_std_max", 1).successful  # an integer for a double
    assert changes == [{"measurement_sigma": 0.002}, {"marker_std_max": 1.0}]
    assert (values["measurement_sigma"], values["marker_std_max"]) == (0.002, 1.0)
    assert node.get_parameter("marker_std_max").value == 1.0

    out_of_range = set_one("measurement_sigma", 20.0)
    assert not out_of_range.successful and "measurement_sigma out of range" in out_of_range.reason
    read_only = set_one("window_size", 7)
    assert not read_only.successful and read_only.reason == "Trying to set a read-only parameter: window_size."
    assert set_one("use_sim_time", True).successful  # rclpy's own, not the callback's
    assert changes == [{"measurement_sigma": 0.002}, {"marker_std_max": 1.0}]
    assert (values["measurement_sigma"], values["window_size"]) == (0.002, 5)
    node.destroy_node()


def test_without_a_callback_every_parameter_is_read_only(context):
    node = make_node(context, "estimator_node")
    values = declare_parameters(node, "estimator_node")
    result = node.set_parameters([Parameter("measurement_sigma", value=0.002)])[0]
    assert not result.successful and "read-only" in result.reason
    assert values["measurement_sigma"] == 0.001
    node.destroy_node()
