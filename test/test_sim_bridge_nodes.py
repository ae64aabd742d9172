"""The estimator node with prediction_source sim_bridge over real DDS: a scripted sim_bridge service
in the test process (nodes/sim_bridge_server.SimBridgeService) answers in frame sim/world, which
/tf_static places in the world; the node's estimates equal those of the same predictions and
stiffness given in-process; a service that is missing, slow or answers badly is counted and
named in /diagnostics, and the steps run degraded, never on a poisoned window; the
sim_bridge_server executable answers with the project's simulator driven by tool poses (in grasp
mode too, and from a best-effort publisher with tool_pose_reliable false), reads every parameter
it declares, and counts and names on /diagnostics each cause of a tool pose it rejects."""
import time
from collections import deque

import numpy as np
import pytest
import scipy.sparse
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import PoseStamped
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy
from scipy.spatial.transform import Rotation
from sim_bridge.srv import FactorGraphState
from std_msgs.msg import UInt32MultiArray
from test_nodes import (  # noqa: F401 - probe and processes are fixtures
    FACTORY,
    KEEP,
    LATCHED,
    S,
    SIDE,
    EstimatorProbe,
    Process,
    assert_clean_exit,
    call_service,
    cloud_msg,
    mesh_msg,
    probe,
    processes,
    pushed_cube,
    ros_args,
    spin_until,
    tool_pose_msg,
    top_points,
)
from tf2_msgs.msg import TFMessage

from meshfg_ros.core.physics.external_prior import FIXED_DIAGONAL, HELD_DOF_STIFFNESS, bridge_state
from meshfg_ros.core.physics.fem import ElasticModel
from meshfg_ros.core.inputs.frames import StampedTransform
from meshfg_ros.core.geometry.mesh import save_mesh
from meshfg_ros.core.scheduler import EstimationScheduler, Prediction, SchedulingTimeouts
from meshfg_ros.core.inputs.world_frame import CLOUD, FramedInput
from meshfg_ros.io.messages import PoseRecord, pose_to_msg
from meshfg_ros.io.tf_messages import TF_STATIC_TOPIC, transforms_to_tf_message
from meshfg_ros.nodes.frame_inputs import TF_STATIC_QOS
from meshfg_ros.nodes import sim_bridge_server
from meshfg_ros.nodes.sim_bridge_client import answer_from_msg
from meshfg_ros.nodes.sim_bridge_server import SERVICE, SimBridgeService, factor_graph_state_response
from meshfg_ros.parameters import estimator_config, load_parameters, node_parameters, world_frame_inputs
from meshfg_msgs.msg import TetraMesh

pytestmark = pytest.mark.slow  # node processes over DDS

SIM_TRANSLATION = np.array([0.01, -0.02, 0.003])
SIM_ROTATION = Rotation.from_euler("z", 30, degrees=True)


def sim_to_world() -> np.ndarray:
    matrix = np.eye(4)
    matrix[:3, :3], matrix[:3, 3] = SIM_ROTATION.as_matrix(), SIM_TRANSLATION
    return matrix


def in_sim_frame(world_positions):
    return SIM_ROTATION.inv().apply(world_positions - SIM_TRANSLATION)


def publish_sim_frame(probe):
    publisher = probe.create_publisher(TFMessage, TF_STATIC_TOPIC, TF_STATIC_QOS)
    publisher.publish(transforms_to_tf_message(
        [StampedTransform("world", "sim/world", 0, SIM_TRANSLATION, SIM_ROTATION.as_quat())], FACTORY))
    return publisher


def pressed(mesh, step):
    """The cube pressed down by 0.6 mm per step at its top, more towards x = SIDE."""
    positions = mesh.vertices.copy()
    height = positions[:, 2] / SIDE
    positions[:, 2] -= 6e-4 * step * height * (0.5 + positions[:, 0] / SIDE)
    return positions


def response_for(mesh, model, world_positions, stamp_ns):
    sim_positions = in_sim_frame(world_positions)
    return factor_graph_state_response(sim_positions, mesh, "sim/world", stamp_ns,
                                       model.stiffness(sim_positions, kind="corotational"))


class ScriptedService:
    """The sim_bridge service of the test process: answers its calls with the queued answers."""

    def __init__(self, probe, name):
        self.answers = deque()
        self.service = SimBridgeService(probe, self._answer, name)

    def _answer(self, request):
        assert request.compute_stiffness_matrix and not request.update_last_mesh
        answer = self.answers.popleft()
        return answer() if callable(answer) else answer


def start_node(probe, processes, tmp_path, namespace, *parameters):
    node = Process(tmp_path, "estimator_node", *ros_args(
        namespace, "prediction_source:=sim_bridge", f"sim_bridge_service:={namespace}/sim/factor_graph_state",
        "points_reliable:=true", *parameters))
    processes.append(node)
    io = EstimatorProbe(probe, namespace)
    assert spin_until(probe, lambda: io.cloud.get_subscription_count() == 1
                      and probe.count_clients(f"{namespace}/sim/factor_graph_state") == 1)
    io.wait_for(clouds_received=0)
    return node, io


def estimate_at(io, stamp_ns):
    for message in io.estimates:
        if message.header.stamp.sec * S + message.header.stamp.nanosec == stamp_ns:
            return message
    raise AssertionError(f"no estimate at {stamp_ns}")


def test_estimates_from_the_service_equal_those_of_the_same_predictions_in_process(probe, processes, tmp_path):
    mesh = pushed_cube()
    model = ElasticModel(mesh.vertices, mesh.tetrahedra, 3000.0, 0.45)
    namespace = "/sb_same"
    overrides = ["window_size:=3", "prediction_timeout:=20.0", "update_time_budget:=60.0"]
    service = ScriptedService(probe, f"{namespace}/sim/factor_graph_state")
    publish_sim_frame(probe)
    node, io = start_node(probe, processes, tmp_path, namespace, *overrides)
    io.mesh.publish(mesh_msg(mesh))
    time.sleep(1.0)  # the node's client matches the service's reply writer (call_service's docstring)
    steps = 5
    clouds = []
    for step in range(1, steps + 1):
        points = top_points(seed=step)
        points[:, 2] -= 6e-4 * step * (0.5 + points[:, 0] / SIDE)
        clouds.append(points)
        service.answers.append(response_for(mesh, model, pressed(mesh, step), step * S))
        io.send(cloud_msg(points, step * S), steps=step)
    counters = io.wait_for(sim_bridge_calls=steps, predictions_received=steps, degraded_steps=0)
    assert counters["sim_bridge_stiffness_rejected"] == "0"

    # The same predictions and stiffness, in-process, through the scheduler the node runs.
    params = load_parameters({"window_size": 3, "prediction_timeout": 20.0, "update_time_budget": 60.0,
                              "points_reliable": True, "prediction_source": "sim_bridge"}, "estimator_node")
    scheduler = EstimationScheduler(mesh, estimator_config(params),
                                    timeouts=SchedulingTimeouts(prediction_timeout=20.0))
    placer = world_frame_inputs(params)
    for step, points in enumerate(clouds, start=1):
        placed, _ = placer.add(FramedInput(CLOUD, step * S, "world", points), 0.0)
        scheduler.add_cloud(step * S, placed[0].data, 0.0, placed[0].viewpoint)
        response = response_for(mesh, model, pressed(mesh, step), step * S)
        positions, stiffness, removed = bridge_state(answer_from_msg(response.fg_state, True), mesh, sim_to_world())
        assert removed is None
        np.testing.assert_allclose(positions, pressed(mesh, step), atol=1e-12)
        scheduler.add_prediction(Prediction(step * S, positions, stiffness=stiffness))
        outcome = scheduler.run(scheduler.next_step(0.0, flush=True))
        live = estimate_at(io, step * S)
        assert not live.degraded
        np.testing.assert_allclose(np.asarray(live.positions).reshape(-1, 3), outcome.result.positions,
                                   rtol=0, atol=1e-8)
    moved = np.abs(outcome.result.positions - mesh.vertices).max()
    assert moved > 1e-3  # the estimates followed the press
    assert_clean_exit(node, node.interrupt())


def test_a_service_that_fails_is_counted_named_and_runs_degraded(probe, processes, tmp_path):
    mesh = pushed_cube()
    model = ElasticModel(mesh.vertices, mesh.tetrahedra, 3000.0, 0.45)
    namespace = "/sb_bad"
    service = ScriptedService(probe, f"{namespace}/sim/factor_graph_state")
    publish_sim_frame(probe)
    node, io = start_node(probe, processes, tmp_path, namespace, "window_size:=3", "prediction_timeout:=1.0",
                          "camera_pose:=[0.025, 0.025, 0.3, 0.0, 0.0, 0.0, 1.0]")  # above the cube
    io.mesh.publish(mesh_msg(mesh))
    time.sleep(1.0)

    def good(step):
        return response_for(mesh, model, pressed(mesh, step), step * S)

    def with_nan(step):
        response = good(step)
        values = np.asarray(response.fg_state.sim_mesh.vertices.data)
        values[7] = np.nan
        response.fg_state.sim_mesh.vertices.data = values.tolist()
        return response

    def too_few_vertices(step):
        return factor_graph_state_response(in_sim_frame(pressed(mesh, step))[:-4], mesh, "sim/world", step * S)

    def indefinite(step):
        stiffness = model.stiffness(None, kind="linear")
        shift = 0.5 * stiffness.diagonal().mean()
        return factor_graph_state_response(in_sim_frame(pressed(mesh, step)), mesh, "sim/world", step * S,
                                           stiffness - shift * scipy.sparse.identity(stiffness.shape[0]))

    def other_mesh(step):
        response = good(step)
        elements = np.asarray(response.fg_state.sim_mesh.elements.data).reshape(-1, 4)
        elements[0] = [0, 1, 2, mesh.vertex_count - 1]
        response.fg_state.sim_mesh.elements.data = elements.reshape(-1).tolist()
        return response

    def slow(step):
        time.sleep(1.6)
        return good(step)

    def stiffness_of_another_size(step):
        response = good(step)
        matrix = response.fg_state.sim_stiffness_mat
        matrix.rows = matrix.cols = 9
        matrix.row_indices, matrix.col_indices, matrix.values = [0, 4, 8], [0, 4, 8], [1.0, 1.0, 1.0]
        return response

    script = [(good, False), (with_nan, True), (too_few_vertices, True), (indefinite, False), (other_mesh, True),
              (slow, True), (stiffness_of_another_size, True), (good, False)]
    expected = {}
    counter_of = {with_nan: "sim_bridge_rejected_malformed", too_few_vertices: "sim_bridge_rejected_mesh",
                  indefinite: "sim_bridge_stiffness_rejected", other_mesh: "sim_bridge_rejected_mesh",
                  slow: "predictions_rejected", stiffness_of_another_size: "sim_bridge_rejected_malformed"}
    for step, (answer, degraded) in enumerate(script, start=1):
        service.answers.append(lambda answer=answer, step=step: answer(step))
        if answer in counter_of:
            expected[counter_of[answer]] = expected.get(counter_of[answer], 0) + 1
        points = top_points(seed=step)
        points[:, 2] -= 6e-4 * step * (0.5 + points[:, 0] / SIDE)
        io.send(cloud_msg(points, step * S), steps=step, **expected)
        estimate = estimate_at(io, step * S)
        assert estimate.degraded == degraded, (step, answer.__name__)
        assert np.isfinite(np.asarray(estimate.positions)).all()
    counters = io.wait_for(sim_bridge_calls=len(script), degraded_steps=5, failed_steps=0, **expected)
    assert counters["sim_bridge_unavailable"] == "0"
    # The last good answer is used as given: the window was not poisoned by the bad ones.
    np.testing.assert_allclose(np.asarray(estimate_at(io, 8 * S).positions).reshape(-1, 3)[mesh.fixed_vertices],
                               mesh.vertices[mesh.fixed_vertices], atol=1e-12)
    assert np.abs(np.asarray(estimate_at(io, 8 * S).positions).reshape(-1, 3) - pressed(mesh, 8)).max() < 2e-3
    messages = [message for message, _ in io.diagnostics]
    assert any("stiffness matrices refused" in message and "indefinite" in message for message in messages), messages
    assert any("ran without a simulator prediction: sim_bridge answer" in message for message in messages), messages
    assert_clean_exit(node, node.interrupt())


def test_a_missing_service_is_named_in_the_diagnostics(probe, processes, tmp_path):
    mesh = pushed_cube()
    namespace = "/sb_none"
    node = Process(tmp_path, "estimator_node", *ros_args(
        namespace, "prediction_source:=sim_bridge", "sim_bridge_service:=/nobody/sim/factor_graph_state",
        "points_reliable:=true", "window_size:=3"))
    processes.append(node)
    io = EstimatorProbe(probe, namespace)
    assert spin_until(probe, lambda: io.cloud.get_subscription_count() == 1)
    io.wait_for(clouds_received=0)
    io.mesh.publish(mesh_msg(mesh))
    for step in range(1, 4):
        io.send(cloud_msg(top_points(seed=step), step * S), steps=step, sim_bridge_unavailable=step,
                degraded_steps=step)
    assert spin_until(probe, lambda: "no sim_bridge service /nobody/sim/factor_graph_state: start the simulator's "
                      "sim_bridge node" in io.diagnostics[-1][0]), io.diagnostics[-1]
    assert_clean_exit(node, node.interrupt())


def test_the_server_executable_answers_with_the_simulator_driven_by_the_tool(probe, processes, tmp_path):
    mesh = pushed_cube()
    path = tmp_path / "cube.vtu"
    save_mesh(mesh, path)
    server = Process(tmp_path, "sim_bridge_server", *ros_args(
        "/sb_server", f"mesh_file:={path}", "world_frame:=sim/world",
        "fixed_box:=[-1.0, -1.0, -0.001, 1.0, 1.0, 0.001]"))
    processes.append(server)
    tool = probe.create_publisher(type(tool_pose_msg([0, 0, 0], 0)), "/sb_server/tool_pose", KEEP)
    client = probe.create_client(FactorGraphState, "/sim/factor_graph_state")
    assert spin_until(probe, lambda: tool.get_subscription_count() == 1)
    top_vertex = int(np.argmin(np.linalg.norm(mesh.vertices - [SIDE / 3, SIDE / 3, SIDE], axis=1)))
    centre = mesh.vertices[top_vertex] + [0.0, 0.0, 0.005]  # the tool sphere (radius 5 mm) on a top vertex
    for step in range(0, 6):
        tool.publish(pose_to_msg(PoseRecord(step * S // 10, "sim/world",
                                            [*(centre - [0, 0, 0.001 * step]), 0.0, 0.0, 0.0, 1.0]), FACTORY))
        spin_until(probe, lambda: False, timeout_s=0.2)
    response = call_service(probe, client, FactorGraphState.Request(compute_stiffness_matrix=True))
    state = response.fg_state
    assert state.sim_mesh.header.frame_id == "sim/world"
    positions = np.asarray(state.sim_mesh.vertices.data).reshape(-1, 3)
    assert positions.shape == mesh.vertices.shape and state.sim_mesh.vertices.size == mesh.vertex_count
    assert positions[top_vertex, 2] < SIDE - 0.002, server.output()  # pressed by the tool (5 mm travel)
    np.testing.assert_array_equal(np.sort(np.asarray(state.sim_mesh.elements.data).reshape(-1, 4), axis=1),
                                  np.sort(mesh.tetrahedra, axis=1))
    matrix = state.sim_stiffness_mat
    assert (matrix.rows, matrix.cols) == (3 * mesh.vertex_count,) * 2
    stiffness = scipy.sparse.coo_matrix((np.asarray(matrix.values, dtype=np.float64),
                                         (np.asarray(matrix.row_indices), np.asarray(matrix.col_indices))),
                                        shape=(matrix.rows, matrix.cols)).toarray()
    np.testing.assert_allclose(stiffness, stiffness.T, rtol=0, atol=1e-6 * np.abs(stiffness).max())
    fixed_dofs = (3 * mesh.fixed_vertices[:, None] + np.arange(3)).reshape(-1)
    assert np.all(np.diag(stiffness)[fixed_dofs] == HELD_DOF_STIFFNESS) and HELD_DOF_STIFFNESS >= FIXED_DIAGONAL
    free = np.setdiff1d(np.arange(3 * mesh.vertex_count), fixed_dofs)
    assert np.diag(stiffness)[free].max() < FIXED_DIAGONAL

    # A cut: the answers keep every slot and list the removed ones; the stiffness is the rest's.
    corner = int(np.flatnonzero(np.all(np.isclose(mesh.vertices, [SIDE, SIDE, SIDE]), axis=1))[0])
    around = np.flatnonzero((mesh.tetrahedra == corner).any(axis=1))
    cuts = probe.create_publisher(UInt32MultiArray, "/sb_server/remove_elements", KEEP)
    assert spin_until(probe, lambda: cuts.get_subscription_count() == 1)
    cuts.publish(UInt32MultiArray(data=around.tolist()))
    assert spin_until(probe, lambda: "cut: " in server.output()), server.output()
    state = call_service(probe, client, FactorGraphState.Request(compute_stiffness_matrix=True)).fg_state
    elements = state.sim_mesh.elements
    np.testing.assert_array_equal(np.asarray(elements.data).reshape(-1, 4), mesh.tetrahedra)
    np.testing.assert_array_equal(np.asarray(elements.invalid_indices), around)
    assert elements.size == len(mesh.tetrahedra) - len(around)
    np.testing.assert_array_equal(np.asarray(state.sim_mesh.vertices.invalid_indices), [corner])
    assert state.sim_mesh.vertices.size == mesh.vertex_count - 1
    rows, values = np.asarray(state.sim_stiffness_mat.row_indices), np.asarray(state.sim_stiffness_mat.values)
    assert np.all(values[np.isin(rows, 3 * corner + np.arange(3))] == 0.0)  # no element left on the corner
    assert_clean_exit(server, server.interrupt())


def test_a_cut_in_the_simulator_is_followed_by_the_published_estimates(probe, processes, tmp_path):
    mesh = pushed_cube()
    corner = int(np.flatnonzero(np.all(np.isclose(mesh.vertices, [SIDE, SIDE, SIDE]), axis=1))[0])
    around = np.flatnonzero((mesh.tetrahedra == corner).any(axis=1))
    keep = np.setdiff1d(np.arange(len(mesh.tetrahedra)), around)
    cut_model = ElasticModel(mesh.vertices, mesh.tetrahedra[keep], 3000.0, 0.45)
    namespace = "/sb_cut"
    service = ScriptedService(probe, f"{namespace}/sim/factor_graph_state")
    publish_sim_frame(probe)
    node, io = start_node(probe, processes, tmp_path, namespace, "window_size:=3", "prediction_timeout:=20.0",
                          "camera_pose:=[0.025, 0.025, 0.3, 0.0, 0.0, 0.0, 1.0]")
    io.mesh.publish(mesh_msg(mesh))
    time.sleep(1.0)

    def cut(step):
        response = response_for(mesh, cut_model, pressed(mesh, step), step * S)
        state = response.fg_state.sim_mesh
        state.elements.invalid_indices, state.elements.size = around.tolist(), len(keep)
        state.vertices.invalid_indices, state.vertices.size = [corner], mesh.vertex_count - 1
        return response

    model = ElasticModel(mesh.vertices, mesh.tetrahedra, 3000.0, 0.45)
    for step in range(1, 5):
        service.answers.append(cut(step) if step >= 3 else response_for(mesh, model, pressed(mesh, step), step * S))
        points = top_points(seed=step)
        points[:, 2] -= 6e-4 * step * (0.5 + points[:, 0] / SIDE)
        points = points[np.linalg.norm(points[:, :2] - [SIDE, SIDE], axis=1) > 0.02]  # none on the removed corner
        io.send(cloud_msg(points, step * S), steps=step)
    io.wait_for(steps=4, degraded_steps=0, sim_bridge_rejected_mesh=0, sim_bridge_rejected_malformed=0)
    for step in range(1, 5):
        estimate = estimate_at(io, step * S)
        positions = np.asarray(estimate.positions).reshape(-1, 3)
        tetrahedra = np.asarray(estimate.tetrahedra, dtype=np.int64).reshape(-1, 4)
        assert np.isfinite(positions).all()
        if step < 3:
            assert len(tetrahedra) == len(mesh.tetrahedra) and len(estimate.removed_elements) == 0
            continue
        np.testing.assert_array_equal(np.asarray(estimate.removed_elements), around)
        np.testing.assert_array_equal(np.asarray(estimate.invalid_vertices), [corner])
        np.testing.assert_array_equal(tetrahedra, mesh.tetrahedra[keep])
        corners = positions[tetrahedra]
        volumes = np.einsum("ij,ij->i", np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]),
                            corners[:, 3] - corners[:, 0])
        assert volumes.min() > 0.0
    assert_clean_exit(node, node.interrupt())


class ParameterReads(dict):
    """A node's parameter values that note each name read."""

    def __init__(self, values):
        super().__init__(values)
        self.read = set()

    def __getitem__(self, name):
        self.read.add(name)
        return super().__getitem__(name)


def test_the_server_reads_every_parameter_it_declares(probe, tmp_path, monkeypatch):
    declared, declare = [], sim_bridge_server.declare_parameters

    def noting_reads(node, node_name):
        declared.append(ParameterReads(declare(node, node_name)))
        return declared[-1]

    monkeypatch.setattr(sim_bridge_server, "declare_parameters", noting_reads)
    save_mesh(pushed_cube(), tmp_path / "cube.vtu")
    node = sim_bridge_server.SimBridgeServer(
        namespace="/sb_reads", parameter_overrides=[Parameter("mesh_file", value=str(tmp_path / "cube.vtu"))])
    try:
        (params,) = declared
        assert set(params) == {parameter.name for parameter in node_parameters("sim_bridge_server")}
        assert params.read == set(params), set(params) - params.read
    finally:
        node.destroy_node()


def grasping_server(tmp_path, namespace):
    """sim_bridge_server in this process on the pushed cube, grasping the top vertex nearest
    (SIDE/3, SIDE/3, SIDE): (node, mesh, the grasped vertex)."""
    mesh = pushed_cube()
    save_mesh(mesh, tmp_path / "cube.vtu")
    grasped = int(np.argmin(np.linalg.norm(mesh.vertices - [SIDE / 3, SIDE / 3, SIDE], axis=1)))
    node = sim_bridge_server.SimBridgeServer(namespace=namespace, parameter_overrides=[
        Parameter("mesh_file", value=str(tmp_path / "cube.vtu")), Parameter("tool_mode", value="grasp"),
        Parameter("grasped_vertices", value=[grasped])])
    return node, mesh, grasped


def test_a_repeated_or_earlier_stamp_keeps_what_the_tool_grasps(probe, tmp_path):
    """A pose stamped at or before the previous moves the tool without a step and keeps the
    grasp's reference: the grasped vertex goes on following the tool (a repeat is not counted,
    a step back is)."""
    node, mesh, grasped = grasping_server(tmp_path, "/sb_repeat")
    try:
        start = mesh.vertices[grasped] + [0.0, 0.0, 0.002]
        for step in range(4):
            node._on_tool_pose(tool_pose_msg(start + [0.0, 0.0, 0.001 * step], step * S // 20))
        node._on_tool_pose(tool_pose_msg(start + [0.0, 0.0, 0.003], 3 * S // 20))  # the same pose and stamp again
        node._on_tool_pose(tool_pose_msg(start + [0.0, 0.0, 0.004], 4 * S // 20))
        assert node._state[grasped] - mesh.vertices[grasped] == pytest.approx([0.0, 0.0, 0.004], abs=1e-9)
        node._on_tool_pose(tool_pose_msg(start + [0.0, 0.0, 0.004], 2 * S // 20))  # a step back: said, not simulated
        node._on_tool_pose(tool_pose_msg(start + [0.0, 0.0, 0.005], 5 * S // 20))
        assert node._state[grasped] - mesh.vertices[grasped] == pytest.approx([0.0, 0.0, 0.005], abs=1e-9)
        counters = node.reports.counters
        assert (counters.tool_poses_received, counters.tool_poses_stamped_back, counters.steps_failed) == (8, 1, 0)
    finally:
        node.destroy_node()


def test_the_server_refuses_a_cut_of_every_grasped_vertex_and_a_degenerate_quaternion(probe, tmp_path):
    """Two inputs the simulator cannot take, each counted with its reason, the server unchanged."""
    node, mesh, grasped = grasping_server(tmp_path, "/sb_refuses")
    try:
        node._on_remove_elements(UInt32MultiArray(data=np.flatnonzero((mesh.tetrahedra == grasped).any(axis=1)).tolist()))
        assert node.reports.counters.cuts_rejected == 1
        assert node.reports.health.last_problem == ('cut refused: tool_mode="grasp" needs a non-empty grasped_vertices '
                                                    'set')
        assert node._mesh.tetrahedron_count == mesh.tetrahedron_count
        tiny = tool_pose_msg(mesh.vertices[grasped], 0)
        tiny.pose.orientation.w = 1e-12
        node._on_tool_pose(tiny)
        assert node.reports.counters.tool_poses_rejected_malformed == 1
        assert node.reports.health.last_problem == "tool_pose rejected: pose quaternion has zero norm"
        assert node._last_stamp_ns is None  # the tool was not placed
    finally:
        node.destroy_node()


@pytest.fixture
def start_server(probe, processes, tmp_path):
    """start_server(namespace, *parameters): sim_bridge_server in `namespace`, its service there
    too; the process and its /diagnostics reports (level, message, counters), appended as they
    arrive. The probe's subscriptions for them end with the test."""
    subscriptions = []

    def start(namespace, *parameters):
        reports = []

        def on_diagnostics(msg):
            reports.extend((status.level, status.message, {kv.key: kv.value for kv in status.values})
                           for status in msg.status if status.name == f"{namespace}/sim_bridge_server: sim_bridge")

        subscriptions.append(probe.create_subscription(DiagnosticArray, "/diagnostics", on_diagnostics, KEEP))
        server = Process(tmp_path, "sim_bridge_server", *ros_args(namespace, *parameters),
                         "-r", f"{SERVICE}:={namespace}{SERVICE}")
        processes.append(server)
        assert spin_until(probe, lambda: reports), server.output()
        return server, reports

    yield start
    for subscription in subscriptions:
        probe.destroy_subscription(subscription)


def first_report(probe, reports, **expected):
    """The first report whose counters have the `expected` values (spinning until it comes)."""
    def found():
        return next((report for report in reports
                     if all(report[2].get(key) == str(value) for key, value in expected.items())), None)

    assert spin_until(probe, lambda: found() is not None), f"expected {expected}, got {reports[-1:]}"
    return found()


def test_the_server_counts_and_names_each_tool_pose_it_rejects(probe, start_server):
    mesh = pushed_cube()
    namespace = "/sb_rejects"
    server, reports = start_server(namespace)
    tool = probe.create_publisher(PoseStamped, f"{namespace}/tool_pose", KEEP)
    meshes = probe.create_publisher(TetraMesh, f"{namespace}/initial_mesh", LATCHED)
    assert spin_until(probe, lambda: tool.get_subscription_count() == 1 and meshes.get_subscription_count() == 1)
    assert reports[-1][:2] == (DiagnosticStatus.WARN, "waiting for initial_mesh")
    above = [SIDE / 2, SIDE / 2, SIDE + 0.01]  # clear of the cube: the tool touches nothing

    tool.publish(tool_pose_msg(above, 1 * S))
    level, message, _ = first_report(probe, reports, tool_poses_rejected_before_mesh=1)
    assert (level, message) == (DiagnosticStatus.WARN, "waiting for initial_mesh; 1 tool poses ignored before it")
    in_map = mesh_msg(mesh)
    in_map.header.frame_id = "map"
    meshes.publish(in_map)
    level, message, _ = first_report(probe, reports, initial_meshes_rejected=1)
    assert (level, message) == (DiagnosticStatus.WARN, "waiting for initial_mesh; 1 tool poses ignored before it; "
                                "1 initial_mesh rejected, the last: initial_mesh in frame 'map', expected 'world': "
                                "rejected")
    meshes.publish(mesh_msg(mesh))
    assert spin_until(probe, lambda: reports[-1][:2] == (DiagnosticStatus.OK, "simulating")), reports[-1]

    zero_quaternion = tool_pose_msg(above, 2 * S)
    zero_quaternion.pose.orientation.w = 0.0
    tool.publish(zero_quaternion)
    level, message, _ = first_report(probe, reports, tool_poses_rejected_malformed=1)
    assert (level, message) == (DiagnosticStatus.WARN, "1 tool poses rejected since the last report; the last: "
                                "tool_pose rejected: pose quaternion is zero")
    in_camera = tool_pose_msg(above, 3 * S)
    in_camera.header.frame_id = "camera"
    tool.publish(in_camera)
    level, message, _ = first_report(probe, reports, tool_poses_rejected_frame=1)
    frame_warning = ("tool_pose in frame 'camera' rejected: this server takes tool poses in its world_frame 'world' "
                     "only; publish them there, or set world_frame")
    assert (level, message) == (DiagnosticStatus.WARN, f"1 tool poses rejected since the last report; the last: "
                                f"{frame_warning}")
    tool.publish(tool_pose_msg(above, 4 * S))
    _, _, counters = first_report(probe, reports, tool_poses_received=4)
    assert spin_until(probe, lambda: reports[-1][:2] == (DiagnosticStatus.OK, "simulating")), reports[-1]
    tool.publish(tool_pose_msg(above, 4 * S))  # a repeated stamp: not a problem
    tool.publish(tool_pose_msg(above, 4 * S - S // 2))  # back by half a second: taken, and said
    level, message, counters = first_report(probe, reports, tool_poses_stamped_back=1)
    back_warning = "tool_pose stamped 0.500 s before the previous one: the tool is put there without a simulation step"
    assert (level, message) == (DiagnosticStatus.WARN, f"1 tool poses stamped back since the last report; the last: "
                                f"{back_warning}")
    assert {key: counters[key] for key in ("tool_poses_received", "tool_poses_rejected_before_mesh",
                                           "tool_poses_rejected_malformed", "tool_poses_rejected_frame",
                                           "tool_poses_rejected", "tool_poses_stamped_back", "steps_failed",
                                           "cuts_rejected")} == {
        "tool_poses_received": "6", "tool_poses_rejected_before_mesh": "1", "tool_poses_rejected_malformed": "1",
        "tool_poses_rejected_frame": "1", "tool_poses_rejected": "3", "tool_poses_stamped_back": "1",
        "steps_failed": "0", "cuts_rejected": "0"}
    assert spin_until(probe, lambda: reports[-1][:2] == (DiagnosticStatus.OK, "simulating")), reports[-1]
    for warning in ("tool_pose before the mesh ignored: set mesh_file or publish initial_mesh",
                    "tool_pose rejected: pose quaternion is zero", frame_warning, back_warning):
        assert warning in server.output(), warning

    # A best-effort publisher cannot reach the reliable subscription (tool_pose_reliable's default):
    # an ERROR, with the fix.
    best_effort = probe.create_publisher(PoseStamped, f"{namespace}/tool_pose",
                                         QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT))
    assert spin_until(probe, lambda: reports[-1][0] == DiagnosticStatus.ERROR), reports[-1]
    assert reports[-1][1].startswith(f"{namespace}/tool_pose from /test_probe never arrives: it publishes best effort")
    assert reports[-1][1].endswith("publish it reliable, or set tool_pose_reliable:=false")
    probe.destroy_publisher(best_effort)
    assert_clean_exit(server, server.interrupt())


def test_the_server_grasps_with_the_poses_of_a_best_effort_publisher(probe, start_server, tmp_path):
    mesh = pushed_cube()
    save_mesh(mesh, tmp_path / "cube.vtu")
    grasped = int(np.argmin(np.linalg.norm(mesh.vertices - [SIDE / 3, SIDE / 3, SIDE], axis=1)))
    namespace = "/sb_grasp"
    server, reports = start_server(namespace, f"mesh_file:={tmp_path / 'cube.vtu'}", "tool_mode:=grasp",
                                   f"grasped_vertices:=[{grasped}]", "tool_pose_reliable:=false")
    tool = probe.create_publisher(PoseStamped, f"{namespace}/tool_pose",
                                  QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT))
    client = probe.create_client(FactorGraphState, f"{namespace}{SERVICE}")
    assert spin_until(probe, lambda: tool.get_subscription_count() == 1), server.output()
    start = mesh.vertices[grasped] + [0.0, 0.0, 0.002]  # the tool just above the vertex it holds

    def lifted_by(height):
        """Whether the server's state has the grasped vertex `height` above its rest position."""
        answer = call_service(probe, client, FactorGraphState.Request()).fg_state.sim_mesh.vertices.data
        return abs(np.asarray(answer).reshape(-1, 3)[grasped, 2] - mesh.vertices[grasped, 2] - height) < 1e-9

    def received():
        return int(reports[-1][2]["tool_poses_received"]) if reports else 0

    # Best effort may lose a pose, or the server's reader may match the probe's writer late: each
    # pose is published again until the server shows it (the grasp's reference until a report
    # counts it, each lift until the state has it). A copy that arrives late is stamped at or
    # before the newest pose: it places the tool without a step and keeps the grasp's reference.
    for _ in range(20):
        tool.publish(tool_pose_msg(start, 0))
        if spin_until(probe, lambda: received() >= 1, timeout_s=1.5):
            break
    assert received() >= 1, server.output()
    for step in range(1, 4):
        for _ in range(20):
            tool.publish(tool_pose_msg(start + [0.0, 0.0, 0.001 * step], step * S // 20))
            if spin_until(probe, lambda: lifted_by(0.001 * step), timeout_s=0.5):
                break
        assert lifted_by(0.001 * step), (step, server.output())
    positions = np.asarray(call_service(probe, client, FactorGraphState.Request()).fg_state.sim_mesh.vertices.data)
    positions = positions.reshape(-1, 3)
    assert spin_until(probe, lambda: received() >= 4), reports[-1]
    assert {key: reports[-1][2][key] for key in ("tool_poses_rejected", "steps_failed")} == {
        "tool_poses_rejected": "0", "steps_failed": "0"}
    # The grasped vertex follows the tool rigidly (3 mm up); the tissue around it follows; the boundary stays.
    np.testing.assert_allclose(positions[grasped], mesh.vertices[grasped] + [0.0, 0.0, 0.003], rtol=0, atol=1e-12)
    free = np.setdiff1d(np.arange(mesh.vertex_count), [grasped, *mesh.fixed_vertices])
    assert np.abs(positions[free] - mesh.vertices[free]).max() > 1e-4
    np.testing.assert_array_equal(positions[mesh.fixed_vertices], mesh.vertices[mesh.fixed_vertices])
    assert_clean_exit(server, server.interrupt())
