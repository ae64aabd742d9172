"""PointCloud2 <-> numpy: layouts, byte orders, non-finite points, malformed clouds, flavours."""

import re
from types import SimpleNamespace

import numpy as np
import pytest

from meshfg_ros.io.messages import (
    POINT_CLOUD2,
    PointCloudRecord,
    RclpyMessageFactory,
    meshfg_typestore,
)
from meshfg_ros.io.pointcloud import (
    FLOAT32,
    FLOAT64,
    UINT8,
    UINT16,
    PointCloudError,
    cloud_record_from_msg,
    cloud_record_to_msg,
    decode_pointcloud2,
    decode_xyz,
    encode_xyz,
)

_NUMPY = {UINT8: "u1", UINT16: "u2", FLOAT32: "f4", FLOAT64: "f8"}


def pack_cloud(columns, layout, point_step, height, width, row_step, big_endian=False):
    """Raw PointCloud2 pieces built independently of the code under test.

    columns: name -> (height*width,) values; layout: list of (name, offset, datatype).
    Bytes not covered by a field (point and row padding) are filled with 0xAB.
    """
    order = ">" if big_endian else "<"
    data = bytearray(b"\xab" * (row_step * height))
    for name, offset, datatype in layout:
        encoded = np.asarray(columns[name], dtype=order + _NUMPY[datatype]).reshape(height, width)
        size = encoded.dtype.itemsize
        for row in range(height):
            for column in range(width):
                start = row * row_step + column * point_step + offset
                data[start:start + size] = encoded[row, column:column + 1].tobytes()
    fields = [SimpleNamespace(name=n, offset=o, datatype=d, count=1) for n, o, d in layout]
    return fields, bytes(data)


@pytest.fixture
def rng():
    return np.random.default_rng(7)


def test_encode_then_decode_gives_float32_rounded_points_and_labels(rng):
    points = rng.normal(size=(50, 3))
    labels = rng.integers(0, 5, size=50)
    msg = encode_xyz(points, "camera", 1_234_567_890_123, extra_fields={"label": labels})
    assert [f.name for f in msg.fields] == ["x", "y", "z", "label"]
    assert [f.offset for f in msg.fields] == [0, 4, 8, 12]
    assert all(f.datatype == FLOAT32 and f.count == 1 for f in msg.fields)
    assert (msg.height, msg.width, msg.point_step, msg.row_step) == (1, 50, 16, 800)
    assert msg.is_dense and not msg.is_bigendian
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (1234, 567_890_123)
    decoded = decode_pointcloud2(msg, extra_fields=["label"])
    np.testing.assert_array_equal(decoded.points, points.astype(np.float32).astype(np.float64))
    np.testing.assert_array_equal(decoded.extra["label"], labels.astype(np.float64))
    assert decoded.dropped_nonfinite == 0


def test_shuffled_fields_point_padding_and_float64(rng):
    n = 6
    columns = {"x": rng.normal(size=n), "y": rng.normal(size=n), "z": rng.normal(size=n),
               "intensity": rng.integers(0, 60000, size=n)}
    layout = [("z", 0, FLOAT64), ("intensity", 8, UINT16), ("x", 16, FLOAT64), ("y", 28, FLOAT32)]
    fields, data = pack_cloud(columns, layout, point_step=40, height=1, width=n, row_step=40 * n)
    decoded = decode_xyz(fields, data, 1, n, 40, 40 * n, False, extra_fields=["intensity"])
    expected = np.stack([columns["x"], columns["y"].astype(np.float32), columns["z"]], axis=1)
    np.testing.assert_array_equal(decoded.points, expected)
    np.testing.assert_array_equal(decoded.extra["intensity"], columns["intensity"])


def test_row_step_padding_keeps_row_major_order(rng):
    height, width, point_step = 3, 4, 12
    row_step = width * point_step + 13
    xyz = rng.normal(size=(height * width, 3)).astype(np.float32)
    columns = dict(zip("xyz", xyz.T))
    layout = [("x", 0, FLOAT32), ("y", 4, FLOAT32), ("z", 8, FLOAT32)]
    fields, data = pack_cloud(columns, layout, point_step, height, width, row_step)
    decoded = decode_xyz(fields, np.frombuffer(data, np.uint8), height, width, point_step, row_step, False)
    np.testing.assert_array_equal(decoded.points, xyz.astype(np.float64))


@pytest.mark.parametrize("datatype", [FLOAT32, FLOAT64])
def test_big_endian_data(rng, datatype):
    n = 9
    xyz = rng.normal(size=(n, 3)).astype(_NUMPY[datatype])
    layout = [("y", 0, datatype), ("x", 8, datatype), ("z", 16, datatype)]
    fields, data = pack_cloud(dict(zip("xyz", xyz.T)), layout, 24, 1, n, 24 * n, big_endian=True)
    decoded = decode_xyz(fields, data, 1, n, 24, 24 * n, True)
    np.testing.assert_array_equal(decoded.points, xyz.astype(np.float64))
    misread = decode_xyz(fields, data, 1, n, 24, 24 * n, False)
    assert not np.array_equal(misread.points, decoded.points)


def test_nonfinite_points_are_dropped_and_counted_even_if_dense_is_claimed(rng):
    points = rng.normal(size=(8, 3))
    points[1, 0] = np.nan
    points[4, 2] = np.inf
    points[6] = -np.inf
    msg = encode_xyz(points, "camera", 5, extra_fields={"label": np.arange(8)})
    assert not msg.is_dense
    msg.is_dense = True  # a lying publisher must not get NaNs through
    decoded = decode_pointcloud2(msg, extra_fields=["label"])
    keep = [0, 2, 3, 5, 7]
    assert decoded.dropped_nonfinite == 3
    np.testing.assert_array_equal(decoded.points, points[keep].astype(np.float32).astype(np.float64))
    np.testing.assert_array_equal(decoded.extra["label"], keep)
    record = cloud_record_from_msg(msg)
    assert record.dropped_nonfinite == 3 and record.points.shape == (5, 3)
    assert record.stamp_ns == 5 and record.frame_id == "camera"


def test_empty_clouds_decode_to_zero_points():
    empty = encode_xyz(np.zeros((0, 3)), "camera", 0)
    assert empty.width == 0 and len(empty.data) == 0
    assert decode_pointcloud2(empty).points.shape == (0, 3)
    no_fields = decode_xyz([], b"", 0, 0, 0, 0, False)
    assert no_fields.points.shape == (0, 3) and no_fields.dropped_nonfinite == 0


XYZ = [("x", 0, FLOAT32), ("y", 4, FLOAT32), ("z", 8, FLOAT32)]


@pytest.mark.parametrize(
    "layout, point_step, row_step, data_size, needle",
    [
        (XYZ[:2], 12, 24, 24, "no 'z' field"),
        ([("x", 0, UINT8), *XYZ[1:]], 12, 24, 24, "must be FLOAT32"),
        ([*XYZ[:2], ("z", 8, FLOAT64)], 12, 24, 24, "does not fit in point_step 12"),
        (XYZ, 8, 16, 16, "does not fit in point_step 8"),
        (XYZ, 12, 24, 23, "data has 23 bytes, expected row_step * height = 24"),
        (XYZ, 12, 20, 24, "row_step 20 is smaller than width * point_step"),
        ([*XYZ, ("x", 0, FLOAT32)], 12, 24, 24, "two fields named 'x'"),
        ([*XYZ[:2], ("z", 8, 42)], 12, 24, 24, "unknown datatype 42"),
    ],
)
def test_malformed_clouds_raise_one_line_errors(layout, point_step, row_step, data_size, needle):
    fields = [SimpleNamespace(name=n, offset=o, datatype=d, count=1) for n, o, d in layout]
    with pytest.raises(PointCloudError, match=re.escape(needle)) as error:
        decode_xyz(fields, bytes(data_size), 1, 2, point_step, row_step, False)
    assert "\n" not in str(error.value)


def test_zero_count_field_is_rejected():
    fields = [SimpleNamespace(name=n, offset=o, datatype=d, count=0 if n == "y" else 1) for n, o, d in XYZ]
    with pytest.raises(PointCloudError, match="'y' has count 0"):
        decode_xyz(fields, bytes(12), 1, 1, 12, 12, False)


def test_decode_is_vectorised_for_a_large_organised_cloud(rng):
    height, width = 480, 640
    xyz = rng.normal(size=(height * width, 3)).astype(np.float32)
    xyz[::7, 1] = np.nan
    packed = np.zeros(height * width, dtype=np.dtype({"names": list("xyz"), "formats": ["<f4"] * 3,
                                                      "offsets": [0, 4, 8], "itemsize": 16}))
    for axis, name in enumerate("xyz"):
        packed[name] = xyz[:, axis]
    rows = np.zeros((height, width * 16 + 32), np.uint8)
    rows[:, :width * 16] = np.frombuffer(packed.tobytes(), np.uint8).reshape(height, width * 16)
    fields = [SimpleNamespace(name=n, offset=o, datatype=d, count=1) for n, o, d in XYZ]
    decoded = decode_xyz(fields, rows, height, width, 16, width * 16 + 32, False)
    finite = np.isfinite(xyz).all(axis=1)
    assert decoded.dropped_nonfinite == np.count_nonzero(~finite)
    np.testing.assert_array_equal(decoded.points, xyz[finite].astype(np.float64))


def test_cloud_record_round_trip_through_a_message(rng):
    record = PointCloudRecord(42, "camera", rng.normal(size=(20, 3)))
    back = cloud_record_from_msg(cloud_record_to_msg(record))
    np.testing.assert_array_equal(back.points, record.points.astype(np.float32).astype(np.float64))
    assert (back.stamp_ns, back.frame_id, back.dropped_nonfinite) == (42, "camera", 0)


def test_rclpy_messages_decode_and_serialise_like_rosbags_ones(rng):
    serialization = pytest.importorskip("rclpy.serialization")
    pytest.importorskip("sensor_msgs.msg")
    points = rng.normal(size=(30, 3))
    points[3, 1] = np.nan
    rclpy_msg = encode_xyz(points, "camera", 10**9 + 1, RclpyMessageFactory(), {"label": np.arange(30)})
    assert type(rclpy_msg).__module__.startswith("sensor_msgs.msg")
    decoded = decode_pointcloud2(rclpy_msg, ["label"])
    reference = decode_pointcloud2(encode_xyz(points, "camera", 10**9 + 1, None, {"label": np.arange(30)}))
    np.testing.assert_array_equal(decoded.points, reference.points)
    assert decoded.dropped_nonfinite == 1
    # Bytes from rclpy's serializer decode in rosbags to the same cloud, and back.
    store = meshfg_typestore()
    via_rosbags = store.deserialize_cdr(serialization.serialize_message(rclpy_msg), POINT_CLOUD2)
    np.testing.assert_array_equal(decode_pointcloud2(via_rosbags).points, reference.points)
    rosbags_bytes = bytes(store.serialize_cdr(via_rosbags, POINT_CLOUD2))
    via_rclpy = serialization.deserialize_message(rosbags_bytes, type(rclpy_msg))
    np.testing.assert_array_equal(decode_pointcloud2(via_rclpy).points, reference.points)
    assert via_rclpy.header.stamp.sec == 1 and via_rclpy.header.stamp.nanosec == 1
