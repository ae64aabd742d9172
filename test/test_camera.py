"""Virtual endoscope: camera geometry, ray casting and the depth sensor model."""

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree
from trimesh.ray.ray_triangle import RayMeshIntersector

from meshfg_ros.synthetic.camera import CaptureOptions, PinholeCamera, capture, first_ray_hits


def square(center_z, half_size, center_xy=(0.0, 0.0)):
    """Two-triangle square in the plane z = center_z, facing -z (towards a camera at z < 0)."""
    x, y = center_xy
    vertices = np.array(
        [
            [x - half_size, y - half_size, center_z],
            [x + half_size, y - half_size, center_z],
            [x + half_size, y + half_size, center_z],
            [x - half_size, y + half_size, center_z],
        ]
    )
    return vertices, np.array([[0, 2, 1], [0, 3, 2]])


def forward_camera(width=64, height=48, fx=50.0):
    """Camera at the origin with the identity orientation: looks along world +z."""
    return PinholeCamera(np.zeros(3), [0, 0, 0, 1], width, height, fx, fx, (width - 1) / 2, (height - 1) / 2)


def test_fronto_parallel_plane_depths_equal_its_distance():
    camera = forward_camera()
    distance = 0.08
    result = capture(camera, *square(distance, 1.0))
    assert len(result.points) == camera.width * camera.height
    np.testing.assert_allclose(result.depths, distance, rtol=0, atol=1e-15)
    np.testing.assert_allclose(result.points[:, 2], distance, rtol=0, atol=1e-15)
    expected_x = (result.pixels[:, 0] - camera.cx) / camera.fx * distance
    expected_y = (result.pixels[:, 1] - camera.cy) / camera.fy * distance
    np.testing.assert_allclose(result.points[:, 0], expected_x, rtol=0, atol=1e-15)
    np.testing.assert_allclose(result.points[:, 1], expected_y, rtol=0, atol=1e-15)
    assert (result.labels == 0).all()
    assert set(np.unique(result.triangle_ids)) == {0, 1}
    pixels, depths = camera.project(result.points)
    np.testing.assert_allclose(pixels, result.pixels, rtol=0, atol=1e-9)
    np.testing.assert_allclose(depths, distance, rtol=0, atol=1e-15)


def test_stride_subsamples_pixel_grid():
    camera = forward_camera(width=10, height=7)
    grid = camera.pixel_grid(3)
    assert grid.tolist() == [[u, v] for v in (0, 3, 6) for u in (0, 3, 6, 9)]
    result = capture(camera, *square(0.1, 1.0), options=CaptureOptions(stride=3))
    assert len(result.points) == 12


@pytest.mark.parametrize("distance", [0.05, 0.2])
def test_depth_noise_matches_sigma(distance):
    camera = forward_camera(width=320, height=240, fx=240.0)
    options = CaptureOptions(noise_constant=0.001, noise_quadratic=0.1)
    sigma = 0.001 + 0.1 * distance**2
    result = capture(camera, *square(distance, 1.0), rng=int(distance * 1000), options=options)
    count = len(result.points)
    assert count == 320 * 240  # noise is far smaller than the depth: nothing dropped
    errors = result.depths - distance
    # Bounds: 5 standard errors of the sample mean (sigma/sqrt(n)) and of the sample standard
    # deviation (sigma/sqrt(2n)).
    assert abs(errors.mean()) < 5 * sigma / np.sqrt(count)
    assert abs(errors.std() / sigma - 1) < 5 / np.sqrt(2 * count)
    # Noise acts along the pixel ray: every point still projects onto its own pixel.
    pixels, depths = camera.project(result.points)
    np.testing.assert_allclose(pixels, result.pixels, rtol=0, atol=1e-8)
    np.testing.assert_allclose(depths, result.depths, rtol=1e-12)


def test_grazing_incidence_thins_points_by_cosine_power():
    camera = forward_camera(width=120, height=90, fx=80.0)
    tilt = np.deg2rad(70.0)
    rotation = trimesh.transformations.rotation_matrix(tilt, [1, 0, 0])[:3, :3]
    vertices, triangles = square(0.0, 3.0)
    vertices = vertices @ rotation.T + [0, 0, 0.5]
    normal = rotation @ [0, 0, 1]
    everything = capture(camera, vertices, triangles, rng=1)
    rays = camera.pixel_rays(everything.pixels)
    cosine = np.abs(rays @ normal) / np.linalg.norm(rays, axis=1)
    exponent = 2.0
    thinned = capture(camera, vertices, triangles, rng=1, options=CaptureOptions(grazing_exponent=exponent))
    keep = cosine**exponent
    # Kept count is a sum of independent Bernoulli(keep) draws: allow 5 standard deviations.
    assert abs(len(thinned.points) - keep.sum()) < 5 * np.sqrt((keep * (1 - keep)).sum())
    assert len(thinned.points) < 0.5 * len(everything.points)
    assert set(map(tuple, thinned.pixels)) <= set(map(tuple, everything.pixels))


def occluded_pixels(camera, occluder_vertices):
    """Pixels whose ray meets the axis-aligned occluder square (in a plane z = const)."""
    pixels = camera.pixel_grid()
    rays = camera.pixel_rays(pixels)  # z = 1, so the ray meets plane z = c at c * ray
    points = rays * occluder_vertices[0, 2]
    low, high = occluder_vertices[:, :2].min(axis=0), occluder_vertices[:, :2].max(axis=0)
    inside = ((points[:, :2] > low) & (points[:, :2] < high)).all(axis=1)
    return set(map(tuple, pixels[inside]))


def test_occluder_in_front_blocks_target_and_leaks_are_labelled():
    camera = forward_camera()
    target = square(0.1, 1.0)
    occluder_vertices, occluder_triangles = square(0.05, 0.0123, center_xy=(0.004, -0.002))
    blocked = occluded_pixels(camera, occluder_vertices)
    assert 100 < len(blocked) < 1000
    occluders = [(occluder_vertices, occluder_triangles, 3)]

    clean = capture(camera, *target, occluders=occluders, rng=0)
    assert len(clean.points) == camera.width * camera.height - len(blocked)
    assert (clean.labels == 0).all()
    assert not blocked & set(map(tuple, clean.pixels))

    leaky = capture(camera, *target, occluders=occluders, rng=0, options=CaptureOptions(leak_fraction=1.0))
    assert len(leaky.points) == camera.width * camera.height
    leaked = leaky.labels == 3
    assert set(map(tuple, leaky.pixels[leaked])) == blocked
    np.testing.assert_allclose(leaky.depths[leaked], 0.05, rtol=0, atol=1e-15)
    np.testing.assert_allclose(leaky.depths[~leaked], 0.1, rtol=0, atol=1e-15)

    fraction = 0.3
    partial = capture(camera, *target, occluders=occluders, rng=0, options=CaptureOptions(leak_fraction=fraction))
    leaks = int((partial.labels == 3).sum())
    assert abs(leaks - fraction * len(blocked)) < 5 * np.sqrt(len(blocked) * fraction * (1 - fraction))


def pixels_within(candidates, targets, radius):
    """Pixels of `candidates` within `radius` (Euclidean) of a pixel of `targets` (k-d tree)."""
    candidates = np.asarray(sorted(candidates))
    gaps, _ = cKDTree(np.asarray(sorted(targets), dtype=float)).query(candidates.astype(float))
    return set(map(tuple, candidates[gaps <= radius]))


@pytest.mark.parametrize("stride, dilation", [(1, 3.0), (2, 3.0), (2, 4.5)])
def test_leak_dilation_keeps_only_occluder_hits_near_the_target(stride, dilation):
    """A tissue patch in front of a background plane, half covered by a tool: with every hit
    leaking, exactly the tool and background pixels within `dilation` pixels of a tissue pixel
    leak, at the occluders' depths."""
    camera = forward_camera()
    tissue = square(0.1, 0.02)
    background = (*square(0.2, 1.0), 1)
    tool = (*square(0.05, 0.006, center_xy=(0.008, 0.0)), 2)
    occluders = [background, tool]
    base = CaptureOptions(stride=stride, leak_fraction=1.0)
    everything = capture(camera, *tissue, occluders=occluders, rng=0, options=base)
    tissue_pixels = set(map(tuple, everything.pixels[everything.labels == 0]))
    tool_pixels = set(map(tuple, everything.pixels[everything.labels == 2]))
    background_pixels = set(map(tuple, everything.pixels[everything.labels == 1]))
    assert len(tissue_pixels) > 50 and len(tool_pixels) > 20 and len(background_pixels) > 200

    leaky = capture(camera, *tissue, occluders=occluders, rng=0,
                    options=CaptureOptions(stride=stride, leak_fraction=1.0, leak_dilation_pixels=dilation))
    assert set(map(tuple, leaky.pixels[leaky.labels == 0])) == tissue_pixels
    expected_tool = pixels_within(tool_pixels, tissue_pixels, dilation)
    expected_background = pixels_within(background_pixels, tissue_pixels, dilation)
    assert set(map(tuple, leaky.pixels[leaky.labels == 2])) == expected_tool
    assert set(map(tuple, leaky.pixels[leaky.labels == 1])) == expected_background
    assert 0 < len(expected_tool) < len(tool_pixels)  # the tool's far side does not leak
    assert 0 < len(expected_background) < len(background_pixels) / 2
    np.testing.assert_allclose(leaky.depths[leaky.labels == 2], 0.05, rtol=0, atol=1e-15)
    np.testing.assert_allclose(leaky.depths[leaky.labels == 1], 0.2, rtol=0, atol=1e-15)


def test_leak_dilation_thins_eligible_hits_by_leak_fraction():
    camera = forward_camera(width=160, height=120, fx=125.0)
    tissue = square(0.1, 0.02)
    occluders = [(*square(0.2, 1.0), 1)]
    dilation, fraction = 6.0, 0.4
    everything = capture(camera, *tissue, occluders=occluders, rng=0, options=CaptureOptions(leak_fraction=1.0))
    eligible = pixels_within(set(map(tuple, everything.pixels[everything.labels == 1])),
                             set(map(tuple, everything.pixels[everything.labels == 0])), dilation)
    result = capture(camera, *tissue, occluders=occluders, rng=5,
                     options=CaptureOptions(leak_fraction=fraction, leak_dilation_pixels=dilation))
    leaked = set(map(tuple, result.pixels[result.labels == 1]))
    assert leaked <= eligible
    count = len(eligible)
    assert abs(len(leaked) - fraction * count) < 5 * np.sqrt(count * fraction * (1 - fraction))


def test_leak_dilation_beyond_the_image_equals_no_dilation():
    """A dilation larger than the image makes every occluder hit eligible, as with the option
    off, and draws the same random numbers: the captures are equal."""
    camera = forward_camera()
    occluders = [(*square(0.2, 1.0), 1), (*square(0.05, 0.006, center_xy=(0.008, 0.0)), 2)]
    off = CaptureOptions(stride=2, noise_constant=1e-3, grazing_exponent=1.0, leak_fraction=0.3)
    wide = CaptureOptions(stride=2, noise_constant=1e-3, grazing_exponent=1.0, leak_fraction=0.3,
                          leak_dilation_pixels=1e4)
    first = capture(camera, *square(0.1, 0.02), occluders=occluders, rng=9, options=off)
    second = capture(camera, *square(0.1, 0.02), occluders=occluders, rng=9, options=wide)
    np.testing.assert_array_equal(first.points, second.points)
    np.testing.assert_array_equal(first.labels, second.labels)
    assert (first.labels > 0).sum() > 10


def test_leak_dilation_without_target_in_view_leaks_nothing():
    camera = forward_camera()
    result = capture(camera, *square(0.1, 0.01, center_xy=(5.0, 5.0)), occluders=[(*square(0.2, 1.0), 1)], rng=0,
                     options=CaptureOptions(leak_fraction=1.0, leak_dilation_pixels=3.0))
    assert len(result.points) == 0


def test_capture_is_deterministic_by_seed():
    camera = forward_camera()
    options = CaptureOptions(noise_constant=0.002, grazing_exponent=1.0)
    first = capture(camera, *square(0.1, 1.0), rng=42, options=options)
    again = capture(camera, *square(0.1, 1.0), rng=42, options=options)
    other = capture(camera, *square(0.1, 1.0), rng=43, options=options)
    np.testing.assert_array_equal(first.points, again.points)
    assert not np.array_equal(first.depths, other.depths)


def test_look_at_follows_ros_optical_convention():
    camera = PinholeCamera.look_at([0, 0, 0], [2, 0, 0], [0, 0, 1], 64, 48, 50.0)
    np.testing.assert_allclose(camera.rotation, [[0, 0, 1], [-1, 0, 0], [0, -1, 0]], atol=1e-12)
    # A point ahead, to the world's right (-y) and above (+z): right of and above the centre.
    pixels, depths = camera.project([[2.0, -0.1, 0.2]])
    assert pixels[0, 0] > camera.cx and pixels[0, 1] < camera.cy
    assert depths[0] == pytest.approx(2.0)


def test_pose_and_frame_round_trips():
    rng = np.random.default_rng(3)
    quaternion = rng.normal(size=4)
    camera = PinholeCamera(rng.normal(size=3), quaternion, 32, 24, 30.0, 31.0, 15.0, 12.0)
    np.testing.assert_allclose(camera.orientation, quaternion / np.linalg.norm(quaternion))
    rebuilt = PinholeCamera(camera.pose[:3], camera.pose[3:], 32, 24, 30.0, 31.0, 15.0, 12.0)
    np.testing.assert_array_equal(rebuilt.pose, camera.pose)
    points = rng.normal(size=(10, 3))
    np.testing.assert_allclose(camera.camera_to_world(camera.world_to_camera(points)), points, atol=1e-12)
    np.testing.assert_allclose(camera.rotation.T @ camera.rotation, np.eye(3), atol=1e-12)


def test_first_ray_hits_matches_trimesh_on_random_triangle_soup():
    rng = np.random.default_rng(11)
    for _ in range(4):
        triangle_count, ray_count = 200, 300
        centres = rng.normal(size=(triangle_count, 1, 3)) * 2
        sizes = rng.uniform(0.05, 1.5, size=(triangle_count, 1, 1))
        vertices = (centres + rng.normal(size=(triangle_count, 3, 3)) * sizes).reshape(-1, 3)
        triangles = np.arange(3 * triangle_count).reshape(-1, 3)
        directions = rng.normal(size=(ray_count, 3))
        directions[:, 2] = np.linalg.norm(directions[:, :2], axis=1) * rng.uniform(0.5, 3, size=ray_count)
        directions /= np.linalg.norm(directions, axis=1)[:, None]
        origin = rng.normal(size=3) * 0.3  # among the triangles: some behind, some straddling
        hits = first_ray_hits(origin, directions, vertices, triangles)

        mesh = trimesh.Trimesh(vertices, triangles, process=False)
        expected_triangle, ray, location = RayMeshIntersector(mesh).intersects_id(
            np.tile(origin, (ray_count, 1)), directions, multiple_hits=False, return_locations=True
        )
        reference = np.full(ray_count, -1)
        reference[ray] = expected_triangle
        np.testing.assert_array_equal(hits.triangles, reference)
        np.testing.assert_allclose(hits.distances[ray], np.linalg.norm(location - origin, axis=1), atol=1e-12)
        assert np.isinf(hits.distances[reference < 0]).all()


def test_bad_input_raises():
    with pytest.raises(ValueError, match="zero norm"):
        PinholeCamera(np.zeros(3), np.zeros(4), 4, 4, 1.0, 1.0, 1.5, 1.5)
    with pytest.raises(ValueError, match="focal"):
        PinholeCamera(np.zeros(3), [0, 0, 0, 1], 4, 4, 0.0, 1.0, 1.5, 1.5)
    with pytest.raises(ValueError, match="leak_fraction"):
        CaptureOptions(leak_fraction=1.5)
    with pytest.raises(ValueError, match="leak_dilation_pixels"):
        CaptureOptions(leak_dilation_pixels=-1.0)
    with pytest.raises(ValueError, match="label"):
        capture(forward_camera(), *square(0.1, 1.0), occluders=[(*square(0.05, 0.01), 0)])
    with pytest.raises(ValueError, match="90 degrees"):
        first_ray_hits(np.zeros(3), [[0, 0, 1], [0, 0, -1], [1, 0, 0]], *square(1.0, 1.0))
    with pytest.raises(ValueError, match="index vertices"):
        capture(forward_camera(), square(0.1, 1.0)[0], [[0, 1, 7]])
