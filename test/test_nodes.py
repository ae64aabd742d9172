"""The node executables over real DDS (separate processes, loopback only; see conftest.py).

Start-up with parameters files and overrides, clean shutdown on SIGINT, the simulator's
prediction semantics, the estimator's robustness to bad input (diagnostics counters, never a
NaN), degraded steps without the simulator and recovery, and the bag player.
"""
import ast
import os
import py_compile
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped, Vector3Stamped
from rcl_interfaces.srv import GetParameters
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import Header
from visualization_msgs.msg import MarkerArray

from meshfg_msgs.msg import EstimatorStatus, PredictionFailure, TetraMesh
from meshfg_ros import blas
from meshfg_ros.synthetic.meshing import cube_mesh
from meshfg_ros.parameters import load_parameters, simulator_config
from meshfg_ros.core.physics.body_load import BodyLoadEstimate
from meshfg_ros.core.physics.model_fit import learn
from meshfg_ros.core.physics.poisson_ratio import PoissonRatioEstimate
from meshfg_ros.core.physics.simulator import ElasticSimulator
from meshfg_ros.io.messages import (
    MeshState,
    MessageValidationError,
    PointCloudRecord,
    PoseRecord,
    RclpyMessageFactory,
    RosbagsMessageFactory,
    header_msg,
    mesh_state_to_msg,
    pose_to_msg,
    stamp_ns_from_msg,
)
from meshfg_ros.io.pointcloud import decode_pointcloud2, encode_xyz
from meshfg_ros.io.recording import RecordingWriter
from meshfg_ros.nodes.estimator_node import PREDICTION_QOS
from meshfg_ros.markers import MAX_ELLIPSOIDS, NAMESPACE_ELLIPSOIDS, NAMESPACE_LEGEND
from meshfg_ros.nodes.ros_conversions import (
    REQUEST_QOS,
    MeshMessages,
    position_covariance_from_msg,
    position_std_from_msg,
    rclpy_message,
)

REPOSITORY = Path(__file__).resolve().parents[1]
CONFIG = REPOSITORY / "config" / "meshfg.yaml"
BIN = Path(sys.executable).parent
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
KEEP = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
FACTORY = RclpyMessageFactory()
S = 1_000_000_000  # ns per second
SIDE = 0.05


# ---------------------------------------------------------------------------- helpers
@pytest.fixture(scope="module")
def probe():
    """A node of the test process that talks to the nodes under test."""
    rclpy.init()
    node = rclpy.create_node("test_probe")
    yield node
    node.destroy_node()
    rclpy.shutdown()


def spin_until(node, condition, timeout_s=30.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            return False
        rclpy.spin_once(node, timeout_sec=0.05)
    return True


class Process:
    """A node executable with its output in a log file."""

    def __init__(self, tmp_path: Path, name: str, *args: str):
        self.log = tmp_path / f"{name}-{time.monotonic_ns()}.log"
        with open(self.log, "w") as stream:
            self.popen = subprocess.Popen([str(BIN / name), *args], stdout=stream, stderr=subprocess.STDOUT,
                                          cwd=tmp_path, env=dict(os.environ))

    def output(self) -> str:
        return self.log.read_text()

    def interrupt(self, timeout_s=20.0) -> int:
        """SIGINT (Ctrl-C); the exit code."""
        self.popen.send_signal(signal.SIGINT)
        return self.popen.wait(timeout=timeout_s)

    def alive(self) -> bool:
        return self.popen.poll() is None

    def kill(self) -> None:
        if self.alive():
            self.popen.kill()
            self.popen.wait()


@pytest.fixture
def processes():
    started: list[Process] = []
    yield started
    for process in started:
        process.kill()


def assert_clean_exit(process: Process, code: int) -> None:
    output = process.output()
    assert code == 0, output
    for sign_of_an_unclean_stop in ("Traceback", "never retrieved", "never awaited"):
        assert sign_of_an_unclean_stop not in output, output


def ros_args(namespace: str, *parameters: str, params_file: Path | None = None) -> list[str]:
    """--ros-args with the namespace, a parameters file, then `-p` overrides (the last one wins)."""
    args = ["--ros-args", "-r", f"__ns:={namespace}"]
    if params_file is not None:
        args += ["--params-file", str(params_file)]
    for parameter in parameters:
        args += ["-p", parameter]
    return args


def pushed_cube():
    mesh = cube_mesh(side=SIDE, divisions=3)
    return mesh.with_fixed(np.flatnonzero(np.isclose(mesh.vertices[:, 2], 0.0)))


def mesh_msg(mesh, stamp_ns=0, positions=None):
    positions = mesh.vertices if positions is None else positions
    return mesh_state_to_msg(MeshState(stamp_ns, "world", 0, positions, mesh.tetrahedra, mesh.surface_triangles,
                                       mesh.fixed_vertices), FACTORY)


def estimate_msg(mesh, stamp_ns, positions):
    """An estimate with its posterior std (float32, as sent: 0 on the fixed vertices, 1 mm
    elsewhere), which weighs what the simulator learns from it; returns (message, std)."""
    std = np.where(np.isin(np.arange(mesh.vertex_count), mesh.fixed_vertices), 0.0, 1e-3).astype(np.float32)
    msg = mesh_msg(mesh, stamp_ns, positions)
    msg.position_std = std
    return msg, std


def top_points(count=40, seed=0):
    """Points on the cube's top face with the default measurement_sigma's noise (1 mm) in depth:
    noise-free points would spread far below measurement_sigma, which the estimator reports."""
    rng = np.random.default_rng(seed)
    return np.column_stack([rng.uniform(0.005, SIDE - 0.005, (count, 2)), SIDE + rng.normal(scale=1e-3, size=count)])


def cloud_msg(points, stamp_ns, frame="world"):
    return encode_xyz(points, frame, stamp_ns, FACTORY)


def tool_pose_msg(position, stamp_ns):
    return pose_to_msg(PoseRecord(stamp_ns, "world", [*position, 0.0, 0.0, 0.0, 1.0]), FACTORY)


def call_service(probe, client, request, timeout_s=30.0, resend_s=5.0):
    """The response to `request` (an idempotent one: the parameter services'), sent again every
    `resend_s` without an answer. Fast DDS drops a response when the client's response reader
    has not been matched within 100 ms of the request (ros2/rmw_fastrtps#390, #467), which
    happens on a loaded machine although wait_for_service returned: the request went out, the
    answer never comes."""
    assert client.wait_for_service(timeout_sec=timeout_s), f"no service {client.srv_name}"
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        future = client.call_async(request)
        if spin_until(probe, future.done, timeout_s=min(resend_s, deadline - time.monotonic())):
            return future.result()
        client.remove_pending_request(future)
    raise AssertionError(f"no response from {client.srv_name} in {timeout_s:g} s")


def get_parameters(probe, node_name: str, names: list[str]) -> dict:
    client = probe.create_client(GetParameters, f"{node_name}/get_parameters")
    try:
        values = call_service(probe, client, GetParameters.Request(names=names)).values
        assert len(values) == len(names), f"{node_name} has not declared all of {names}"
        return {name: rclpy.parameter.parameter_value_to_python(value) for name, value in zip(names, values)}
    finally:
        probe.destroy_client(client)


def simulation_reports(probe, namespace: str) -> list:
    """(message, counters) of each /diagnostics status of the simulation node in `namespace`,
    appended as they arrive."""
    reports = []

    def on_diagnostics(msg):
        reports.extend((status.message, {kv.key: kv.value for kv in status.values})
                       for status in msg.status if status.name == f"{namespace}/simulation_node: simulation")

    probe.create_subscription(DiagnosticArray, "/diagnostics", on_diagnostics, KEEP)
    return reports


# ---------------------------------------------------------------------------- start, parameters, stop
@pytest.mark.slow
def test_executables_read_parameters_and_stop_cleanly_on_sigint(probe, processes, tmp_path):
    separate = [Process(tmp_path, "simulation_node", *ros_args("/p_sep", "youngs_modulus:=4500.0", params_file=CONFIG)),
                Process(tmp_path, "estimator_node", *ros_args("/p_sep", "window_size:=7", params_file=CONFIG))]
    stack = Process(tmp_path, "meshfg_stack", *ros_args("/p_stack", "tool_radius:=0.002", params_file=CONFIG))
    processes += [*separate, stack]
    # Relative topics: the namespace applies. (Parameter services answer before the parameters are
    # declared; the topics exist after.)
    assert spin_until(probe, lambda: probe.count_subscribers("/p_sep/points") == 1
                      and probe.count_publishers("/p_sep/predicted_mesh") == 1
                      and probe.count_publishers("/p_stack/estimated_mesh") == 1)
    simulation = get_parameters(probe, "/p_sep/simulation_node", ["youngs_modulus", "simulator", "grasped_vertices"])
    assert simulation == {"youngs_modulus": 4500.0, "simulator": "vbd", "grasped_vertices": []}
    estimator = get_parameters(probe, "/p_sep/estimator_node", ["window_size", "measurement_sigma", "camera_pose"])
    assert estimator["window_size"] == 7 and estimator["measurement_sigma"] == 0.001
    assert list(estimator["camera_pose"]) == [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]
    assert get_parameters(probe, "/p_stack/simulation_node", ["tool_radius"]) == {"tool_radius": 0.002}
    assert get_parameters(probe, "/p_stack/estimator_node", ["world_frame"]) == {"world_frame": "world"}
    for process in [*separate, stack]:
        assert_clean_exit(process, process.interrupt())


@pytest.mark.slow
def test_invalid_parameters_stop_the_node_with_a_message(processes, tmp_path):
    window = Process(tmp_path, "estimator_node", *ros_args("/bad", "window_size:=0"))
    grasp = Process(tmp_path, "simulation_node", *ros_args("/bad", "tool_mode:=grasp"))
    processes += [window, grasp]
    assert window.popen.wait(timeout=60) == 1
    assert "window_size" in window.output() and "Traceback" not in window.output()
    assert grasp.popen.wait(timeout=60) == 1
    assert "simulation_node: invalid parameters: tool_mode 'grasp' needs grasped_vertices" in grasp.output()


# ---------------------------------------------------------------------------- simulation node
class SimulationProbe:
    """Publishes the simulation node's inputs and collects its predictions and failures."""

    def __init__(self, probe, namespace):
        self.node = probe
        self.predictions, self.failures, self.loads = [], [], []
        self._subscriptions = [
            probe.create_subscription(TetraMesh, f"{namespace}/predicted_mesh", self.predictions.append, KEEP),
            probe.create_subscription(PredictionFailure, f"{namespace}/prediction_failed", self.failures.append,
                                      KEEP),
            probe.create_subscription(Vector3Stamped, f"{namespace}/body_acceleration", self.loads.append, KEEP)]
        self.mesh = probe.create_publisher(TetraMesh, f"{namespace}/initial_mesh", LATCHED)
        self.estimate = probe.create_publisher(TetraMesh, f"{namespace}/estimated_mesh", LATCHED)
        self.pose = probe.create_publisher(PoseStamped, f"{namespace}/tool_pose", KEEP)
        self.request = probe.create_publisher(Header, f"{namespace}/prediction_request", KEEP)

    def wait_connected(self) -> None:
        """Until the node's subscriptions and publishers (but initial_mesh's) match the probe's."""
        assert spin_until(self.node, lambda: all(
            publisher.get_subscription_count() == 1 for publisher in (self.estimate, self.pose, self.request))
            and all(subscription.get_publisher_count() == 1 for subscription in self._subscriptions))


@pytest.mark.slow
def test_simulation_node_predicts_from_the_latest_estimate(probe, processes, tmp_path):
    mesh = pushed_cube()
    params = load_parameters({"tool_radius": 0.01, "estimate_timeout": 1.0})
    node = Process(tmp_path, "simulation_node",
                   *ros_args("/sim", "tool_radius:=0.01", "estimate_timeout:=1.0"))
    processes.append(node)
    io = SimulationProbe(probe, "/sim")
    predictions, failures = io.predictions, io.failures
    mesh_publisher, estimate_publisher, pose_publisher, request_publisher = io.mesh, io.estimate, io.pose, io.request
    io.wait_connected()
    mesh_publisher.publish(mesh_msg(mesh))
    centre = np.array([SIDE / 2, SIDE / 2, SIDE + 0.011])
    poses = [centre - [0.0, 0.0, 1e-3 * k] for k in range(5)]

    def send_pose(k, stamp_ns):
        pose_publisher.publish(tool_pose_msg(poses[k], stamp_ns))

    def request(stamp_ns):  # what the estimator node sends for each cloud it accepts
        request_publisher.publish(header_msg(stamp_ns, "world", FACTORY))

    def received(count):
        assert spin_until(probe, lambda: len(predictions) >= count), f"{len(predictions)} predictions"
        return predictions[count - 1]

    send_pose(0, 1 * S)  # the first pose only starts the simulation
    send_pose(1, 2 * S)
    request(2 * S)
    first = received(1)
    estimate = np.asarray(first.positions).reshape(-1, 3) + [1e-4, 0.0, 0.0]
    with_std, std = estimate_msg(mesh, 2 * S, estimate)
    estimate_publisher.publish(with_std)
    send_pose(2, 3 * S)
    request(3 * S)  # predicted from the estimate of 2 s
    received(2)
    send_pose(3, 4 * S)
    send_pose(3, 4 * S)  # repeated stamp: dropped
    estimate_publisher.publish(mesh_msg(mesh, 10 * S, estimate + 1e-3))  # not a predicted stamp: ignored
    request(4 * S)  # no estimate of 3 s: after estimate_timeout, from the state of 2 s
    received(3)
    send_pose(4, 5 * S)
    request(5 * S)
    received(4)
    # An estimate with the top face pushed through the fixed bottom: the next request cannot be
    # predicted, and the node says so on prediction_failed (stamped like the request) instead.
    crushed = mesh.vertices.copy()
    crushed[np.isclose(crushed[:, 2], SIDE), 2] = -SIDE
    estimate_publisher.publish(mesh_msg(mesh, 5 * S, crushed))
    send_pose(4, 6 * S)
    request(6 * S)
    assert spin_until(probe, lambda: len(failures) == 1)
    assert stamp_ns_from_msg(failures[0].header.stamp) == 6 * S and failures[0].header.frame_id == "world"
    assert "inverted" in failures[0].reason
    # A looped recording: the stamps jump back, the simulation restarts from the initial mesh.
    send_pose(0, 1 * S)
    send_pose(1, 2 * S)
    request(2 * S)
    received(5)
    # Tool poses need not share the clouds' stamps: a request between two poses is predicted
    # with the pose interpolated at its stamp.
    estimate_publisher.publish(with_std)
    send_pose(2, 3 * S)
    request(2 * S + S // 2)
    received(6)
    spin_until(probe, lambda: len(predictions) > 6, timeout_s=1.5)

    def pose(position):
        return np.concatenate([position, [0.0, 0.0, 0.0, 1.0]])

    # The estimate's correction of its prediction teaches the body load and the Poisson ratio of
    # the later predictions (core/physics/model_fit.py); the restarted timeline forgets them and learns
    # them again from the same estimate.
    simulator = ElasticSimulator(mesh, simulator_config(params))
    body_load, poisson_ratio = BodyLoadEstimate(simulator), PoissonRatioEstimate(simulator)
    simulator.reset(pose(poses[0]))
    expected = [simulator.predict(mesh.vertices, pose(poses[1]), 1.0)]
    learn(mesh, body_load, poisson_ratio, expected[0], estimate, std.astype(float))
    learnt = body_load.acceleration
    for k in (2, 3, 4):
        expected.append(simulator.predict(estimate, pose(poses[k]), 1.0))
    expected.append(expected[0])
    body_load.reset()
    poisson_ratio.reset()
    simulator.reset(pose(poses[0]))
    learn(mesh, body_load, poisson_ratio, simulator.predict(mesh.vertices, pose(poses[1]), 1.0), estimate,
          std.astype(float))
    expected.append(simulator.predict(estimate, pose(0.5 * (poses[1] + poses[2])), 0.5))
    assert [stamp_ns_from_msg(p.header.stamp) for p in predictions] == [2 * S, 3 * S, 4 * S, 5 * S, 2 * S,
                                                                           2 * S + S // 2]
    assert all(p.header.frame_id == "world" for p in predictions)
    for message, positions in zip(predictions, expected, strict=True):
        np.testing.assert_allclose(np.asarray(message.positions).reshape(-1, 3), positions, rtol=0, atol=1e-12)
    assert not np.array_equal(expected[1], expected[0])  # the tool did push the cube
    # After each estimate it took: the load learnt so far (the crushed estimate's own is forgotten
    # when its prediction fails; the looped recording restarts from none).
    loads = [(stamp_ns_from_msg(m.header.stamp), [m.vector.x, m.vector.y, m.vector.z]) for m in io.loads]
    assert [stamp for stamp, _ in loads] == [2 * S, 5 * S, 2 * S]
    np.testing.assert_allclose(loads[0][1], learnt, rtol=0, atol=1e-12)
    np.testing.assert_allclose(loads[2][1], learnt, rtol=0, atol=1e-12)
    assert np.linalg.norm(learnt) > 0.0
    assert node.alive()
    assert_clean_exit(node, node.interrupt())


def test_simulation_node_predicts_a_stalled_streams_stamps_then_learns_from_their_estimates(probe, processes, tmp_path):
    """A request no tool pose covers fails (a stall); once poses come, the node publishes the
    stalled stamp's catch-up prediction before the new one, and learns the load from that
    stamp's estimate when it comes on catch_up_estimate (the estimator's cloud run again)."""
    mesh = pushed_cube()
    node = Process(tmp_path, "simulation_node", *ros_args("/catch", "tool_radius:=0.01"))
    processes.append(node)
    io = SimulationProbe(probe, "/catch")
    again = probe.create_publisher(TetraMesh, "/catch/catch_up_estimate", KEEP)
    reports = simulation_reports(probe, "/catch")
    io.wait_connected()
    assert spin_until(probe, lambda: again.get_subscription_count() == 1)
    io.mesh.publish(mesh_msg(mesh))
    centre = np.array([SIDE / 2, SIDE / 2, SIDE + 0.011])
    io.pose.publish(tool_pose_msg(centre, 1 * S))
    io.request.publish(header_msg(2 * S, "world", FACTORY))  # no pose within the horizon
    assert spin_until(probe, lambda: len(io.failures) == 1)
    degraded, std = estimate_msg(mesh, 2 * S, mesh.vertices)
    degraded.degraded = True
    io.estimate.publish(degraded)
    io.pose.publish(tool_pose_msg(centre - [0.0, 0.0, 2e-3], 3 * S))
    io.request.publish(header_msg(3 * S, "world", FACTORY))
    assert spin_until(probe, lambda: len(io.predictions) == 2)
    assert [stamp_ns_from_msg(m.header.stamp) for m in io.predictions] == [2 * S, 3 * S]
    caught_up = np.asarray(io.predictions[0].positions).reshape(-1, 3)
    sank = caught_up.copy()
    sank[std > 0, 2] -= 2e-4  # the tissue sank further than the catch-up predicted
    estimate, _ = estimate_msg(mesh, 2 * S, sank)
    again.publish(estimate)
    assert spin_until(probe, lambda: reports and reports[-1][1].get("catch_up_estimates_learnt") == "1")
    counters = reports[-1][1]
    assert counters["catch_up_predictions"] == "1" and float(counters["body_acceleration_z"]) < -1e-3
    assert node.alive()
    assert_clean_exit(node, node.interrupt())


@pytest.mark.slow
def test_simulation_node_answers_the_requests_and_poses_that_came_before_its_mesh(probe, processes, tmp_path):
    """Tool poses, two requests and the estimate answering the first, all before the mesh: once
    it comes, both requests are predicted, the second from that estimate, at once (handed on out
    of arrival order, the estimate would come before its request and be ignored, and the second
    request would wait estimate_timeout, here longer than the test waits)."""
    mesh = pushed_cube()
    node = Process(tmp_path, "simulation_node", *ros_args("/simearly", "tool_radius:=0.01", "estimate_timeout:=60.0"))
    processes.append(node)
    io, reports = SimulationProbe(probe, "/simearly"), simulation_reports(probe, "/simearly")
    predictions = io.predictions
    mesh_publisher, estimate_publisher, pose_publisher, request_publisher = io.mesh, io.estimate, io.pose, io.request
    io.wait_connected()
    assert spin_until(probe, lambda: reports)
    centre = np.array([SIDE / 3, SIDE / 3, SIDE + 0.011])  # above a vertex of the top face
    poses = [np.concatenate([centre - [0.0, 0.0, depth], [0.0, 0.0, 0.0, 1.0]]) for depth in (0.0, 2e-3, 3e-3)]
    estimate = mesh.vertices + [1e-4, 0.0, 0.0]
    pose_publisher.publish(tool_pose_msg(poses[0][:3], 1 * S))
    pose_publisher.publish(tool_pose_msg(poses[1][:3], 2 * S))
    request_publisher.publish(header_msg(2 * S, "world", FACTORY))
    assert spin_until(probe, lambda: reports[-1][1].get("inputs_held_before_mesh") == "3"), reports[-1]
    with_std, std = estimate_msg(mesh, 2 * S, estimate)
    estimate_publisher.publish(with_std)  # the estimator ran that step without one
    pose_publisher.publish(tool_pose_msg(poses[2][:3], 3 * S))
    request_publisher.publish(header_msg(3 * S, "world", FACTORY))
    assert spin_until(probe, lambda: reports[-1][1].get("inputs_held_before_mesh") == "6"), reports[-1]
    assert reports[-1][0] == "waiting for initial_mesh; 6 inputs held until it comes"
    assert not predictions
    mesh_publisher.publish(mesh_msg(mesh))
    assert spin_until(probe, lambda: len(predictions) == 2), node.output()
    simulator = ElasticSimulator(mesh, simulator_config(load_parameters({"tool_radius": 0.01})))
    simulator.reset(poses[0])
    expected = [simulator.predict(mesh.vertices, poses[1], 1.0)]
    # the estimate's correction, as a load and a Poisson ratio
    learn(mesh, BodyLoadEstimate(simulator), PoissonRatioEstimate(simulator), expected[0], estimate, std.astype(float))
    expected.append(simulator.predict(estimate, poses[2], 1.0))
    assert [stamp_ns_from_msg(p.header.stamp) for p in predictions] == [2 * S, 3 * S]
    for message, positions in zip(predictions, expected, strict=True):
        np.testing.assert_allclose(np.asarray(message.positions).reshape(-1, 3), positions, rtol=0, atol=1e-12)
    assert not np.allclose(expected[0], mesh.vertices, rtol=0, atol=1e-4)  # the held poses did push the cube
    assert spin_until(probe, lambda: reports[-1][1].get("predictions") == "2"
                      and reports[-1][1].get("inputs_dropped_before_mesh") == "0"), reports[-1]
    assert_clean_exit(node, node.interrupt())


# ---------------------------------------------------------------------------- estimator node
class EstimatorProbe:
    """Publishes the estimator node's inputs and collects its outputs."""

    def __init__(self, probe, namespace):
        self.node = probe
        self.estimates, self.statuses, self.diagnostics, self.markers = [], [], [], []
        probe.create_subscription(MarkerArray, f"{namespace}/markers", self.markers.append, KEEP)
        probe.create_subscription(TetraMesh, f"{namespace}/estimated_mesh", self.estimates.append,
                                  QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE,
                                             durability=DurabilityPolicy.TRANSIENT_LOCAL))
        self.status_subscription = probe.create_subscription(
            EstimatorStatus, f"{namespace}/status", self.statuses.append, KEEP)
        probe.create_subscription(DiagnosticArray, "/diagnostics", self._on_diagnostics, KEEP)
        self.mesh = probe.create_publisher(TetraMesh, f"{namespace}/initial_mesh", LATCHED)
        self.prediction = probe.create_publisher(TetraMesh, f"{namespace}/predicted_mesh", PREDICTION_QOS)
        self.cloud = probe.create_publisher(PointCloud2, f"{namespace}/points", KEEP)
        self.status_name = f"{namespace}/estimator_node: estimation"

    def _on_diagnostics(self, msg):
        for status in msg.status:
            if status.name == self.status_name:
                self.diagnostics.append((status.message, {kv.key: kv.value for kv in status.values}))

    def counters(self) -> dict:
        return self.diagnostics[-1][1] if self.diagnostics else {}

    def wait_for(self, **expected) -> dict:
        """Spin until the diagnostics show the `expected` counter values; the counters."""
        matches = lambda: all(self.counters().get(key) == str(value) for key, value in expected.items())  # noqa: E731
        assert spin_until(self.node, matches, timeout_s=30.0), f"expected {expected}, got {self.counters()}"
        return self.counters()

    def send(self, msg, **expected) -> dict:
        """Publish the cloud, again every 5 s while the node has not received it (clouds go
        best-effort: on a loaded machine the node's reader may match the probe's writer after
        the writer matched it, and drops what came before), then wait for `expected`."""
        received = int(self.counters().get("clouds_received", "0"))
        for _ in range(6):
            self.cloud.publish(msg)
            if spin_until(self.node, lambda: int(self.counters().get("clouds_received", "0")) > received,
                          timeout_s=5.0):
                break
        return self.wait_for(**expected)


@pytest.mark.slow
def test_estimator_node_survives_bad_input_and_recovers_from_a_missing_simulator(probe, processes, tmp_path):
    mesh = pushed_cube()
    node = Process(tmp_path, "estimator_node", *ros_args(
        "/est", "prediction_timeout:=0.3", "window_size:=3", "camera_frame:=endoscope",
        "camera_pose:=[0.0, 0.0, 0.1, 1.0, 0.0, 0.0, 0.0]"))
    processes.append(node)
    io = EstimatorProbe(probe, "/est")
    assert spin_until(probe, lambda: io.cloud.get_subscription_count() == 1
                      and io.prediction.get_subscription_count() == 1
                      and io.status_subscription.get_publisher_count() == 1)
    io.wait_for(clouds_received=0)
    assert io.diagnostics[-1][0] == "waiting for initial_mesh"
    one_vertex_short = mesh_msg(mesh)
    one_vertex_short.positions = one_vertex_short.positions[:-3]  # malformed: the elements name a vertex it lacks
    io.mesh.publish(one_vertex_short)  # refused, counted and named while the node waits
    io.wait_for(initial_meshes_rejected=1)
    assert io.diagnostics[-1][0].startswith("waiting for initial_mesh; 1 initial_mesh rejected, the last: "
                                            "initial_mesh rejected: "), io.diagnostics[-1][0]
    io.mesh.publish(mesh_msg(mesh))
    points = top_points()

    # The probe publishes predicted_mesh but answers nothing, as a simulator that never answers:
    # the first cloud waits for it MAX_PREDICTION_WAIT_S (as for one that sets up, next test),
    # then runs degraded; the later ones wait prediction_timeout.
    io.send(cloud_msg(points, 1 * S), steps=1, degraded_steps=1)
    malformed = cloud_msg(points, 2 * S)
    malformed.data = malformed.data[:-5]
    io.send(malformed, clouds_rejected_malformed=1)
    io.send(cloud_msg(np.zeros((0, 3)), 2 * S), clouds_rejected_empty=1)
    io.send(cloud_msg(np.full((6, 3), np.nan), 2 * S), clouds_rejected_empty=2, nan_points_dropped=6)
    io.send(cloud_msg(points, 2 * S, frame="map"), clouds_rejected_frame=1)
    io.send(cloud_msg(points, 1 * S), clouds_rejected_stamp=1)  # repeated stamp
    io.send(cloud_msg(points, S // 2), clouds_rejected_stamp=2)  # older than the newest state
    # Camera-frame cloud (camera 0.1 m above, looking down): moved to the world; NaN points dropped.
    in_camera = (points - [0.0, 0.0, 0.1]) * [1.0, -1.0, -1.0]
    with_nan = np.vstack([in_camera, np.full((3, 3), np.nan)])
    io.send(cloud_msg(with_nan, 2 * S, frame="endoscope"), steps=2, degraded_steps=2, nan_points_dropped=9)
    assert io.statuses[-1].num_points == len(points) and io.statuses[-1].num_points_rejected == 0

    # The simulator comes back: the step pairs with its prediction and is not degraded.
    io.prediction.publish(mesh_msg(mesh, 3 * S))
    counters = io.send(cloud_msg(points, 3 * S), steps=3, degraded_steps=2)
    assert counters["predictions_received"] == "1"
    # health tells the truth: most recent steps ran without the simulator
    assert io.diagnostics[-1][0].startswith("2 of the last 3 steps ran without a simulator prediction")
    # A prediction that arrives too late (its cloud went degraded): ignored.
    io.send(cloud_msg(points, 4 * S), steps=4, degraded_steps=3)
    io.prediction.publish(mesh_msg(mesh, 4 * S))
    io.wait_for(predictions_rejected=1)
    # A looped recording: the stamp jumps back by more than 1 s, the estimator restarts.
    io.send(cloud_msg(points, S // 5), steps=5, clock_jumps_back=1)
    # Absurd coordinates: gated away, the step still yields a finite estimate.
    io.send(cloud_msg(np.full((5, 3), 1e30), S // 2), steps=6)

    assert spin_until(probe, lambda: len(io.estimates) == 6 and len(io.statuses) == 6)
    counters = io.counters()
    assert counters["clouds_received"] == "12" and counters["clouds_rejected"] == "6"
    assert counters["failed_steps"] == "0" and counters["nonfinite_estimates"] == "0"
    assert float(counters["last_solve_time_ms"]) > 0.0 and float(counters["median_latency_ms"]) > 0.0
    assert [stamp_ns_from_msg(e.header.stamp) for e in io.estimates] == [S, 2 * S, 3 * S, 4 * S, S // 5, S // 2]
    assert [e.step for e in io.estimates] == [1, 2, 3, 4, 1, 2]  # restarted from the initial mesh
    assert [s.degraded for s in io.statuses] == [True, True, False, True, True, True]
    assert io.statuses[-1].num_points == 0 and io.statuses[-1].num_points_rejected == 5
    for estimate in io.estimates:  # never a NaN
        assert np.isfinite(estimate.positions).all() and np.isfinite(estimate.position_std).all()
        assert len(estimate.position_std) == mesh.vertex_count
        assert len(estimate.tetrahedra) == 4 * mesh.tetrahedron_count
    for status in io.statuses:
        assert np.isfinite([status.initial_cost, status.final_cost, status.solve_time_ms]).all()
    # Markers of the newest estimates (built while someone subscribes).
    assert spin_until(probe, lambda: io.markers and stamp_ns_from_msg(io.markers[-1].markers[0].header.stamp) == S // 2)
    surface, wireframe, cloud = io.markers[-1].markers[:3]
    assert len(surface.points) == len(surface.colors) == 3 * len(mesh.surface_triangles)
    assert surface.header.frame_id == "world" and len(wireframe.points) > 0 and len(cloud.points) == 5
    # The std's legend and the covariance's ellipsoids, one per free surface vertex (fewer than the bound).
    ellipsoids = [m for m in io.markers[-1].markers if m.ns == NAMESPACE_ELLIPSOIDS]
    assert len(ellipsoids) == min(len(np.setdiff1d(mesh.surface_vertices, mesh.fixed_vertices)), MAX_ELLIPSOIDS)
    assert any(m.ns == NAMESPACE_LEGEND and m.text.endswith(" mm") for m in io.markers[-1].markers)
    # The measured top face stays near z = SIDE.
    top = np.isclose(mesh.vertices[:, 2], SIDE)
    assert np.abs(np.asarray(io.estimates[2].positions).reshape(-1, 3)[top, 2] - SIDE).max() < 2e-3
    assert node.alive()
    assert_clean_exit(node, node.interrupt())


@pytest.mark.slow
def test_the_first_cloud_waits_for_a_simulation_node_that_sets_up(probe, processes, tmp_path):
    """A simulation node that is there (it publishes predicted_mesh) but answers the first request
    only after prediction_timeout, as when it sets up on a large mesh: the first cloud waits for
    that answer and is estimated with it, not degraded. (The answer comes a second after the
    request, three times prediction_timeout: where the node ran the cloud degraded, the step
    counts it.)"""
    mesh = pushed_cube()
    node = Process(tmp_path, "estimator_node", *ros_args("/setup", "prediction_timeout:=0.3", "window_size:=3"))
    processes.append(node)
    io = EstimatorProbe(probe, "/setup")
    requests = []
    probe.create_subscription(Header, "/setup/prediction_request", requests.append, REQUEST_QOS)
    assert spin_until(probe, lambda: io.cloud.get_subscription_count() == 1
                      and io.prediction.get_subscription_count() == 1
                      and io.status_subscription.get_publisher_count() == 1)
    io.mesh.publish(mesh_msg(mesh))
    io.wait_for(clouds_received=0)
    io.send(cloud_msg(top_points(), 1 * S), clouds_received=1)
    assert spin_until(probe, lambda: any(stamp_ns_from_msg(r.stamp) == 1 * S for r in requests))
    time.sleep(1.0)  # the simulator's set-up
    io.prediction.publish(mesh_msg(mesh, 1 * S))
    counters = io.wait_for(steps=1)
    assert counters["degraded_steps"] == "0" and counters["predictions_received"] == "1"
    assert counters.get("predictions_rejected", "0") == "0"
    assert_clean_exit(node, node.interrupt())


@pytest.mark.slow
def test_estimator_node_estimates_a_cloud_that_came_before_its_mesh(probe, processes, tmp_path):
    node = Process(tmp_path, "estimator_node", *ros_args("/estearly", "prediction_timeout:=0.3", "window_size:=3"))
    processes.append(node)
    io = EstimatorProbe(probe, "/estearly")
    assert spin_until(probe, lambda: io.cloud.get_subscription_count() == 1
                      and io.status_subscription.get_publisher_count() == 1)
    io.wait_for(clouds_received=0)
    io.send(cloud_msg(top_points(), 1 * S), clouds_received=1, inputs_held_before_mesh=1)
    assert io.diagnostics[-1][0] == "waiting for initial_mesh; 1 inputs held until it comes"
    io.mesh.publish(mesh_msg(pushed_cube()))
    io.wait_for(steps=1, degraded_steps=1, inputs_dropped_before_mesh=0)  # no simulator here: degraded
    assert spin_until(probe, lambda: io.statuses)
    assert stamp_ns_from_msg(io.statuses[0].header.stamp) == 1 * S
    assert io.statuses[0].num_points == len(top_points())
    assert_clean_exit(node, node.interrupt())


@pytest.mark.slow
def test_estimator_node_runs_a_step_at_once_when_the_simulator_reports_a_failure(probe, processes, tmp_path):
    """A PredictionFailure for a cloud's stamp releases that cloud degraded without waiting for
    prediction_timeout (60 s here, twice as long as any wait below)."""
    mesh = pushed_cube()
    node = Process(tmp_path, "estimator_node", *ros_args("/fail", "prediction_timeout:=60.0", "window_size:=3"))
    processes.append(node)
    io = EstimatorProbe(probe, "/fail")
    failure = probe.create_publisher(PredictionFailure, "/fail/prediction_failed", PREDICTION_QOS)
    assert spin_until(probe, lambda: io.cloud.get_subscription_count() == 1
                      and io.prediction.get_subscription_count() == 1 and failure.get_subscription_count() == 1)
    io.wait_for(clouds_received=0)  # the node is up and its diagnostics reach the probe
    io.mesh.publish(mesh_msg(mesh))
    points = top_points()

    def report_failure(stamp_ns):
        failure.publish(PredictionFailure(header=header_msg(stamp_ns, "world", FACTORY), reason="test: inverted"))

    io.cloud.publish(cloud_msg(points, 1 * S))
    report_failure(1 * S)
    io.wait_for(steps=1, degraded_steps=1, predictions_failed=1)
    report_failure(2 * S)  # before its cloud: kept for it
    io.send(cloud_msg(points, 2 * S), steps=2, degraded_steps=2, predictions_failed=2)
    report_failure(2 * S)  # its cloud is done: counted, nothing else
    io.wait_for(predictions_failed=3, steps=2)
    io.prediction.publish(mesh_msg(mesh, 3 * S))  # the simulator is back: the next step pairs
    io.send(cloud_msg(points, 3 * S), steps=3, degraded_steps=2)
    assert [status.degraded for status in io.statuses] == [True, True, False]
    assert node.alive()
    assert_clean_exit(node, node.interrupt())


def test_estimator_node_runs_a_stalled_streams_clouds_again_with_the_catch_up_predictions(probe, processes, tmp_path):
    """Clouds the simulator could not predict and no tool pose covers (a stalled tool stream) run
    degraded (after prediction_timeout, the wait for a tool pose) and are held; the simulator's
    catch-up predictions for them, which come after they ran, are taken, and the next cloud's
    step first runs them again: their estimates go to the simulation node on catch_up_estimate,
    not to estimated_mesh."""
    mesh = pushed_cube()
    node = Process(tmp_path, "estimator_node", *ros_args("/again", "prediction_timeout:=0.5", "window_size:=3"))
    processes.append(node)
    io = EstimatorProbe(probe, "/again")
    failure = probe.create_publisher(PredictionFailure, "/again/prediction_failed", PREDICTION_QOS)
    pose = probe.create_publisher(PoseStamped, "/again/tool_pose", KEEP)
    again = []
    probe.create_subscription(TetraMesh, "/again/catch_up_estimate", again.append, KEEP)
    assert spin_until(probe, lambda: io.cloud.get_subscription_count() == 1
                      and io.prediction.get_subscription_count() == 1 and failure.get_subscription_count() == 1)
    io.wait_for(clouds_received=0)
    io.mesh.publish(mesh_msg(mesh))
    points = top_points()
    pose.publish(tool_pose_msg([SIDE / 2, SIDE / 2, SIDE + 0.011], S // 2))  # then the tool stream stalls
    for k in (1, 2):
        io.cloud.publish(cloud_msg(points, k * S))
        failure.publish(PredictionFailure(header=header_msg(k * S, "world", FACTORY), reason="test: no tool pose"))
        io.wait_for(steps=k, degraded_steps=k)
    for k in (1, 2):
        io.prediction.publish(mesh_msg(mesh, k * S))  # the catch-up, after their clouds ran
    io.prediction.publish(mesh_msg(mesh, 3 * S))
    pose.publish(tool_pose_msg([SIDE / 2, SIDE / 2, SIDE + 0.011], 3 * S))  # poses again
    io.send(cloud_msg(points, 3 * S), steps=3, degraded_steps=2, clouds_run_again=2, predictions_rejected=0)
    assert spin_until(probe, lambda: len(again) == 2)
    assert [stamp_ns_from_msg(m.header.stamp) for m in again] == [1 * S, 2 * S]
    assert not any(m.degraded for m in again) and all(len(m.position_std) == len(mesh.vertices) for m in again)
    assert [status.degraded for status in io.statuses] == [True, True, False]
    assert node.alive()
    assert_clean_exit(node, node.interrupt())


# A node whose timer fires at once, under an executor that receives SIGINT right after it has made a
# callback's task and before it runs it: the moment a KeyboardInterrupt would orphan that task.
SIGNAL_BETWEEN_TASK_AND_RUN = """
import os, signal
from rclpy.executors import Executor
from rclpy.node import Node
from meshfg_ros.nodes.runtime import run_nodes
make_handler = Executor._make_handler
def make_handler_then_signal(self, *args):
    task = make_handler(self, *args)
    os.kill(os.getpid(), signal.SIGINT)
    return task
Executor._make_handler = make_handler_then_signal
ran = []
class Ticking(Node):
    def __init__(self):
        super().__init__("ticking")
        self.create_timer(0.01, lambda: ran.append(1))
code = run_nodes("ticking", [Ticking], args=["ticking"])
print("exit", code, "callbacks run", len(ran))
"""


@pytest.mark.slow
def test_a_signal_between_making_and_running_a_callback_stops_the_node_cleanly():
    result = subprocess.run([sys.executable, "-c", SIGNAL_BETWEEN_TASK_AND_RUN], capture_output=True, text=True,
                            timeout=60)
    output = result.stdout + result.stderr
    assert result.returncode == 0, output
    assert "exit 0 callbacks run 1" in output  # the callback whose task was made still ran, once
    assert "never awaited" not in output and "Traceback" not in output, output


@pytest.mark.slow
def test_estimated_mesh_reaches_a_late_subscriber(probe, processes, tmp_path):
    mesh = pushed_cube()
    node = Process(tmp_path, "estimator_node", *ros_args("/late", "prediction_timeout:=0.0"))
    processes.append(node)
    mesh_publisher = probe.create_publisher(TetraMesh, "/late/initial_mesh", LATCHED)
    cloud_publisher = probe.create_publisher(PointCloud2, "/late/points", KEEP)
    statuses, diagnostics = [], []
    status_subscription = probe.create_subscription(EstimatorStatus, "/late/status", statuses.append, KEEP)
    probe.create_subscription(DiagnosticArray, "/diagnostics", lambda m: diagnostics.extend(
        s for s in m.status if s.name == "/late/estimator_node: estimation"), KEEP)
    # A best-effort reader drops what arrives before it has matched the writer: wait until the node
    # has been up for a while (its first diagnostics), not only until our writer sees it.
    assert spin_until(probe, lambda: cloud_publisher.get_subscription_count() == 1
                      and status_subscription.get_publisher_count() == 1 and diagnostics)
    mesh_publisher.publish(mesh_msg(mesh))
    cloud_publisher.publish(cloud_msg(top_points(), 7 * S))
    assert spin_until(probe, lambda: len(statuses) == 1)
    late = []  # transient-local: subscribing after the publication still delivers the newest state
    probe.create_subscription(TetraMesh, "/late/estimated_mesh", late.append, LATCHED)
    assert spin_until(probe, lambda: len(late) == 1)
    assert stamp_ns_from_msg(late[0].header.stamp) == 7 * S
    # ... with its covariance: symmetric 3x3 blocks, zero on the fixed vertices, positive variances
    # elsewhere, whose trace / 3 is the std's square (to float32's rounding of both).
    covariance = position_covariance_from_msg(late[0])
    assert covariance.shape == (mesh.vertex_count, 3, 3)
    np.testing.assert_array_equal(covariance, covariance.transpose(0, 2, 1))
    variances = np.einsum("vii->vi", covariance)
    fixed = np.isin(np.arange(mesh.vertex_count), mesh.fixed_vertices)
    assert not covariance[fixed].any() and (variances[~fixed] > 0.0).all()
    std = position_std_from_msg(late[0], mesh.vertex_count)
    np.testing.assert_allclose(variances.sum(axis=1) / 3.0, std**2, rtol=1e-6, atol=0.0)
    assert_clean_exit(node, node.interrupt())
    # The executable chose CHOLMOD's BLAS at start-up as every entry point does (this session's
    # conftest too: same CPU, same environment).
    assert f"sparse Cholesky BLAS: {blas.backend().name}, {blas.backend().threads} thread(s)" in node.output()


# ---------------------------------------------------------------------------- bag player
@pytest.fixture(scope="module")
def small_recording(tmp_path_factory):
    """Initial mesh, 4 tool poses and 4 clouds 0.2 s apart."""
    path = tmp_path_factory.mktemp("bag") / "small"
    mesh = pushed_cube()
    poses = [PoseRecord(S + k * S // 5, "world", [0.01 * k, 0.0, 0.1, 0.0, 0.0, 0.0, 1.0]) for k in range(4)]
    clouds = [PointCloudRecord(S + k * S // 5, "world", top_points(10 + k, seed=k)) for k in range(4)]
    with RecordingWriter(path) as writer:
        writer.write("/rec/initial_mesh", MeshState(S, "world", 0, mesh.vertices, mesh.tetrahedra,
                                                    mesh.surface_triangles, mesh.fixed_vertices))
        for pose, cloud in zip(poses, clouds, strict=True):
            writer.write("/rec/tool_pose", pose)
            writer.write("/rec/points", cloud)
    return path, mesh, poses, clouds


@pytest.mark.slow
def test_bag_player_plays_the_recording_with_clock(probe, processes, tmp_path, small_recording):
    path, mesh, poses, clouds = small_recording
    received = {"mesh": [], "poses": [], "clouds": [], "clock": []}
    probe.create_subscription(TetraMesh, "/rec/initial_mesh", received["mesh"].append, LATCHED)
    probe.create_subscription(PoseStamped, "/rec/tool_pose", received["poses"].append, KEEP)
    probe.create_subscription(PointCloud2, "/rec/points", received["clouds"].append, KEEP)
    probe.create_subscription(Clock, "/clock", received["clock"].append, KEEP)
    player = Process(tmp_path, "bag_player", str(path), "--rate", "2", "--wait-for-subscribers", "30")
    processes.append(player)
    last_stamp_ns = poses[-1].stamp_ns
    assert spin_until(probe, lambda: player.popen.poll() is not None and len(received["clouds"]) == 4
                      and received["clock"] and stamp_ns_from_msg(received["clock"][-1].clock) == last_stamp_ns)
    assert_clean_exit(player, player.popen.returncode)
    assert len(received["mesh"]) == 1 and np.array_equal(np.asarray(received["mesh"][0].positions),
                                                         mesh.vertices.reshape(-1))
    assert [stamp_ns_from_msg(m.header.stamp) for m in received["poses"]] == [p.stamp_ns for p in poses]
    assert received["poses"][-1].pose.position.x == pytest.approx(0.03)
    for message, cloud in zip(received["clouds"], clouds, strict=True):
        recorded = cloud.points.astype(np.float32)  # clouds are recorded as FLOAT32 x, y, z
        np.testing.assert_array_equal(decode_pointcloud2(message).points, recorded)
    # Sim time over DDS from the first stamp to the last; the pacing itself (rate, /clock between
    # the messages) is checked against a virtual clock in test_bag_player.py.
    clock = [stamp_ns_from_msg(m.clock) for m in received["clock"]]
    assert clock == sorted(clock) and clock[0] == S and clock[-1] == last_stamp_ns


@pytest.mark.slow
def test_bag_player_errors_and_interrupt(probe, processes, tmp_path, small_recording):
    missing = Process(tmp_path, "bag_player", str(tmp_path / "nothing"))
    unknown_topic = Process(tmp_path, "bag_player", str(small_recording[0]), "--topics", "/rec/nothing")
    waiting = Process(tmp_path, "bag_player", str(small_recording[0]), "--topics", "/rec/points",
                      "--wait-for-subscribers", "600", *ros_args("/", ), "-r", "/rec/points:=/nobody/points")
    processes += [missing, unknown_topic, waiting]
    assert missing.popen.wait(timeout=60) == 1
    assert "does not exist" in missing.output() and "Traceback" not in missing.output()
    assert unknown_topic.popen.wait(timeout=60) == 1
    assert "topic /rec/nothing is not in" in unknown_topic.output()
    # Interrupted while it waits for a subscriber that never comes.
    assert spin_until(probe, lambda: probe.count_publishers("/nobody/points") == 1)
    assert waiting.alive()
    assert_clean_exit(waiting, waiting.interrupt())


def test_launch_file_is_valid_python():
    launch_file = REPOSITORY / "launch" / "meshfg.launch.py"
    py_compile.compile(str(launch_file), doraise=True)
    launch = pytest.importorskip("launch")
    pytest.importorskip("launch_ros")  # (with the repository on sys.path, `launch` alone is its launch/ folder)
    namespace = {}
    exec(compile(launch_file.read_text(), str(launch_file), "exec"), namespace)
    assert isinstance(namespace["generate_launch_description"](), launch.LaunchDescription)


def _launch_file_calls(tree: ast.Module, name: str) -> list[ast.Call]:
    return [node for node in ast.walk(tree)
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id == name]


def test_launch_file_starts_installed_executables_with_the_arguments_it_declares():
    """What the launch file does, read without launch_ros (not on PyPI, so the test above skips
    here): every executable it starts is a console script of setup.py, the arguments it declares
    are those its usage line advertises and those it reads, and bag_player takes what it passes."""
    launch_file = REPOSITORY / "launch" / "meshfg.launch.py"
    tree = ast.parse(launch_file.read_text())
    scripts = set(re.findall(r'"(\w+) = meshfg_ros[\w.]*:main"', (REPOSITORY / "setup.py").read_text()))
    started = {call.args[0].value for call in _launch_file_calls(tree, "pipeline_node")}
    started |= {keyword.value.value for call in _launch_file_calls(tree, "Node") for keyword in call.keywords
                if keyword.arg == "executable" and isinstance(keyword.value, ast.Constant)}
    assert started == {"simulation_node", "estimator_node", "meshfg_stack", "bag_player"}
    assert started <= scripts, started - scripts
    declared = {call.args[0].value for call in _launch_file_calls(tree, "DeclareLaunchArgument")}
    advertised = set(re.findall(r"(\w+):=", ast.get_docstring(tree)))
    read = {call.args[0].value for call in _launch_file_calls(tree, "LaunchConfiguration")}
    assert declared == advertised == read == {"namespace", "params_file", "single_process", "bag", "rate",
                                              "use_sim_time"}
    (player,) = [call for call in _launch_file_calls(tree, "Node")
                 if any(keyword.arg == "executable" and getattr(keyword.value, "value", None) == "bag_player"
                        for keyword in call.keywords)]
    (arguments,) = [keyword.value for keyword in player.keywords if keyword.arg == "arguments"]
    options = [element.value for element in arguments.elts if isinstance(element, ast.Constant)]
    from meshfg_ros.nodes.bag_player import parse_arguments

    assert parse_arguments(["bag_player", "recording", *[part for option in options for part in (option, "2.0")]]).rate == 2.0


def test_position_std_of_an_estimate_is_taken_unless_malformed():
    """A TetraMesh's std is the simulator's weight for each vertex: taken with the right count
    and no NaN or negative entry (an infinite entry is a vertex the estimate knows nothing of);
    None when the message has none or a malformed one."""
    mesh = cube_mesh(side=SIDE, divisions=2)
    msg, std = estimate_msg(mesh, S, mesh.vertices)
    np.testing.assert_array_equal(position_std_from_msg(msg, mesh.vertex_count), std)
    msg.position_std = np.where(std > 0, np.float32(np.inf), std)
    assert np.isinf(position_std_from_msg(msg, mesh.vertex_count)).sum() == np.count_nonzero(std)
    for malformed in (std[:-1], np.where(std > 0, np.float32(np.nan), std), np.where(std > 0, -std, std),
                      np.zeros(0, dtype=np.float32)):
        msg.position_std = malformed
        assert position_std_from_msg(msg, mesh.vertex_count) is None, malformed


def test_position_covariance_of_an_estimate_reads_back_or_is_refused_with_its_reason():
    """What a planner reads from estimated_mesh: the (N, 3, 3) blocks the estimator sent (as
    float32), None without any, and a clear error for a malformed field."""
    mesh = cube_mesh(side=SIDE, divisions=2).with_fixed([0, 1])
    rng = np.random.default_rng(4)
    factors = rng.normal(scale=1e-4, size=(mesh.vertex_count, 3, 3))
    covariance = factors @ factors.transpose(0, 2, 1)
    covariance = 0.5 * (covariance + covariance.transpose(0, 2, 1))
    covariance[mesh.fixed_vertices] = 0.0
    state = MeshState(S, "world", 1, mesh.vertices, mesh.tetrahedra, mesh.surface_triangles, mesh.fixed_vertices)
    msg = MeshMessages(state).message(S, "world", 1, mesh.vertices, position_covariance=covariance)
    read = position_covariance_from_msg(msg)
    scale = np.abs(covariance).max(axis=(1, 2), keepdims=True)
    assert read.shape == covariance.shape and (np.abs(read - covariance) <= 2**-24 * scale).all()
    np.testing.assert_array_equal(read, read.transpose(0, 2, 1))
    assert not read[:2].any()
    assert position_covariance_from_msg(MeshMessages(state).message(S, "world", 1, mesh.vertices)) is None
    sent = np.asarray(msg.position_covariance)
    entry = np.arange(sent.size)  # vertex 2's are 12 to 17: xx xy xz yy yz zz
    for malformed, reason in ((sent[:-1], f"has {sent.size - 1} values, expected 6 per vertex ({sent.size}) or 0"),
                              (np.where(entry == 13, np.float32(np.nan), sent), "vertex 2 is not finite"),
                              (np.where(entry == 15, -sent, sent), "vertex 2 has a negative variance")):
        msg.position_covariance = malformed
        with pytest.raises(MessageValidationError, match=re.escape(reason)):
            position_covariance_from_msg(msg)


def test_recorded_messages_of_any_type_convert_to_rclpy():
    make = RosbagsMessageFactory().make
    info = make("sensor_msgs/msg/CameraInfo", header=header_msg(5 * S, "camera"), height=480, width=640,
                distortion_model="plumb_bob", d=np.array([0.1, -0.2, 0.0, 0.0, 0.01]),
                k=np.arange(9.0), r=np.eye(3).reshape(-1), p=np.arange(12.0), binning_x=0, binning_y=0,
                roi=make("sensor_msgs/msg/RegionOfInterest", x_offset=1, y_offset=2, height=3, width=4,
                         do_rectify=True))
    converted = rclpy_message(info)
    assert type(converted).__module__.startswith("sensor_msgs.msg")
    assert stamp_ns_from_msg(converted.header.stamp) == 5 * S and converted.header.frame_id == "camera"
    assert (converted.height, converted.width, converted.distortion_model) == (480, 640, "plumb_bob")
    np.testing.assert_array_equal(converted.d, [0.1, -0.2, 0.0, 0.0, 0.01])
    np.testing.assert_array_equal(converted.k, np.arange(9.0))
    assert converted.roi.do_rectify and converted.roi.width == 4
    text = rclpy_message(make("std_msgs/msg/String", data='{"scenario": "x"}'))
    assert text.data == '{"scenario": "x"}'
    markers = rclpy_message(make("visualization_msgs/msg/MarkerArray", markers=[]))
    assert isinstance(markers, MarkerArray) and markers.markers == []
