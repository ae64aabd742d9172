"""Tests for meshfg_ros.synthetic.meshing: structured cube / box meshes and the airway phantom."""

import numpy as np
import pytest

from meshfg_ros.synthetic.meshing import (
    MeshingParameterError,
    airway_phantom,
    box_mesh,
    cross_section_area,
    cube_mesh,
    structured_box_mesh,
)


@pytest.fixture(scope="module")
def phantom():
    return airway_phantom()


def lumen_ellipsoid_slice_areas(phantom, heights: np.ndarray, samples: int = 5000) -> np.ndarray:
    """Exact-geometry area of (ellipsoid slice) ∩ (lumen disk) at each height, by midpoint rule in y."""
    radius = phantom.inner_radius
    centre, (ax, ay, az) = phantom.tumour_centre, phantom.tumour_semi_axes
    scale = np.sqrt(np.clip(1.0 - ((heights - centre[2]) / az) ** 2, 0.0, None))[:, None]
    y = (np.arange(samples) + 0.5) / samples * 2 * radius - radius
    disk_half_width = np.sqrt(radius**2 - y**2)[None, :]
    with np.errstate(invalid="ignore", divide="ignore"):
        ellipse_half_width = ax * scale * np.sqrt(np.clip(1.0 - (y[None, :] / (ay * scale)) ** 2, 0.0, None))
    ellipse_half_width = np.nan_to_num(ellipse_half_width)
    overlap = np.minimum(disk_half_width, centre[0] + ellipse_half_width) - np.maximum(
        -disk_half_width, centre[0] - ellipse_half_width
    )
    overlap = np.where(ellipse_half_width > 0.0, np.clip(overlap, 0.0, None), 0.0)
    return overlap.sum(axis=1) * (2 * radius / samples)


def test_default_cube_counts_volume_and_orientation():
    cube = cube_mesh()
    assert cube.vertex_count == 512
    assert cube.tetrahedron_count == 6 * 7**3
    assert cube.flipped_count == 0  # generated positively oriented
    assert np.all(cube.signed_volumes() > 0.0)
    assert cube.volume() == pytest.approx(1.0, abs=1e-12)
    assert cube.fixed_vertices.size == 0
    # Conforming split: only the outer faces are boundary faces (2 triangles per cell face).
    assert cube.surface_triangles.shape[0] == 6 * 7**2 * 2
    assert cube.surface_vertices.size == 8**3 - 6**3


def test_cube_side_and_origin():
    cube = cube_mesh(side=0.05, divisions=3, origin=(1.0, 2.0, 3.0))
    assert cube.vertex_count == 64
    assert cube.volume() == pytest.approx(0.05**3, rel=1e-12)
    assert np.allclose(cube.vertices.min(axis=0), [1.0, 2.0, 3.0], rtol=0, atol=1e-15)
    assert np.allclose(cube.vertices.max(axis=0), [1.05, 2.05, 3.05], rtol=0, atol=1e-15)


def test_box_mesh_reaches_target_size():
    box = box_mesh()
    assert box.vertex_count == 22**3  # nearest cell count to 10000 vertices in a cube
    assert box.volume() == pytest.approx(1e-3, rel=1e-12)
    flat_box = box_mesh(target_vertices=5000, size=(0.2, 0.1, 0.05))
    assert abs(flat_box.vertex_count - 5000) < 0.05 * 5000
    extent = np.ptp(flat_box.vertices, axis=0)
    assert np.allclose(extent, [0.2, 0.1, 0.05], rtol=1e-14)
    cell = extent / (np.array([np.unique(flat_box.vertices[:, a]).size for a in range(3)]) - 1)
    assert cell.max() / cell.min() == pytest.approx(1.0, abs=1e-9)


def test_generator_parameters_are_checked():
    with pytest.raises(MeshingParameterError, match="divisions"):
        structured_box_mesh((1, 1, 1), (2, 0, 2))
    with pytest.raises(MeshingParameterError, match="size"):
        structured_box_mesh((1, -1, 1), (2, 2, 2))
    with pytest.raises(MeshingParameterError, match="divisions must be an integer"):
        cube_mesh(divisions=2.5)
    with pytest.raises(MeshingParameterError, match="does not cross the wall"):
        airway_phantom(tumour_centre_radius=0.0, tumour_semi_axes=(0.005, 0.005, 0.005))


def test_cross_section_area_of_cube():
    cube = cube_mesh(side=2.0, divisions=4)
    assert cross_section_area(cube, (1.0, 1.0, 1.0), (0.0, 0.0, 1.0)) == pytest.approx(4.0, rel=1e-12)
    diagonal = cross_section_area(cube, (1.0, 1.0, 1.0), (1.0, 1.0, 0.0))
    assert diagonal == pytest.approx(2.0 * 2.0 * np.sqrt(2.0), rel=1e-12)
    assert cross_section_area(cube, (0.0, 0.0, 5.0), (0.0, 0.0, 1.0)) == 0.0


def test_airway_tumour_mesh(phantom):
    tumour = phantom.tumour
    assert 300 <= tumour.vertex_count <= 1500
    assert np.all(tumour.signed_volumes() > 0.0)
    heights = np.linspace(phantom.tumour_centre[2] - phantom.tumour_semi_axes[2],
                          phantom.tumour_centre[2] + phantom.tumour_semi_axes[2], 801)
    areas = lumen_ellipsoid_slice_areas(phantom, 0.5 * (heights[1:] + heights[:-1]))
    exact_volume = areas.sum() * (heights[1] - heights[0])
    # The mesh is inscribed in the curved surfaces, so slightly smaller.
    assert 0.97 * exact_volume < tumour.volume() < exact_volume


def test_airway_tumour_interface_is_fixed(phantom):
    tumour = phantom.tumour
    radius = phantom.inner_radius
    fixed = tumour.fixed_vertices
    assert fixed.size > 0
    assert np.all(np.isin(fixed, tumour.surface_vertices))
    fixed_radii = np.linalg.norm(tumour.vertices[fixed, :2], axis=1)
    assert np.all(np.abs(fixed_radii - radius) < 1e-6)
    free_surface = np.setdiff1d(tumour.surface_vertices, fixed)
    assert free_surface.size > fixed.size
    assert np.all(np.linalg.norm(tumour.vertices[free_surface, :2], axis=1) < radius - 1e-4)
    # Interface triangles lie on the wall, facing radially out of the lumen.
    triangles = tumour.surface_triangles
    on_interface = np.all(np.isin(triangles, fixed), axis=1)
    centres = tumour.vertices[triangles[on_interface]].mean(axis=1)
    radial = centres[:, :2] / np.linalg.norm(centres[:, :2], axis=1, keepdims=True)
    normals = tumour.triangle_normals()[on_interface]
    assert np.all(np.einsum("ij,ij->i", normals[:, :2], radial) > 0.99)


def test_airway_occludes_about_half_the_lumen(phantom):
    assert 0.35 < phantom.occluded_fraction < 0.65
    exact_area = lumen_ellipsoid_slice_areas(phantom, phantom.tumour_centre[2:3])[0]
    exact = exact_area / (np.pi * phantom.inner_radius**2)
    assert phantom.occluded_fraction == pytest.approx(exact, abs=0.01)


def test_airway_wall_surface(phantom):
    vertices, triangles = phantom.wall_vertices, phantom.wall_triangles
    assert np.allclose(np.linalg.norm(vertices[:, :2], axis=1), phantom.inner_radius, rtol=1e-14)
    assert vertices[:, 2].min() == 0.0 and vertices[:, 2].max() == pytest.approx(phantom.length)
    corners = vertices[triangles]
    normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    outward = corners.mean(axis=1)[:, :2]
    assert np.all(np.einsum("ij,ij->i", normals[:, :2], outward) < 0.0)  # faces the lumen
    # Open tube: total area close to the cylinder's side area.
    area = 0.5 * np.linalg.norm(normals, axis=1).sum()
    assert area == pytest.approx(2 * np.pi * phantom.inner_radius * phantom.length, rel=2e-3)


def test_airway_phantom_is_deterministic(phantom):
    again = airway_phantom()
    assert np.array_equal(again.tumour.vertices, phantom.tumour.vertices)
    assert np.array_equal(again.tumour.tetrahedra, phantom.tumour.tetrahedra)
    assert np.array_equal(again.tumour.fixed_vertices, phantom.tumour.fixed_vertices)
    assert again.occluded_fraction == phantom.occluded_fraction
