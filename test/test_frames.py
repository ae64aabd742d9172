"""core.inputs.frames: a ROS-free tf buffer (chains, interpolation, bounded history, lookup errors)."""
import numpy as np
import pytest
from pytransform3d.transform_manager import TransformManager
from scipy.spatial.transform import Rotation

from meshfg_ros.core.inputs.frames import FrameLookupError, InvalidTransformError, StampedTransform, TransformBuffer

EPOCH_NS = 1_700_000_000_000_000_000  # stamps of a real clock: precision must survive them
NS = 1_000_000_000


def matrix(rotation: Rotation, translation) -> np.ndarray:
    result = np.eye(4)
    result[:3, :3] = rotation.as_matrix()
    result[:3, 3] = translation
    return result


def transform(parent, child, stamp_ns, rotation: Rotation, translation) -> StampedTransform:
    return StampedTransform(parent, child, stamp_ns, np.asarray(translation, dtype=float), rotation.as_quat())


# The robot of the tests: a camera arm whose joint turns and slides at constant rates (so that
# linear + slerp interpolation between 100 Hz samples is exact), and a tool arm.
WORLD_FROM_ECM_BASE = (Rotation.from_euler("x", 30, degrees=True), (0.5, 0.1, 0.8))
ECM_FROM_OPTICAL = (Rotation.from_euler("zyx", [90, 0, -90], degrees=True), (0.0, 0.02, 0.35))
WORLD_FROM_PSM_BASE = (Rotation.from_euler("y", -20, degrees=True), (-0.3, 0.2, 0.7))


def ecm_base_from_ecm(t_s: float):
    return Rotation.from_rotvec((0.2 + 0.5 * t_s) * np.array([0.0, 0.6, 0.8])), (0.01 * t_s, -0.02 * t_s, 0.1)


def psm_base_from_tool(t_s: float):
    return Rotation.from_euler("z", 10 + 40 * t_s, degrees=True), (0.05 * t_s, 0.0, 0.2 - 0.03 * t_s)


def robot_buffer(**options) -> TransformBuffer:
    buffer = TransformBuffer(**options)
    buffer.set_transform(transform("world", "ecm_base", 0, *WORLD_FROM_ECM_BASE), static=True)
    buffer.set_transform(transform("ecm", "endoscope_optical_frame", 0, *ECM_FROM_OPTICAL), static=True)
    buffer.set_transform(transform("world", "psm1_base", 0, *WORLD_FROM_PSM_BASE), static=True)
    for k in range(201):  # 2 s at 100 Hz
        stamp = EPOCH_NS + k * NS // 100
        buffer.set_transforms([transform("ecm_base", "ecm", stamp, *ecm_base_from_ecm(k / 100)),
                               transform("psm1_base", "psm1_tool", stamp, *psm_base_from_tool(k / 100))])
    return buffer


def known_world_from_optical(t_s: float) -> np.ndarray:
    return matrix(*WORLD_FROM_ECM_BASE) @ matrix(*ecm_base_from_ecm(t_s)) @ matrix(*ECM_FROM_OPTICAL)


def test_moving_camera_points_match_composed_transforms():
    buffer = robot_buffer()
    points = np.random.default_rng(3).uniform(-0.1, 0.1, (1000, 3)) + [0.0, 0.0, 0.15]
    for t_s in (0.0, 0.0123, 0.7777777, 1.2345, 2.0):
        stamp = EPOCH_NS + round(t_s * NS)
        world = buffer.transform_points(points, "world", "endoscope_optical_frame", stamp)
        expected = points @ known_world_from_optical(t_s)[:3, :3].T + known_world_from_optical(t_s)[:3, 3]
        np.testing.assert_allclose(world, expected, rtol=0, atol=1e-9)


def test_chain_through_world_matches_pytransform3d():
    """An independent chain resolver (pytransform3d, A2B = pose of A in B) on the same edges."""
    buffer = robot_buffer()
    t_s = 1.05
    manager = TransformManager()
    manager.add_transform("ecm_base", "world", matrix(*WORLD_FROM_ECM_BASE))
    manager.add_transform("ecm", "ecm_base", matrix(*ecm_base_from_ecm(t_s)))
    manager.add_transform("endoscope_optical_frame", "ecm", matrix(*ECM_FROM_OPTICAL))
    manager.add_transform("psm1_base", "world", matrix(*WORLD_FROM_PSM_BASE))
    manager.add_transform("psm1_tool", "psm1_base", matrix(*psm_base_from_tool(t_s)))
    stamp = EPOCH_NS + round(t_s * NS)
    for target, source in [("endoscope_optical_frame", "psm1_tool"), ("psm1_tool", "ecm"), ("ecm", "ecm"),
                           ("ecm_base", "world")]:
        np.testing.assert_allclose(buffer.lookup(target, source, stamp), manager.get_transform(source, target),
                                   rtol=0, atol=1e-12, err_msg=f"{target} <- {source}")


def test_lookup_and_its_reverse_are_inverse():
    buffer = robot_buffer()
    stamp = EPOCH_NS + 1_234_567_891
    forward = buffer.lookup("endoscope_optical_frame", "psm1_tool", stamp)
    backward = buffer.lookup("psm1_tool", "endoscope_optical_frame", stamp)
    assert forward.dtype == np.float64 and forward.shape == (4, 4)
    np.testing.assert_allclose(forward @ backward, np.eye(4), atol=1e-14)


def two_sample_buffer(second_rotation: Rotation, **options) -> TransformBuffer:
    buffer = TransformBuffer(**options)
    buffer.set_transform(transform("world", "tool", EPOCH_NS, Rotation.identity(), (0.0, 0.0, 0.0)))
    buffer.set_transform(transform("world", "tool", EPOCH_NS + NS, second_rotation, (1.0, 2.0, 3.0)))
    return buffer


def test_midpoint_is_linear_in_translation_and_slerp_in_rotation():
    axis = np.array([1.0, 1.0, 0.0]) / np.sqrt(2.0)
    buffer = two_sample_buffer(Rotation.from_rotvec(np.pi / 2 * axis))
    middle = buffer.lookup("world", "tool", EPOCH_NS + NS // 2)
    np.testing.assert_allclose(middle[:3, 3], [0.5, 1.0, 1.5], atol=1e-12)
    np.testing.assert_allclose(middle[:3, :3], Rotation.from_rotvec(np.pi / 4 * axis).as_matrix(), atol=1e-12)
    # A quarter of the way: slerp's 22.5 degrees (normalised linear quaternion blending gives 20.9).
    quarter = Rotation.from_matrix(buffer.lookup("world", "tool", EPOCH_NS + NS // 4)[:3, :3])
    assert quarter.magnitude() == pytest.approx(np.pi / 8, abs=1e-12)
    np.testing.assert_allclose(quarter.as_rotvec() / quarter.magnitude(), axis, atol=1e-12)


def test_slerp_takes_the_short_way_whatever_the_quaternion_sign():
    rotation = Rotation.from_euler("z", 170, degrees=True)
    negated = Rotation.from_quat(-rotation.as_quat())
    for second in (rotation, negated):
        middle = two_sample_buffer(second).lookup("world", "tool", EPOCH_NS + NS // 2)
        np.testing.assert_allclose(middle[:3, :3], Rotation.from_euler("z", 85, degrees=True).as_matrix(), atol=1e-12)


def test_no_extrapolation_by_default():
    buffer = two_sample_buffer(Rotation.identity())
    np.testing.assert_allclose(buffer.lookup("world", "tool", EPOCH_NS + NS)[:3, 3], [1.0, 2.0, 3.0])
    with pytest.raises(FrameLookupError) as error:
        buffer.lookup("world", "tool", EPOCH_NS + NS + 1)
    assert error.value.reason == FrameLookupError.BEYOND_HORIZON


def test_extrapolation_within_the_horizon_continues_the_motion():
    buffer = two_sample_buffer(Rotation.from_euler("z", 10, degrees=True), extrapolation_horizon_s=0.05)
    ahead = buffer.lookup("world", "tool", EPOCH_NS + NS + 40_000_000)
    np.testing.assert_allclose(ahead[:3, 3], [1.04, 2.08, 3.12], atol=1e-12)
    np.testing.assert_allclose(ahead[:3, :3], Rotation.from_euler("z", 10.4, degrees=True).as_matrix(), atol=1e-12)
    with pytest.raises(FrameLookupError) as error:
        buffer.lookup("world", "tool", EPOCH_NS + NS + 60_000_000)
    assert error.value.reason == FrameLookupError.BEYOND_HORIZON
    message = str(error.value)
    assert "60 ms beyond the newest transform 'world' -> 'tool'" in message
    assert "extrapolation horizon 50 ms" in message and "\n" not in message


def test_stamp_older_than_the_buffer():
    buffer = TransformBuffer(buffer_duration_s=1.0)
    for k in range(31):  # 3 s at 10 Hz: only the last second stays
        buffer.set_transform(transform("world", "tool", EPOCH_NS + k * NS // 10, Rotation.identity(), (k, 0, 0)))
    np.testing.assert_allclose(buffer.lookup("world", "tool", EPOCH_NS + 2 * NS)[:3, 3], [20, 0, 0])
    with pytest.raises(FrameLookupError) as error:
        buffer.lookup("world", "tool", EPOCH_NS + 1_999_999_999)
    assert error.value.reason == FrameLookupError.TOO_OLD
    assert "older than the buffered transforms 'world' -> 'tool'" in str(error.value)
    assert "buffer 1 s" in str(error.value)


def test_a_jump_back_restarts_the_history_and_a_late_sample_joins_it():
    """A looped recording's /tf starts again 2 s earlier: the edge follows the new timeline at
    once (a lookup at a new stamp interpolates the new samples, not the old ones); a sample late
    by less than jump_back_s is inserted in order."""
    buffer = TransformBuffer(jump_back_s=1.0)
    for k in range(21):  # 2 s at 10 Hz, moving +x
        buffer.set_transform(transform("world", "tool", EPOCH_NS + k * NS // 10, Rotation.identity(), (k, 0, 0)))
    for k in range(3):  # the loop: the same stamps again, moving -x
        buffer.set_transform(transform("world", "tool", EPOCH_NS + k * NS // 10, Rotation.identity(), (-k, 0, 0)))
    np.testing.assert_allclose(buffer.lookup("world", "tool", EPOCH_NS + NS // 20)[:3, 3], [-0.5, 0, 0])
    with pytest.raises(FrameLookupError) as error:  # the old timeline is gone
        buffer.lookup("world", "tool", EPOCH_NS + NS)
    assert error.value.reason == FrameLookupError.BEYOND_HORIZON
    buffer.set_transform(transform("world", "tool", EPOCH_NS + NS // 20, Rotation.identity(), (7, 0, 0)))
    np.testing.assert_allclose(buffer.lookup("world", "tool", EPOCH_NS + NS // 20)[:3, 3], [7, 0, 0])
    np.testing.assert_allclose(buffer.lookup("world", "tool", EPOCH_NS + 2 * NS // 10)[:3, 3], [-2, 0, 0])


def test_unknown_frame_and_separate_trees():
    buffer = robot_buffer()
    buffer.set_transform(transform("odom", "base_link", 0, Rotation.identity(), (0, 0, 0)), static=True)
    with pytest.raises(FrameLookupError) as error:
        buffer.lookup("world", "camera_link", EPOCH_NS)
    assert error.value.reason == FrameLookupError.UNKNOWN_FRAME
    assert str(error.value).startswith("unknown frame 'camera_link' (known frames: base_link, ecm, ecm_base,")
    with pytest.raises(FrameLookupError) as error:
        buffer.lookup("base_link", "psm1_tool", EPOCH_NS)
    assert error.value.reason == FrameLookupError.NO_PATH
    assert "separate trees, rooted at 'odom' and 'world'" in str(error.value)


def test_static_edges_hold_at_every_stamp_and_leading_slashes_are_ignored():
    buffer = robot_buffer()
    for stamp in (0, EPOCH_NS - 10 * NS, EPOCH_NS + 100 * NS):
        np.testing.assert_allclose(buffer.lookup("/world", "psm1_base", stamp), matrix(*WORLD_FROM_PSM_BASE),
                                   atol=1e-15)


def test_out_of_order_samples_give_the_same_lookups():
    rng = np.random.default_rng(5)
    stamps = EPOCH_NS + np.arange(50) * 20_000_000
    rotations = Rotation.random(50, random_state=rng)
    translations = rng.normal(size=(50, 3))
    in_order, shuffled = TransformBuffer(), TransformBuffer()
    for k in range(50):
        in_order.set_transform(transform("a", "b", int(stamps[k]), rotations[k], translations[k]))
    for k in rng.permutation(50):
        shuffled.set_transform(transform("a", "b", int(stamps[k]), rotations[k], translations[k]))
    for stamp in EPOCH_NS + rng.integers(0, 49 * 20_000_000, 20):
        np.testing.assert_array_equal(shuffled.lookup("a", "b", int(stamp)), in_order.lookup("a", "b", int(stamp)))


def test_a_lookup_at_a_sample_stamp_does_not_depend_on_the_samples_after_it():
    """A node may look a cloud's stamp up before or after the next /tf sample arrives (a loaded
    machine delays it); the replay looks it up as the recording's arrival order says. Where the
    stamp is a sample's, both must give the same matrix, bit for bit: the lookup's arithmetic is
    the same on one machine, and a difference of one rounding was amplified into 12 um of the
    live estimates (test_robot_wiring under load)."""
    rng = np.random.default_rng(11)
    stamps = EPOCH_NS + np.arange(8) * 100_000_000
    rotations = Rotation.random(8, random_state=rng)
    translations = rng.normal(size=(8, 3))
    samples = [transform("world", "arm", int(stamps[k]), rotations[k], translations[k]) for k in range(8)]
    complete, growing = TransformBuffer(), TransformBuffer()
    complete.set_transforms(samples)
    for k in range(8):
        growing.set_transform(samples[k])
        if k == 0:
            continue
        newest = growing.lookup("world", "arm", int(stamps[k]))  # the stamp is the newest sample's
        np.testing.assert_array_equal(newest, complete.lookup("world", "arm", int(stamps[k])))


def test_history_is_bounded_in_time_and_count():
    buffer = TransformBuffer(buffer_duration_s=1.0, max_samples_per_edge=50)
    for k in range(1000):  # 10 s at 100 Hz
        buffer.set_transform(transform("a", "b", k * NS // 100, Rotation.identity(), (k, 0, 0)))
    with pytest.raises(FrameLookupError) as error:
        buffer.lookup("a", "b", 950 * NS // 100 - 1)  # 1 s would keep 101 samples; the cap keeps 50
    assert error.value.reason == FrameLookupError.TOO_OLD
    np.testing.assert_allclose(buffer.lookup("a", "b", 950 * NS // 100)[:3, 3], [950, 0, 0])
    late = TransformBuffer(buffer_duration_s=1.0, jump_back_s=2.0)
    late.set_transform(transform("a", "b", 2 * NS, Rotation.identity(), (0, 0, 0)))
    assert not late.set_transform(transform("a", "b", NS // 2, Rotation.identity(), (0, 0, 0)))  # 1.5 s late
    np.testing.assert_allclose(late.lookup("a", "b", 2 * NS)[:3, 3], [0, 0, 0])


def test_a_message_with_a_bad_transform_keeps_the_good_ones():
    buffer = TransformBuffer()
    refused = buffer.set_transforms([
        StampedTransform("world", "x", EPOCH_NS, np.zeros(3), np.zeros(4)),
        transform("world", "y", EPOCH_NS, Rotation.identity(), (1, 2, 3)),
    ])
    assert len(refused) == 1 and "'world' -> 'x'" in refused[0] and "zero norm" in refused[0]
    np.testing.assert_allclose(buffer.lookup("world", "y", EPOCH_NS)[:3, 3], [1, 2, 3])
    assert "x" not in buffer.frames


def test_loops_and_bad_transforms_are_rejected():
    buffer = robot_buffer()
    tool_before = buffer.lookup("world", "psm1_tool", EPOCH_NS)
    with pytest.raises(InvalidTransformError, match="would close a loop"):
        buffer.set_transform(transform("endoscope_optical_frame", "world", 0, Rotation.identity(), (0, 0, 0)))
    with pytest.raises(InvalidTransformError, match="two different, non-empty frame names"):
        buffer.set_transform(transform("world", "world", 0, Rotation.identity(), (0, 0, 0)))
    with pytest.raises(InvalidTransformError, match="zero norm"):
        buffer.set_transform(StampedTransform("world", "x", 0, np.zeros(3), np.zeros(4)))
    with pytest.raises(InvalidTransformError, match="non-finite"):
        buffer.set_transform(StampedTransform("world", "x", 0, np.array([np.nan, 0, 0]), np.array([0, 0, 0, 1.0])))
    with pytest.raises(InvalidTransformError, match=r"'world' -> 'psm1_tool': stamp -5 ns is outside \[0, 2\*\*63\)"):
        buffer.set_transform(transform("world", "psm1_tool", -5, Rotation.identity(), (0, 0, 0)))
    with pytest.raises(InvalidTransformError, match="integer number of nanoseconds, got float"):
        buffer.set_transform(transform("world", "psm1_tool", 1.5, Rotation.identity(), (0, 0, 0)))
    # A rejected transform changes nothing: psm1_tool still hangs below psm1_base, not world.
    np.testing.assert_array_equal(buffer.lookup("world", "psm1_tool", EPOCH_NS), tool_before)


def test_a_new_parent_replaces_the_edge():
    buffer = robot_buffer()
    buffer.set_transform(transform("psm1_base", "endoscope_optical_frame", 0, Rotation.identity(), (0, 0, 1)),
                         static=True)
    np.testing.assert_allclose(buffer.lookup("psm1_base", "endoscope_optical_frame", 0)[:3, 3], [0, 0, 1])
