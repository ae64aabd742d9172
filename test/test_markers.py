"""MarkerArray of an estimate: structure RViz and Foxglove accept, colours from the posterior std."""
import numpy as np
import pytest
from rclpy.serialization import deserialize_message, serialize_message
from visualization_msgs.msg import Marker, MarkerArray

from meshfg_ros.synthetic.meshing import cube_mesh
from meshfg_ros.io.messages import RclpyMessageFactory, RosbagsMessageFactory, meshfg_typestore
from meshfg_ros.markers import mesh_markers, std_colours, surface_edges

STAMP_NS = 12_345_678_901


@pytest.fixture(scope="module")
def cube():
    return cube_mesh(side=0.05, divisions=3)


def coordinates(points) -> np.ndarray:
    return np.array([[p.x, p.y, p.z] for p in points]).reshape(-1, 3)


def rgba(colours) -> np.ndarray:
    return np.array([[c.r, c.g, c.b, c.a] for c in colours]).reshape(-1, 4)


def test_surface_edges_of_a_tetrahedron_face_pair():
    triangles = np.array([[0, 1, 2], [2, 1, 3]])
    np.testing.assert_array_equal(surface_edges(triangles), [[0, 1], [0, 2], [1, 2], [1, 3], [2, 3]])


def test_std_colours_run_from_blue_to_red_and_clip():
    colours = std_colours(np.array([0.0, 1e-3, 2e-3, 5e-3]), std_max=2e-3)
    np.testing.assert_allclose(colours[0], [0.230, 0.299, 0.754, 1.0])
    np.testing.assert_allclose(colours[1], [0.865, 0.865, 0.865, 1.0])
    np.testing.assert_allclose(colours[2], [0.706, 0.016, 0.150, 1.0])
    np.testing.assert_array_equal(colours[3], colours[2])  # beyond std_max: clipped to red
    auto = std_colours(np.array([0.0, 4e-3]))  # std_max 0: the largest std is red
    np.testing.assert_allclose(auto[1], colours[2])
    np.testing.assert_allclose(std_colours(np.zeros(3)), np.tile(colours[0], (3, 1)))  # all zero: blue


def test_marker_array_structure(cube):
    rng = np.random.default_rng(3)
    positions = cube.vertices + rng.normal(scale=1e-4, size=cube.vertices.shape)
    position_std = rng.uniform(1e-4, 3e-3, cube.vertex_count)
    points = rng.uniform(0.0, 0.05, (57, 3))
    triangles = cube.surface_triangles
    array = mesh_markers(positions, triangles, position_std, points, "world", STAMP_NS,
                         factory=RclpyMessageFactory())
    assert isinstance(array, MarkerArray)
    surface, wireframe, cloud = array.markers
    assert [m.type for m in array.markers] == [Marker.TRIANGLE_LIST, Marker.LINE_LIST, Marker.POINTS]
    assert len({(m.ns, m.id) for m in array.markers}) == 3
    for marker in array.markers:
        assert marker.action == Marker.ADD
        assert marker.header.frame_id == "world"
        assert marker.header.stamp.sec * 10**9 + marker.header.stamp.nanosec == STAMP_NS
        assert marker.ns.startswith("meshfg/")
        assert (marker.pose.orientation.x, marker.pose.orientation.y, marker.pose.orientation.z,
                marker.pose.orientation.w) == (0.0, 0.0, 0.0, 1.0)
        assert min(marker.scale.x, marker.scale.y, marker.scale.z) > 0.0
        assert marker.color.a > 0.0
        assert (marker.lifetime.sec, marker.lifetime.nanosec) == (0, 0)  # until replaced
        assert np.isfinite(coordinates(marker.points)).all()
    # Triangle list: 3 points per surface triangle, one colour per point.
    assert len(surface.points) == 3 * len(triangles)
    np.testing.assert_array_equal(coordinates(surface.points), positions[triangles.reshape(-1)])
    colours = rgba(surface.colors)
    assert colours.shape == (3 * len(triangles), 4)
    assert np.isfinite(colours).all() and (colours[:, 3] > 0).all()
    # Per-vertex std mapping: every corner carries its vertex's colour.
    np.testing.assert_allclose(colours, std_colours(position_std)[triangles.reshape(-1)], atol=1e-7)
    corners = triangles.reshape(-1)
    most_certain = corners == corners[np.argmin(position_std[corners])]
    most_uncertain = corners == corners[np.argmax(position_std[corners])]
    assert (colours[most_uncertain, 0] > colours[most_certain, 0]).all()  # redder
    assert (colours[most_uncertain, 2] < colours[most_certain, 2]).all()  # less blue
    # Wireframe: 2 points per unique surface edge.
    edges = surface_edges(triangles)
    assert len(wireframe.points) == 2 * len(edges)
    np.testing.assert_array_equal(coordinates(wireframe.points), positions[edges.reshape(-1)])
    # Measured points.
    np.testing.assert_array_equal(coordinates(cloud.points), points)
    # A valid message: it survives CDR serialisation (colours are float32 on the wire).
    restored = deserialize_message(serialize_message(array), MarkerArray)
    np.testing.assert_array_equal(coordinates(restored.markers[0].points), coordinates(surface.points))
    np.testing.assert_allclose(rgba(restored.markers[0].colors), colours, rtol=1e-7)


def test_unknown_std_gives_a_grey_surface_and_no_points_an_empty_cloud(cube):
    array = mesh_markers(cube.vertices, cube.surface_triangles, None, None, "world", 0,
                         factory=RclpyMessageFactory())
    surface, _, cloud = array.markers
    assert len(surface.colors) == 0 and surface.color.a == 1.0
    assert len(cloud.points) == 0 and cloud.scale.x > 0.0


def test_recording_flavour_matches_rclpy_flavour(cube):
    position_std = np.linspace(0.0, 1e-3, cube.vertex_count)
    args = (cube.vertices, cube.surface_triangles, position_std, cube.vertices[:5], "world", 7)
    live = mesh_markers(*args, factory=RclpyMessageFactory())
    recorded = mesh_markers(*args, factory=RosbagsMessageFactory())
    raw = meshfg_typestore().serialize_cdr(recorded, "visualization_msgs/msg/MarkerArray")
    as_live = deserialize_message(serialize_message(live), MarkerArray)
    assert deserialize_message(bytes(raw), MarkerArray) == as_live
