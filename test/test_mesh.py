"""Tests for meshfg_ros.core.geometry.mesh: validation, orientation, surface topology and file IO."""

from pathlib import Path

import meshio
import numpy as np
import pytest

from meshfg_ros.core.geometry.mesh import (
    DegenerateMeshError,
    DofPattern,
    InvalidMeshError,
    MeshFileError,
    TetMesh,
    cross,
    inverted_elements,
    load_mesh,
    orient_tetrahedra,
    save_mesh,
    signed_volumes,
)

LIVER_PATH = Path("/work/shared/data/liver.msh")


@pytest.fixture(scope="module")
def liver() -> TetMesh:
    return load_mesh(LIVER_PATH)


def unit_tetrahedron_pair() -> tuple[np.ndarray, np.ndarray]:
    """Two positive tetrahedra sharing the face (0, 1, 2)."""
    vertices = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [0, 0, -1]], dtype=float)
    tets = np.array([[0, 1, 2, 3], [0, 2, 1, 4]])
    return vertices, tets


def test_liver_loads_with_expected_counts_and_volume(liver):
    assert liver.vertex_count == 181
    assert liver.tetrahedron_count == 596
    assert liver.flipped_count == 0
    assert liver.volume() == pytest.approx(36.56085, abs=1e-4)
    assert np.all(liver.signed_volumes() > 0.0)
    assert liver.vertices.dtype == np.float64 and liver.tetrahedra.dtype == np.int64
    assert liver.name == "liver"


def test_liver_surface_is_closed_and_consistently_oriented(liver):
    triangles = liver.surface_triangles
    directed = np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]])
    _, undirected_counts = np.unique(np.sort(directed, axis=1), axis=0, return_counts=True)
    assert np.all(undirected_counts == 2)
    # Consistent orientation: each directed edge occurs once (its twin runs the other way).
    _, directed_counts = np.unique(directed, axis=0, return_counts=True)
    assert np.all(directed_counts == 1)
    # Euler characteristic of a closed genus-0 surface.
    edge_count = undirected_counts.size
    assert liver.surface_vertices.size - edge_count + triangles.shape[0] == 2


def test_surface_orientation_is_outward_by_divergence_theorem(liver):
    corners = liver.vertices[liver.surface_triangles]
    enclosed = np.einsum("ij,ij->i", corners[:, 0], np.cross(corners[:, 1], corners[:, 2])).sum() / 6
    assert enclosed == pytest.approx(liver.volume(), rel=1e-12)
    # Same check through the unit normals: integral of x . n dA equals 3 V.
    areas = 0.5 * np.linalg.norm(
        np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1
    )
    flux = np.einsum("ij,ij->i", corners.mean(axis=1), liver.triangle_normals()) @ areas
    assert flux == pytest.approx(3 * liver.volume(), rel=1e-12)


def test_vertex_sets_partition_and_normals(liver):
    all_vertices = np.union1d(liver.surface_vertices, liver.internal_vertices)
    assert np.array_equal(all_vertices, np.arange(liver.vertex_count))
    assert np.intersect1d(liver.surface_vertices, liver.internal_vertices).size == 0
    normals = liver.vertex_normals()
    assert np.allclose(np.linalg.norm(normals[liver.surface_vertices], axis=1), 1.0)
    assert np.all(normals[liver.internal_vertices] == 0.0)
    assert np.allclose(np.linalg.norm(liver.triangle_normals(), axis=1), 1.0)


def test_edges_are_unique_and_ordered(liver):
    edges = liver.edges
    assert np.all(edges[:, 0] < edges[:, 1])
    assert np.unique(edges, axis=0).shape[0] == edges.shape[0]
    # Euler for a 3-ball triangulation: V - E + F - T = 1.
    face_corners = [[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3]]
    all_faces = np.sort(liver.tetrahedra[:, face_corners].reshape(-1, 3), axis=1)
    face_count = np.unique(all_faces, axis=0).shape[0]
    assert liver.vertex_count - edges.shape[0] + face_count - liver.tetrahedron_count == 1


def test_flipped_tetrahedra_are_fixed(liver):
    tets = liver.tetrahedra.copy()
    flipped = np.array([0, 17, 300])
    tets[flipped] = tets[flipped][:, [1, 0, 2, 3]]
    assert np.all(signed_volumes(liver.vertices, tets)[flipped] < 0)
    repaired = TetMesh(liver.vertices, tets)
    assert repaired.flipped_count == 3
    assert np.all(repaired.signed_volumes() > 0)
    assert repaired.volume() == pytest.approx(liver.volume(), rel=1e-14)
    fixed_tets, count = orient_tetrahedra(liver.vertices, tets)
    assert count == 3
    assert np.array_equal(np.sort(fixed_tets, axis=1), np.sort(tets, axis=1))


def test_cross_and_volumes_are_numpys_values(liver):
    """mesh.cross gives np.cross's very values; signed volumes agree with the determinants to
    rounding (the triple product at corner 0)."""
    rng = np.random.default_rng(3)
    a, b = rng.normal(size=(500, 3)), rng.normal(size=(500, 3))
    assert np.array_equal(cross(a, b), np.cross(a, b))
    assert np.array_equal(cross(a[:, None], b[None, :5]), np.cross(a[:, None], b[None, :5]))
    corners = liver.vertices[liver.tetrahedra]
    determinants = np.linalg.det(corners[:, 1:] - corners[:, :1]) / 6.0
    volumes = signed_volumes(liver.vertices, liver.tetrahedra)
    np.testing.assert_allclose(volumes, determinants, rtol=1e-12, atol=1e-15 * np.abs(determinants).max())


def test_volumes_take_read_only_strided_and_stacked_states_alike(liver):
    """The compiled volumes are typed once (kernel_types.py): a read-only state (a mesh's), a
    strided one, int32 element indices and a stack of states all give the writable state's
    values, and the longest edges are those of the edge vectors at corner 0."""
    volumes, longest = signed_volumes(liver.vertices, liver.tetrahedra, longest_edges=True)
    read_only = liver.vertices.copy()
    read_only.setflags(write=False)
    strided = np.asfortranarray(liver.vertices)
    for vertices in (read_only, strided):
        assert np.array_equal(signed_volumes(vertices, liver.tetrahedra.astype(np.int32)), volumes)
    stacked = signed_volumes(np.stack([liver.vertices, 2.0 * liver.vertices]), liver.tetrahedra)
    np.testing.assert_allclose(stacked, [volumes, 8.0 * volumes], rtol=1e-14)
    corners = liver.vertices[liver.tetrahedra]
    edges = np.linalg.norm(corners[:, 1:] - corners[:, :1], axis=2).max(axis=1)
    np.testing.assert_allclose(longest, edges, rtol=1e-14)


def test_degenerate_element_raises_naming_its_index():
    vertices, tets = unit_tetrahedron_pair()
    vertices = np.vstack([vertices, [[0.5, 0.5, 0.0]]])  # on the plane of vertices 0, 1, 2
    flat_tets = np.vstack([tets, [[0, 1, 2, 5]]])
    with pytest.raises(DegenerateMeshError, match=r"1 degenerate tetrahedra .*elements \[2\]") as info:
        TetMesh(vertices, flat_tets)
    assert info.value.element_indices.tolist() == [2]
    with pytest.raises(DegenerateMeshError, match=r"repeated vertex indices.*\[1\]"):
        TetMesh(vertices[:5], np.array([[0, 1, 2, 3], [0, 2, 2, 4]]))


def test_invalid_arrays_raise_clear_errors():
    vertices, tets = unit_tetrahedron_pair()
    with pytest.raises(InvalidMeshError, match=r"shape \(N, 3\)"):
        TetMesh(vertices[:, :2], tets)
    with pytest.raises(InvalidMeshError, match="out of range"):
        TetMesh(vertices, tets + 1)
    with pytest.raises(InvalidMeshError, match="integer"):
        TetMesh(vertices, tets.astype(float))
    with pytest.raises(InvalidMeshError, match=r"shape \(M>0, 4\)"):
        TetMesh(vertices, tets[:, :3])
    with pytest.raises(InvalidMeshError, match="belong to no tetrahedron"):
        TetMesh(np.vstack([vertices, [[5.0, 5.0, 5.0]]]), tets)
    with pytest.raises(InvalidMeshError, match="fixed_vertices index out of range"):
        TetMesh(vertices, tets, fixed_vertices=[7])


def test_with_vertices_and_with_fixed_share_topology(liver):
    fixed = liver.with_fixed([9, 3, 3, 1])
    assert fixed.fixed_vertices.tolist() == [1, 3, 9]
    assert fixed.free_vertices.size == liver.vertex_count - 3
    moved = fixed.with_vertices(liver.vertices * 2.0)
    assert moved.surface_triangles is liver.surface_triangles
    assert moved.edges is liver.edges
    assert np.array_equal(moved.fixed_vertices, [1, 3, 9])
    assert moved.volume() == pytest.approx(8 * liver.volume(), rel=1e-12)
    with pytest.raises(ValueError):
        moved.vertices[0, 0] = 1.0
    with pytest.raises(InvalidMeshError, match="181 rows"):
        liver.with_vertices(liver.vertices[:-1])


@pytest.mark.parametrize("suffix", [".msh", ".vtu", ".vtk"])
def test_save_load_round_trip(liver, tmp_path, suffix):
    original = liver.with_fixed([0, 42, 180])
    path = tmp_path / f"liver{suffix}"
    save_mesh(original, path)
    loaded = load_mesh(path)
    assert np.array_equal(loaded.vertices, original.vertices)
    assert np.array_equal(loaded.tetrahedra, original.tetrahedra)
    assert np.array_equal(loaded.fixed_vertices, original.fixed_vertices)


def test_gmsh22_file_loads(liver, tmp_path):
    path = tmp_path / "liver22.msh"
    legacy_mesh = meshio.Mesh(liver.vertices, [("tetra", liver.tetrahedra)])
    meshio.write(path, legacy_mesh, file_format="gmsh22", binary=False)
    loaded = load_mesh(path)
    assert np.array_equal(loaded.tetrahedra, liver.tetrahedra)
    assert loaded.fixed_vertices.size == 0


def test_non_tetrahedral_files_raise(liver, tmp_path):
    surface = meshio.Mesh(liver.vertices, [("triangle", liver.surface_triangles)])
    for suffix in (".vtu", ".msh"):
        path = tmp_path / f"surface{suffix}"
        meshio.write(path, surface)
        with pytest.raises(MeshFileError, match="is not a tetrahedral mesh"):
            load_mesh(path)
    legacy = tmp_path / "triangle_v1.msh"
    legacy.write_text("$NOD\n3\n1 0 0 0\n2 1 0 0\n3 0 1 0\n$ENDNOD\n$ELM\n1\n1 2 1 1 3 1 2 3\n$ENDELM\n")
    with pytest.raises(MeshFileError, match="is not a tetrahedral mesh"):
        load_mesh(legacy)
    with pytest.raises(MeshFileError, match="does not exist"):
        load_mesh(tmp_path / "missing.msh")
    with pytest.raises(MeshFileError, match="is a folder, not a mesh file"):
        load_mesh(tmp_path)
    recording = tmp_path / "recording"
    recording.mkdir()
    (recording / "metadata.yaml").write_text("rosbag2_bagfile_information: {}\n")
    with pytest.raises(MeshFileError, match=r"is a recording, not a mesh file: `meshfg mesh export .*recording --out"):
        load_mesh(recording)
    with pytest.raises(MeshFileError, match="unsupported mesh format"):
        save_mesh(liver, tmp_path / "liver.stl")


def test_inverted_elements_are_the_flat_flipped_and_non_finite_ones():
    vertices = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0],
                         [0.0, 0.0, -1.0], [1.0, 1.0, 0.0], [np.nan, 0.0, 0.0]])
    tetrahedra = np.array([[0, 1, 2, 3],   # positive
                           [0, 1, 2, 4],   # flipped
                           [0, 1, 2, 5],   # flat
                           [6, 1, 2, 3]])  # NaN corner
    np.testing.assert_array_equal(inverted_elements(vertices, tetrahedra), [1, 2, 3])


def test_sorted_unique_is_numpys_unique():
    from meshfg_ros.core.geometry.mesh import sorted_unique

    keys = np.random.default_rng(3).integers(0, 500, 5000)
    np.testing.assert_array_equal(sorted_unique(keys), np.unique(keys))
    np.testing.assert_array_equal(sorted_unique(np.array([7])), [7])


def test_dof_pattern_holds_every_dof_pair_of_vertices_sharing_an_element():
    """DofPattern against the pairs listed one by one: rows sorted, each vertex's own block (also
    of a vertex of no element, here vertex 6), positions and mirrors where they are."""
    tetrahedra = np.array([[0, 1, 2, 3], [1, 2, 3, 4], [3, 4, 5, 2]])
    vertex_count = 7
    pattern = DofPattern(tetrahedra, vertex_count)
    adjacent = {(v, v) for v in range(vertex_count)}
    adjacent |= {(a, b) for tet in tetrahedra for a in tet for b in tet}
    expected = sorted((3 * a + i, 3 * b + k) for a, b in adjacent for i in range(3) for k in range(3))
    rows = pattern.rows()
    assert list(zip(rows.tolist(), pattern.indices.tolist())) == expected
    pair_rows, pair_columns = np.array(expected).T
    ranks = pattern.vertex_ranks(pair_rows // 3, pair_columns // 3)
    assert np.array_equal(pattern.positions(pair_rows, ranks, pair_columns % 3), np.arange(len(expected)))
    mirror = pattern.transposed_positions()
    assert np.array_equal(rows[mirror], pattern.indices) and np.array_equal(pattern.indices[mirror], rows)
