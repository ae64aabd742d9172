"""Inputs in any frame: clouds from a camera moving on a /tf chain and tool poses in a robot base
frame give the same estimates as the same inputs in world_frame (core/inputs/world_frame.py, replay)."""
import numpy as np
import pytest
from offline_helpers import BASE, NOISE_SIGMA, OPTICAL, TOOL_RADIUS, robot_statics, tiny_scenario
from scipy.spatial.transform import Rotation

from meshfg_ros.core.inputs.frames import StampedTransform, TransformBuffer
from meshfg_ros.core.inputs.pose_history import pose_matrix
from meshfg_ros.core.inputs.world_frame import CLOUD, POSE, FramedInput, WorldFrameInputs, pose_in
from meshfg_ros.io.messages import MeshState, PointCloudRecord, PoseRecord
from meshfg_ros.io.recording import RecordingWriter
from meshfg_ros.io.tf_messages import TF_STATIC_TOPIC, TF_TOPIC, transforms_to_tf_message
from meshfg_ros.core.scheduler import OfflinePipeline, run_offline
from meshfg_ros.parameters import estimator_config, simulator_config
from meshfg_ros.replay import load_inputs, replay_recording
from meshfg_ros.synthetic.scenarios import FIRST_STAMP_NS
from meshfg_ros.topics import INITIAL_MESH_TOPIC, POINTS_TOPIC, TOOL_POSE_TOPIC

PARAMS = {"max_iterations": 3, "tool_radius": TOOL_RADIUS, "measurement_sigma": NOISE_SIGMA,
          "simulator_substeps": 4, "simulator_iterations": 4}


def arm_pose(stamp_ns: int) -> np.ndarray:
    """world -> ecm_link: an arm that swings and moves (its pose at a stamp)."""
    t = (stamp_ns - FIRST_STAMP_NS) / 1e9
    rotation = Rotation.from_euler("xyz", [10.0 * np.sin(t), 5.0 * t, -20.0 + 3.0 * t], degrees=True)
    return np.array([0.02 * t, 0.1 - 0.01 * t, 0.25, *rotation.as_quat()])


def optical_pose(stamp_ns: int) -> np.ndarray:
    """world -> endoscope_optical_frame at a stamp, composed by hand."""
    return pose_in(pose_matrix(arm_pose(stamp_ns)), OPTICAL)


def write(path, scenario, framed: bool) -> None:
    """The scenario's inputs, in world_frame or (framed) clouds in the moving optical frame and
    tool poses in a robot base frame, with /tf (a 10 Hz arm) and /tf_static."""
    mesh = scenario.initial_mesh
    with RecordingWriter(path) as writer:
        writer.write(INITIAL_MESH_TOPIC, MeshState(FIRST_STAMP_NS, "world", 0, mesh.vertices, mesh.tetrahedra,
                                                   mesh.surface_triangles, mesh.fixed_vertices))
        if framed:
            writer.write(TF_STATIC_TOPIC, transforms_to_tf_message(robot_statics()), FIRST_STAMP_NS)
        poses = [(FIRST_STAMP_NS, scenario.initial_tool_pose)] + [(s.stamp_ns, s.tool_pose) for s in scenario.steps]
        last = scenario.steps[-1].stamp_ns
        for stamp in range(FIRST_STAMP_NS, last + 200_000_000, 100_000_000):
            if framed:
                arm = arm_pose(stamp)
                writer.write(TF_TOPIC, transforms_to_tf_message([StampedTransform("world", "ecm_link", stamp,
                                                                                  arm[:3], arm[3:])]), stamp)
        for index, (stamp, tool_pose) in enumerate(poses):
            frame, pose = "world", np.asarray(tool_pose, dtype=np.float64)
            if framed:
                frame, pose = "psm1_base", pose_in(np.linalg.inv(pose_matrix(BASE)), pose)
            writer.write(TOOL_POSE_TOPIC, PoseRecord(stamp, frame, pose), stamp)
            if index == 0:
                continue
            points = scenario.steps[index - 1].points
            frame = "world"
            if framed:
                to_optical = np.linalg.inv(pose_matrix(optical_pose(stamp)))
                points, frame = points @ to_optical[:3, :3].T + to_optical[:3, 3], "endoscope_optical_frame"
            # the cloud is logged 150 ms after its stamp (camera latency): the /tf around it is in
            writer.write(POINTS_TOPIC, PointCloudRecord(stamp, frame, points), stamp + 150_000_000)


@pytest.fixture(scope="module")
def scenario():
    return tiny_scenario(steps=3)


def test_clouds_in_a_moving_optical_frame_give_the_world_frame_estimates(scenario, tmp_path):
    """The recorded clouds (FLOAT32 in the optical frame) moved into the world by the hand-composed
    chain, and the tool poses in the world, fed to the step loop directly: the same estimates as
    the replay that places both through /tf, to 1e-9 m."""
    write(tmp_path / "framed", scenario, framed=True)
    framed = replay_recording(tmp_path / "framed", PARAMS)
    inputs = load_inputs(tmp_path / "framed")
    params = framed.parameters
    pipeline = OfflinePipeline(inputs.initial_mesh, simulator_config(params), estimator_config(params))
    events = [("pose", FIRST_STAMP_NS, scenario.initial_tool_pose)]
    for step, cloud in zip(scenario.steps, inputs.clouds, strict=True):
        to_world = pose_matrix(optical_pose(cloud.stamp_ns))
        events += [("pose", step.stamp_ns, step.tool_pose),
                   ("cloud", cloud.stamp_ns, cloud.points @ to_world[:3, :3].T + to_world[:3, 3])]
    in_world = list(run_offline(pipeline, events))
    assert len(in_world) == len(framed.steps) == 3
    for a, b in zip(in_world, framed.steps):
        assert a.stamp_ns == b.stamp_ns and not b.result.degraded
        np.testing.assert_allclose(b.points, a.points, rtol=0, atol=1e-9)
        np.testing.assert_allclose(b.result.positions, a.result.positions, rtol=0, atol=1e-9)
    # and the points did move: the optical frame is not the world
    assert np.abs(inputs.clouds[0].points - framed.steps[0].points).max() > 0.05


def test_an_input_waits_for_its_transform_then_is_set_aside_with_the_reason():
    placer = WorldFrameInputs("world", TransformBuffer(), wait_s=0.5)
    cloud = FramedInput(CLOUD, 2_000_000_000, "camera", np.zeros((4, 3)), arrival_s=10.0)
    pose = FramedInput(POSE, 2_000_000_000, "world", np.array([0, 0, 0, 0, 0, 0, 1.0]), arrival_s=10.1)
    second = FramedInput(CLOUD, 2_100_000_000, "camera", np.ones((4, 3)), arrival_s=10.1)
    assert placer.add(cloud, 10.0) == ([], [])
    assert placer.add(second, 10.1) == ([], [])  # behind the waiting cloud of its stream
    assert placer.add(pose, 10.1) == ([pose], [])  # another stream's input is not held up
    for stamp in (2_000_000_000, 2_100_000_000):
        placer.transforms.set_transform(StampedTransform("world", "camera", stamp, [0.0, 0.0, 1.0],
                                                         [0.0, 0.0, 0.0, 1.0]))
    placed, set_aside = placer.release(10.2)
    assert [item.stamp_ns for item in placed] == [2_000_000_000, 2_100_000_000] and not set_aside
    np.testing.assert_allclose(placed[0].data, [[0.0, 0.0, 1.0]] * 4)
    late = FramedInput(CLOUD, 3_000_000_000, "camera", np.zeros((1, 3)), arrival_s=11.0)
    assert placer.add(late, 11.0) == ([], [])  # beyond the newest transform: waits
    placed, set_aside = placer.release(11.6)
    assert placed == [] and len(set_aside) == 1 and "beyond" in set_aside[0].reason


def test_a_cloud_carries_the_camera_origin_as_its_viewpoint():
    """Whatever frame a cloud comes in, its viewpoint is camera_frame's origin at its stamp; a
    camera frame nothing places gives none."""
    camera = np.array([0.1, -0.2, 0.3, 1.0, 0.0, 0.0, 0.0])
    placer = WorldFrameInputs("world", fallback={"camera": pose_matrix(camera)}, viewpoint_frame="camera")
    for frame in ("camera", "world"):
        placed, _ = placer.add(FramedInput(CLOUD, 1, frame, np.zeros((2, 3))))
        np.testing.assert_allclose(placed[0].viewpoint, camera[:3], atol=1e-15)
    pose, _ = placer.add(FramedInput(POSE, 2, "world", np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0])))
    assert pose[0].viewpoint is None
    unknown = WorldFrameInputs("world", viewpoint_frame="endoscope")
    placed, _ = unknown.add(FramedInput(CLOUD, 1, "world", np.zeros((2, 3))))
    assert placed[0].viewpoint is None


def test_a_static_fallback_serves_a_frame_no_transform_names():
    camera = np.array([0.0, 0.0, 0.1, 1.0, 0.0, 0.0, 0.0])  # looking down
    placer = WorldFrameInputs("world", fallback={"camera": pose_matrix(camera)})
    placed, _ = placer.add(FramedInput(CLOUD, 1, "camera", np.array([[0.0, 0.0, 0.1]])))
    np.testing.assert_allclose(placed[0].data, [[0.0, 0.0, 0.0]], atol=1e-15)
