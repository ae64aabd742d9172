"""The nodes under hostile input: input far outside the scene and bad stamps counted in /diagnostics
(estimator and simulation node, over real DDS), an ERROR while the solver answers no cloud, and a
shutdown that does not wait for an update that does not end."""
import threading
import time
from types import SimpleNamespace

import numpy as np
import pytest
import rclpy
from diagnostic_msgs.msg import DiagnosticStatus
from geometry_msgs.msg import PoseStamped
from std_msgs.msg import Header
from rclpy.parameter import Parameter
from test_nodes import (  # noqa: F401 - probe and processes are fixtures
    FACTORY,
    KEEP,
    LATCHED,
    S,
    SIDE,
    EstimatorProbe,
    Process,
    assert_clean_exit,
    cloud_msg,
    mesh_msg,
    probe,
    processes,
    pushed_cube,
    ros_args,
    simulation_reports,
    spin_until,
    tool_pose_msg,
    top_points,
)

from meshfg_msgs.msg import TetraMesh
from meshfg_ros.core.estimation.estimator import EstimatorStepError, SlidingWindowEstimator
from meshfg_ros.io.messages import MeshState, PoseRecord, header_msg, pose_to_msg


@pytest.mark.slow
def test_estimator_node_counts_input_set_aside_and_bad_stamps(probe, processes, tmp_path):
    mesh = pushed_cube()
    # the camera above the measured top face (at the default origin, below it, the node warns of the camera)
    node = Process(tmp_path, "estimator_node", *ros_args("/hostile", "prediction_timeout:=0.3", "window_size:=3",
                                                         "camera_pose:=[0.025, 0.025, 0.15, 1.0, 0.0, 0.0, 0.0]"))
    processes.append(node)
    io = EstimatorProbe(probe, "/hostile")
    tool = probe.create_publisher(PoseStamped, "/hostile/tool_pose", KEEP)
    assert spin_until(probe, lambda: io.cloud.get_subscription_count() == 1 and tool.get_subscription_count() == 1
                      and io.prediction.get_subscription_count() == 1)
    io.wait_for(clouds_received=0)
    io.mesh.publish(mesh_msg(mesh))
    points = top_points()
    top = int(np.flatnonzero(np.isclose(mesh.vertices[:, 2], SIDE))[0])
    far = mesh.vertices.copy()
    far[top] = 1e20
    io.prediction.publish(mesh_msg(mesh, 1 * S, far))
    tool.publish(tool_pose_msg([1e20, 0.0, 0.0], 1 * S))
    counters = io.send(cloud_msg(np.vstack([points, np.full((5, 3), 1e30)]), 1 * S), steps=1, degraded_steps=1,
                       predictions_rejected_far=1, clouds_with_far_points=1, tool_poses_ignored_far=1)
    assert counters["predictions_rejected_inverted"] == "0" and counters["predictions_rejected_innovation"] == "0"
    assert io.statuses[-1].num_points == len(points) and io.statuses[-1].num_points_rejected == 5
    io.send(cloud_msg(points, -2 * S), clouds_rejected_stamp=1)  # a negative header time
    io.prediction.publish(mesh_msg(mesh, 2 * S))
    io.send(cloud_msg(points, 2 * S), steps=2, degraded_steps=1, predictions_rejected_far=1)
    assert io.diagnostics[-1][0] == "estimating"
    assert np.isfinite(np.asarray(io.estimates[-1].positions)).all()
    assert node.alive()
    assert_clean_exit(node, node.interrupt())


@pytest.mark.slow
def test_simulation_node_counts_rejected_tool_poses_in_its_diagnostics(probe, processes, tmp_path):
    mesh = pushed_cube()
    node = Process(tmp_path, "simulation_node", *ros_args("/simhostile", "estimate_timeout:=0.0"))
    processes.append(node)
    reports = simulation_reports(probe, "/simhostile")
    mesh_publisher = probe.create_publisher(TetraMesh, "/simhostile/initial_mesh", LATCHED)
    poses = probe.create_publisher(PoseStamped, "/simhostile/tool_pose", KEEP)
    assert spin_until(probe, lambda: poses.get_subscription_count() == 1 and reports)
    assert reports[-1][0] == "waiting for initial_mesh"
    in_map = mesh_msg(mesh)
    in_map.header.frame_id = "map"
    mesh_publisher.publish(in_map)  # refused, counted and named while the node waits
    assert spin_until(probe, lambda: reports[-1][1].get("initial_meshes_rejected") == "1"), reports[-1:]
    assert reports[-1][0] == ("waiting for initial_mesh; 1 initial_mesh rejected, the last: initial_mesh in frame "
                              "'map', expected 'world': rejected")
    mesh_publisher.publish(mesh_msg(mesh))
    centre = [SIDE / 2, SIDE / 2, SIDE + 0.011]
    poses.publish(tool_pose_msg(centre, 1 * S))  # the first pose resets the simulator
    poses.publish(tool_pose_msg([1e20, 0.0, 0.0], 2 * S))
    poses.publish(tool_pose_msg(centre, -1 * S))
    poses.publish(pose_to_msg(PoseRecord(3 * S, "map", [*centre, 0.0, 0.0, 0.0, 1.0]), FACTORY))
    poses.publish(tool_pose_msg(centre, 4 * S))
    requests = probe.create_publisher(Header, "/simhostile/prediction_request", KEEP)
    assert spin_until(probe, lambda: requests.get_subscription_count() == 1)
    requests.publish(header_msg(4 * S, "world", FACTORY))  # a cloud at 4 s: predicted
    expected = dict(tool_poses_received="5", tool_poses_rejected_far="1", tool_poses_rejected_stamp="1",
                    tool_poses_rejected_frame="1", tool_poses_rejected="3", requests="1", predictions="1")
    assert spin_until(probe, lambda: reports and all(reports[-1][1].get(k) == v for k, v in expected.items())), \
        reports[-1:]
    # An estimate whose posterior std has a wrong count: its positions are taken (the next
    # prediction starts from them), its std is not, and the diagnostics say so.
    estimates = probe.create_publisher(TetraMesh, "/simhostile/estimated_mesh", LATCHED)
    assert spin_until(probe, lambda: estimates.get_subscription_count() == 1)
    estimate = mesh_msg(mesh, 4 * S)
    estimate.position_std = [1e-3, 1e-3]
    estimates.publish(estimate)
    assert spin_until(probe, lambda: reports[-1][1].get("estimate_std_ignored") == "1"), reports[-1:]
    assert spin_until(probe, lambda: any(message.startswith("1 estimates' position_std malformed")
                                         for message, _ in reports)), [message for message, _ in reports]
    assert reports[-1][1]["estimates_ignored"] == "0" and float(reports[-1][1]["poisson_ratio"]) == 0.45
    assert node.alive()
    assert_clean_exit(node, node.interrupt())


@pytest.mark.slow
def test_a_stuck_update_is_an_error_and_does_not_hold_up_shutdown(monkeypatch):
    """An update that never returns (the issue's SVD hang): after the prediction timeout and two
    time budgets the diagnostics say ERROR, and destroying the node does not wait for it."""
    from meshfg_ros.nodes.estimator_node import EstimatorNode

    entered, release = threading.Event(), threading.Event()

    def stuck(self, *args, **kwargs):
        entered.set()
        release.wait()
        raise EstimatorStepError("released")

    monkeypatch.setattr(SlidingWindowEstimator, "update", stuck)
    context = rclpy.Context()  # its own: the module's probe holds the default one
    context.init()
    try:
        node = EstimatorNode(context=context, parameter_overrides=[Parameter("prediction_timeout", value=0.0),
                                                  Parameter("update_time_budget", value=0.01)])
        reports = []
        node.outputs._diagnostics = SimpleNamespace(publish=reports.append)
        mesh = pushed_cube()
        node._set_mesh(mesh, MeshState(0, "world", 0, mesh.vertices, mesh.tetrahedra, mesh.surface_triangles,
                                        mesh.fixed_vertices))
        node._on_cloud(cloud_msg(top_points(), 1 * S))
        assert entered.wait(30.0)
        for _ in range(100):  # the limit: 0 s + 2 x 0.01 s + the margin of 1 s
            time.sleep(0.1)
            node.outputs.report()
            if reports[-1].status[0].level == DiagnosticStatus.ERROR:
                break
        assert reports[-1].status[0].level == DiagnosticStatus.ERROR
        assert reports[-1].status[0].message.startswith("no estimate for the clouds of the last")
        stopper = threading.Thread(target=node.destroy_node)
        stopper.start()
        stopper.join(60.0)
        assert not stopper.is_alive() and not release.is_set()
    finally:
        release.set()
        context.try_shutdown()
