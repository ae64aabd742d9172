"""Evaluation metrics: known answers for vertex RMSE, the surface metrics of the evaluation
(d_CD, d_RMSE, d_H95 as evaluation/evaluate.py computes them, split by what the camera sees),
the observable split, and the calibration of a published per-vertex standard deviation."""

import numpy as np
import pytest
import trimesh
from scipy.stats import chi2

from meshfg_ros.evaluation import metrics
from meshfg_ros.evaluation.evaluate import SURFACE_METRICS, EvaluationInputs, evaluate_step
from meshfg_ros.evaluation.metrics import correction_alignment
from meshfg_ros.io.messages import MeshState
from meshfg_ros.synthetic.camera import PinholeCamera, capture

UNIT_SQUARE = (
    np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 1.0, 0.0], [0.0, 1.0, 0.0]]),
    np.array([[0, 1, 2], [0, 2, 3]]),
)
STAMP = 1  # the one evaluated step of surface_metrics


def surface_metrics(triangles, truth, estimate, samples=20000, camera_center=None, cloud=None,
                    observed_faces=None) -> dict:
    """The evaluation's surface metrics {region: {metric: value}} of one step whose estimate
    `estimate` (N, 3) and truth `truth` (N, 3) are bare surfaces on `triangles` (no tetrahedra,
    no fixed vertex), split by the camera at `camera_center` seeing `cloud` or, without a
    camera, by `observed_faces`."""
    def surface(positions):
        return MeshState(0, "world", 0, positions, np.zeros((0, 4), np.int64), triangles)

    inputs = EvaluationInputs(
        scenario="surface", stamps=(STAMP,), truth_mesh=surface(truth), truth={STAMP: np.asarray(truth, float)},
        estimate_mesh=surface(estimate), estimates={"factor_graph": {STAMP: np.asarray(estimate, float)}},
        predictions={}, clouds={STAMP: np.zeros((0, 3)) if cloud is None else np.asarray(cloud, float)},
        camera_center=camera_center, observed_faces=observed_faces)
    return evaluate_step(inputs, STAMP, samples)["surface"]["factor_graph"]


def test_vertex_rmse_hand_computed():
    truth = np.zeros((3, 3))
    estimate = np.array([[3.0, 4.0, 0.0], [0.0, 0.0, 0.0], [1.0, 2.0, 2.0]])  # errors 5, 0, 3
    assert metrics.vertex_rmse(estimate, truth) == pytest.approx(np.sqrt(34 / 3), rel=1e-15)
    assert metrics.vertex_rmse(estimate, truth, indices=[0, 2]) == pytest.approx(np.sqrt(17), rel=1e-15)
    assert metrics.vertex_rmse(estimate, truth, indices=[1]) == 0.0
    with pytest.raises(ValueError, match="differ in shape"):
        metrics.vertex_rmse(estimate, truth[:2])
    with pytest.raises(ValueError, match="at least one"):
        metrics.vertex_rmse(estimate, truth, indices=np.array([], dtype=int))


def test_sample_surface_is_uniform_by_area_and_deterministic():
    vertices = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [3, 0, 0], [0, 3, 0]])
    triangles = np.array([[0, 1, 2], [0, 3, 4]])  # areas 0.5 and 4.5 (nested, overlapping)
    count = 20000
    points, faces = metrics.sample_surface(vertices, triangles, count, seed=5, return_faces=True)
    assert points.shape == (count, 3) and faces.shape == (count,)
    np.testing.assert_array_equal(points, metrics.sample_surface(vertices, triangles, count, seed=5))
    assert not np.array_equal(points, metrics.sample_surface(vertices, triangles, count, seed=6))
    # Every point lies in the triangle it is attributed to.
    scale = np.where(faces == 0, 1.0, 3.0)
    assert (points[:, 2] == 0).all() and (points[:, :2] >= 0).all()
    assert (points[:, 0] + points[:, 1] <= scale + 1e-12).all()
    # Face 0 holds 10% of the area: binomial count within 5 standard deviations.
    small = (faces == 0).sum()
    assert abs(small - 0.1 * count) < 5 * np.sqrt(count * 0.1 * 0.9)
    with pytest.raises(ValueError, match="zero area"):
        metrics.sample_surface(np.zeros((3, 3)), [[0, 1, 2]], 10)


def test_shifted_plane_distances_equal_the_shift():
    """Two unit squares, the estimate shifted by d along their normal. Each sample of either
    lies exactly d from the other surface (the evaluation measures samples against the other
    surface, not against its samples), so d_CD, d_RMSE and d_H95 all equal d. Against the other
    square's 2000 samples they would exceed it by the in-plane gap to the nearest sample, about
    1/(2 pi rho d) = 1.6 mm (3 % of d) for rho = 2000 samples per unit area."""
    vertices, triangles = UNIT_SQUARE
    shift = 0.05
    result = surface_metrics(triangles, vertices, vertices + [0.0, 0.0, shift], samples=2000)
    assert set(result) == {"full"}  # no camera and no observed faces: no observable split
    for name in SURFACE_METRICS:
        assert result["full"][name] == pytest.approx(shift, rel=1e-12)


def test_identical_surfaces_have_zero_distances():
    vertices, triangles = UNIT_SQUARE
    result = surface_metrics(triangles, vertices, vertices.copy(), samples=500)
    for name in SURFACE_METRICS:
        assert result["full"][name] == pytest.approx(0.0, abs=1e-12)


def test_half_square_against_the_square_is_one_sided():
    """The estimate covers the half x <= 0.5 of the true unit square. Estimate -> truth every
    distance is 0: d_RMSE (one-sided) is 0. Truth -> estimate a sample at x is max(x - 0.5, 0)
    away, x uniform: mean 1/8, 95th percentile 0.45, so d_CD = 1/16 and d_H95 = 0.45. With the
    two swapped, d_RMSE = sqrt(E[max(x - 0.5, 0)^2]) = sqrt(1/24). Tolerances: five standard
    errors of 20000 samples."""
    vertices, triangles = UNIT_SQUARE
    half = vertices * [0.5, 1.0, 1.0]
    result = surface_metrics(triangles, vertices, half)["full"]
    assert result["rmse"] == pytest.approx(0.0, abs=1e-12)
    assert result["chamfer"] == pytest.approx(1 / 16, abs=3e-3)
    assert result["h95"] == pytest.approx(0.45, abs=8e-3)
    swapped = surface_metrics(triangles, half, vertices)["full"]
    assert swapped["rmse"] == pytest.approx(np.sqrt(1 / 24), rel=0.03)
    assert swapped["chamfer"] == pytest.approx(1 / 16, abs=3e-3)
    assert swapped["h95"] == pytest.approx(0.45, abs=8e-3)


def test_surface_metrics_are_split_by_what_the_camera_sees():
    """A small square in front of a large one, seen from the origin through measured points
    behind the small one. The estimate moves the hidden large square d away: the observable
    region (the small square, first hit by the rays) has zero distances, the unobserved one
    (the large square) exactly d, and the whole surface d on the large square's share of the
    area, 4 of 4.25 (d_H95 = d: 94 % of either side's samples lie on the large square)."""
    front = UNIT_SQUARE[0] * [0.5, 0.5, 0.0] + [0.0, 0.0, 1.0]  # x, y in [0, 0.5] at z = 1
    back = UNIT_SQUARE[0] * [2.0, 2.0, 0.0] + [-0.5, -0.5, 2.0]  # x, y in [-0.5, 1.5] at z = 2
    truth = np.vstack((front, back))
    triangles = np.vstack((UNIT_SQUARE[1], UNIT_SQUARE[1] + 4))
    shift = 0.01
    estimate = truth + np.where(np.arange(8) >= 4, shift, 0.0)[:, None] * [0.0, 0.0, 1.0]
    cloud = np.array([[0.2, 0.1, 2.0], [0.1, 0.2, 2.0]])  # rays through both front triangles
    result = surface_metrics(triangles, truth, estimate, camera_center=np.zeros(3), cloud=cloud)
    assert set(result) == {"full", "observable", "unobserved"}
    for name in SURFACE_METRICS:
        assert result["observable"][name] == pytest.approx(0.0, abs=1e-12)
        assert result["unobserved"][name] == pytest.approx(shift, rel=1e-12)
    back_share = 4.0 / 4.25
    assert result["full"]["rmse"] == pytest.approx(shift * np.sqrt(back_share), rel=0.01)
    assert result["full"]["chamfer"] == pytest.approx(shift * back_share, rel=0.01)
    assert result["full"]["h95"] == pytest.approx(shift, rel=1e-12)


def test_a_region_without_faces_has_no_metrics():
    """Every face observed: the unobserved region is empty and its metrics are undefined (NaN),
    while the observable one is the whole surface."""
    vertices, triangles = UNIT_SQUARE
    shift = 0.05
    result = surface_metrics(triangles, vertices, vertices + [0.0, 0.0, shift], samples=2000,
                             observed_faces=np.ones(len(triangles), bool))
    for name in SURFACE_METRICS:
        assert np.isnan(result["unobserved"][name])
        assert result["observable"][name] == pytest.approx(shift, rel=1e-12)
        assert result["full"][name] == pytest.approx(shift, rel=1e-12)


def test_observable_region_of_sphere_is_visible_cap():
    """A camera at distance D from a unit sphere sees the cap cos(theta) >= 1/D, a fraction
    (1 - 1/D)/2 of the area. On the icosphere the cap's rim cuts through triangles that are
    in or out whole, so the marked fraction may differ from the analytic one by the area of a
    strip one longest edge wide along the rim, sin(theta) * edge / 2 of the sphere."""
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=1.0)
    vertices, triangles = np.asarray(sphere.vertices), np.asarray(sphere.faces)
    distance = 2.0
    half_angle = np.arcsin(1 / distance)
    camera = PinholeCamera.look_at([0, 0, -distance], [0, 0, 0], [0, 1, 0], 256, 256, 128 / np.tan(1.15 * half_angle))
    measured = capture(camera, vertices, triangles, rng=0).points
    observed = metrics.observable_triangles(camera.position, measured, vertices, triangles)

    areas = sphere.area_faces
    fraction = areas[observed].sum() / areas.sum()
    analytic = (1 - 1 / distance) / 2
    rim_strip = np.sqrt(1 - 1 / distance**2) * sphere.edges_unique_length.max() / 2
    assert abs(fraction - analytic) < rim_strip

    # First hits on a closed convex surface are front-facing; triangles clearly facing the
    # camera span several pixels and must all be hit.
    towards_camera = camera.position - sphere.triangles_center
    towards_camera /= np.linalg.norm(towards_camera, axis=1)[:, None]
    facing = np.einsum("ij,ij->i", sphere.face_normals, towards_camera)
    assert not observed[facing < 0].any()
    assert observed[facing > 0.3].all()


def test_observable_triangles_respects_occlusion():
    front = UNIT_SQUARE[0] * [0.5, 0.5, 0] + [0.0, 0.0, 1.0]  # covers x, y in [0, 0.5] at z = 1
    back = UNIT_SQUARE[0] * [2, 2, 0] + [-0.5, -0.5, 2.0]
    vertices = np.vstack((front, back))
    triangles = np.vstack((UNIT_SQUARE[1], UNIT_SQUARE[1] + 4))
    camera_center = np.zeros(3)
    measured = np.array([[0.1, 0.1, 2.0], [0.2, 0.3, 2.0]])  # rays pass through the front square
    observed = metrics.observable_triangles(camera_center, measured, vertices, triangles)
    assert observed[:2].any() and not observed[2:].any()


def test_unobserved_external_vertices():
    triangles = np.array([[0, 1, 2], [1, 2, 3], [3, 4, 5]])
    surface = np.array([0, 1, 2, 3, 4, 5, 6])
    mask = np.array([True, False, False])
    np.testing.assert_array_equal(metrics.observed_vertices(triangles, mask), [0, 1, 2])
    np.testing.assert_array_equal(metrics.unobserved_external_vertices(surface, triangles, mask), [3, 4, 5, 6])
    # Measurement associations as triangle ids, repeated as several points share a triangle.
    np.testing.assert_array_equal(metrics.unobserved_external_vertices(surface, triangles, [2, 2, 1]), [0, 6])
    with pytest.raises(ValueError, match="outside"):
        metrics.observed_vertices(triangles, [3])


def test_correction_alignment_hand_computed():
    prediction = np.zeros((3, 3))
    truth = np.array([[1.0, 0.0, 0.0], [0.0, 2.0, 0.0], [0.0, 0.0, 0.0]])
    half_way = correction_alignment(prediction, 0.5 * truth, truth)
    assert half_way["alignment"] == pytest.approx(1.0) and half_way["gain"] == pytest.approx(0.5)
    away = correction_alignment(prediction, -truth, truth)
    assert away["alignment"] == pytest.approx(-1.0) and away["gain"] == pytest.approx(-1.0)
    unrelated = correction_alignment(prediction, np.array([[0.0, 0.0, 1.0]] * 3), truth)
    assert unrelated["alignment"] == pytest.approx(0.0) and unrelated["gain"] == pytest.approx(0.0)
    only_vertex_1 = correction_alignment(prediction, truth * [[-1.0], [3.0], [1.0]], truth, indices=[1])
    assert only_vertex_1["gain"] == pytest.approx(3.0)


def test_correction_alignment_along_and_across_directions():
    """Normals +z: a correction that gets the normal error right and slides the wrong way."""
    prediction = np.zeros((2, 3))
    normals = np.tile([0.0, 0.0, 1.0], (2, 1))
    truth = np.array([[1.0, 0.0, 2.0], [0.0, 1.0, -2.0]])
    estimate = np.array([[-1.0, 0.0, 1.0], [0.0, -1.0, -1.0]])
    along = correction_alignment(prediction, estimate, truth, directions=normals)
    assert along["alignment"] == pytest.approx(1.0) and along["gain"] == pytest.approx(0.5)
    across = correction_alignment(prediction, estimate, truth, directions=normals, across=True)
    assert across["alignment"] == pytest.approx(-1.0) and across["gain"] == pytest.approx(-1.0)


def test_correction_alignment_is_undefined_without_a_correction():
    prediction = np.zeros((2, 3))
    assert np.isnan(correction_alignment(prediction, prediction, np.ones((2, 3)))["alignment"])
    assert np.isnan(correction_alignment(prediction, np.ones((2, 3)), prediction)["gain"])
    with pytest.raises(ValueError, match="across needs directions"):
        correction_alignment(prediction, prediction, prediction, across=True)


def test_summarise():
    assert metrics.summarise([1.0, 2.0, 3.0, 4.0]) == pytest.approx((2.5, np.sqrt(1.25)), rel=1e-15)
    with pytest.raises(ValueError, match="at least one"):
        metrics.summarise([])


def gaussian_errors(count, seed, std_scale=1.0):
    """(estimate, truth, published std) of `count` vertices whose errors are drawn from
    N(0, s_i^2 I3), s_i log-uniform over two decades; the published std is std_scale * s_i."""
    rng = np.random.default_rng(seed)
    truth = rng.uniform(-0.05, 0.05, size=(count, 3))
    true_std = 10.0 ** rng.uniform(-5.0, -3.0, size=count)
    estimate = truth + rng.normal(size=(count, 3)) * true_std[:, None]
    return estimate, truth, std_scale * true_std


def test_calibration_of_a_calibrated_estimator():
    """Errors drawn with the published std: mean NEES 3 and every nominal level met, within
    five sampling standard deviations (NEES is chi2(3): variance 6; coverage binomial)."""
    count = 20000
    result = metrics.calibration(*gaussian_errors(count, seed=3))
    assert result.vertices == count and result.left_out == 0 and result.zero_std_vertices == 0
    assert result.mean_nees == pytest.approx(3.0, abs=5 * np.sqrt(6 / count))
    assert result.coverage_95 == pytest.approx(0.95, abs=5 * np.sqrt(0.95 * 0.05 / count))
    levels = np.asarray(metrics.CALIBRATION_LEVELS)
    np.testing.assert_allclose(result.coverage(), levels, atol=5 * np.sqrt(0.25 / count))


def test_calibration_of_an_overconfident_and_an_underconfident_estimator():
    """A std half the true one quadruples NEES (mean 12) and covers only chi2.cdf(7.815 / 4, 3)
    = 42 % inside the 95 % ellipsoid; a std twice the true one gives mean 0.75, all inside."""
    count = 20000
    tolerance = 5 * np.sqrt(0.25 / count)
    overconfident = metrics.calibration(*gaussian_errors(count, seed=4, std_scale=0.5))
    assert overconfident.mean_nees == pytest.approx(12.0, abs=5 * 4 * np.sqrt(6 / count))
    assert overconfident.coverage_95 == pytest.approx(chi2.cdf(chi2.ppf(0.95, 3) / 4, 3), abs=tolerance)
    assert overconfident.coverage_95 < 0.5
    underconfident = metrics.calibration(*gaussian_errors(count, seed=5, std_scale=2.0))
    assert underconfident.mean_nees == pytest.approx(0.75, abs=5 * np.sqrt(6 / count) / 4)
    assert underconfident.coverage_95 > 0.999
    assert (underconfident.coverage() > np.asarray(metrics.CALIBRATION_LEVELS)).all()


def test_calibration_hand_computed_with_vertices_left_out():
    """Errors 5 (std 5) and 2 (std 1): NEES 1 and 4. Left out: a zero std with no error (a fixed
    vertex), a zero std with an error (infinitely overconfident, counted apart), NaN and inf."""
    truth = np.zeros((6, 3))
    estimate = np.array([[3.0, 4.0, 0.0], [0.0, 0.0, 2.0], [0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 0.0, 0.0],
                         [0.0, 0.0, 3.0]])
    std = np.array([5.0, 1.0, 0.0, 0.0, np.nan, np.inf])
    result = metrics.calibration(estimate, truth, std)
    np.testing.assert_allclose(result.nees, [1.0, 4.0], rtol=1e-15)
    assert (result.vertices, result.left_out, result.zero_std_vertices) == (2, 4, 1)
    assert result.mean_nees == pytest.approx(2.5, rel=1e-15)
    assert result.median_std == pytest.approx(3.0, rel=1e-15)
    assert result.median_error == pytest.approx(3.5, rel=1e-15)  # errors 5 and 2
    assert result.coverage_95 == 1.0
    np.testing.assert_array_equal(result.coverage([0.5, 0.95]), [0.5, 1.0])  # chi2(3) median 2.37
    only_second = metrics.calibration(estimate, truth, std, vertices=[1, 3])
    assert (only_second.vertices, only_second.left_out, only_second.zero_std_vertices) == (1, 1, 1)
    assert only_second.mean_nees == pytest.approx(4.0, rel=1e-15)
    summary = result.summary()
    assert summary["vertices"] == 2 and summary["zero_std_vertices"] == 1 and summary["left_out"] == 4
    assert summary["mean_nees"] == pytest.approx(2.5) and summary["median_std_m"] == pytest.approx(3.0)
    assert summary["median_error_m"] == pytest.approx(3.5)
    assert summary["reliability"]["nominal"] == list(metrics.CALIBRATION_LEVELS)
    assert len(summary["reliability"]["empirical"]) == len(metrics.CALIBRATION_LEVELS)


def test_the_95_percent_ellipsoid_is_chi_squared_with_three_degrees_of_freedom():
    """NEES just inside and just outside chi2.ppf(0.95, 3) = 7.815 (not 1.96^2, the 1-D bound)."""
    bound = chi2.ppf(0.95, 3)
    estimate = np.array([[np.sqrt(bound * 0.999), 0.0, 0.0], [np.sqrt(bound * 1.001), 0.0, 0.0]])
    assert metrics.calibration(estimate, np.zeros((2, 3)), np.ones(2)).coverage_95 == 0.5


def test_calibration_pools_vertices_and_says_when_it_is_undefined():
    estimate, truth, std = gaussian_errors(100, seed=6)
    first, second = metrics.calibration(estimate[:40], truth[:40], std[:40]), \
        metrics.calibration(estimate[40:], truth[40:], std[40:])
    pooled = metrics.Calibration.pooled([first, second])
    whole = metrics.calibration(estimate, truth, std)
    assert pooled.mean_nees == pytest.approx(whole.mean_nees, rel=1e-12)
    np.testing.assert_array_equal(pooled.coverage(), whole.coverage())
    empty = metrics.calibration(estimate, truth, np.zeros(100))
    assert empty.vertices == 0 and empty.zero_std_vertices == 100 and np.isnan(empty.mean_nees)
    assert empty.summary()["mean_nees"] is None and empty.summary()["coverage_95"] is None
    assert metrics.Calibration.pooled([]).vertices == 0
    with pytest.raises(ValueError, match="negative"):
        metrics.calibration(estimate, truth, -std)
    with pytest.raises(ValueError, match="std must have shape"):
        metrics.calibration(estimate, truth, std[:-1])
    with pytest.raises(ValueError, match="levels"):
        whole.coverage([0.5, 1.0])
