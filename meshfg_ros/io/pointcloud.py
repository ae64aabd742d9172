"""sensor_msgs/PointCloud2 <-> numpy, vectorised, for rosbags and rclpy messages alike.

sensor_msgs_py is not on PyPI, and its reader ignores row_step and keeps NaN points of clouds
that claim is_dense; this decoder honours any field order, padding inside and after points,
row padding (row_step), both byte orders and FLOAT32/FLOAT64 coordinates, and always drops
non-finite points (counting them). Malformed clouds raise PointCloudError.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from meshfg_ros.io.messages import (
    POINT_CLOUD2,
    MessageFactory,
    PointCloudRecord,
    RosbagsMessageFactory,
    header_msg,
    stamp_ns_from_msg,
)

# sensor_msgs/PointField datatype codes and their numpy kinds (byte order added per cloud).
INT8, UINT8, INT16, UINT16, INT32, UINT32, FLOAT32, FLOAT64 = range(1, 9)
_NUMPY_KINDS = {
    INT8: "i1", UINT8: "u1", INT16: "i2", UINT16: "u2",
    INT32: "i4", UINT32: "u4", FLOAT32: "f4", FLOAT64: "f8",
}
_COORDINATES = ("x", "y", "z")


class PointCloudError(ValueError):
    """A PointCloud2 is malformed or cannot be decoded as x/y/z points."""


@dataclass(frozen=True, eq=False)
class DecodedCloud:
    """Finite points (K, 3) float64 in row-major cloud order, with the count of dropped ones.

    extra maps each requested extra field name to its (K,) float64 values for the same points.
    """

    points: np.ndarray
    dropped_nonfinite: int
    extra: dict[str, np.ndarray]


def _field_layout(fields: Sequence[Any], names: Sequence[str], point_step: int, big_endian: bool):
    """numpy dtype reading `names` out of one point of `point_step` bytes."""
    by_name: dict[str, Any] = {}
    for point_field in fields:
        if point_field.name in by_name:
            raise PointCloudError(f"PointCloud2 has two fields named {point_field.name!r}")
        by_name[point_field.name] = point_field
    byte_order = ">" if big_endian else "<"
    formats, offsets = [], []
    for name in names:
        if name not in by_name:
            raise PointCloudError(
                f"PointCloud2 has no {name!r} field (fields: {', '.join(by_name) or 'none'})"
            )
        point_field = by_name[name]
        datatype, offset, count = int(point_field.datatype), int(point_field.offset), int(point_field.count)
        if datatype not in _NUMPY_KINDS:
            raise PointCloudError(f"field {name!r} has unknown datatype {datatype}")
        if name in _COORDINATES and datatype not in (FLOAT32, FLOAT64):
            raise PointCloudError(f"field {name!r} has datatype {datatype}; x, y, z must be FLOAT32 (7) or FLOAT64 (8)")
        if count < 1:
            raise PointCloudError(f"field {name!r} has count {count}; expected at least 1")
        kind = np.dtype(byte_order + _NUMPY_KINDS[datatype])
        if offset < 0 or offset + kind.itemsize > point_step:
            raise PointCloudError(
                f"field {name!r} (offset {offset}, {kind.itemsize} bytes) does not fit in point_step {point_step}"
            )
        formats.append(kind)
        offsets.append(offset)
    try:
        return np.dtype({"names": list(names), "formats": formats, "offsets": offsets, "itemsize": point_step})
    except ValueError as error:  # numpy lays out at most 2**31 - 1 bytes per point
        raise PointCloudError(f"point_step {point_step} cannot be laid out: {error}") from None


def decode_xyz(
    fields: Sequence[Any],
    data: Any,
    height: int,
    width: int,
    point_step: int,
    row_step: int,
    is_bigendian: bool,
    extra_fields: Sequence[str] = (),
) -> DecodedCloud:
    """Decode x/y/z (and `extra_fields`) of a PointCloud2 given its fields and byte buffer.

    fields: objects with name, offset, datatype, count (PointField of any flavour).
    data: any byte buffer (bytes, numpy uint8 array, array.array('B'), memoryview).
    Points with a NaN or infinite coordinate are dropped and counted, whatever is_dense says.
    """
    height, width, point_step, row_step = int(height), int(width), int(point_step), int(row_step)
    if min(height, width, point_step, row_step) < 0:
        raise PointCloudError("PointCloud2 height, width, point_step and row_step must be non-negative")
    names = list(dict.fromkeys([*_COORDINATES, *extra_fields]))
    if height * width == 0:
        return DecodedCloud(np.zeros((0, 3)), 0, {name: np.zeros(0) for name in names[3:]})
    layout = _field_layout(fields, names, point_step, bool(is_bigendian))
    if row_step < width * point_step:
        raise PointCloudError(
            f"row_step {row_step} is smaller than width * point_step = {width} * {point_step}"
        )
    try:
        raw = np.frombuffer(data, dtype=np.uint8)
    except (TypeError, ValueError, BufferError) as error:
        raise PointCloudError(f"PointCloud2 data is not a byte buffer: {error}") from None
    if raw.size < row_step * height:
        raise PointCloudError(
            f"PointCloud2 data has {raw.size} bytes, expected row_step * height = {row_step * height}"
        )
    # One strided view covers point padding (itemsize) and row padding (row strides): no copy.
    grid = np.ndarray(shape=(height, width), dtype=layout, buffer=raw, strides=(row_step, point_step))
    points = np.stack([grid[name].reshape(-1) for name in _COORDINATES], axis=1).astype(np.float64)
    finite = np.isfinite(points).all(axis=1)
    extra = {name: grid[name].reshape(-1)[finite].astype(np.float64) for name in names[3:]}
    return DecodedCloud(points[finite], int(finite.size - np.count_nonzero(finite)), extra)


def decode_pointcloud2(msg: Any, extra_fields: Sequence[str] = ()) -> DecodedCloud:
    """decode_xyz on a PointCloud2 message of either flavour (rosbags or rclpy)."""
    return decode_xyz(
        msg.fields, msg.data, msg.height, msg.width, msg.point_step, msg.row_step,
        msg.is_bigendian, extra_fields,
    )


def encode_xyz(
    points: ArrayLike,
    frame_id: str,
    stamp_ns: int,
    factory: MessageFactory | None = None,
    extra_fields: Mapping[str, ArrayLike] | None = None,
) -> Any:
    """Unorganised little-endian PointCloud2 with FLOAT32 x, y, z and one FLOAT32 per extra field.

    points: (K, 3); extra_fields: name -> (K,) values (e.g. 'label'). is_dense is set only if
    every point is finite. factory builds the message (rosbags by default, or rclpy).
    """
    factory = RosbagsMessageFactory() if factory is None else factory
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise PointCloudError(f"points must be (K, 3), got shape {points.shape}")
    extra = dict(extra_fields or {})
    if clash := set(extra) & set(_COORDINATES):
        raise PointCloudError(f"extra field names clash with coordinates: {sorted(clash)}")
    names = list(_COORDINATES) + list(extra)
    layout = np.dtype({
        "names": names,
        "formats": ["<f4"] * len(names),
        "offsets": [4 * index for index in range(len(names))],
        "itemsize": 4 * len(names),
    })
    packed = np.empty(points.shape[0], dtype=layout)
    for axis, name in enumerate(_COORDINATES):
        packed[name] = points[:, axis]
    for name, values in extra.items():
        values = np.asarray(values, dtype=np.float64).reshape(-1)
        if values.size != points.shape[0]:
            raise PointCloudError(f"extra field {name!r} has {values.size} values for {points.shape[0]} points")
        packed[name] = values
    point_fields = [
        factory.make("sensor_msgs/msg/PointField", name=name, offset=4 * index, datatype=FLOAT32, count=1)
        for index, name in enumerate(names)
    ]
    return factory.make(
        POINT_CLOUD2,
        header=header_msg(stamp_ns, frame_id, factory),
        height=1,
        width=points.shape[0],
        fields=point_fields,
        is_bigendian=False,
        point_step=layout.itemsize,
        row_step=layout.itemsize * points.shape[0],
        data=factory.sequence(np.frombuffer(packed.tobytes(), dtype=np.uint8), np.uint8),
        is_dense=bool(np.isfinite(points).all()),
    )


def cloud_record_from_msg(msg: Any) -> PointCloudRecord:
    """PointCloudRecord (finite points, dropped count) from a PointCloud2 of either flavour."""
    decoded = decode_pointcloud2(msg)
    return PointCloudRecord(
        stamp_ns=stamp_ns_from_msg(msg.header.stamp),
        frame_id=msg.header.frame_id,
        points=decoded.points,
        dropped_nonfinite=decoded.dropped_nonfinite,
    )


def cloud_record_to_msg(record: PointCloudRecord, factory: MessageFactory | None = None) -> Any:
    """PointCloud2 (FLOAT32 x, y, z) for `record`."""
    return encode_xyz(record.points, record.frame_id, record.stamp_ns, factory)
