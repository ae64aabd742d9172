"""Message records, converters and rosbag2 (MCAP) recordings, checked by independent readers."""

import json
import re
import shutil
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from rosbags.highlevel import AnyReader
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from scipy.spatial.transform import Rotation

from meshfg_ros.io.messages import (
    SHORTER_MSG_DEFINITIONS,
    MSG_DEFINITIONS,
    TETRA_MESH,
    MeshState,
    MessageValidationError,
    PointCloudRecord,
    PoseRecord,
    RclpyMessageFactory,
    RosbagsMessageFactory,
    StatusRecord,
    UnknownMessageTypeError,
    header_msg,
    mesh_state_from_msg,
    mesh_state_to_msg,
    meshfg_typestore,
    pose_from_msg,
    pose_to_msg,
    status_from_msg,
    status_to_msg,
)
from meshfg_ros.io.pointcloud import encode_xyz
from meshfg_ros.io.recording import (
    CorruptRecordingError,
    EmptyRecordingError,
    InvalidRecordedMessageError,
    NotARecordingError,
    RecordingError,
    RecordingExistsError,
    RecordingNotFoundError,
    RecordingReader,
    RecordingWriter,
    TopicNotFoundError,
    TopicTypeError,
    UnsupportedMessageError,
)

REPO = Path(__file__).resolve().parents[1]


def grid_mesh(n):
    """n^3 grid vertices (metres) and its Kuhn split into 6 tetrahedra per cube, vectorised."""
    axis = np.linspace(0.0, 0.05, n)
    vertices = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), axis=-1).reshape(-1, 3)
    index = np.arange(n**3).reshape(n, n, n)
    corners = np.stack(
        [index[i:n - 1 + i, j:n - 1 + j, k:n - 1 + k].ravel() for i in (0, 1) for j in (0, 1) for k in (0, 1)],
        axis=1,
    )
    kuhn = np.array([[0, 1, 3, 7], [0, 1, 5, 7], [0, 2, 3, 7], [0, 2, 6, 7], [0, 4, 5, 7], [0, 4, 6, 7]])
    tetrahedra = corners[:, kuhn].reshape(-1, 4)
    bottom = index[:, :, 0]
    quads = np.stack([bottom[:-1, :-1], bottom[1:, :-1], bottom[1:, 1:], bottom[:-1, 1:]], -1).reshape(-1, 4)
    triangles = np.concatenate([quads[:, [0, 2, 1]], quads[:, [0, 3, 2]]])
    return vertices, tetrahedra, triangles


def posterior_covariance(rng, vertex_count, fixed_vertices):
    """Symmetric positive definite 3x3 blocks (m^2): axes turned at random, stds of 0.05 to 1 mm
    along them (condition numbers up to 400; the estimator's on the bundled scenes reach 11), zero
    on the fixed vertices, as the estimator gives them."""
    axes = Rotation.random(vertex_count, random_state=rng).as_matrix()
    variances = rng.uniform(5e-5, 1e-3, (vertex_count, 3)) ** 2
    covariance = np.einsum("vij,vj,vkj->vik", axes, variances, axes)
    covariance = 0.5 * (covariance + covariance.transpose(0, 2, 1))
    covariance[fixed_vertices] = 0.0
    return covariance


@pytest.fixture(scope="module")
def mesh_states():
    vertices, tetrahedra, triangles = grid_mesh(22)
    rng = np.random.default_rng(3)
    fixed_vertices = np.arange(0, 22**3, 22)
    return [
        MeshState(
            stamp_ns=1_700_000_000_000_000_000 + step * 33_000_000,
            frame_id="tissue",
            step=step,
            positions=vertices + rng.normal(scale=1e-3, size=vertices.shape),
            tetrahedra=tetrahedra,
            surface_triangles=triangles,
            fixed_vertices=fixed_vertices,
            position_std=rng.uniform(1e-4, 1e-3, size=len(vertices)) if step else np.zeros(0),
            position_covariance=posterior_covariance(rng, len(vertices), fixed_vertices) if step else (),
        )
        for step in range(3)
    ]


def status(step):
    return StatusRecord(1_700_000_000_000_000_000 + step * 33_000_000, "tissue", step, 4 + step,
                        10.5 * step, 0.25, 12.75, 2000 + step, step, 5, step != 1, step == 2,
                        f"step {step} done")


def assert_same_mesh(actual, expected):
    assert (actual.stamp_ns, actual.frame_id, actual.step) == (expected.stamp_ns, expected.frame_id, expected.step)
    np.testing.assert_array_equal(actual.positions, expected.positions)
    np.testing.assert_array_equal(actual.tetrahedra, expected.tetrahedra)
    np.testing.assert_array_equal(actual.surface_triangles, expected.surface_triangles)
    np.testing.assert_array_equal(actual.fixed_vertices, expected.fixed_vertices)
    np.testing.assert_array_equal(actual.position_std, expected.position_std.astype(np.float32))
    # Carried as float32: each entry rounded once (and the blocks stay symmetric).
    np.testing.assert_array_equal(actual.position_covariance, expected.position_covariance.astype(np.float32))


def marker_array(store, state):
    """A visualization_msgs/MarkerArray with the surface as a TRIANGLE_LIST (rosbags classes)."""
    factory = RosbagsMessageFactory(store)
    make = factory.make
    corners = state.positions[state.surface_triangles[:4].reshape(-1)]
    marker = make(
        "visualization_msgs/msg/Marker",
        header=header_msg(state.stamp_ns, state.frame_id, factory), ns="surface", id=7, type=11,
        action=0,
        pose=make("geometry_msgs/msg/Pose", position=make("geometry_msgs/msg/Point", x=0.0, y=0.0, z=0.0),
                  orientation=make("geometry_msgs/msg/Quaternion", x=0.0, y=0.0, z=0.0, w=1.0)),
        scale=make("geometry_msgs/msg/Vector3", x=1.0, y=1.0, z=1.0),
        color=make("std_msgs/msg/ColorRGBA", r=0.8, g=0.3, b=0.3, a=1.0),
        lifetime=make("builtin_interfaces/msg/Duration", sec=0, nanosec=0), frame_locked=False,
        points=[make("geometry_msgs/msg/Point", x=float(x), y=float(y), z=float(z)) for x, y, z in corners],
        colors=[], texture_resource="",
        texture=make("sensor_msgs/msg/CompressedImage", header=header_msg(0, "", factory), format="",
                     data=np.zeros(0, np.uint8)),
        uv_coordinates=[], text="", mesh_resource="",
        mesh_file=make("visualization_msgs/msg/MeshFile", filename="", data=np.zeros(0, np.uint8)),
        mesh_use_embedded_materials=False,
    )
    return make("visualization_msgs/msg/MarkerArray", markers=[marker])


@pytest.fixture(scope="module")
def recording(tmp_path_factory, mesh_states):
    """A recording of every message kind, written with log times out of order.

    Clouds are raw PointCloud2 messages with one NaN point each, as a depth camera sends them.
    """
    rng = np.random.default_rng(5)
    base = mesh_states[0].stamp_ns
    clouds = []
    for step in range(3):
        points = rng.normal(size=(300, 3))
        points[step] = np.nan
        clouds.append(SimpleNamespace(stamp_ns=base + step * 33_000_000 - 1_000_000, points=points))
    poses = [PoseRecord(base + k * 10_000_000, "world", [0.01 * k, 0.0, 0.1, 0.0, 0.0, 0.0, 1.0])
             for k in range(8)]
    store = meshfg_typestore()
    markers = marker_array(store, mesh_states[0])
    path = tmp_path_factory.mktemp("recordings") / "session"
    with RecordingWriter(path) as writer:
        for state in reversed(mesh_states):
            writer.write("/meshfg/mesh", state)
        for step in range(3):
            writer.write("/meshfg/status", status(step))
            writer.write("/camera/points", encode_xyz(clouds[step].points, "camera", clouds[step].stamp_ns))
        for pose in poses:
            writer.write("/tool/pose", pose)
        writer.write("/meshfg/markers", markers, base + 5)
    return SimpleNamespace(path=path, clouds=clouds, poses=poses, markers=markers)


def test_message_definitions_match_the_meshfg_msgs_package():
    for typename, text in MSG_DEFINITIONS.items():
        name = typename.split("/")[-1]
        assert (REPO / "meshfg_msgs" / "msg" / f"{name}.msg").read_text() == text


def test_type_hashes_match_what_rosidl_generates(tmp_path):
    """The definitions embedded in recordings hash like a colcon build of meshfg_msgs would."""
    adapter = pytest.importorskip("rosidl_adapter.msg")
    generator = pytest.importorskip("rosidl_generator_type_description")
    share = Path(sys.prefix, "share")  # where the ros-jazzy-* wheels put their share/ files
    if not (share / "std_msgs" / "msg" / "Header.json").is_file():
        pytest.skip("no std_msgs type descriptions under sys.prefix/share")
    idl_tuples = []
    for typename in MSG_DEFINITIONS:
        name = typename.split("/")[-1]
        adapter.convert_msg_to_idl(REPO / "meshfg_msgs", "meshfg_msgs", Path("msg", f"{name}.msg"),
                                   tmp_path / "idl" / "msg")
        idl_tuples.append(f"{tmp_path / 'idl'}:msg/{name}.idl")
    arguments = tmp_path / "arguments.json"
    arguments.write_text(json.dumps({
        "package_name": "meshfg_msgs", "output_dir": str(tmp_path / "json"), "idl_tuples": idl_tuples,
        "include_paths": [f"std_msgs:{share / 'std_msgs'}", f"builtin_interfaces:{share / 'builtin_interfaces'}"],
    }))
    store = meshfg_typestore()
    for generated in generator.generate_type_hash(str(arguments)):
        top = json.loads(Path(generated).read_text())["type_hashes"][0]
        assert top["hash_string"] == store.hash_rihs01(top["type_name"])


def test_mesh_state_converts_to_a_message_and_back(mesh_states):
    state = mesh_states[1]
    msg = mesh_state_to_msg(state)
    assert msg.positions.dtype == np.float64 and msg.positions.shape == (3 * 22**3,)
    assert msg.tetrahedra.dtype == np.uint32 and msg.position_std.dtype == np.float32
    assert msg.header.stamp.sec == 1_700_000_000 and msg.header.stamp.nanosec == 33_000_000
    np.testing.assert_array_equal(msg.positions[3:6], state.positions[1])
    assert_same_mesh(mesh_state_from_msg(msg), state)


def test_position_covariance_travels_as_float32_upper_triangles(mesh_states):
    state = mesh_states[1]
    msg = mesh_state_to_msg(state)
    assert msg.position_covariance.dtype == np.float32 and msg.position_covariance.shape == (6 * 22**3,)
    block = state.position_covariance[1]
    np.testing.assert_array_equal(msg.position_covariance[6:12], np.float32(
        [block[0, 0], block[0, 1], block[0, 2], block[1, 1], block[1, 2], block[2, 2]]))
    covariance = mesh_state_from_msg(msg).position_covariance
    assert covariance.shape == (22**3, 3, 3) and covariance.dtype == np.float64
    np.testing.assert_array_equal(covariance, covariance.transpose(0, 2, 1))
    assert not covariance[state.fixed_vertices].any()
    scale = np.abs(state.position_covariance).max(axis=(1, 2), keepdims=True)
    assert (np.abs(covariance - state.position_covariance) <= 1e-7 * scale).all()  # float32's 24 bits
    # Rounded to float32, these blocks keep their smallest eigenvalue positive (positive definite).
    assert np.linalg.eigvalsh(np.delete(covariance, state.fixed_vertices, axis=0))[:, 0].min() > 0.0
    # Without a covariance the field is empty, and reads back as none.
    empty = mesh_state_to_msg(mesh_states[0])
    assert empty.position_covariance.shape == (0,)
    assert mesh_state_from_msg(empty).position_covariance.shape == (0, 3, 3)


@pytest.mark.parametrize("values, needle", [
    (np.zeros(6 * 4 - 1, np.float32), "position_covariance has 23 values, expected 6 per vertex (24) or 0"),
    (np.tile(np.float32([1, 0, 0, 1, 0, np.nan]), 4), "position_covariance of vertex 0 is not finite"),
    (np.float32([1, 0, 0, 1, 0, 1] * 2 + [1, 0, 0, -1, 0, 1] + [1, 0, 0, 1, 0, 1]),
     "position_covariance of vertex 2 has a negative variance"),
])
def test_a_malformed_covariance_field_is_refused_with_its_reason(values, needle):
    msg = mesh_state_to_msg(MeshState(0, "tissue", 1, np.eye(4, 3), [[0, 1, 2, 3]]))
    msg.position_covariance = values
    with pytest.raises(MessageValidationError, match=re.escape(needle)):
        mesh_state_from_msg(msg)


def test_converters_accept_rclpy_style_messages(mesh_states):
    """Duck typing: array.array sequences and plain attribute objects, as rclpy messages have."""
    rclpy_arrays = RclpyMessageFactory()
    factory = SimpleNamespace(make=lambda typename, **fields: SimpleNamespace(**fields),
                              sequence=rclpy_arrays.sequence)
    state = mesh_states[2]
    msg = mesh_state_to_msg(state, factory)
    assert msg.positions.typecode == "d" and msg.tetrahedra.typecode == "I"
    assert msg.position_std.typecode == "f"
    assert_same_mesh(mesh_state_from_msg(msg), state)
    assert status_from_msg(status_to_msg(status(2), factory)) == status(2)


def test_pose_round_trips_through_real_rclpy_messages():
    serialization = pytest.importorskip("rclpy.serialization")
    pytest.importorskip("geometry_msgs.msg")
    record = PoseRecord(-1_500_000_000, "world", [1.0, -2.0, 3.5, 0.0, 0.6, 0.0, 0.8])
    rclpy_msg = pose_to_msg(record, RclpyMessageFactory())
    assert type(rclpy_msg).__module__.startswith("geometry_msgs.msg")
    assert (rclpy_msg.header.stamp.sec, rclpy_msg.header.stamp.nanosec) == (-2, 500_000_000)
    via_rosbags = meshfg_typestore().deserialize_cdr(serialization.serialize_message(rclpy_msg),
                                                     "geometry_msgs/msg/PoseStamped")
    back = pose_from_msg(via_rosbags)
    assert (back.stamp_ns, back.frame_id) == (record.stamp_ns, "world")
    np.testing.assert_array_equal(back.pose, record.pose)


def test_factories_name_unknown_message_types():
    with pytest.raises(UnknownMessageTypeError, match="meshfg_msgs/msg/Nope"):
        RosbagsMessageFactory().make("meshfg_msgs/msg/Nope")
    with pytest.raises(UnknownMessageTypeError, match="no_such_package/msg/Nope"):
        RclpyMessageFactory().make("no_such_package/msg/Nope")


@pytest.mark.parametrize(
    "change, needle",
    [
        ({"positions": np.zeros(10)}, "positions has 10 values, not a multiple of 3"),
        ({"positions": [[0.0, 0.0, np.nan]] * 4}, "positions of vertex 0 are not finite"),
        ({"tetrahedra": [[0, 1, 2, 4]]}, "tetrahedra index 4 is out of range for 4 vertices"),
        ({"tetrahedra": [0, 1, 2]}, "tetrahedra has 3 indices, not a multiple of 4"),
        ({"surface_triangles": [[0, -1, 2]]}, "surface_triangles index -1 is out of range"),
        ({"fixed_vertices": [0.5]}, "fixed_vertices holds non-integer vertex indices"),
        ({"position_std": [0.1, 0.1]}, "position_std has 2 values, expected 4 or 0"),
        ({"position_std": [0.1, 0.1, -0.1, 0.1]}, "position_std must be finite and non-negative"),
        ({"position_covariance": np.zeros((3, 3, 3))}, "position_covariance must be (4, 3, 3) or empty, got shape"),
        ({"position_covariance": np.zeros(12)}, "position_covariance has 12 values, expected 6 per vertex (24) or 0"),
        ({"position_covariance": np.tile(np.diag([1.0, 1.0, np.inf]), (4, 1, 1))},
         "position_covariance of vertex 0 is not finite"),
        ({"position_covariance": np.concatenate([np.tile(np.eye(3), (3, 1, 1)), -np.eye(3)[None]])},
         "position_covariance of vertex 3 has a negative variance"),
        ({"position_covariance": np.tile([[1.0, 0.5, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], (4, 1, 1))},
         "position_covariance of vertex 0 is not symmetric"),
        ({"step": -1}, "step = -1 is outside the uint32 range"),
    ],
)
def test_invalid_mesh_states_raise_specific_errors(change, needle):
    fields = dict(stamp_ns=0, frame_id="tissue", step=0, positions=np.eye(4, 3), tetrahedra=[[0, 1, 2, 3]])
    with pytest.raises(MessageValidationError, match=re.escape(needle)):
        MeshState(**{**fields, **change})


def test_invalid_poses_and_stamps_raise():
    with pytest.raises(MessageValidationError, match="quaternion is zero"):
        PoseRecord(0, "world", [0.0] * 7)
    with pytest.raises(MessageValidationError, match=r"shape \(7,\)"):
        PoseRecord(0, "world", [0.0] * 6)
    with pytest.raises(MessageValidationError, match="int32 seconds"):
        header_msg(2**31 * 10**9, "world")


def test_recording_round_trip(recording, mesh_states):
    with RecordingReader(recording.path) as reader:
        assert {name: (info.msgtype, info.count) for name, info in reader.topics.items()} == {
            "/meshfg/mesh": ("meshfg_msgs/msg/TetraMesh", 3),
            "/meshfg/status": ("meshfg_msgs/msg/EstimatorStatus", 3),
            "/camera/points": ("sensor_msgs/msg/PointCloud2", 3),
            "/tool/pose": ("geometry_msgs/msg/PoseStamped", 8),
            "/meshfg/markers": ("visualization_msgs/msg/MarkerArray", 1),
        }
        assert reader.message_count == 18
        assert reader.start_ns == recording.clouds[0].stamp_ns
        assert reader.end_ns == recording.poses[-1].stamp_ns  # the latest log time
        everything = list(reader.messages())
        log_times = [m.log_time_ns for m in everything]
        assert log_times == sorted(log_times) and len(everything) == 18
        for read, written in zip(reader.records("/meshfg/mesh", MeshState), mesh_states, strict=True):
            assert_same_mesh(read, written)
        assert list(reader.records("/meshfg/status", StatusRecord)) == [status(k) for k in range(3)]
        for read, written in zip(reader.records("/camera/points", PointCloudRecord), recording.clouds, strict=True):
            keep = np.isfinite(written.points).all(axis=1)
            np.testing.assert_array_equal(read.points, written.points[keep].astype(np.float32))
            assert read.dropped_nonfinite == 1 and read.stamp_ns == written.stamp_ns
        poses = list(reader.records("/tool/pose", PoseRecord))
        np.testing.assert_array_equal([p.pose for p in poses], [p.pose for p in recording.poses])
        (markers,) = [m for m in everything if m.topic == "/meshfg/markers"]
        marker = markers.data.markers[0]
        assert markers.msgtype == "visualization_msgs/msg/MarkerArray" and marker.type == 11
        written_points = [(p.x, p.y, p.z) for p in recording.markers.markers[0].points]
        assert [(p.x, p.y, p.z) for p in marker.points] == written_points
        window = list(reader.messages(["/tool/pose"], start_ns=poses[2].stamp_ns, stop_ns=poses[5].stamp_ns))
        assert [m.data.stamp_ns for m in window] == [p.stamp_ns for p in poses[2:5]]


def test_mcap_library_decodes_the_recording_from_embedded_definitions(recording, mesh_states):
    mcap_reader = pytest.importorskip("mcap.reader")
    decoder = pytest.importorskip("mcap_ros2.decoder")
    with open(recording.path / f"{recording.path.name}.mcap", "rb") as stream:
        reader = mcap_reader.make_reader(stream, decoder_factories=[decoder.DecoderFactory()])
        assert reader.get_header().profile == "ros2"
        decoded = {}
        for schema, channel, _, message in reader.iter_decoded_messages():
            assert schema.encoding == "ros2msg" and channel.message_encoding == "cdr"
            decoded.setdefault(channel.topic, []).append(message)
    assert [m.step for m in decoded["/meshfg/mesh"]] == [0, 1, 2]
    np.testing.assert_array_equal(np.reshape(decoded["/meshfg/mesh"][1].positions, (-1, 3)),
                                  mesh_states[1].positions)
    np.testing.assert_array_equal(np.reshape(decoded["/meshfg/mesh"][1].tetrahedra, (-1, 4)),
                                  mesh_states[1].tetrahedra)
    assert [m.message for m in decoded["/meshfg/status"]] == ["step 0 done", "step 1 done", "step 2 done"]
    assert decoded["/camera/points"][0].width == 300
    assert decoded["/tool/pose"][3].pose.position.x == pytest.approx(0.03, abs=0.0)
    assert decoded["/meshfg/markers"][0].markers[0].ns == "surface"


def test_rosbags_decodes_the_recording_without_meshfg_msgs(recording, mesh_states):
    with AnyReader([recording.path]) as reader:  # no default typestore: embedded definitions only
        assert "meshfg_msgs/msg/TetraMesh" not in get_typestore(Stores.ROS2_JAZZY).types
        (connection,) = [c for c in reader.connections if c.topic == "/meshfg/mesh"]
        raw = [data for _, _, data in reader.messages([connection])]
        msg = reader.deserialize(raw[2], connection.msgtype)
        assert type(msg) is not meshfg_typestore().types[TETRA_MESH]
        assert_same_mesh(mesh_state_from_msg(msg), mesh_states[2])


def test_compressed_mcap_is_smaller_and_reads_back(tmp_path, mesh_states):
    for name, compress in [("plain", False), ("zstd", True)]:
        with RecordingWriter(tmp_path / name, compress=compress) as writer:
            writer.write("/mesh", mesh_states[0])
    size = {name: (tmp_path / name / f"{name}.mcap").stat().st_size for name in ("plain", "zstd")}
    assert size["zstd"] < 0.6 * size["plain"]
    with RecordingReader(tmp_path / "zstd") as reader:
        (state,) = reader.records("/mesh", MeshState)
    assert_same_mesh(state, mesh_states[0])
    mcap_reader = pytest.importorskip("mcap.reader")
    decoder = pytest.importorskip("mcap_ros2.decoder")
    with open(tmp_path / "zstd" / "zstd.mcap", "rb") as stream:
        reader = mcap_reader.make_reader(stream, decoder_factories=[decoder.DecoderFactory()])
        ((_, _, _, message),) = list(reader.iter_decoded_messages())
    np.testing.assert_array_equal(np.reshape(message.positions, (-1, 3)), mesh_states[0].positions)


def test_sqlite3_storage_round_trip(tmp_path, mesh_states):
    with RecordingWriter(tmp_path / "db", storage="sqlite3") as writer:
        writer.write("/mesh", mesh_states[1])
    assert (tmp_path / "db" / "db.db3").is_file()
    with RecordingReader(tmp_path / "db") as reader:
        (state,) = reader.records("/mesh", MeshState)
    assert_same_mesh(state, mesh_states[1])


def test_writer_finalises_what_was_written_before_an_exception(tmp_path):
    with pytest.raises(RuntimeError, match="estimator failed"):
        with RecordingWriter(tmp_path / "partial") as writer:
            writer.write("/meshfg/status", status(0))
            writer.write("/meshfg/status", status(1))
            raise RuntimeError("estimator failed")
    with RecordingReader(tmp_path / "partial") as reader:
        assert list(reader.records("/meshfg/status", StatusRecord)) == [status(0), status(1)]


def test_writer_refuses_existing_paths_and_mixed_topic_types(tmp_path, mesh_states):
    (tmp_path / "taken").mkdir()
    with pytest.raises(RecordingExistsError, match="never overwritten"):
        RecordingWriter(tmp_path / "taken")
    with RecordingWriter(tmp_path / "new") as writer:
        writer.write("/meshfg/mesh", mesh_states[0])
        with pytest.raises(TopicTypeError, match="holds meshfg_msgs/msg/TetraMesh, cannot write"):
            writer.write("/meshfg/mesh", status(0))
        with pytest.raises(UnsupportedMessageError, match="cannot record a dict"):
            writer.write("/other", {"x": 1})
        with pytest.raises(ValueError, match="MarkerArray has no header stamp"):
            writer.write("/markers", marker_array(meshfg_typestore(), mesh_states[0]))
    assert writer.counts == {"/meshfg/mesh": 1}
    with pytest.raises(RecordingExistsError):
        RecordingWriter(tmp_path / "new")


def test_reader_errors_are_specific_and_one_line(tmp_path, recording):
    def check(error_type, path, needle):
        with pytest.raises(error_type, match=re.escape(needle)) as error:
            RecordingReader(path)
        assert isinstance(error.value, RecordingError) and "\n" not in str(error.value)

    check(RecordingNotFoundError, tmp_path / "absent", "does not exist")
    (tmp_path / "plain").mkdir()
    check(NotARecordingError, tmp_path / "plain", "no metadata.yaml")
    (tmp_path / "file.mcap").write_bytes(b"\x89MCAP0\r\n")
    check(NotARecordingError, tmp_path / "file.mcap", "is not a rosbag2 recording")

    storage = f"{recording.path.name}.mcap"
    for name, mutate, needle in [
        ("zero", lambda data: b"", "seems to be empty"),
        ("truncated", lambda data: data[: len(data) // 2], "cannot open recording"),
        ("garbage", lambda data: b"not an mcap file" * 64, "File magic is invalid"),
    ]:
        broken = tmp_path / name
        shutil.copytree(recording.path, broken)
        (broken / storage).rename(broken / f"{name}.mcap")
        (broken / f"{name}.mcap").write_bytes(mutate((recording.path / storage).read_bytes()))
        metadata = (recording.path / "metadata.yaml").read_text().replace(storage, f"{name}.mcap")
        (broken / "metadata.yaml").write_text(metadata)
        check(CorruptRecordingError, broken, needle)

    with RecordingWriter(tmp_path / "empty"):
        pass
    check(EmptyRecordingError, tmp_path / "empty", "holds no messages")

    with RecordingReader(recording.path) as reader:
        with pytest.raises(TopicNotFoundError, match="topic /nope is not in"):
            reader.messages(["/nope"])
        with pytest.raises(TopicTypeError, match="holds geometry_msgs/msg/PoseStamped, expected meshfg_msgs"):
            reader.records("/tool/pose", MeshState)


def test_invalid_recorded_mesh_is_reported_with_topic_and_time(tmp_path, mesh_states):
    msg = mesh_state_to_msg(mesh_states[0])
    msg.tetrahedra[5] = 22**3 + 3
    with RecordingWriter(tmp_path / "bad") as writer:
        writer.write("/meshfg/mesh", msg)
    with RecordingReader(tmp_path / "bad") as reader:
        with pytest.raises(InvalidRecordedMessageError,
                           match=f"/meshfg/mesh at {mesh_states[0].stamp_ns} ns: tetrahedra index 10651"):
            list(reader.records("/meshfg/mesh", MeshState))


def test_a_different_tetra_mesh_definition_is_refused(tmp_path):
    """A recording made with another version of TetraMesh must not be read as this one."""
    store = get_typestore(Stores.ROS2_JAZZY)
    store.register(get_types_from_msg("std_msgs/Header header\nfloat64[] positions\n", TETRA_MESH))
    old = store.types[TETRA_MESH](header=header_msg(0, "tissue", RosbagsMessageFactory(store)),
                                  positions=np.zeros(3))
    with Writer(tmp_path / "old", version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        connection = writer.add_connection("/meshfg/mesh", TETRA_MESH, typestore=store)
        writer.write(connection, 1, store.serialize_cdr(old, TETRA_MESH))
    with RecordingReader(tmp_path / "old") as reader:
        assert reader.topics["/meshfg/mesh"].count == 1
        with pytest.raises(TopicTypeError, match="recorded meshfg_msgs/msg/TetraMesh definition differs"):
            reader.messages()


CUT_FIELDS = ("invalid_vertices", "removed_elements")


@pytest.mark.parametrize("missing", [CUT_FIELDS, (*CUT_FIELDS, "position_covariance"),
                                     (*CUT_FIELDS, "position_covariance", "degraded")])
def test_a_recording_with_a_shorter_tetra_mesh_is_read_with_its_own_definition(tmp_path, missing):
    """Recordings whose TetraMesh lacks the cut fields, position_covariance too, or degraded too
    (the bundled ones) are readable; their meshes read as uncut, without covariance and not
    degraded."""
    (shorter,) = [text for text in SHORTER_MSG_DEFINITIONS[TETRA_MESH]
                  if all(f" {name} " not in text for name in missing)
                  and all(f" {name} " in text for name in {"position_covariance", "degraded"} - set(missing))]
    assert all(f" {name} " in MSG_DEFINITIONS[TETRA_MESH] for name in missing)
    store = get_typestore(Stores.ROS2_JAZZY)
    store.register(get_types_from_msg(shorter, TETRA_MESH))
    corners = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    fields = dict(header=header_msg(5, "tissue", RosbagsMessageFactory(store)), step=3, positions=corners.reshape(-1),
                  tetrahedra=np.array([0, 1, 2, 3], np.uint32), surface_triangles=np.zeros(0, np.uint32),
                  fixed_vertices=np.array([0], np.uint32), position_std=np.zeros(0, np.float32))
    if "degraded" not in missing:
        fields["degraded"] = True
    if "position_covariance" not in missing:
        fields["position_covariance"] = np.zeros(0, np.float32)
    with Writer(tmp_path / "shorter", version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        connection = writer.add_connection("/meshfg/mesh", TETRA_MESH, typestore=store)
        writer.write(connection, 5, store.serialize_cdr(store.types[TETRA_MESH](**fields), TETRA_MESH))
    with RecordingReader(tmp_path / "shorter") as reader:
        (state,) = list(reader.records("/meshfg/mesh", MeshState))
    assert state.step == 3 and state.degraded is ("degraded" not in missing) and state.fixed_vertices.tolist() == [0]
    np.testing.assert_array_equal(state.positions[3], [0.0, 0.0, 1.0])
    assert state.position_covariance.shape == (0, 3, 3)
    assert state.invalid_vertices.size == state.removed_elements.size == 0


@pytest.mark.parametrize("bag", sorted(path.name for path in (REPO / "bags").iterdir() if path.is_dir()))
def test_the_bundled_recordings_meshes_still_load(bag):
    """The bundled recordings hold TetraMesh without degraded and position_covariance."""
    with RecordingReader(REPO / "bags" / bag) as reader:
        (initial,) = list(reader.records("/meshfg/initial_mesh", MeshState))
        truths = list(reader.records("/meshfg/ground_truth", MeshState))
    assert initial.tet_mesh().vertex_count > 0 and len(truths) > 1
    assert all(truth.positions.shape == initial.positions.shape for truth in truths)
    assert initial.position_covariance.shape == (0, 3, 3) and not initial.degraded
