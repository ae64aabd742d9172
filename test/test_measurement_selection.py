"""The measurement front end (core/estimation/measurement_selection.py): the gate, the back-face
test, each point's noise from its ray, the order of the selected points, the tool gate and the
innovation test, and a measurement factor that takes the selection as it is."""

import numpy as np
import pytest

from meshfg_ros.core.estimation import factors, measurement_selection
from meshfg_ros.core.estimation.factors import PointToSurfaceFactor
from meshfg_ros.core.estimation.measurement_selection import (
    GATE_SIGMAS,
    TOOL_MARGIN_SIGMAS,
    drop_points_on_tool,
    innovation_test,
    select_points,
)
from meshfg_ros.core.estimation.noise import NoiseModelError, RayNoise
from meshfg_ros.core.geometry.closest_point import ClosestPointIndex
from meshfg_ros.core.inputs.input_checks import REJECTIONS, Scene
from meshfg_ros.evaluation.metrics import sample_surface
from meshfg_ros.synthetic.meshing import cube_mesh

SIGMA = 1e-3


@pytest.fixture(scope="module")
def cube():
    return cube_mesh(side=0.1, divisions=3)


def test_the_gate_drops_far_points(cube):
    points = np.array([[0.05, 0.05, 0.101], [0.05, 0.05, 0.2], [0.5, 0.5, 0.5], [0.05, -0.001, 0.05]])
    selected = select_points(points, cube.surface_triangles, cube.vertices, SIGMA, gating_distance=0.01)
    assert len(selected.points) == 2 and selected.num_gated == 2
    assert sorted(map(tuple, selected.points)) == sorted(map(tuple, points[[0, 3]]))


def test_the_data_driven_gate_follows_the_clouds_spread_within_its_bounds(cube):
    """gating_distance 0: GATE_SIGMAS robust spreads of the distances, the spread taken between
    1 and GATE_SPREAD_CAP sigmas."""
    rng = np.random.default_rng(5)
    on_surface = sample_surface(cube.vertices, cube.surface_triangles, 200, rng)
    top = on_surface[:, 2] > 0.1 - 1e-9
    on_top = on_surface[top] + [0.0, 0.0, 1.0] * rng.normal(scale=SIGMA, size=(int(top.sum()), 1))
    far = np.array([[0.05, 0.05, 0.1 + 3 * GATE_SIGMAS * SIGMA], [0.02, 0.07, 0.1 + 0.5 * GATE_SIGMAS * SIGMA]])
    points = np.concatenate([on_top, far])
    selected = select_points(points, cube.surface_triangles, cube.vertices, SIGMA, gating_distance=0.0)
    assert selected.num_gated == 1 and far[1].tolist() in selected.points.tolist()
    # A nominal sigma ten times too small: the gate widens with the spread.
    assert select_points(points, cube.surface_triangles, cube.vertices, SIGMA / 10, 0.0).num_gated == 1
    # The gate is never narrower than GATE_SIGMAS sigmas, however tight the cloud.
    exact = np.concatenate([on_surface[top], far[1:]])
    assert select_points(exact, cube.surface_triangles, cube.vertices, SIGMA, 0.0).num_gated == 0


class _NoQueries:
    """Stands in for ClosestPointIndex where a test asserts that no closest-point query is made."""

    def __init__(self, *args, **kwargs):
        raise AssertionError("a closest-point query was made")


def test_selected_points_are_ordered_by_triangle_with_their_association(cube, monkeypatch):
    """The selection lists its points in the order of their closest triangles (faster queries in
    the factor's later associations), and hands the factor their association in that order."""
    rng = np.random.default_rng(3)
    points = sample_surface(cube.vertices, cube.surface_triangles, 60, rng)
    selected = select_points(points, cube.surface_triangles, cube.vertices, SIGMA, gating_distance=0.01)
    assert len(selected.points) == len(points)
    assert np.all(np.diff(selected.association.triangle) >= 0)
    order = [int(np.flatnonzero(np.all(points == point, axis=1))[0]) for point in selected.points]
    assert sorted(order) == list(range(len(points))) and order != list(range(len(points)))
    fresh = ClosestPointIndex(cube.vertices, cube.surface_triangles).associate(selected.points)
    np.testing.assert_array_equal(selected.association.triangle, fresh.triangle)
    np.testing.assert_array_equal(selected.association.closest, fresh.closest)
    # Given the innovation test's association, the selection makes no query of its own and selects alike.
    given = ClosestPointIndex(cube.vertices, cube.surface_triangles).associate(points)
    monkeypatch.setattr(measurement_selection, "ClosestPointIndex", _NoQueries)
    reused = select_points(points, cube.surface_triangles, cube.vertices, SIGMA, 0.01, association=given)
    np.testing.assert_array_equal(reused.points, selected.points)


def test_points_against_back_faces_are_dropped_as_leaks(cube):
    """A camera above the cube (side 0.1 m, bottom at z = 0) sees its top face; a leak onto the
    table beside it lies just outside a side face whose closest point faces down and away."""
    top = np.array([[0.02, 0.03, 0.1005], [0.07, 0.05, 0.0995], [0.05, 0.08, 0.1002]])
    table = np.array([[0.101, 0.05, -0.0005], [0.05, -0.0008, -0.0002]])  # beside the bottom edges
    points = np.concatenate([top, table])
    camera = np.array([0.05, 0.05, 0.5])
    selected = select_points(points, cube.surface_triangles, cube.vertices, SIGMA, 0.01, viewpoint=camera)
    assert selected.num_back_facing == 2 and selected.num_gated == 2
    assert not selected.back_facing_test_skipped
    assert sorted(map(tuple, selected.points)) == sorted(map(tuple, top))
    # Without a viewpoint the distance gate alone keeps them (they are within a millimetre).
    assert len(select_points(points, cube.surface_triangles, cube.vertices, SIGMA, 0.01).points) == 5
    # Seen from below, most points would face away: the viewpoint is not the sensor's, nothing is dropped.
    below = select_points(points, cube.surface_triangles, cube.vertices, SIGMA, 0.01,
                          viewpoint=np.array([0.05, 0.05, -0.5]))
    assert below.back_facing_test_skipped and len(below.points) == 5 and below.num_back_facing == 0


def test_each_points_noise_follows_its_rays_incidence_on_its_face(cube):
    """Seen from a camera above the cube and a little to its +x side, the top face is met nearly
    head-on (above the floor) and the +x face grazing (below it): each point's sigma scales with
    |cos| of its ray against its face's normal, floored, normalised so that the median point
    keeps the cloud's sigma."""
    camera = np.array([0.15, 0.05, 0.4])
    top = np.array([[0.02, 0.03, 0.1003], [0.05, 0.05, 0.0998], [0.08, 0.06, 0.1001]])
    side = np.array([[0.1002, 0.05, 0.05], [0.0999, 0.03, 0.08]])
    points = np.concatenate([top, side])
    selected = select_points(points, cube.surface_triangles, cube.vertices, SIGMA, 0.01, viewpoint=camera)
    assert len(selected.points) == 5
    rays = selected.points - camera
    rays /= np.linalg.norm(rays, axis=1)[:, None]
    on_top = np.isclose(selected.points[:, 2], 0.1, atol=1e-3)
    incidence = np.where(on_top, np.abs(rays[:, 2]), np.abs(rays[:, 0]))  # normals +z and +x
    floor = RayNoise(SIGMA).floor
    assert incidence[on_top].min() > floor > incidence[~on_top].max()  # the side face is the grazing one
    floored = np.maximum(incidence, floor)
    expected = SIGMA * floored / np.median(floored)
    weights = selected.noise.point_weights(5)
    np.testing.assert_allclose(weights, 1.0 / expected**2, rtol=1e-9)
    assert np.ptp(weights[on_top]) > 1e-3 * weights[on_top].max()  # unfloored: each at its own incidence
    # A viewpoint most points face away from is not the sensor's (the back-face test is skipped):
    # its rays do not weight the points either.
    wrong = select_points(points, cube.surface_triangles, cube.vertices, SIGMA, 0.01,
                          viewpoint=np.array([0.05, 0.05, -0.5]))
    assert wrong.back_facing_test_skipped
    np.testing.assert_allclose(wrong.noise.point_weights(5), 1.0 / SIGMA**2, rtol=1e-12)
    # Without a viewpoint there are no rays: every point keeps the cloud's sigma.
    unseen = select_points(points, cube.surface_triangles, cube.vertices, SIGMA, 0.01)
    np.testing.assert_allclose(unseen.noise.point_weights(5), 1.0 / SIGMA**2, rtol=1e-12)


def test_ray_noise_floors_grazing_rays_and_degenerate_faces():
    camera = np.array([0.3, 0.05, 0.2])
    top = np.array([[0.02, 0.03, 0.1003], [0.05, 0.05, 0.0998], [0.08, 0.06, 0.1001]])
    up = np.tile([0.0, 0.0, 1.0], (3, 1))
    # With the floor above every point's incidence, all points weigh alike.
    np.testing.assert_allclose(RayNoise(SIGMA, floor=1.0).on_surface(top, up, camera).point_weights(3),
                               1.0 / SIGMA**2, rtol=1e-12)
    # A NaN normal (a degenerate face) takes the floor instead of a NaN weight.
    normals = np.array([[0.0, 0.0, 1.0], [np.nan] * 3, [0.0, 0.0, 1.0]])
    noise = RayNoise(SIGMA, floor=0.5).on_surface(top, normals, camera)
    rays = top - camera
    incidence = np.abs(rays[:, 2]) / np.linalg.norm(rays, axis=1)
    incidence[1] = 0.5
    incidence = np.maximum(incidence, 0.5)
    np.testing.assert_allclose(noise.point_weights(3), (np.median(incidence) / (SIGMA * incidence)) ** 2, rtol=1e-12)
    with pytest.raises(NoiseModelError):
        RayNoise(SIGMA, floor=0.0)


def test_the_factor_takes_the_selection_as_it_is(cube, monkeypatch):
    """The measurement factor answers its first query at the selection's vertices from the
    selection's association, without a query of its own."""
    camera = np.array([0.3, 0.05, 0.2])
    points = sample_surface(cube.vertices, cube.surface_triangles, 80, np.random.default_rng(8))
    selected = select_points(points, cube.surface_triangles, cube.vertices, SIGMA, 0.01, viewpoint=camera)
    factor = PointToSurfaceFactor(0, selected.points, cube.surface_triangles, cube.vertex_count, selected.noise,
                                  association_at=(selected.vertices, selected.association))
    monkeypatch.setattr(factors, "ClosestPointIndex", _NoQueries)
    assert factor.associate({0: cube.vertices.copy()}) is selected.association


def test_the_tool_gate_drops_points_within_a_margin_of_the_sphere():
    pose = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0])
    radius = 0.005
    reach = radius + TOOL_MARGIN_SIGMAS * SIGMA
    points = np.array([[0.0, 0.0, 0.9 * reach], [0.0, 1.1 * reach, 0.0], [0.002, 0.0, 0.0]])
    kept, dropped = drop_points_on_tool(points, pose, "sphere", radius, SIGMA)
    assert dropped == 2 and kept.tolist() == points[[1]].tolist()
    # The margin is at most a radius: a sigma set far too large does not drop the cloud around the tool.
    assert drop_points_on_tool(np.array([[0.0, 0.0, 2.1 * radius]]), pose, "sphere", radius, 1.0)[1] == 0
    assert drop_points_on_tool(points, pose, "grasp", radius, SIGMA) == (points, 0)
    assert drop_points_on_tool(points, None, "sphere", radius, SIGMA) == (points, 0)


def test_the_innovation_test_sets_aside_a_prediction_the_cloud_contradicts(cube):
    points = sample_surface(cube.vertices, cube.surface_triangles, 300, np.random.default_rng(2))
    scene = Scene.of(cube.vertices)
    kept = innovation_test(points, cube.vertices, cube.vertices, cube.surface_triangles, SIGMA, scene)
    assert kept.prediction is cube.vertices and kept.rejection is None
    assert len(kept.association.triangle) == len(points)
    shifted = cube.vertices + [0.0, 0.0, 0.05]
    rejected = innovation_test(points, shifted, cube.vertices, cube.surface_triangles, SIGMA, scene)
    assert rejected.prediction is None and rejected.association is None
    assert rejected.rejection.startswith(REJECTIONS["predictions_rejected_innovation"])
    # Nothing better to replace it with: a prediction as wrong as the copy-forward is kept.
    assert innovation_test(points, shifted, shifted, cube.surface_triangles, SIGMA, scene).prediction is shifted
