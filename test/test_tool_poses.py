"""core.inputs.tool_poses: tool poses interpolated to cloud stamps, bounded extrapolation, countable reasons."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation, Slerp

from meshfg_ros.core.inputs.pose_history import InvalidPoseError
from meshfg_ros.core.inputs.tool_poses import PoseUnavailable, ToolPoseBuffer

EPOCH_NS = 1_700_000_000_000_000_000
PERIOD_NS = 100_000_000  # 10 Hz
OFFSET_NS = 3_000_000  # queries 3 ms after each pose
AXIS = np.array([2.0, -1.0, 2.0]) / 3.0


def tool_pose(t_s: float) -> np.ndarray:
    """A tool that slides and turns about a fixed axis at constant rates: exact under linear + slerp."""
    position = np.array([0.01, -0.02, 0.15]) + t_s * np.array([0.02, 0.005, -0.01])
    return np.concatenate([position, Rotation.from_rotvec((0.3 + 0.8 * t_s) * AXIS).as_quat()])


def assert_same_pose(actual, expected, atol=1e-9):
    np.testing.assert_allclose(actual[:3], expected[:3], rtol=0, atol=atol)
    np.testing.assert_allclose(Rotation.from_quat(actual[3:]).as_matrix(), Rotation.from_quat(expected[3:]).as_matrix(),
                               rtol=0, atol=atol)


def ten_hertz_buffer(count=30, **options) -> ToolPoseBuffer:
    buffer = ToolPoseBuffer(**options)
    for k in range(count):
        buffer.insert(EPOCH_NS + k * PERIOD_NS, tool_pose(k * PERIOD_NS / 1e9))
    return buffer


def test_ten_hertz_poses_interpolate_to_stamps_three_ms_later():
    buffer = ten_hertz_buffer()
    for k in range(29):
        stamp = EPOCH_NS + k * PERIOD_NS + OFFSET_NS
        assert_same_pose(buffer.pose_at(stamp), tool_pose((k * PERIOD_NS + OFFSET_NS) / 1e9))


def test_interpolation_matches_scipy_slerp_on_random_rotations():
    rng = np.random.default_rng(11)
    stamps = EPOCH_NS + np.arange(20) * PERIOD_NS
    rotations, positions = Rotation.random(20, random_state=rng), rng.normal(size=(20, 3))
    buffer = ToolPoseBuffer()
    for stamp, rotation, position in zip(stamps, rotations, positions):
        buffer.insert(int(stamp), np.concatenate([position, rotation.as_quat()]))
    slerp = Slerp((stamps - EPOCH_NS) / 1e9, rotations)
    for k in range(19):
        stamp = int(stamps[k]) + OFFSET_NS
        fraction = OFFSET_NS / PERIOD_NS
        expected = np.concatenate([positions[k] + fraction * (positions[k + 1] - positions[k]),
                                   slerp((stamp - EPOCH_NS) / 1e9).as_quat()])
        assert_same_pose(buffer.pose_at(stamp), expected)


def test_extrapolation_stops_at_the_horizon():
    buffer = ten_hertz_buffer(extrapolation_horizon_s=0.05)
    newest = EPOCH_NS + 29 * PERIOD_NS
    assert_same_pose(buffer.pose_at(newest + 50_000_000), tool_pose(2.95))  # constant velocity: exact here
    with pytest.raises(PoseUnavailable) as error:
        buffer.pose_at(newest + 50_000_001)
    assert error.value.reason == PoseUnavailable.BEYOND_HORIZON
    assert "50 ms beyond the newest" in str(error.value) and "extrapolation horizon 50 ms" in str(error.value)


def test_unavailable_reasons_are_counted():
    buffer = ToolPoseBuffer()
    with pytest.raises(PoseUnavailable) as error:
        buffer.pose_at(EPOCH_NS)
    assert error.value.reason == PoseUnavailable.EMPTY
    buffer = ten_hertz_buffer()
    for stamp in (EPOCH_NS - 1, EPOCH_NS - PERIOD_NS, EPOCH_NS + 40 * PERIOD_NS):
        with pytest.raises(PoseUnavailable):
            buffer.pose_at(stamp)
    assert buffer.unavailable == {PoseUnavailable.BEFORE_FIRST: 2, PoseUnavailable.BEYOND_HORIZON: 1}
    assert_same_pose(buffer.pose_at(EPOCH_NS), tool_pose(0.0))


def test_single_pose_holds_within_the_horizon():
    buffer = ToolPoseBuffer(extrapolation_horizon_s=0.1)
    buffer.insert(EPOCH_NS, tool_pose(0.0))
    assert_same_pose(buffer.pose_at(EPOCH_NS + 100_000_000), tool_pose(0.0))


def test_out_of_order_insertion_gives_the_same_poses():
    in_order = ten_hertz_buffer()
    shuffled = ToolPoseBuffer()
    for k in np.random.default_rng(2).permutation(30):
        shuffled.insert(EPOCH_NS + int(k) * PERIOD_NS, tool_pose(k * PERIOD_NS / 1e9))
    for stamp in EPOCH_NS + np.arange(0, 29 * PERIOD_NS, 7_000_000):
        np.testing.assert_array_equal(shuffled.pose_at(int(stamp)), in_order.pose_at(int(stamp)))


def test_repeated_stamp_replaces_the_pose():
    buffer = ten_hertz_buffer()
    buffer.insert(EPOCH_NS + 5 * PERIOD_NS, tool_pose(100.0))
    assert len(buffer) == 30
    assert_same_pose(buffer.pose_at(EPOCH_NS + 5 * PERIOD_NS), tool_pose(100.0))


def test_jump_back_is_dropped_until_cleared():
    buffer = ten_hertz_buffer(buffer_duration_s=1.0)
    assert not buffer.insert(EPOCH_NS - 60 * 10**9, tool_pose(0.0))  # a looped recording starts again
    buffer.clear()
    assert buffer.insert(EPOCH_NS - 60 * 10**9, tool_pose(0.0))
    assert buffer.insert(EPOCH_NS - 60 * 10**9 + PERIOD_NS, tool_pose(0.1))
    assert_same_pose(buffer.pose_at(EPOCH_NS - 60 * 10**9 + OFFSET_NS), tool_pose(0.003))


def test_memory_is_bounded():
    buffer = ToolPoseBuffer(buffer_duration_s=1.0, max_samples=500)
    for k in range(5000):  # 5 s at 1 kHz
        buffer.insert(k * 1_000_000, tool_pose(k / 1000))
    assert len(buffer) == 500
    with pytest.raises(PoseUnavailable) as error:
        buffer.pose_at(4_499_000_000)
    assert error.value.reason == PoseUnavailable.BEFORE_FIRST
    buffer = ToolPoseBuffer(buffer_duration_s=1.0)
    for k in range(5000):
        buffer.insert(k * 1_000_000, tool_pose(k / 1000))
    assert len(buffer) == 1001  # stamps within 1 s of the newest, both ends included


def test_bad_poses_and_stamps_are_rejected():
    buffer = ToolPoseBuffer()
    with pytest.raises(InvalidPoseError, match="7 values"):
        buffer.insert(EPOCH_NS, [0.0, 0.0, 0.0, 1.0])
    with pytest.raises(InvalidPoseError, match="zero norm"):
        buffer.insert(EPOCH_NS, [0.0] * 7)
    with pytest.raises(InvalidPoseError, match="integer number of nanoseconds"):
        buffer.insert(1.5, tool_pose(0.0))
    assert len(buffer) == 0
