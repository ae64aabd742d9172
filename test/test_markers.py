"""MarkerArray of an estimate: structure RViz and Foxglove accept, colours from the posterior std,
the colour scale's legend, and the covariance's ellipsoids."""
import numpy as np
import pytest
from rclpy.serialization import deserialize_message, serialize_message
from scipy.spatial.transform import Rotation
from visualization_msgs.msg import Marker, MarkerArray

from meshfg_ros.synthetic.meshing import cube_mesh
from meshfg_ros.io.messages import RclpyMessageFactory, RosbagsMessageFactory, meshfg_typestore
from meshfg_ros.markers import (
    MAX_ELLIPSOIDS,
    NAMESPACE_ELLIPSOIDS,
    NAMESPACE_LEGEND,
    mesh_markers,
    spread_surface_sample,
    std_colours,
    surface_edges,
)

STAMP_NS = 12_345_678_901


@pytest.fixture(scope="module")
def cube():
    return cube_mesh(side=0.05, divisions=3)


def coordinates(points) -> np.ndarray:
    return np.array([[p.x, p.y, p.z] for p in points]).reshape(-1, 3)


def rgba(colours) -> np.ndarray:
    return np.array([[c.r, c.g, c.b, c.a] for c in colours]).reshape(-1, 4)


def in_namespace(array, namespace) -> list:
    return sorted((m for m in array.markers if m.ns == namespace), key=lambda m: m.id)


# The 95 % region of a 3-D Gaussian: semi-axes sqrt(chi-square_3(0.95)) = 2.7955 standard deviations.
RADIUS_95 = 2.7955


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
    surface, wireframe, cloud = array.markers[:3]
    assert [m.type for m in array.markers[:3]] == [Marker.TRIANGLE_LIST, Marker.LINE_LIST, Marker.POINTS]
    assert len({(m.ns, m.id) for m in array.markers}) == len(array.markers)
    assert {m.ns for m in array.markers[3:]} == {NAMESPACE_LEGEND}  # no covariance: no ellipsoids
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
    surface, _, cloud = array.markers  # and no legend
    assert len(surface.colors) == 0 and surface.color.a == 1.0
    assert len(cloud.points) == 0 and cloud.scale.x > 0.0


def test_recording_flavour_matches_rclpy_flavour(cube):
    position_std = np.linspace(0.0, 1e-3, cube.vertex_count)
    covariance = position_std[:, None, None] ** 2 * np.eye(3)
    args = (cube.vertices, cube.surface_triangles, position_std, cube.vertices[:5], "world", 7)
    live = mesh_markers(*args, factory=RclpyMessageFactory(), position_covariance=covariance)
    recorded = mesh_markers(*args, factory=RosbagsMessageFactory(), position_covariance=covariance)
    assert in_namespace(live, NAMESPACE_ELLIPSOIDS) and in_namespace(live, NAMESPACE_LEGEND)
    raw = meshfg_typestore().serialize_cdr(recorded, "visualization_msgs/msg/MarkerArray")
    as_live = deserialize_message(serialize_message(live), MarkerArray)
    assert deserialize_message(bytes(raw), MarkerArray) == as_live


def test_legend_gives_the_colour_scale_in_mm(cube):
    position_std = np.linspace(0.0, 3e-3, cube.vertex_count)
    clipped = mesh_markers(cube.vertices, cube.surface_triangles, position_std, None, "world", 0, std_max=2e-3,
                           factory=RclpyMessageFactory())
    bar, *texts = in_namespace(clipped, NAMESPACE_LEGEND)
    assert bar.type == Marker.CUBE_LIST and len(bar.points) == len(bar.colors) > 2
    heights = coordinates(bar.points)[:, 2]
    assert (np.diff(heights) > 0).all()  # upwards from 0 to the scale's end
    np.testing.assert_allclose(rgba(bar.colors)[[0, -1]], std_colours(np.array([0.0, 1.0]), 1.0), atol=0.06)
    assert (coordinates(bar.points)[:, 0] > cube.vertices[:, 0].max()).all()  # beside the mesh, not on it
    assert all(text.type == Marker.TEXT_VIEW_FACING and text.scale.z > 0.0 for text in texts)
    ticks = [text for text in texts if text.text.endswith(" mm")]
    assert [tick.text for tick in ticks] == ["0 mm", "0.5 mm", "1 mm", "1.5 mm", ">= 2 mm"]
    # Each tick is in the colour it labels, at the height of that colour on the bar.
    np.testing.assert_allclose([[t.color.r, t.color.g, t.color.b, t.color.a] for t in ticks],
                               std_colours(np.array([0.0, 0.5, 1.0, 1.5, 2.0]), 2.0), atol=1e-6)
    assert [t.pose.position.z for t in ticks] == sorted(t.pose.position.z for t in ticks)
    assert any("std" in text.text for text in texts)  # the title
    # std_max 0: the scale ends at the largest std, which is no bound.
    automatic = mesh_markers(cube.vertices, cube.surface_triangles, position_std, None, "world", 0,
                             factory=RclpyMessageFactory())
    assert [t.text for t in in_namespace(automatic, NAMESPACE_LEGEND) if t.text.endswith(" mm")][-1] == "3 mm"


def test_ellipsoids_have_the_axes_of_their_covariance(cube):
    """diag(a^2, b^2, c^2) turned by a rotation per vertex: each ellipsoid is a SPHERE at its
    vertex, with full axes 2 x 2.7955 x (a, b, c) along the turned x, y, z axes."""
    mesh = cube.with_fixed(np.flatnonzero(np.isclose(cube.vertices[:, 2], 0.0)))
    rng = np.random.default_rng(11)
    rotations = Rotation.random(mesh.vertex_count, random_state=12)
    sigmas = np.array([0.2e-3, 0.5e-3, 1.1e-3])  # a < b < c
    covariance = np.einsum("vij,j,vkj->vik", rotations.as_matrix(), sigmas**2, rotations.as_matrix())
    covariance[mesh.fixed_vertices] = 0.0
    position_std = np.sqrt(np.einsum("vii->v", covariance) / 3.0)
    positions = mesh.vertices + rng.normal(scale=1e-4, size=mesh.vertices.shape)
    array = mesh_markers(positions, mesh.surface_triangles, position_std, None, "world", STAMP_NS,
                         factory=RclpyMessageFactory(), position_covariance=covariance)
    ellipsoids = in_namespace(array, NAMESPACE_ELLIPSOIDS)
    free_surface = np.setdiff1d(mesh.surface_vertices, mesh.fixed_vertices)
    assert len(ellipsoids) == len(free_surface)  # fewer than MAX_ELLIPSOIDS: all of them
    assert [m.id for m in ellipsoids] == list(range(len(ellipsoids)))
    centres = np.array([[m.pose.position.x, m.pose.position.y, m.pose.position.z] for m in ellipsoids])
    vertices = np.array([np.flatnonzero((positions == centre).all(axis=1))[0] for centre in centres])
    np.testing.assert_array_equal(vertices, free_surface)  # at free surface vertices, none fixed
    for marker, vertex in zip(ellipsoids, vertices, strict=True):
        assert marker.type == Marker.SPHERE and marker.action == Marker.ADD and 0.0 < marker.color.a < 1.0
        lengths = np.array([marker.scale.x, marker.scale.y, marker.scale.z])
        np.testing.assert_allclose(lengths, 2.0 * RADIUS_95 * sigmas, rtol=1e-4)
        quaternion = [marker.pose.orientation.x, marker.pose.orientation.y, marker.pose.orientation.z,
                      marker.pose.orientation.w]
        axes = Rotation.from_quat(quaternion).as_matrix()
        # The marker's x, y, z axes along the vertex's a, b, c axes (either sign).
        alignment = np.abs(np.einsum("ij,ij->j", axes, rotations[vertex].as_matrix()))
        np.testing.assert_allclose(alignment, 1.0, atol=1e-9)
    legend = [m.text for m in in_namespace(array, NAMESPACE_LEGEND)]
    assert any("95 %" in text for text in legend)


def test_ellipsoids_are_bounded_and_spread_over_the_surface():
    mesh = cube_mesh(side=0.05, divisions=16)
    fixed = np.flatnonzero(np.isclose(mesh.vertices[:, 2], 0.0))
    candidates = np.setdiff1d(mesh.surface_vertices, fixed)
    assert len(candidates) > 4 * MAX_ELLIPSOIDS
    chosen = spread_surface_sample(mesh.vertices, mesh.surface_triangles, fixed)
    assert len(chosen) == MAX_ELLIPSOIDS and np.isin(chosen, candidates).all()
    points = mesh.vertices[chosen]
    separation = np.linalg.norm(points[:, None] - points[None], axis=2)[np.triu_indices(len(chosen), 1)].min()
    covering = np.linalg.norm(mesh.vertices[candidates][:, None] - points[None], axis=2).min(axis=1).max()
    assert covering <= separation  # even: no surface vertex farther from the sample than its points from each other
    covariance = np.tile(1e-8 * np.eye(3), (mesh.vertex_count, 1, 1))
    covariance[fixed] = 0.0
    array = mesh_markers(mesh.vertices, mesh.surface_triangles, None, None, "world", 0,
                         factory=RclpyMessageFactory(), position_covariance=covariance)
    ellipsoids = in_namespace(array, NAMESPACE_ELLIPSOIDS)
    assert len(ellipsoids) == MAX_ELLIPSOIDS  # the sample of the vertices whose covariance is not zero
    centres = np.array([[m.pose.position.x, m.pose.position.y, m.pose.position.z] for m in ellipsoids])
    np.testing.assert_array_equal(centres, points)


def test_a_singular_covariance_gives_a_flat_but_valid_ellipsoid(cube):
    covariance = np.zeros((cube.vertex_count, 3, 3))
    covariance[:, 2, 2] = 1e-8  # known in x and y, 0.1 mm in z
    covariance[:, 0, 0] = -1e-22  # float32 rounding of a zero eigenvalue
    array = mesh_markers(cube.vertices, cube.surface_triangles, None, None, "world", 0,
                         factory=RclpyMessageFactory(), position_covariance=covariance)
    for marker in in_namespace(array, NAMESPACE_ELLIPSOIDS):
        scale = sorted([marker.scale.x, marker.scale.y, marker.scale.z])
        assert 0.0 < scale[0] <= scale[1] < 1e-4 and scale[2] == pytest.approx(2.0 * RADIUS_95 * 1e-4, rel=1e-4)
    restored = deserialize_message(serialize_message(array), MarkerArray)
    assert len(restored.markers) == len(array.markers)
