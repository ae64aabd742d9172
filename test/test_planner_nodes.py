"""The planner interface over real DDS: the estimator node's `surface_query` service and the
example planner `tool_clearance_node`, as separate processes (see test_nodes.py's helpers).

Most estimates they answer on are published by the test on the estimator node's `estimated_mesh`
(a deformed cube with a per-vertex covariance), so the expected answers are known: distances
from a brute-force point-to-mesh distance, signs from the winding number, the rest from the
core (core/geometry/surface_query.py) on the estimate as the message carries it. One test has the node
estimate clouds and checks that the service answers on its newest estimate.
"""
import time

import igl
import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import PoseStamped, TransformStamped
from rcl_interfaces.srv import SetParameters
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from scipy.spatial.transform import Rotation
from tf2_msgs.msg import TFMessage

from meshfg_msgs.srv import SurfaceQuery as SurfaceQueryService
from meshfg_ros.core.geometry.surface_query import SurfaceQuery
from meshfg_ros.io.messages import MeshState, header_msg, mesh_state_from_msg, mesh_state_to_msg, stamp_ns_from_msg
from meshfg_ros.nodes.planner_service import points_from_flat
from meshfg_ros.planner_client import SurfaceQueryClient, SurfaceQueryError
from meshfg_ros.synthetic.meshing import cube_mesh
from test_nodes import (  # noqa: F401 - probe and processes are fixtures
    FACTORY,
    KEEP,
    LATCHED,
    S,
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
    top_points,
)
from test_surface_query import exact_distances

pytestmark = pytest.mark.slow
TF_STATIC = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
ESTIMATE_STAMP_NS, ESTIMATE_STEP = 5 * S + 250_000_000, 7
# The planner's frame in world: turned 30 degrees about z and moved.
PLANNER_ROTATION = Rotation.from_euler("z", 30.0, degrees=True)
PLANNER_TRANSLATION = np.array([0.1, -0.05, 0.02])


def estimate_msg():
    """A deformed 4 cm cube with a different random covariance (0.3-1.5 mm) at each vertex."""
    mesh = cube_mesh(side=0.04, divisions=4)
    rng = np.random.default_rng(21)
    vertices = mesh.vertices + 0.002 * np.sin(mesh.vertices[:, [1, 2, 0]] * 80.0)
    factors = rng.uniform(0.3e-3, 1.5e-3, size=(mesh.vertex_count, 1, 1)) * Rotation.random(
        mesh.vertex_count, random_state=3).as_matrix() * rng.uniform(0.5, 1.0, size=(mesh.vertex_count, 1, 3))
    state = MeshState(ESTIMATE_STAMP_NS, "world", ESTIMATE_STEP, vertices, mesh.tetrahedra, mesh.surface_triangles,
                      position_covariance=factors @ factors.transpose(0, 2, 1))
    return mesh_state_to_msg(state, FACTORY)


def planner_frame_msg():
    transform = TransformStamped(header=header_msg(0, "world", FACTORY), child_frame_id="planner")
    transform.transform.translation.x, transform.transform.translation.y, transform.transform.translation.z = \
        PLANNER_TRANSLATION.tolist()
    (transform.transform.rotation.x, transform.transform.rotation.y, transform.transform.rotation.z,
     transform.transform.rotation.w) = PLANNER_ROTATION.as_quat().tolist()
    return TFMessage(transforms=[transform])


def to_planner(points_world):
    return PLANNER_ROTATION.inv().apply(points_world - PLANNER_TRANSLATION)


def request(points, frame_id="world", stamp_ns=0):
    msg = SurfaceQueryService.Request()
    msg.header = header_msg(stamp_ns, frame_id, FACTORY)
    msg.points = FACTORY.sequence(points, np.float64)
    return msg


def statuses(probe, name):
    """(level, message, counters) of each /diagnostics status called `name`, appended as they come."""
    found = []

    def on_diagnostics(msg):
        found.extend((status.level, status.message, {kv.key: kv.value for kv in status.values})
                     for status in msg.status if status.name == name)

    probe.create_subscription(DiagnosticArray, "/diagnostics", on_diagnostics, KEEP)
    return found


def test_estimator_node_answers_surface_queries_in_any_frame_on_the_newest_estimate(probe, processes, tmp_path):
    namespace = "/planner_query"
    node = Process(tmp_path, "estimator_node", *ros_args(namespace))
    processes.append(node)
    client = probe.create_client(SurfaceQueryService, f"{namespace}/surface_query")
    reports = statuses(probe, f"{namespace}/estimator_node: surface queries")
    rng = np.random.default_rng(8)
    points = rng.uniform(-0.01, 0.05, size=(1000, 3))

    # No estimate yet: refused with the reason, and said on /diagnostics.
    refused = call_service(probe, client, request(points[:3]))
    assert not refused.success and refused.message == "no estimate yet: the estimator has published none"
    assert spin_until(probe, lambda: any(level == DiagnosticStatus.WARN and "surface queries refused" in message
                                         and int(counters["queries_refused_no_estimate"]) >= 1
                                         for level, message, counters in reports), timeout_s=10.0), reports[-3:]

    probe.create_publisher(TFMessage, "/tf_static", TF_STATIC).publish(planner_frame_msg())
    estimate = estimate_msg()
    probe.create_publisher(type(estimate), f"{namespace}/estimated_mesh", LATCHED).publish(estimate)
    deadline = time.monotonic() + 30.0
    while not (answer := call_service(probe, client, request(points))).success and time.monotonic() < deadline:
        spin_until(probe, lambda: False, timeout_s=0.2)
    assert answer.success, answer.message
    assert (stamp_ns_from_msg(answer.header.stamp), answer.estimate_step, answer.header.frame_id) == (
        ESTIMATE_STAMP_NS, ESTIMATE_STEP, "world")

    state = mesh_state_from_msg(estimate)  # the estimate as the node has it (covariance in float32)
    signed = np.asarray(answer.signed_distances)
    np.testing.assert_allclose(np.abs(signed), exact_distances(points, state.positions, state.surface_triangles),
                               rtol=0.0, atol=1e-9)
    inside = igl.winding_number(state.positions, state.surface_triangles, points) > 0.5
    assert inside.sum() > 100 and np.array_equal(signed < 0.0, inside)
    expected = SurfaceQuery(state.positions, state.surface_triangles, state.position_covariance).query(points)
    np.testing.assert_allclose(points_from_flat(answer.closest_points), expected.closest, rtol=0.0, atol=1e-15)
    np.testing.assert_allclose(points_from_flat(answer.normals), expected.normal, rtol=0.0, atol=1e-15)
    np.testing.assert_allclose(answer.distance_std, expected.distance_std, rtol=1e-12)
    assert 0.2e-3 < np.median(answer.distance_std) < 2e-3

    # The same points given in the planner's frame (through /tf_static, which may reach the node
    # after the estimate did): the same answers, in it.
    deadline = time.monotonic() + 30.0
    while (not (in_planner := call_service(probe, client, request(to_planner(points), "planner"))).success
           and "unknown frame" in in_planner.message and time.monotonic() < deadline):
        spin_until(probe, lambda: False, timeout_s=0.2)
    assert in_planner.success and in_planner.header.frame_id == "planner", in_planner.message
    np.testing.assert_allclose(in_planner.signed_distances, signed, rtol=0.0, atol=1e-12)
    np.testing.assert_allclose(points_from_flat(in_planner.closest_points), to_planner(expected.closest), atol=1e-12)
    np.testing.assert_allclose(points_from_flat(in_planner.normals), PLANNER_ROTATION.inv().apply(expected.normal),
                               atol=1e-12)
    np.testing.assert_allclose(in_planner.distance_std, expected.distance_std, rtol=1e-12)

    # The Python client: the same answers as arrays, a refusal as SurfaceQueryError with the reason.
    python_client = SurfaceQueryClient(probe, f"{namespace}/surface_query")
    for _ in range(3):  # a response the transport drops to a just-matched client is asked again
        try:
            answered = python_client.query(to_planner(points[:5]), frame_id="planner", timeout_s=5.0)
            break
        except SurfaceQueryError as error:
            assert "no answer" in str(error), error
    assert (answered.stamp_ns, answered.step, answered.frame_id) == (ESTIMATE_STAMP_NS, ESTIMATE_STEP, "planner")
    np.testing.assert_allclose(answered.signed_distance, signed[:5], rtol=0.0, atol=1e-12)
    np.testing.assert_allclose(answered.closest, to_planner(expected.closest[:5]), atol=1e-12)
    np.testing.assert_allclose(answered.distance_std, expected.distance_std[:5], rtol=1e-12)
    with pytest.raises(SurfaceQueryError, match="unknown frame 'elsewhere'"):
        python_client.query(points[:1], frame_id="elsewhere", timeout_s=10.0)

    # A malformed estimate is not taken: the queries go on on the previous one.
    malformed = estimate_msg()
    malformed.header.stamp.sec, malformed.positions = 9, malformed.positions[:-1]
    probe.create_publisher(type(estimate), f"{namespace}/estimated_mesh", LATCHED).publish(malformed)
    assert spin_until(probe, lambda: reports and reports[-1][2]["estimates_unreadable"] == "1", timeout_s=10.0)
    again = call_service(probe, client, request(points[:5]))
    assert stamp_ns_from_msg(again.header.stamp) == ESTIMATE_STAMP_NS
    np.testing.assert_allclose(again.signed_distances, signed[:5], rtol=0.0, atol=1e-15)

    # A frame /tf does not know and a non-finite point: refused with the reason; the node goes on.
    unknown = call_service(probe, client, request(points[:2], "nowhere"))
    assert not unknown.success and "unknown frame 'nowhere'" in unknown.message
    not_finite = call_service(probe, client, request(np.array([[0.0, np.nan, 0.0]])))
    assert not not_finite.success and "NaN or infinite" in not_finite.message
    four_values = request(np.zeros((1, 3)))
    four_values.points = FACTORY.sequence(np.zeros(4), np.float64)
    odd = call_service(probe, client, four_values)
    assert not odd.success and odd.message == "points rejected: points has 4 values, not a multiple of 3 (x y z per point)"
    assert spin_until(probe, lambda: reports and reports[-1][2]["queries_refused_frame"] == "2"
                      and reports[-1][2]["queries_refused_points"] == "2", timeout_s=10.0), reports[-1:]
    assert int(reports[-1][2]["queries_answered"]) >= 2
    assert_clean_exit(node, node.interrupt())


def test_the_service_answers_on_the_estimators_own_newest_estimate(probe, processes, tmp_path):
    namespace = "/planner_own"
    node = Process(tmp_path, "estimator_node", *ros_args(namespace, "prediction_timeout:=0.3", "window_size:=3"))
    processes.append(node)
    io = EstimatorProbe(probe, namespace)
    client = probe.create_client(SurfaceQueryService, f"{namespace}/surface_query")
    assert spin_until(probe, lambda: io.cloud.get_subscription_count() == 1
                      and io.status_subscription.get_publisher_count() == 1)
    io.wait_for(clouds_received=0)
    io.mesh.publish(mesh_msg(pushed_cube()))
    points = np.random.default_rng(4).uniform(-0.01, 0.06, size=(200, 3))
    for stamp_s in (1, 2):  # no simulator here: degraded steps, each with its estimate and covariance
        io.send(cloud_msg(top_points(seed=stamp_s), stamp_s * S), steps=stamp_s)
        assert spin_until(probe, lambda: io.estimates and stamp_ns_from_msg(io.estimates[-1].header.stamp) == stamp_s * S)
        estimate = mesh_state_from_msg(io.estimates[-1])
        assert estimate.position_covariance.size
        deadline = time.monotonic() + 10.0
        while (stamp_ns_from_msg((answer := call_service(probe, client, request(points))).header.stamp) != stamp_s * S
               and time.monotonic() < deadline):  # the node's own subscription may take the estimate a moment later
            spin_until(probe, lambda: False, timeout_s=0.1)
        assert answer.success and (stamp_ns_from_msg(answer.header.stamp), answer.estimate_step) == (
            stamp_s * S, estimate.step), answer.message
        np.testing.assert_allclose(np.abs(answer.signed_distances),
                                   exact_distances(points, estimate.positions, estimate.surface_triangles),
                                   rtol=0.0, atol=1e-9)
        expected = SurfaceQuery(estimate.positions, estimate.surface_triangles,
                                estimate.position_covariance).query(points)
        np.testing.assert_allclose(answer.distance_std, expected.distance_std, rtol=1e-12)
    assert_clean_exit(node, node.interrupt())


def test_tool_clearance_node_keeps_the_tip_k_std_from_the_tissue(probe, processes, tmp_path):
    namespace = "/planner_clearance"
    estimator = Process(tmp_path, "estimator_node", *ros_args(namespace))
    planner = Process(tmp_path, "tool_clearance_node", *ros_args(namespace, "clearance_sigmas:=3.0",
                                                                  "min_clearance:=0.0005"))
    processes += [estimator, planner]
    reports = statuses(probe, f"{namespace}/tool_clearance_node: tool clearance")
    safe = []
    probe.create_subscription(PoseStamped, f"{namespace}/safe_tip_pose", safe.append, KEEP)
    desired_publisher = probe.create_publisher(PoseStamped, f"{namespace}/desired_tip_pose", KEEP)

    def desired(position, stamp_ns):
        msg = PoseStamped(header=header_msg(stamp_ns, "world", FACTORY))
        msg.pose.position.x, msg.pose.position.y, msg.pose.position.z = position
        msg.pose.orientation.x, msg.pose.orientation.w = 0.6, 0.8
        return msg

    def safe_pose_for(msg):
        """Publish `msg` every 2 s until its safe pose comes (a request or an answer the
        transport drops on a loaded machine is asked again); that pose."""
        answered = lambda: any(stamp_ns_from_msg(pose.header.stamp) == stamp_ns_from_msg(msg.header.stamp)  # noqa: E731
                               for pose in safe)
        for _ in range(15):
            desired_publisher.publish(msg)
            if spin_until(probe, answered, timeout_s=2.0):
                return next(pose for pose in safe if pose.header.stamp == msg.header.stamp)
        raise AssertionError(f"no safe_tip_pose for the desired pose at {msg.header.stamp}; {reports[-1:]}")

    # Before any estimate the desired pose cannot be checked: held back, not published.
    assert spin_until(probe, lambda: desired_publisher.get_subscription_count() > 0, timeout_s=30.0)
    for _ in range(3):
        desired_publisher.publish(desired((0.02, 0.02, 0.03), 1 * S))
        spin_until(probe, lambda: False, timeout_s=0.5)
    assert spin_until(probe, lambda: any(level == DiagnosticStatus.WARN and "held back" in message
                                         for level, message, _ in reports), timeout_s=15.0), reports[-3:]
    assert not safe

    estimate = estimate_msg()
    probe.create_publisher(type(estimate), f"{namespace}/estimated_mesh", LATCHED).publish(estimate)
    state = mesh_state_from_msg(estimate)
    surface = SurfaceQuery(state.positions, state.surface_triangles, state.position_covariance)
    # Under the top face (inside the tissue): moved out along the normal to 3 std of the distance there.
    top = surface.query([[0.021, 0.019, 0.05]])
    tip = top.closest[0] - 0.001 * top.normal[0]
    pose = safe_pose_for(desired(tip, 2 * S))
    moved = np.array([pose.pose.position.x, pose.pose.position.y, pose.pose.position.z])
    after = surface.query([moved])
    required = 3.0 * after.distance_std[0]
    assert required > 0.0005  # the std sets the clearance here, not min_clearance
    np.testing.assert_allclose(after.signed_distance[0], required, rtol=0.0, atol=1e-9)
    np.testing.assert_allclose(moved, tip + (required + 0.001) * top.normal[0], rtol=0.0, atol=1e-9)
    assert (pose.header.frame_id, pose.pose.orientation.x, pose.pose.orientation.w) == ("world", 0.6, 0.8)
    # clearance_sigmas set while the node runs applies to the next pose.
    setter = probe.create_client(SetParameters, f"{namespace}/tool_clearance_node/set_parameters")
    result = call_service(probe, setter, SetParameters.Request(
        parameters=[Parameter("clearance_sigmas", value=5.0).to_parameter_msg()])).results[0]
    assert result.successful, result.reason
    pose = safe_pose_for(desired(tip, 4 * S))
    after = surface.query([[pose.pose.position.x, pose.pose.position.y, pose.pose.position.z]])
    np.testing.assert_allclose(after.signed_distance[0], 5.0 * after.distance_std[0], rtol=0.0, atol=1e-9)
    # Far from the tissue: passed on as desired.
    far = safe_pose_for(desired((0.02, 0.02, 0.1), 3 * S))
    assert (far.pose.position.x, far.pose.position.y, far.pose.position.z) == (0.02, 0.02, 0.1)
    assert spin_until(probe, lambda: reports and reports[-1][0] == DiagnosticStatus.OK
                      and int(reports[-1][2]["poses_moved_out"]) >= 1, timeout_s=10.0), reports[-1:]
    # A best-effort publisher never reaches the reliable subscription: an ERROR, with the fix.
    best_effort = probe.create_publisher(PoseStamped, f"{namespace}/desired_tip_pose",
                                         QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT))
    assert spin_until(probe, lambda: reports[-1][0] == DiagnosticStatus.ERROR, timeout_s=15.0), reports[-1:]
    assert reports[-1][1].startswith(f"{namespace}/desired_tip_pose from /test_probe never arrives: it publishes "
                                     "best effort"), reports[-1][1]
    assert reports[-1][1].endswith("publish it with the QoS of the README's topic table"), reports[-1][1]
    probe.destroy_publisher(best_effort)
    assert_clean_exit(planner, planner.interrupt())
    assert_clean_exit(estimator, estimator.interrupt())
