"""Cuts over real DDS: the simulation node cuts on a remove_elements request and with the tool's
blade, its predictions carry the cut topology, and the estimator (meshfg_stack) follows it: its
estimated_mesh lists the removed elements and invalid vertices, leaves them out of its
tetrahedra and surface, and never moves a removed vertex."""

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import UInt32MultiArray
from test_nodes import (KEEP, LATCHED, SIDE, S, Process, assert_clean_exit, cloud_msg, mesh_msg, probe,  # noqa: F401
                        processes, pushed_cube, ros_args, spin_until, tool_pose_msg)

from meshfg_msgs.msg import TetraMesh
from meshfg_ros.core.geometry.topology import cut_elements
from meshfg_ros.io.messages import mesh_state_from_msg

TOOL_RADIUS = 0.01


def wound(mesh):
    """Element slots of a blade box through the top of the cube, off the tool's path."""
    return cut_elements(mesh, [0.012, SIDE / 2, 0.04], [0.005, 0.02, 0.012])


def top_cloud(mesh, count=60, seed=0):
    """Points on the cut cube's top surface (the wound's faces excluded), 1 mm noise in depth."""
    rng = np.random.default_rng(seed)
    top = mesh.vertices[np.intersect1d(mesh.surface_vertices, np.flatnonzero(mesh.vertices[:, 2] > SIDE - 1e-9))]
    points = top[rng.integers(0, len(top), count)] + rng.uniform(-2e-3, 2e-3, (count, 3)) * [1, 1, 0]
    points[:, 2] += rng.normal(scale=1e-3, size=count)
    return points


@pytest.mark.slow
def test_a_requested_cut_reaches_the_predictions_and_the_estimates(probe, processes, tmp_path):
    mesh = pushed_cube()
    removed = wound(mesh)
    cut = mesh.without_elements(removed)
    assert cut.invalid_vertices.size
    stack = Process(tmp_path, "meshfg_stack", *ros_args("/cut", f"tool_radius:={TOOL_RADIUS}",
                                                         "prediction_timeout:=5.0"))
    processes.append(stack)
    mesh_publisher = probe.create_publisher(TetraMesh, "/cut/initial_mesh", LATCHED)
    pose_publisher = probe.create_publisher(PoseStamped, "/cut/tool_pose", KEEP)
    cut_publisher = probe.create_publisher(UInt32MultiArray, "/cut/remove_elements", KEEP)
    cloud_publisher = probe.create_publisher(PointCloud2, "/cut/points", KEEP)
    predictions, estimates, diagnostics = [], [], []
    subscriptions = [probe.create_subscription(TetraMesh, "/cut/predicted_mesh", predictions.append, KEEP),
                     probe.create_subscription(TetraMesh, "/cut/estimated_mesh", estimates.append, LATCHED)]
    probe.create_subscription(DiagnosticArray, "/diagnostics", lambda m: diagnostics.extend(
        {kv.key: kv.value for kv in s.values} for s in m.status if s.name == "/cut/simulation_node: simulation"), KEEP)
    assert spin_until(probe, lambda: all(p.get_subscription_count() >= 1 for p in (
        pose_publisher, cut_publisher, cloud_publisher)) and all(s.get_publisher_count() == 1 for s in subscriptions)
        and diagnostics)
    mesh_publisher.publish(mesh_msg(mesh))
    centre = np.array([0.035, SIDE / 2, SIDE + TOOL_RADIUS + 1e-3])
    pose_publisher.publish(tool_pose_msg(centre, 1 * S))

    def step(k, cloud_mesh):
        pose_publisher.publish(tool_pose_msg(centre - [0.0, 0.0, 5e-4 * k], (k + 1) * S))
        cloud_publisher.publish(cloud_msg(top_cloud(cloud_mesh, seed=k), (k + 1) * S))
        assert spin_until(probe, lambda: len(estimates) >= k and len(predictions) >= k), \
            f"{len(predictions)} predictions, {len(estimates)} estimates\n{stack.output()}"

    step(1, mesh)
    cut_publisher.publish(UInt32MultiArray(data=removed.astype(np.uint32).tolist()))
    cut_publisher.publish(UInt32MultiArray(data=[mesh.tetrahedron_count + 5]))  # out of range: counted, refused
    assert spin_until(probe, lambda: diagnostics and diagnostics[-1]["cuts_rejected"] == "1"
                      and diagnostics[-1]["elements_removed"] == str(removed.size)), stack.output()
    before = np.asarray(estimates[0].positions).reshape(-1, 3)
    step(2, cut)
    step(3, cut)
    first = mesh_state_from_msg(predictions[0])
    assert first.removed_elements.size == 0 and first.invalid_vertices.size == 0
    for message in (*predictions[1:], *estimates[1:]):
        state = mesh_state_from_msg(message)
        np.testing.assert_array_equal(state.removed_elements, removed)
        np.testing.assert_array_equal(state.invalid_vertices, cut.invalid_vertices)
        np.testing.assert_array_equal(state.tetrahedra, cut.tetrahedra)
        np.testing.assert_array_equal(state.surface_triangles, cut.surface_triangles)
        np.testing.assert_array_equal(state.fixed_vertices, mesh.fixed_vertices)
    last = mesh_state_from_msg(estimates[-1])
    np.testing.assert_array_equal(last.positions[cut.invalid_vertices], before[cut.invalid_vertices])
    assert np.all(last.position_std[cut.invalid_vertices] == 0.0)
    assert np.all(np.isfinite(last.positions))
    assert_clean_exit(stack, stack.interrupt())


@pytest.mark.slow
def test_the_tool_blade_cuts_what_it_reaches(probe, processes, tmp_path):
    mesh = pushed_cube()
    # A blade 1 cm long under the tool's centre, 6 mm deep into the top once the tool is lowered.
    node = Process(tmp_path, "simulation_node", *ros_args(
        "/blade", f"tool_radius:={TOOL_RADIUS}", "blade_half_extents:=[0.0005, 0.005, 0.003]",
        f"blade_offset:=[-0.02, 0.0, {-TOOL_RADIUS}]"))
    processes.append(node)
    mesh_publisher = probe.create_publisher(TetraMesh, "/blade/initial_mesh", LATCHED)
    pose_publisher = probe.create_publisher(PoseStamped, "/blade/tool_pose", KEEP)
    diagnostics = []
    probe.create_subscription(DiagnosticArray, "/diagnostics", lambda m: diagnostics.extend(
        {kv.key: kv.value for kv in s.values} for s in m.status if s.name == "/blade/simulation_node: simulation"),
        KEEP)
    assert spin_until(probe, lambda: pose_publisher.get_subscription_count() == 1 and diagnostics)
    mesh_publisher.publish(mesh_msg(mesh))
    above = np.array([0.035, SIDE / 2, SIDE + TOOL_RADIUS + 0.01])  # the blade 7 mm above the top: no cut
    pose_publisher.publish(tool_pose_msg(above, 1 * S))
    assert spin_until(probe, lambda: diagnostics and diagnostics[-1]["tool_poses_received"] == "1")
    assert diagnostics[-1]["elements_removed"] == "0"
    lowered = above - [0.0, 0.0, 0.01]
    pose_publisher.publish(tool_pose_msg(lowered, 2 * S))
    blade_centre = lowered + [-0.02, 0.0, -TOOL_RADIUS]
    expected = cut_elements(mesh, blade_centre, [0.0005, 0.005, 0.003])
    assert expected.size
    assert spin_until(probe, lambda: diagnostics[-1]["elements_removed"] == str(expected.size)), node.output()
    assert diagnostics[-1]["cuts_rejected"] == "0"
    assert_clean_exit(node, node.interrupt())
