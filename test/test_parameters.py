"""The parameters, derived from the configurations' fields: config/meshfg.yaml matches them,
each node declares those of the configurations it reads, validation names the key, core configs
follow, --help describes them."""
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np
import pytest
import yaml
from rcl_interfaces.msg import ParameterType

from meshfg_ros.core.estimation.estimator import EstimatorConfig
from meshfg_ros.core.settings import setting
from meshfg_ros.core.inputs.world_frame import CLOUD, FramedInput
from meshfg_ros.parameters import (
    PARAMETERS,
    OpenLoopSimulatorConfig,
    ParameterError,
    check_parameter_names,
    config_changes,
    config_from_parameters,
    default_parameters,
    estimator_changes,
    estimator_config,
    load_mesh_file,
    world_frame_inputs,
    load_parameters,
    node_parameters,
    parameter_names,
    parameters_help,
    read_parameters_file,
    shared_settings,
    simulator_config,
)
from meshfg_ros.core.physics.simulator import SimulatorConfig
from meshfg_ros.nodes.ros_parameters import parameter_descriptor

CONFIG = Path(__file__).resolve().parents[1] / "config" / "meshfg.yaml"
PYTHON_TYPES = {"double": float, "integer": int, "string": str, "bool": bool}


def config_section() -> dict:
    document = yaml.safe_load(CONFIG.read_text())
    assert list(document) == ["/**"]
    return document["/**"]["ros__parameters"]


def test_config_file_lists_every_parameter_at_its_default_with_its_ros_type():
    section = config_section()
    assert list(section) == [parameter.name for parameter in PARAMETERS]
    for parameter in PARAMETERS:
        value = section[parameter.name]
        if parameter.type.endswith("_array"):
            assert tuple(value) == parameter.default, parameter.name
            element_type = PYTHON_TYPES[parameter.type.removesuffix("_array")]
            assert all(type(item) is element_type for item in value), parameter.name
        else:
            # The exact type: ROS rejects 3000 (an integer) for a double parameter.
            assert type(value) is PYTHON_TYPES[parameter.type], parameter.name
            assert value == parameter.default, parameter.name
    assert read_parameters_file(CONFIG) == default_parameters()


def test_every_default_is_valid_and_described():
    assert load_parameters() == default_parameters()
    assert len({parameter.name for parameter in PARAMETERS}) == len(PARAMETERS)
    for parameter in PARAMETERS:
        assert parameter.validate(parameter.default) == parameter.default
        assert parameter.description.endswith(".") and len(parameter.description) > 20


def test_descriptors_carry_type_range_and_choices():
    by_name = {parameter.name: parameter_descriptor(parameter) for parameter in PARAMETERS}
    assert by_name["poisson_ratio"].type == ParameterType.PARAMETER_DOUBLE
    (poisson_range,) = by_name["poisson_ratio"].floating_point_range
    assert (poisson_range.from_value, poisson_range.to_value) == (0.001, 0.499)
    (window_range,) = by_name["window_size"].integer_range
    assert (window_range.from_value, window_range.to_value, window_range.step) == (1, 100, 1)
    assert by_name["tool_mode"].additional_constraints == "one of: sphere, grasp"
    assert by_name["grasped_vertices"].type == ParameterType.PARAMETER_INTEGER_ARRAY
    assert by_name["camera_pose"].additional_constraints == "exactly 7 values"
    assert all(descriptor.read_only and descriptor.description for descriptor in by_name.values())
    sigma = next(parameter for parameter in PARAMETERS if parameter.name == "measurement_sigma")
    assert not parameter_descriptor(sigma, read_only=False).read_only


@pytest.mark.parametrize("mapping, message", [
    ({"youngs_modulus_pa": 1.0}, r"unknown parameter youngs_modulus_pa \(did you mean youngs_modulus\?\)"),
    ({"youngs_modulus": "soft"}, "youngs_modulus must be a number"),
    ({"youngs_modulus": True}, "youngs_modulus must be a number"),
    ({"youngs_modulus": float("nan")}, "youngs_modulus must be finite"),
    ({"youngs_modulus": -5.0}, r"youngs_modulus = -5.0 is outside \[1, 1e\+09\]"),
    ({"poisson_ratio": 0.5}, r"poisson_ratio = 0.5 is outside \[0.001, 0.499\]"),
    ({"window_size": 2.0}, "window_size must be an integer"),
    ({"window_size": 0}, r"window_size = 0 is outside \[1, 100\]"),
    ({"spd_projection": 1}, "spd_projection must be a bool"),
    ({"tool_mode": "scalpel"}, "tool_mode must be one of sphere, grasp; got 'scalpel'"),
    ({"world_frame": 3}, "world_frame must be a string"),
    ({"camera_pose": [0.0, 0.0, 0.0, 1.0]}, "camera_pose must have 7 values, got 4"),
    ({"camera_pose": "identity"}, "camera_pose must be a list"),
    ({"camera_pose": [0.0] * 7}, "camera_pose: pose quaternion has zero norm"),
    ({"tool_mode": "grasp", "grasped_vertices": [1, -2]}, r"grasped_vertices\[1\] = -2 is outside \[0, inf\]"),
    ({"tool_mode": "grasp", "grasped_vertices": [1.5]}, r"grasped_vertices\[0\] must be an integer"),
    ({"tool_mode": "grasp"}, "tool_mode 'grasp' needs grasped_vertices"),
    ({"grasped_vertices": [1, 2]}, "grasped_vertices is set but tool_mode is not 'grasp'"),
])
def test_invalid_parameters_name_the_key(mapping, message):
    with pytest.raises(ParameterError, match=message):
        load_parameters(mapping)


def test_values_are_normalised():
    params = load_parameters({"youngs_modulus": 5000, "tool_mode": "grasp", "grasped_vertices": np.array([3, 1]),
                              "camera_pose": [1, 2, 3, 0, 0, 0, 1]})
    assert type(params["youngs_modulus"]) is float and params["youngs_modulus"] == 5000.0
    assert params["grasped_vertices"] == (3, 1) and all(type(v) is int for v in params["grasped_vertices"])
    assert params["camera_pose"] == (1.0, 2.0, 3.0, 0.0, 0.0, 0.0, 1.0)
    with pytest.raises(ParameterError, match="parameters must be a mapping"):
        load_parameters([("youngs_modulus", 1.0)])


def test_core_configurations_follow_the_parameters():
    params = load_parameters({"youngs_modulus": 8000.0, "poisson_ratio": 0.4, "density": 1100.0,
                              "tool_radius": 0.002, "simulator_substeps": 4, "simulator_iterations": 7,
                              "window_size": 5, "measurement_sigma": 0.0005, "max_iterations": 3})
    simulator = simulator_config(params)
    assert (simulator.youngs_modulus, simulator.poisson_ratio, simulator.density, simulator.tool_radius,
            simulator.substeps, simulator.solver_iterations) == (8000.0, 0.4, 1100.0, 0.002, 4, 7)
    estimator = estimator_config(params)
    assert (estimator.window_size, estimator.measurement_sigma, estimator.max_iterations) == (5, 0.0005, 3)
    # The table's defaults are the estimator's own.
    assert estimator_config(default_parameters()) == EstimatorConfig()
    assert simulator_config(default_parameters()) == SimulatorConfig()


def test_parameters_file_formats(tmp_path):
    ros_file = tmp_path / "ros.yaml"
    ros_file.write_text(yaml.safe_dump({
        "/**": {"ros__parameters": {"window_size": 4, "use_sim_time": True}},
        "estimator_node": {"ros__parameters": {"window_size": 6}},
        "simulation_node": {"ros__parameters": {"youngs_modulus": 9000.0}},
    }))
    assert read_parameters_file(ros_file)["window_size"] == 4
    node_params = read_parameters_file(ros_file, node_name="estimator_node")
    assert node_params["window_size"] == 6 and node_params["youngs_modulus"] == 3000.0
    flat = tmp_path / "flat.yaml"
    flat.write_text("factors: full\nmax_iterations: 12\n")
    assert read_parameters_file(flat)["max_iterations"] == 12
    bad = tmp_path / "bad.yaml"
    bad.write_text("- 1\n- 2\n")
    with pytest.raises(ParameterError, match="must hold a mapping"):
        read_parameters_file(bad)
    unknown = tmp_path / "unknown.yaml"
    unknown.write_text("max_iteration: 12\n")
    with pytest.raises(ParameterError, match=r"unknown parameter max_iteration \(did you mean max_iterations\?\)"):
        read_parameters_file(unknown)
    with pytest.raises(ParameterError, match="cannot read parameters file"):
        read_parameters_file(tmp_path / "missing.yaml")


def test_camera_pose_places_camera_frame_clouds_when_tf_knows_nothing_of_it():
    quarter_turn_about_z = [0.0, 0.0, np.sqrt(0.5), np.sqrt(0.5)]
    params = load_parameters({"camera_pose": [1.0, 2.0, 3.0, *quarter_turn_about_z], "camera_frame": "endoscope"})
    placer = world_frame_inputs(params)
    points = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 2.0]])
    placed, _ = placer.add(FramedInput(CLOUD, 1, "world", points))
    assert placed[0].data is points
    placed, _ = placer.add(FramedInput(CLOUD, 2, "endoscope", points))
    np.testing.assert_allclose(placed[0].data, [[1.0, 3.0, 3.0], [1.0, 2.0, 5.0]], atol=1e-15)
    placed, set_aside = placer.add(FramedInput(CLOUD, 3, "map", points), now_s=0.0)
    assert placed == [] and set_aside == []  # waits for /tf to name "map" ...
    placed, set_aside = placer.release(now_s=params["transform_timeout"])
    assert placed == [] and set_aside[0].reason.startswith("unknown frame")  # ... then is set aside, why


# ---------------------------------------------------------------------------- derived from the fields
def test_the_parameters_are_the_setting_fields_of_the_configurations():
    # A field whose name differs from its parameter's keeps the user-visible parameter name.
    assert parameter_names(SimulatorConfig) == {
        "youngs_modulus": "youngs_modulus", "poisson_ratio": "poisson_ratio", "density": "density",
        "tool_radius": "tool_radius", "tool_mode": "tool_mode", "tool_contact": "tool_contact",
        "substeps": "simulator_substeps", "solver_iterations": "simulator_iterations", "solver": "simulator",
        "estimate_body_load": "estimate_body_load", "estimate_poisson_ratio": "estimate_poisson_ratio"}
    # Internal fields are no parameters; every estimator setting is one (no knob the nodes cannot set).
    internal = {item.name for item in fields(SimulatorConfig)} - set(parameter_names(SimulatorConfig))
    assert internal == {"damping", "gravity", "deterministic"}
    assert set(parameter_names(EstimatorConfig)) == {item.name for item in fields(EstimatorConfig)}
    by_name = {parameter.name: parameter for parameter in PARAMETERS}
    assert by_name["camera_pose"].type == "double_array" and by_name["grasped_vertices"].type == "integer_array"
    assert {name for name, parameter in by_name.items() if parameter.dynamic} == {
        "measurement_sigma", "simulation_sigma", "temporal_sigma", "robust_scale", "gating_distance", "marker_std_max"}


def test_each_node_declares_the_parameters_of_the_configurations_it_reads():
    simulation = {parameter.name for parameter in node_parameters("simulation_node")}
    estimator = {parameter.name for parameter in node_parameters("estimator_node")}
    assert {"density", "simulator", "simulator_substeps", "grasped_vertices", "estimate_timeout"} <= simulation - estimator
    assert {"measurement_sigma", "window_size", "camera_pose", "prediction_timeout", "marker_std_max"} <= \
        estimator - simulation
    # The tissue model and the tool are both configurations' fields; frames and mesh are both nodes'.
    assert simulation & estimator == {"youngs_modulus", "poisson_ratio", "tool_radius", "tool_mode", "world_frame",
                                      "mesh_file", "clock_jump_threshold", "mesh_scale", "mesh_pose", "fixed_vertices",
                                      "fixed_plane", "fixed_box", "fixed_groups", "transform_timeout",
                                      "tool_pose_horizon", "tool_pose_reliable"}
    assert simulation | estimator == {parameter.name for parameter in PARAMETERS}
    assert [parameter.name for parameter in node_parameters("bag_player")] == [
        "rate", "wait_for_subscribers", "subscribers", "clock_frequency", "delay", "loop"]


def test_sim_bridge_server_declares_what_its_open_loop_simulator_reads():
    """The simulator's settings but the learning switches (no estimate reaches it), the grasp, the
    initial mesh and the tool_pose QoS; no stamp rule, /tf wait or extrapolation: it takes the
    tool poses in world_frame as they come."""
    server = [parameter.name for parameter in node_parameters("sim_bridge_server")]
    assert server == ["youngs_modulus", "poisson_ratio", "tool_radius", "tool_mode", "density", "tool_contact",
                      "simulator_substeps", "simulator_iterations", "simulator", "grasped_vertices", "world_frame",
                      "mesh_file", "mesh_scale", "mesh_pose", "fixed_vertices", "fixed_plane", "fixed_box",
                      "fixed_groups", "tool_pose_reliable"]
    with pytest.raises(ParameterError, match="tool_mode 'grasp' needs grasped_vertices"):
        load_parameters({"tool_mode": "grasp"}, node="sim_bridge_server")
    params = load_parameters({"tool_mode": "grasp", "grasped_vertices": [3], "youngs_modulus": 5e3},
                             "sim_bridge_server")
    simulator = config_from_parameters(OpenLoopSimulatorConfig, params)
    assert (simulator.tool_mode, simulator.youngs_modulus) == ("grasp", 5e3)
    assert not simulator.estimate_body_load and not simulator.estimate_poisson_ratio
    # A /** section of the pipeline's parameters is accepted; the server ignores what it does not declare.
    check_parameter_names(["estimate_body_load", "clock_jump_threshold", "tool_pose_horizon"], "sim_bridge_server")


def test_a_parameter_of_two_configurations_is_declared_once():
    """The tissue model and the tool are one field each, which both configurations inherit; a
    configuration that declares one of them again is refused, even alike."""
    from meshfg_ros import parameters

    @dataclass(frozen=True)
    class Other:
        youngs_modulus: float = setting(3e3, "Young's modulus of the tissue model in pascals.", range=(1.0, 1e9))

    assert parameters._merged((SimulatorConfig, EstimatorConfig))
    with pytest.raises(ParameterError, match="parameter youngs_modulus is declared again in Other"):
        parameters._merged((SimulatorConfig, Other))


def test_node_scoped_validation_and_unknown_names():
    # The grasp rule needs both parameters: the estimator node has no grasped_vertices.
    assert load_parameters({"tool_mode": "grasp"}, node="estimator_node")["tool_mode"] == "grasp"
    with pytest.raises(ParameterError, match="tool_mode 'grasp' needs grasped_vertices"):
        load_parameters({"tool_mode": "grasp"}, node="simulation_node")
    with pytest.raises(ParameterError, match="camera_pose: pose quaternion has zero norm"):
        load_parameters({"camera_pose": [0] * 7}, node="estimator_node")
    assert set(load_parameters(node="simulation_node")) == {p.name for p in node_parameters("simulation_node")}
    # A node accepts (and ignores) the other nodes' parameters and use_sim_time, not a typo.
    check_parameter_names(["density", "rate", "use_sim_time", "measurement_sigma"], "estimator_node")
    with pytest.raises(ParameterError, match=r"^unknown parameter tool_radiuss \(did you mean tool_radius\?\)$"):
        check_parameter_names(["world_frame", "tool_radiuss"], "estimator_node")
    with pytest.raises(ParameterError, match=r"^unknown parameter use_sim_tim \(did you mean use_sim_time\?\)$"):
        check_parameter_names(["use_sim_tim"], "simulation_node")
    with pytest.raises(ParameterError, match=r"^unknown parameter xyz \(known: rate, wait_for_subscribers, "):
        check_parameter_names(["xyz"], "bag_player")


def test_config_changes_and_shared_settings_follow_the_field_names():
    changes = {"simulator_substeps": 4, "measurement_sigma": 0.002, "marker_std_max": 0.01}
    assert config_changes(SimulatorConfig, changes) == {"substeps": 4}
    assert estimator_changes(changes) == {"measurement_sigma": 0.002}
    model = SimulatorConfig(youngs_modulus=5e3, poisson_ratio=0.4, tool_radius=0.002, tool_mode="grasp", density=900.0)
    assert shared_settings(model, EstimatorConfig) == {"youngs_modulus": 5e3, "poisson_ratio": 0.4,
                                                       "tool_radius": 0.002, "tool_mode": "grasp"}
    grasp = estimator_config(load_parameters({"tool_mode": "grasp", "grasped_vertices": [3]}))
    assert (grasp.tool_mode, grasp.tool_radius) == ("grasp", 0.005)


def test_help_describes_every_parameter_of_the_nodes():
    text = parameters_help(["simulation_node", "estimator_node"])
    assert text.startswith("Parameters of simulation_node") and "\nParameters of estimator_node" in text
    estimator_part = text[text.index("Parameters of estimator_node"):]
    for parameter in node_parameters("estimator_node"):
        assert f"\n  {parameter.name} ({parameter.summary()})\n" in estimator_part
        assert " ".join(parameter.description.split()[:4]) in " ".join(estimator_part.split())
    assert "  measurement_sigma (double, default 0.001, range [1e-09, 10], dynamic)" in text
    assert "  tool_mode (string, default 'sphere', one of: sphere, grasp, read-only)" in text
    assert "  camera_pose (double_array, default [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0], range [-1000, 1000], 7 values, " \
           "read-only)" in text


def test_a_mesh_file_that_cannot_be_read_is_a_parameter_error(tmp_path):
    with pytest.raises(ParameterError, match=r"^cannot load mesh_file /nonexistent/organ\.msh: "):
        load_mesh_file(load_parameters({"mesh_file": "/nonexistent/organ.msh"}))
    garbage = tmp_path / "organ.vtu"
    garbage.write_text("not a mesh\n")
    with pytest.raises(ParameterError, match="cannot load mesh_file .*organ.vtu") as error:
        load_mesh_file(load_parameters({"mesh_file": str(garbage)}))
    assert "\n" not in str(error.value)


def test_mesh_file_placement_and_fixed_vertices_come_from_the_parameters(tmp_path):
    from meshfg_ros.core.geometry.mesh import save_mesh
    from meshfg_ros.synthetic.meshing import cube_mesh

    cube = cube_mesh(side=0.02, divisions=3)
    save_mesh(cube.with_vertices(1e3 * cube.vertices).with_fixed(np.zeros(0, dtype=np.int64)), tmp_path / "mm.vtu")
    with pytest.raises(ParameterError, match="fixed"):
        load_mesh_file(load_parameters({"mesh_file": str(tmp_path / "mm.vtu")}))
    pose = [0.1, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]
    bottom = load_mesh_file(load_parameters({"mesh_file": str(tmp_path / "mm.vtu"), "mesh_scale": 0.001,
                                             "mesh_pose": pose, "fixed_plane": [0, 0, 0, 0, 0, 1, 1e-6]}))
    np.testing.assert_allclose(bottom.vertices, cube.vertices + [0.1, 0.0, 0.0], atol=1e-15)
    np.testing.assert_array_equal(bottom.fixed_vertices, np.flatnonzero(np.isclose(cube.vertices[:, 2], 0.0)))
    box = load_mesh_file(load_parameters({"mesh_file": str(tmp_path / "mm.vtu"), "mesh_scale": 0.001,
                                          "fixed_box": [-1, -1, -1, 1, 1, 1e-6], "fixed_vertices": [26]}))
    np.testing.assert_array_equal(box.fixed_vertices, np.union1d(bottom.fixed_vertices, [26]))
    with pytest.raises(ParameterError, match="fixed_plane needs 0 or 7 values"):
        load_parameters({"fixed_plane": [0.0, 0.0, 1.0]})


@pytest.mark.parametrize("name", ["bad name", "a//b", "1a", "/a/", ""])
def test_sim_bridge_service_must_be_a_ros_name(name):
    with pytest.raises(ParameterError, match="sim_bridge_service must be a ROS service name"):
        load_parameters({"sim_bridge_service": name}, "estimator_node")
    assert load_parameters({"sim_bridge_service": "/robot/sim/factor_graph_state", "prediction_source": "sim_bridge"},
                           "estimator_node")["prediction_source"] == "sim_bridge"
    with pytest.raises(ParameterError, match="prediction_source must be one of simulation_node, sim_bridge"):
        load_parameters({"prediction_source": "xpbd"}, "estimator_node")
