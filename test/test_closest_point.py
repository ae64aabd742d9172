"""Closest point on triangles: Voronoi regions, exact Jacobian (autograd + finite differences),
and the association (surface grid, libigl's tree beyond its reach) against brute force (a
perturbed cube, the liver, degenerate and far-flung surfaces)."""

import numpy as np
import pytest
import torch
from torch.func import jacrev, vmap

from meshfg_ros.core.geometry import closest_point
from meshfg_ros.core.geometry.closest_point import (
    GRID_MAX_REACH_EDGES,
    REGION_EDGE_AB,
    REGION_EDGE_AC,
    REGION_EDGE_BC,
    REGION_FACE,
    REGION_VERTEX_A,
    REGION_VERTEX_B,
    REGION_VERTEX_C,
    ClosestPointIndex,
    InvalidGeometryError,
    brute_force_closest,
    project_onto_mesh_triangles,
    project_onto_triangles,
    projection_jacobian,
)
from meshfg_ros.synthetic.meshing import cube_mesh

ALL_REGIONS = (REGION_FACE, REGION_VERTEX_A, REGION_VERTEX_B, REGION_VERTEX_C, REGION_EDGE_AB, REGION_EDGE_AC, REGION_EDGE_BC)


def torch_closest_point(p, a, b, c):
    """Ericson's closest point on a triangle in torch (one point), for autograd reference."""
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = ab @ ap, ac @ ap
    bp = p - b
    d3, d4 = ab @ bp, ac @ bp
    cp = p - c
    d5, d6 = ab @ cp, ac @ cp
    vc = d1 * d4 - d3 * d2
    vb = d5 * d2 - d1 * d6
    va = d3 * d6 - d5 * d4
    face = a + ab * (vb / (va + vb + vc)) + ac * (vc / (va + vb + vc))
    edge_bc = b + (c - b) * ((d4 - d3) / ((d4 - d3) + (d5 - d6)))
    edge_ac = a + ac * (d2 / (d2 - d6))
    edge_ab = a + ab * (d1 / (d1 - d3))
    # Nested where in reverse priority: the first passing test of Ericson's order wins.
    result = face
    result = torch.where((va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0), edge_bc, result)
    result = torch.where((vb <= 0) & (d2 >= 0) & (d6 <= 0), edge_ac, result)
    result = torch.where((d6 >= 0) & (d5 <= d6), c, result)
    result = torch.where((vc <= 0) & (d1 >= 0) & (d3 <= 0), edge_ab, result)
    result = torch.where((d3 >= 0) & (d4 <= d3), b, result)
    result = torch.where((d1 <= 0) & (d2 <= 0), a, result)
    return result


def random_cases(rng, count):
    """Random non-sliver triangles (quality > 0.05, as on a mesh surface) and points spread
    around them so every region is hit."""
    a, b, c = (rng.normal(size=(4 * count, 3)) for _ in range(3))
    area2 = np.linalg.norm(np.cross(b - a, c - a), axis=1)
    edges2 = ((b - a) ** 2).sum(1) + ((c - b) ** 2).sum(1) + ((a - c) ** 2).sum(1)
    good = np.flatnonzero(2 * np.sqrt(3) * area2 / edges2 > 0.05)[:count]
    a, b, c = a[good], b[good], c[good]
    weights = rng.uniform(-1.0, 2.0, size=(count, 3))
    weights /= weights.sum(axis=1, keepdims=True)
    normal = np.cross(b - a, c - a)
    points = weights[:, :1] * a + weights[:, 1:2] * b + weights[:, 2:] * c + rng.normal(size=(count, 1)) * normal
    return points, a, b, c


def test_every_voronoi_region_is_classified_and_closest_is_optimal():
    rng = np.random.default_rng(0)
    points, a, b, c = random_cases(rng, 4000)
    projection = project_onto_triangles(points, a, b, c)
    assert set(np.unique(projection.region)) == set(ALL_REGIONS)
    bary = projection.barycentric
    assert np.allclose(bary.sum(axis=1), 1.0) and bary.min() >= -1e-12
    # No barycentric sample of the triangle is closer than the projection.
    samples = rng.dirichlet(np.ones(3), size=400)
    sampled = np.einsum("sk,pkj->psj", samples, np.stack([a, b, c], axis=1))
    sampled_distance = ((sampled - points[:, None]) ** 2).sum(-1).min(axis=1)
    assert np.all(projection.squared_distance <= sampled_distance + 1e-12)


def test_regions_of_hand_placed_points():
    a, b, c = np.array([0.0, 0, 0]), np.array([1.0, 0, 0]), np.array([0.0, 1, 0])
    cases = {
        REGION_FACE: ([0.2, 0.2, 0.5], [0.2, 0.2, 0.0]),
        REGION_VERTEX_A: ([-1.0, -1.0, 0.3], a),
        REGION_VERTEX_B: ([2.0, -0.5, 0.0], b),
        REGION_VERTEX_C: ([-0.5, 2.0, 0.0], c),
        REGION_EDGE_AB: ([0.5, -1.0, 0.0], [0.5, 0.0, 0.0]),
        REGION_EDGE_AC: ([-1.0, 0.5, 0.0], [0.0, 0.5, 0.0]),
        REGION_EDGE_BC: ([1.0, 1.0, 0.0], [0.5, 0.5, 0.0]),
    }
    points = np.array([point for point, _ in cases.values()])
    tile = np.ones((len(points), 1))
    projection = project_onto_triangles(points, tile * a, tile * b, tile * c)
    assert projection.region.tolist() == list(cases)
    assert np.allclose(projection.closest, np.array([closest for _, closest in cases.values()]), atol=1e-15)


def test_jacobian_matches_torch_autograd_in_every_region():
    rng = np.random.default_rng(1)
    points, a, b, c = random_cases(rng, 3000)
    analytic = projection_jacobian(points, a, b, c)
    torch_inputs = [torch.tensor(x, dtype=torch.float64) for x in (points, a, b, c)]
    reference = vmap(jacrev(torch_closest_point, argnums=(1, 2, 3)))(*torch_inputs)
    reference = torch.cat(reference, dim=-1).numpy()
    regions = project_onto_triangles(points, a, b, c).region
    for code in ALL_REGIONS:
        mask = regions == code
        assert mask.sum() > 20
        np.testing.assert_allclose(analytic[mask], reference[mask], rtol=1e-9, atol=1e-10)


def test_jacobian_matches_central_finite_differences():
    rng = np.random.default_rng(2)
    points, a, b, c = random_cases(rng, 2000)
    projection = project_onto_triangles(points, a, b, c)
    analytic = projection_jacobian(points, a, b, c, projection.region)
    corners = np.concatenate([a, b, c], axis=1)
    step = 1e-6
    numeric = np.zeros_like(analytic)
    # Points within the step of a region boundary have a kink; skip only those.
    stable = np.ones(len(points), dtype=bool)
    for column in range(9):
        plus, minus = corners.copy(), corners.copy()
        plus[:, column] += step
        minus[:, column] -= step
        forward = project_onto_triangles(points, plus[:, :3], plus[:, 3:6], plus[:, 6:])
        backward = project_onto_triangles(points, minus[:, :3], minus[:, 3:6], minus[:, 6:])
        numeric[:, :, column] = (forward.closest - backward.closest) / (2 * step)
        stable &= (forward.region == projection.region) & (backward.region == projection.region)
    assert stable.mean() > 0.99
    np.testing.assert_allclose(analytic[stable], numeric[stable], rtol=1e-6, atol=1e-7)


def test_jacobian_times_residual_is_the_fixed_barycentric_gradient():
    rng = np.random.default_rng(3)
    points, a, b, c = random_cases(rng, 500)
    projection = project_onto_triangles(points, a, b, c)
    jacobian = projection_jacobian(points, a, b, c, projection.region)
    residual = projection.closest - points
    gradient = np.einsum("pij,pi->pj", jacobian, residual)
    fixed = np.einsum("pk,pi->pki", projection.barycentric, residual).reshape(-1, 9)
    np.testing.assert_allclose(gradient, fixed, rtol=1e-8, atol=1e-10)


@pytest.fixture(scope="module")
def cube_surface():
    mesh = cube_mesh(side=1.0, divisions=6)
    rng = np.random.default_rng(4)
    vertices = mesh.vertices + rng.normal(scale=0.02, size=mesh.vertices.shape)
    return vertices, mesh.surface_triangles


def test_index_association_equals_brute_force(cube_surface):
    vertices, triangles = cube_surface
    rng = np.random.default_rng(5)
    points = rng.uniform(-0.3, 1.3, size=(1500, 3))
    index = ClosestPointIndex(vertices, triangles)
    fast = index.associate(points)
    slow = brute_force_closest(points, vertices, triangles)
    np.testing.assert_allclose(fast.distance, slow.distance, rtol=0, atol=1e-14)
    np.testing.assert_allclose(fast.closest, slow.closest, rtol=0, atol=1e-14)
    # Where the triangles differ it is a tie (a shared edge or vertex): same distance on both.
    corners = vertices[triangles[fast.triangle]]
    own = project_onto_triangles(points, corners[:, 0], corners[:, 1], corners[:, 2])
    np.testing.assert_allclose(np.sqrt(own.squared_distance), slow.distance, rtol=0, atol=1e-14)


def test_projection_on_mesh_triangles_equals_the_corner_form_and_checks_its_indices(cube_surface):
    """The form LM's frozen associations use (triangle indices into a state's vertices) gives
    what the corner form gives, and an index past the triangles (or past the vertices) is an
    IndexError, not a read of other memory (the compiled loop is bounds-checked)."""
    vertices, triangles = cube_surface
    rng = np.random.default_rng(11)
    points = rng.uniform(-0.3, 1.3, size=(300, 3))
    index = rng.integers(0, len(triangles), size=300)
    on_mesh = project_onto_mesh_triangles(points, vertices, triangles, index)
    corners = vertices[triangles[index]]
    by_corners = project_onto_triangles(points, corners[:, 0], corners[:, 1], corners[:, 2])
    np.testing.assert_allclose(on_mesh.closest, by_corners.closest, rtol=0, atol=1e-15)
    np.testing.assert_array_equal(on_mesh.region, by_corners.region)
    with pytest.raises(IndexError):
        project_onto_mesh_triangles(points[:2], vertices, triangles, np.array([0, len(triangles)]))
    with pytest.raises(IndexError):
        project_onto_mesh_triangles(points[:1], vertices, np.array([[0, 1, len(vertices)]]), np.array([0]))


def test_index_gating_rejects_far_points(cube_surface):
    vertices, triangles = cube_surface
    points = np.array([[0.5, 0.5, 1.05], [0.5, 0.5, 3.0], [-2.0, 0.5, 0.5]])
    association = ClosestPointIndex(vertices, triangles).associate(points, max_distance=0.2)
    assert association.triangle[0] >= 0 and association.triangle[1] == -1 and association.triangle[2] == -1
    assert np.isinf(association.distance[1:]).all()


def test_bad_input_raises():
    with pytest.raises(InvalidGeometryError, match="points"):
        ClosestPointIndex(np.zeros((3, 3)), np.array([[0, 1, 2]])).associate(np.zeros((4, 2)))
    with pytest.raises(InvalidGeometryError, match="index"):
        ClosestPointIndex(np.zeros((3, 3)), np.array([[0, 1, 3]]))


def test_index_association_on_the_liver_equals_brute_force():
    """A real anatomical surface (SOFA's liver: curved, uneven triangles) and points on both
    sides of it, near and far: same distances and closest points as all pairs."""
    from meshfg_ros.synthetic.scenarios import liver_mesh

    mesh = liver_mesh()
    vertices, triangles = mesh.vertices, mesh.surface_triangles
    rng = np.random.default_rng(8)
    anchors = vertices[rng.choice(np.unique(triangles), 600)]
    scale = np.ptp(vertices, axis=0).max()
    points = anchors + rng.normal(scale=0.02 * scale, size=anchors.shape)
    points = np.concatenate([points, rng.uniform(vertices.min(0) - 0.2 * scale, vertices.max(0) + 0.2 * scale, (200, 3))])
    fast = ClosestPointIndex(vertices, triangles).associate(points)
    slow = brute_force_closest(points, vertices, triangles)
    np.testing.assert_allclose(fast.distance, slow.distance, rtol=0, atol=1e-15 * scale)
    np.testing.assert_allclose(fast.closest, slow.closest, rtol=0, atol=1e-14 * scale)
    assert np.all(fast.triangle >= 0) and np.all(np.isin(fast.region, ALL_REGIONS))


def test_index_of_one_triangle_and_empty_queries():
    vertices = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [5.0, 5.0, 5.0]])
    index = ClosestPointIndex(vertices, np.array([[0, 1, 2]]))
    association = index.associate(np.array([[0.2, 0.2, 1.0], [2.0, -1.0, 0.0]]))
    np.testing.assert_allclose(association.closest, [[0.2, 0.2, 0.0], [1.0, 0.0, 0.0]])
    np.testing.assert_array_equal(association.region, [REGION_FACE, REGION_VERTEX_B])
    np.testing.assert_allclose(association.distance, [1.0, np.sqrt(2.0)])
    empty = index.associate(np.zeros((0, 3)))
    assert empty.triangle.shape == (0,) and empty.closest.shape == (0, 3)


def _grid_answers(index: ClosestPointIndex, points) -> np.ndarray:
    """The surface grid's own answers (-1 where it defers to libigl's tree)."""
    return closest_point._grid_closest(np.ascontiguousarray(points, dtype=np.float64), index.vertices,
                                       index.triangles, *index._grid, index._most_scanned)


def _median_edge(vertices, triangles) -> float:
    corners = vertices[triangles]
    return float(np.median(np.linalg.norm(corners - np.roll(corners, 1, axis=1), axis=2)))


@pytest.mark.parametrize("scan_beyond_reach", [False, True])
@pytest.mark.parametrize("reach_edges", [None, 0.2, 0.8])
def test_the_grid_answers_the_points_within_its_reach_as_the_all_pairs_search_does(reach_edges, scan_beyond_reach):
    """Points on both sides of the liver's surface (curved, uneven triangles) at distances up to
    three times the grid's reach, and points spread over a box three times the liver's size: every
    point the grid answers gets the all-pairs search's triangle (its first minimiser: the lowest
    index among ties); every point within the reach is answered by the grid, and with
    `scan_beyond_reach` every one within 1.5 times the reach too (from the cells around it), while
    far points are passed on to libigl; without it every point beyond the reach is."""
    from meshfg_ros.synthetic.scenarios import liver_mesh

    mesh = liver_mesh()
    vertices, triangles = mesh.vertices, mesh.surface_triangles
    edge = _median_edge(vertices, triangles)
    reach = None if reach_edges is None else reach_edges * edge
    index = ClosestPointIndex(vertices, triangles, reach, scan_beyond_reach=scan_beyond_reach)
    effective = (closest_point.GRID_REACH_EDGES if reach_edges is None else reach_edges) * edge
    rng = np.random.default_rng(21)
    anchors = vertices[rng.choice(np.unique(triangles), 1500)]
    directions = rng.normal(size=anchors.shape)
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    near = anchors + directions * rng.uniform(0.0, 3.0 * effective, size=(len(anchors), 1))
    low, high = vertices.min(axis=0), vertices.max(axis=0)
    spread = rng.uniform(low - (high - low), high + (high - low), size=(1500, 3))
    points = np.concatenate([near, spread])
    answered = _grid_answers(index, points)
    reference = brute_force_closest(points, vertices, triangles)
    mine = answered >= 0
    np.testing.assert_array_equal(answered[mine], reference.triangle[mine])
    within = reference.distance < 0.999 * effective
    beyond = (reference.distance > 1.001 * effective) & (reference.distance < 1.5 * effective)
    assert within.sum() > 300 and beyond.sum() > 100
    assert np.all(mine[within])
    if scan_beyond_reach:
        assert np.all(mine[beyond])
        assert np.count_nonzero(~mine) > 100  # the far points go to libigl's tree
    else:
        assert not mine[reference.distance > 1.001 * effective].any()
    full = index.associate(points)
    np.testing.assert_allclose(full.distance, reference.distance, rtol=0, atol=1e-15)


def test_the_grid_breaks_ties_as_the_all_pairs_search_does():
    """Points on the plane that bisects two triangles sharing an edge (and on their shared
    vertices' normals) are as close to both: the grid, like the all-pairs search, takes the
    lower index, whatever order the triangles are listed in."""
    vertices = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1.0, 1.0, 0.0]])
    for triangles in (np.array([[0, 1, 2], [1, 3, 2]]), np.array([[1, 3, 2], [0, 1, 2]])):
        t = np.linspace(0.1, 0.9, 9)
        points = np.column_stack([t, 1.0 - t, np.full_like(t, 0.05)])  # above the shared edge
        index = ClosestPointIndex(vertices, triangles, reach=0.2)
        answered = _grid_answers(index, points)
        reference = brute_force_closest(points, vertices, triangles)
        assert np.all(answered == 0)
        np.testing.assert_array_equal(answered, reference.triangle)


def test_a_reach_beyond_the_largest_is_held_to_it_and_no_reach_means_the_default():
    vertices, triangles = cube_mesh(side=1.0, divisions=6).vertices, cube_mesh(side=1.0, divisions=6).surface_triangles
    edge = _median_edge(vertices, triangles)
    largest = ClosestPointIndex(vertices, triangles, reach=1e3)._grid[3]
    assert largest == pytest.approx((GRID_MAX_REACH_EDGES * edge) ** 2, rel=1e-6)
    default = ClosestPointIndex(vertices, triangles)._grid[3]
    for reach in (0.0, -1.0, np.inf, np.nan):
        assert ClosestPointIndex(vertices, triangles, reach=reach)._grid[3] == default
    assert default == pytest.approx((closest_point.GRID_REACH_EDGES * edge) ** 2, rel=1e-6)


@pytest.mark.parametrize("scan_beyond_reach", [False, True])
def test_degenerate_and_far_flung_surfaces_are_searched_exactly(scan_beyond_reach):
    """Triangles that are all one point (no edge length to size the grid by), and a surface with
    one triangle 1e70 m away (the grid's cells would be countless at the edge length, and the
    rounding slack swallows the reach): the association still equals the all-pairs search."""
    rng = np.random.default_rng(3)
    points = rng.uniform(-1.0, 1.0, size=(200, 3))
    collapsed = np.zeros((4, 3))
    index = ClosestPointIndex(collapsed, np.array([[0, 1, 2], [1, 2, 3]]), scan_beyond_reach=scan_beyond_reach)
    np.testing.assert_allclose(index.associate(points).distance, np.linalg.norm(points, axis=1), rtol=0, atol=1e-15)
    mesh = cube_mesh(side=1.0, divisions=4)
    far = np.concatenate([mesh.vertices, [[1e70, 0.0, 0.0], [1e70, 1.0, 0.0], [1e70, 0.0, 1.0]]])
    n = len(mesh.vertices)
    triangles = np.concatenate([mesh.surface_triangles, [[n, n + 1, n + 2]]])
    index = ClosestPointIndex(far, triangles, scan_beyond_reach=scan_beyond_reach)
    assert np.prod(index._grid[1]) <= 64 * len(triangles)
    association = index.associate(points)
    reference = brute_force_closest(points, far, triangles)
    if scan_beyond_reach:  # the grid answers every point here, breaking ties as the all-pairs search
        np.testing.assert_array_equal(association.triangle, reference.triangle)
    np.testing.assert_allclose(association.distance, reference.distance, rtol=0, atol=1e-15)
