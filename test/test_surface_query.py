"""The planner's surface queries (core/geometry/surface_query.py), the client without ROS
(planner_client.py) and the newest-stamp lookups they place points with (core/inputs/frames.py,
core/inputs/world_frame.py).

Distances are checked against an exact point-to-mesh distance computed here by brute force over
every triangle (the plane projection where it falls inside the triangle, else the nearest of the
three edges' closest points: not the closed form the module uses), inside/outside against
libigl's generalised winding number and against meshes whose inside is known, and the standard
deviation against Monte Carlo draws from the covariance.
"""
import subprocess
import sys
from pathlib import Path

import igl
import numpy as np
import pytest
import yaml

from meshfg_ros.core.geometry.closest_point import InvalidGeometryError
from meshfg_ros.core.inputs.frames import FrameLookupError, StampedTransform, TransformBuffer
from meshfg_ros.core.geometry.mesh import TetMesh
from meshfg_ros.core.geometry.surface_query import SurfaceQuery
from meshfg_ros.core.inputs.world_frame import WorldFrameInputs
from meshfg_ros.io.messages import MeshState
from meshfg_ros.io.recording import RecordingWriter
from meshfg_ros.parameters import default_parameters, load_parameters
from meshfg_ros.planner_client import RecordedSurface, SurfaceAnswer, SurfaceQueryError, clearance_positions
from meshfg_ros.synthetic.meshing import cube_mesh, structured_box_mesh
from meshfg_ros.synthetic.scenarios import liver_mesh
from meshfg_ros.topics import ESTIMATED_MESH_TOPIC


# ---------------------------------------------------------------------------- references
def _segment_closest(points, u, v):
    """Closest points of segments u-v to points, all (P, 3)."""
    e = v - u
    t = np.clip(np.einsum("ij,ij->i", points - u, e) / np.einsum("ij,ij->i", e, e), 0.0, 1.0)
    return u + t[:, None] * e


def exact_distances(points, vertices, triangles):
    """Unsigned distance of each point to the triangle mesh: the minimum over every triangle."""
    a, b, c = (vertices[triangles[:, k]] for k in range(3))
    best = np.full(len(points), np.inf)
    for p_index in range(0, len(points), 50):  # chunks of points x all triangles
        p = points[p_index:p_index + 50]
        pairs = np.repeat(p, len(triangles), axis=0)
        aa, bb, cc = (np.tile(x, (len(p), 1)) for x in (a, b, c))
        normal = np.cross(bb - aa, cc - aa)
        normal /= np.linalg.norm(normal, axis=1, keepdims=True)
        on_plane = pairs - np.einsum("ij,ij->i", pairs - aa, normal)[:, None] * normal
        inside = np.ones(len(pairs), dtype=bool)
        for u, v in ((aa, bb), (bb, cc), (cc, aa)):
            inside &= np.einsum("ij,ij->i", np.cross(v - u, on_plane - u), normal) >= 0.0
        candidates = [np.where(inside[:, None], on_plane, np.inf)]
        candidates += [_segment_closest(pairs, u, v) for u, v in ((aa, bb), (bb, cc), (cc, aa))]
        distance = np.min([np.linalg.norm(pairs - q, axis=1) for q in candidates], axis=0)
        best[p_index:p_index + 50] = distance.reshape(len(p), len(triangles)).min(axis=1)
    return best


def l_shaped_mesh() -> TetMesh:
    """A 4 x 4 x 2 cm box without its quarter x > 2 cm, y > 2 cm: concave edges and corners."""
    box = structured_box_mesh((0.04, 0.04, 0.02), (8, 8, 4))
    centroids = box.vertices[box.tetrahedra].mean(axis=1)
    kept = box.tetrahedra[~((centroids[:, 0] > 0.02) & (centroids[:, 1] > 0.02))]
    used, tetrahedra = np.unique(kept, return_inverse=True)
    return TetMesh(box.vertices[used], tetrahedra.reshape(-1, 4))


def inside_l_shape(points):
    in_box = np.all((points > 0.0) & (points < [0.04, 0.04, 0.02]), axis=1)
    return in_box & ~((points[:, 0] >= 0.02) & (points[:, 1] >= 0.02))


def near_surface_points(vertices, triangles, rng, count, spread):
    """Points around random surface points (on faces, edges and corners) within `spread`."""
    corners = vertices[triangles[rng.integers(len(triangles), size=count)]]
    weights = rng.dirichlet([0.3, 0.3, 0.3], size=count)  # many near edges and corners
    return np.einsum("kc,kcj->kj", weights, corners) + rng.normal(scale=spread, size=(count, 3))


@pytest.fixture(scope="module")
def liver():
    mesh = liver_mesh()
    rng = np.random.default_rng(3)
    # A deformed state, as an estimate is: smooth displacement of every vertex.
    vertices = mesh.vertices + 0.003 * np.sin(mesh.vertices[:, [1, 2, 0]] * 60.0)
    return vertices, mesh.surface_triangles, rng


# ---------------------------------------------------------------------------- distance and sign
def test_distances_equal_the_exact_point_to_mesh_distance(liver):
    vertices, triangles, rng = liver
    low, high = vertices.min(axis=0), vertices.max(axis=0)
    points = np.vstack([rng.uniform(low - 0.02, high + 0.02, size=(300, 3)),
                        near_surface_points(vertices, triangles, rng, 300, 0.002)])
    answer = SurfaceQuery(vertices, triangles).query(points)
    np.testing.assert_allclose(np.abs(answer.signed_distance), exact_distances(points, vertices, triangles),
                               rtol=0.0, atol=1e-9)
    # The closest point lies on its triangle at that distance.
    np.testing.assert_allclose(np.linalg.norm(points - answer.closest, axis=1), np.abs(answer.signed_distance),
                               rtol=0.0, atol=1e-12)
    corners = vertices[triangles[answer.triangle]]
    np.testing.assert_allclose(np.einsum("kc,kcj->kj", answer.barycentric, corners), answer.closest, atol=1e-12)


def test_sign_agrees_with_the_winding_number_near_and_far(liver):
    vertices, triangles, rng = liver
    low, high = vertices.min(axis=0), vertices.max(axis=0)
    points = np.vstack([rng.uniform(low - 0.01, high + 0.01, size=(500, 3)),
                        near_surface_points(vertices, triangles, rng, 1000, 2e-4)])
    signed = SurfaceQuery(vertices, triangles).query(points).signed_distance
    inside = igl.winding_number(vertices, triangles, points) > 0.5
    assert inside.sum() > 300 and (~inside).sum() > 300
    assert np.array_equal(signed < 0.0, inside)


def test_sign_is_right_at_concave_edges_and_corners():
    mesh = l_shaped_mesh()
    rng = np.random.default_rng(5)
    # Around the concave edge x = y = 2 cm, its two ends, and the corners of the notch.
    along = rng.uniform(0.0, 0.02, size=400)
    points = np.column_stack([0.02 + rng.normal(scale=1e-3, size=400), 0.02 + rng.normal(scale=1e-3, size=400), along])
    points = np.vstack([points, [0.02, 0.02, 0.02] + rng.normal(scale=1e-3, size=(200, 3))])
    points = points[np.abs(points - 0.02).min(axis=1) > 1e-6]  # off the surface itself
    answer = SurfaceQuery(mesh.vertices, mesh.surface_triangles).query(points)
    assert np.array_equal(answer.signed_distance < 0.0, inside_l_shape(points))
    np.testing.assert_allclose(np.abs(answer.signed_distance),
                               exact_distances(points, mesh.vertices, mesh.surface_triangles), atol=1e-9)


def test_the_normal_is_the_unit_gradient_of_the_signed_distance(liver):
    vertices, triangles, rng = liver
    surface = SurfaceQuery(vertices, triangles)
    points = near_surface_points(vertices, triangles, rng, 300, 0.003)
    answer = surface.query(points)
    np.testing.assert_allclose(np.linalg.norm(answer.normal, axis=1), 1.0, atol=1e-12)
    # Along the normal the signed distance grows at rate 1 (central differences of 1 um).
    step = 1e-6
    ahead = surface.query(points + step * answer.normal).signed_distance
    behind = surface.query(points - step * answer.normal).signed_distance
    np.testing.assert_allclose((ahead - behind) / (2 * step), 1.0, atol=1e-6)
    # The closest point is back along it at the signed distance.
    np.testing.assert_allclose(points - answer.signed_distance[:, None] * answer.normal, answer.closest, atol=1e-12)


def test_a_point_on_the_surface_has_distance_zero_and_the_outward_pseudo_normal():
    mesh = cube_mesh(side=0.02, divisions=2)
    corner, edge_middle, face_middle = [0.02, 0.02, 0.02], [0.01, 0.02, 0.02], [0.005, 0.005, 0.02]
    answer = SurfaceQuery(mesh.vertices, mesh.surface_triangles).query([corner, edge_middle, face_middle])
    np.testing.assert_allclose(answer.signed_distance, 0.0, atol=1e-15)
    np.testing.assert_allclose(answer.normal[0], np.ones(3) / np.sqrt(3), atol=1e-12)
    np.testing.assert_allclose(answer.normal[1], [0.0, 1 / np.sqrt(2), 1 / np.sqrt(2)], atol=1e-12)
    np.testing.assert_allclose(answer.normal[2], [0.0, 0.0, 1.0], atol=1e-12)


def test_bad_input_is_refused_with_its_reason():
    mesh = cube_mesh(side=0.02, divisions=2)
    surface = SurfaceQuery(mesh.vertices, mesh.surface_triangles)
    with pytest.raises(InvalidGeometryError, match="NaN or infinite"):
        surface.query([[0.0, np.nan, 0.0]])
    with pytest.raises(InvalidGeometryError, match="shape"):
        surface.query([0.0, 0.0])
    with pytest.raises(InvalidGeometryError, match="position_covariance"):
        SurfaceQuery(mesh.vertices, mesh.surface_triangles, np.zeros((3, 3, 3)))
    assert surface.query(np.zeros((0, 3))).signed_distance.shape == (0,)
    assert surface.query([[0.01, 0.01, 0.01]]).distance_std is None  # no covariance, no std


# ---------------------------------------------------------------------------- standard deviation
def _query_points_over_faces(vertices, triangles, rng, count, height):
    """Points `height` off the middle of random faces (inside for negative heights): their
    closest points stay inside those faces under small perturbations of the vertices."""
    chosen = rng.choice(len(triangles), size=count, replace=False)
    corners = vertices[triangles[chosen]]
    weights = rng.dirichlet([8.0, 8.0, 8.0], size=count)
    normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    return np.einsum("kc,kcj->kj", weights, corners) + height * normal


def _drawn_distances(vertices, triangles, points, displacements):
    return np.array([SurfaceQuery(vertices + d, triangles).query(points).signed_distance for d in displacements])


DRAWS = 2000
# The standard error of a standard deviation estimated from n normal draws is std / sqrt(2 (n - 1)):
# four of them bound the Monte Carlo error of each point's comparison.
MC_TOLERANCE = 4.0 / np.sqrt(2 * (DRAWS - 1))


def test_std_equals_monte_carlo_when_the_vertices_errors_are_fully_correlated():
    mesh = cube_mesh(side=0.03, divisions=3)
    vertices, triangles = mesh.vertices, mesh.surface_triangles
    rng = np.random.default_rng(11)
    # Blocks a_i^2 C0 drawn with one shared normal vector: corners' errors fully correlated.
    c0 = np.array([[1.0, 0.3, -0.2], [0.3, 0.8, 0.1], [-0.2, 0.1, 1.5]]) * 1e-10  # ~10 um
    scale = rng.uniform(0.3, 1.5, size=len(vertices))
    covariance = scale[:, None, None] ** 2 * c0
    points = np.vstack([_query_points_over_faces(vertices, triangles, rng, 10, 0.002),
                        _query_points_over_faces(vertices, triangles, rng, 10, -0.0003)])
    answer = SurfaceQuery(vertices, triangles, covariance).query(points)
    shared = rng.normal(size=(DRAWS, 3)) @ np.linalg.cholesky(c0).T
    drawn = _drawn_distances(vertices, triangles, points, scale[None, :, None] * shared[:, None, :])
    np.testing.assert_allclose(drawn.std(axis=0, ddof=1), answer.distance_std, rtol=MC_TOLERANCE)


def test_std_bounds_monte_carlo_of_independent_vertices_from_above_within_sqrt3():
    mesh = cube_mesh(side=0.03, divisions=3)
    vertices, triangles = mesh.vertices, mesh.surface_triangles
    rng = np.random.default_rng(12)
    factors = rng.normal(size=(len(vertices), 3, 3)) * 1e-5
    covariance = factors @ factors.transpose(0, 2, 1)
    points = _query_points_over_faces(vertices, triangles, rng, 20, 0.001)
    answer = SurfaceQuery(vertices, triangles, covariance).query(points)
    displacements = np.einsum("nij,dnj->dni", factors, rng.normal(size=(DRAWS, len(vertices), 3)))
    drawn_std = _drawn_distances(vertices, triangles, points, displacements).std(axis=0, ddof=1)
    assert np.all(drawn_std <= answer.distance_std * (1.0 + MC_TOLERANCE))
    assert np.all(drawn_std >= answer.distance_std / np.sqrt(3.0) * (1.0 - MC_TOLERANCE))


def test_std_is_the_corners_covariance_along_the_normal():
    mesh = cube_mesh(side=0.02, divisions=1)
    vertices, triangles = mesh.vertices, mesh.surface_triangles
    variance_along_z = np.where(vertices[:, 2] > 0.01, 4e-6, 0.0)  # the top's vertices: 2 mm along z
    covariance = np.zeros((len(vertices), 3, 3))
    covariance[:, 2, 2] = variance_along_z
    points = [[0.01, 0.01, 0.025], [0.01, 0.01, -0.005], [-0.005, 0.01, 0.015]]
    answer = SurfaceQuery(vertices, triangles, covariance).query(points)
    # Above the top: all its corners move 2 mm along the normal; below the fixed bottom: none.
    # Beside the side face x = 0 (normal along -x): the top's errors are across the normal.
    np.testing.assert_allclose(answer.distance_std, [2e-3, 0.0, 0.0], atol=1e-15)


# ---------------------------------------------------------------------------- clearance, recordings
def test_clearance_moves_points_out_to_k_std_and_keeps_clear_ones():
    mesh = cube_mesh(side=0.03, divisions=3)
    vertices, triangles = mesh.vertices, mesh.surface_triangles
    covariance = np.tile(np.eye(3) * 1e-6, (len(vertices), 1, 1))  # 1 mm in every direction
    surface = SurfaceQuery(vertices, triangles, covariance)
    points = np.array([[0.012, 0.017, 0.029], [0.012, 0.017, 0.031], [0.012, 0.017, 0.05], [0.014, 0.013, 0.02]])
    found = surface.query(points)
    answer = SurfaceAnswer(0, 0, False, "world", found.closest, found.signed_distance, found.normal,
                           found.distance_std)
    moved = clearance_positions(points, answer, clearance_sigmas=3.0, min_clearance=0.002)
    after = surface.query(moved).signed_distance
    np.testing.assert_allclose(after[[0, 1, 3]], 0.003, atol=1e-12)  # 3 std of 1 mm
    assert np.array_equal(moved[2], points[2])  # 2 cm clear: kept
    without_std = SurfaceAnswer(0, 0, False, "world", found.closest, found.signed_distance, found.normal, None)
    np.testing.assert_allclose(surface.query(clearance_positions(points, without_std, 3.0, 0.002)).signed_distance,
                               [0.002, 0.002, 0.02, 0.002], atol=1e-12)


def _estimate(mesh, stamp_ns, lift):
    vertices = mesh.vertices + [0.0, 0.0, lift]
    return MeshState(stamp_ns, "world", stamp_ns // 1_000_000_000, vertices, mesh.tetrahedra, mesh.surface_triangles,
                     position_covariance=np.tile(np.eye(3) * 1e-6, (mesh.vertex_count, 1, 1)))


def test_recorded_surface_answers_on_the_newest_estimate_at_or_before_the_stamp(tmp_path):
    mesh = cube_mesh(side=0.02, divisions=2)
    with RecordingWriter(tmp_path / "run") as writer:
        for stamp_s, lift in ((1, 0.0), (2, 0.005)):
            writer.write(ESTIMATED_MESH_TOPIC, _estimate(mesh, stamp_s * 1_000_000_000, lift), stamp_s * 1_000_000_000)
    recorded = RecordedSurface.from_recording(tmp_path / "run")
    above = [[0.01, 0.01, 0.03]]
    first = recorded.query(above, stamp_ns=1_500_000_000)
    last = recorded.query(above)
    assert (first.stamp_ns, first.step, last.stamp_ns, last.step) == (1_000_000_000, 1, 2_000_000_000, 2)
    np.testing.assert_allclose([first.signed_distance[0], last.signed_distance[0]], [0.01, 0.005], atol=1e-12)
    # The covariance travels as float32: its std is 1 mm to float32's precision.
    np.testing.assert_allclose(last.distance_std, 1e-3, rtol=1e-6)
    with pytest.raises(SurfaceQueryError, match="no estimate at or before"):
        recorded.query(above, stamp_ns=999)


def test_the_recording_client_needs_no_ros(tmp_path):
    mesh = cube_mesh(side=0.02, divisions=2)
    with RecordingWriter(tmp_path / "run") as writer:
        writer.write(ESTIMATED_MESH_TOPIC, _estimate(mesh, 1_000_000_000, 0.0), 1_000_000_000)
    script = (f"import sys; from meshfg_ros.planner_client import RecordedSurface; "
              f"d = RecordedSurface.from_recording({str(tmp_path / 'run')!r}).query([[0.01, 0.01, 0.03]]); "
              "ros = [m for m in sys.modules if m.split('.')[0] in ('rclpy', 'meshfg_msgs', 'geometry_msgs')]; "
              "print(round(float(d.signed_distance[0]), 9), ros)")
    completed = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert completed.returncode == 0, completed.stderr
    assert completed.stdout.split() == ["0.01", "[]"]


# ---------------------------------------------------------------------------- placing query points
def _transform(parent, child, stamp_ns, x):
    return StampedTransform(parent, child, stamp_ns, np.array([x, 0.0, 0.0]), np.array([0.0, 0.0, 0.0, 1.0]))


def test_the_newest_stamp_of_a_chain_is_its_oldest_newest_transform():
    buffer = TransformBuffer()
    buffer.set_transform(_transform("world", "base", 0, 1.0), static=True)
    for stamp_ns, x in ((100, 0.0), (300, 0.3)):
        buffer.set_transform(_transform("base", "arm", stamp_ns, x))
    for stamp_ns, x in ((100, 0.0), (200, 0.2)):
        buffer.set_transform(_transform("arm", "tip", stamp_ns, x))
    assert buffer.newest_stamp("world", "tip") == 200
    assert buffer.newest_stamp("tip", "arm") == 200
    assert buffer.newest_stamp("world", "base") is None  # static only: any stamp
    with pytest.raises(FrameLookupError, match="unknown frame 'nowhere'"):
        buffer.newest_stamp("world", "nowhere")
    placer = WorldFrameInputs("world", buffer)
    # Stamp None: at 200 ns, where arm is 0.15 m along (halfway from 0.0 to 0.3 over 100..300 ns) and tip 0.2 m.
    np.testing.assert_allclose(placer.matrix_to_world("tip", None)[:3, 3], [1.0 + 0.15 + 0.2, 0.0, 0.0], atol=1e-12)
    np.testing.assert_array_equal(placer.matrix_to_world("world", None), np.eye(4))
    with pytest.raises(FrameLookupError, match="beyond the newest"):
        placer.matrix_to_world("tip", 250)


def test_the_example_planners_parameters_file_sets_its_parameters_at_their_defaults():
    document = yaml.safe_load((Path(__file__).resolve().parents[1] / "config" / "tool_clearance.yaml").read_text())
    values = document["/**"]["ros__parameters"]
    assert load_parameters(values, "tool_clearance_node") == default_parameters("tool_clearance_node") == values
