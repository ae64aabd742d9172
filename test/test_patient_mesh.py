"""core.inputs.patient_mesh: a user's own mesh (no fixed data, mm, CT frame) made ready for the simulator."""
import meshio
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from meshfg_ros.core.geometry.mesh import MeshFileError, load_mesh, save_mesh
from meshfg_ros.core.inputs.patient_mesh import (
    Box,
    FixedSelection,
    PatientMeshError,
    Plane,
    check_against_clouds,
    check_simulatable,
    plausible_units,
    prepare_mesh,
    read_patient_mesh,
)
from meshfg_ros.synthetic.meshing import gmsh_model, structured_box_mesh
from meshfg_ros.synthetic.scenarios import LIVER_PATH_CANDIDATES

LIVER_FILE = next(path for path in LIVER_PATH_CANDIDATES if path.is_file())
LIVER_METRES_PER_UNIT = 0.03  # the scenarios' scale of the unitless SOFA liver


def write_plain(path, vertices, tetrahedra):
    """A mesh file as a user brings it: tetrahedra only, no `fixed` point data."""
    meshio.write(path, meshio.Mesh(np.asarray(vertices, dtype=np.float64), [("tetra", np.asarray(tetrahedra))]))
    return path


@pytest.fixture
def box_file(tmp_path):
    box = structured_box_mesh((0.1, 0.06, 0.04), (5, 3, 2))
    return write_plain(tmp_path / "box.vtu", box.vertices, box.tetrahedra), box


@pytest.fixture(scope="module")
def gmsh_groups_file(tmp_path_factory):
    """A gmsh box 0.1 x 0.05 x 0.04 m with a physical surface 'base' (z = 0) and volume 'organ'."""
    path = tmp_path_factory.mktemp("gmsh") / "groups.msh"
    with gmsh_model("groups", {"Mesh.MeshSizeMax": 0.02}) as gmsh:
        volume = gmsh.model.occ.addBox(0, 0, 0, 0.1, 0.05, 0.04)
        gmsh.model.occ.synchronize()
        faces = [tag for _, tag in gmsh.model.getBoundary([(3, volume)], oriented=False)]
        bottom = [tag for tag in faces if abs(gmsh.model.occ.getCenterOfMass(2, tag)[2]) < 1e-12]
        gmsh.model.addPhysicalGroup(2, bottom, name="base")
        gmsh.model.addPhysicalGroup(3, [volume], name="organ")
        gmsh.model.mesh.generate(3)
        gmsh.write(str(path))
    return path


def test_fixed_by_indices(box_file):
    path, _ = box_file
    assert prepare_mesh(path, FixedSelection(indices=(0, 7, 40, 41))).fixed_vertices.tolist() == [0, 7, 40, 41]


def test_fixed_by_plane_in_any_orientation(box_file):
    path, box = box_file
    mesh = prepare_mesh(path, FixedSelection(planes=(Plane((5.0, -3.0, 0.0), (0.0, 0.0, -2.0), 1e-9),)))
    np.testing.assert_array_equal(mesh.fixed_vertices, np.flatnonzero(box.vertices[:, 2] == 0.0))
    slanted = prepare_mesh(path, FixedSelection(planes=(Plane((0.1, 0.0, 0.0), (1.0, 1.0, 0.0), 0.0101),)))
    distances = np.abs((box.vertices - [0.1, 0.0, 0.0]) @ (np.array([1.0, 1.0, 0.0]) / np.sqrt(2.0)))
    np.testing.assert_array_equal(slanted.fixed_vertices, np.flatnonzero(distances <= 0.0101))
    assert 3 <= slanted.fixed_vertices.size < box.vertex_count


def test_fixed_by_box(box_file):
    path, box = box_file
    mesh = prepare_mesh(path, FixedSelection(boxes=(Box((-1.0, -1.0, -1.0), (0.02, 1.0, 1.0)),)))
    np.testing.assert_array_equal(mesh.fixed_vertices, np.flatnonzero(box.vertices[:, 0] <= 0.02))


def test_fixed_by_gmsh_physical_group(gmsh_groups_file):
    read = read_patient_mesh(gmsh_groups_file)
    assert sorted(read.groups) == ["base", "organ"]
    mesh = prepare_mesh(gmsh_groups_file, FixedSelection(groups=("base",)))
    np.testing.assert_array_equal(mesh.fixed_vertices, np.flatnonzero(np.abs(mesh.vertices[:, 2]) < 1e-12))
    assert mesh.fixed_vertices.size > 10
    assert read.groups["organ"].size == mesh.vertex_count


def test_selections_combine_as_a_union(box_file):
    path, box = box_file
    selection = FixedSelection(indices=(int(np.argmax(box.vertices[:, 2])),),
                               planes=(Plane((0, 0, 0), (0, 0, 1), 0.0),), boxes=(Box((0.1, 0, 0), (0.1, 0.06, 0.04)),))
    expected = (box.vertices[:, 2] == 0.0) | (box.vertices[:, 0] == 0.1)
    expected[np.argmax(box.vertices[:, 2])] = True
    np.testing.assert_array_equal(prepare_mesh(path, selection).fixed_vertices, np.flatnonzero(expected))


def test_file_fixed_data_is_kept_and_matches_load_mesh(tmp_path):
    box = structured_box_mesh((0.1, 0.1, 0.1), (3, 3, 3))
    project_mesh = box.with_fixed(np.flatnonzero(box.vertices[:, 2] == 0.0))
    save_mesh(project_mesh, tmp_path / "project.msh")
    prepared, loaded = prepare_mesh(tmp_path / "project.msh"), load_mesh(tmp_path / "project.msh")
    np.testing.assert_array_equal(prepared.vertices, loaded.vertices)
    np.testing.assert_array_equal(prepared.tetrahedra, loaded.tetrahedra)
    np.testing.assert_array_equal(prepared.fixed_vertices, loaded.fixed_vertices)
    with_more = prepare_mesh(tmp_path / "project.msh", FixedSelection(indices=(63,)))
    assert with_more.fixed_vertices.tolist() == sorted({*loaded.fixed_vertices.tolist(), 63})


def test_unknown_group_and_bad_selections(box_file, gmsh_groups_file):
    with pytest.raises(PatientMeshError, match=r"no group 'wall' \(groups: base, organ\)"):
        prepare_mesh(gmsh_groups_file, FixedSelection(groups=("wall",)))
    path, box = box_file
    with pytest.raises(PatientMeshError, match=r"no group 'base' \(groups: none\)"):
        prepare_mesh(path, FixedSelection(groups=("base",)))
    with pytest.raises(PatientMeshError, match=rf"index out of range \[0, {box.vertex_count}\)"):
        prepare_mesh(path, FixedSelection(indices=(box.vertex_count,)))
    with pytest.raises(PatientMeshError, match="non-zero normal"):
        prepare_mesh(path, FixedSelection(planes=(Plane((0, 0, 0), (0, 0, 0), 0.01),)))


def test_scale_and_pose_place_the_mesh_and_selections_apply_in_the_world(tmp_path):
    box = structured_box_mesh((100.0, 60.0, 40.0), (5, 3, 2))  # millimetres, CT frame
    path = write_plain(tmp_path / "ct.vtu", box.vertices, box.tetrahedra)
    rotation = Rotation.from_euler("xyz", [10, -20, 90], degrees=True)
    pose = [0.3, -0.1, 0.9, *rotation.as_quat()]
    world_bottom_point = rotation.apply([0.0, 0.0, 0.0]) + pose[:3]
    world_bottom_normal = rotation.apply([0.0, 0.0, 1.0])
    mesh = prepare_mesh(path, FixedSelection(planes=(Plane(tuple(world_bottom_point), tuple(world_bottom_normal), 1e-6),)),
                        scale=0.001, pose=pose)
    np.testing.assert_allclose(mesh.vertices, rotation.apply(0.001 * box.vertices) + pose[:3], rtol=0, atol=1e-15)
    np.testing.assert_array_equal(mesh.fixed_vertices, np.flatnonzero(box.vertices[:, 2] == 0.0))
    assert mesh.volume() == pytest.approx(0.1 * 0.06 * 0.04, rel=1e-12)
    with pytest.raises(PatientMeshError, match="mesh_scale must be a positive number"):
        prepare_mesh(path, FixedSelection(indices=(0,)), scale=-0.001)
    with pytest.raises(PatientMeshError, match="mesh_pose: pose quaternion has zero norm"):
        prepare_mesh(path, FixedSelection(indices=(0,)), pose=[0, 0, 0, 0, 0, 0, 0])


def test_a_mesh_without_fixed_vertices_fails_in_one_line(box_file):
    path, _ = box_file
    with pytest.raises(PatientMeshError) as error:
        prepare_mesh(path)
    message = str(error.value)
    assert message == (f"{path}: the mesh has no fixed vertices, so the simulator's stiffness is singular: select "
                       "some (fixed vertex indices, a plane, a box or a group of the mesh file)")


def test_collinear_fixed_vertices_and_loose_parts_fail(tmp_path):
    box = structured_box_mesh((0.1, 0.1, 0.1), (2, 2, 2))
    edge = np.flatnonzero((box.vertices[:, 1] == 0.0) & (box.vertices[:, 2] == 0.0))  # 3 vertices on a line
    with pytest.raises(PatientMeshError, match=r"1 of 1 connected parts of the mesh \(27 vertices\) are held by fewer"):
        check_simulatable(box.with_fixed(edge))
    second = structured_box_mesh((0.1, 0.1, 0.1), (1, 1, 1), origin=(0.5, 0.0, 0.0))
    two_parts = write_plain(tmp_path / "two.vtu", np.vstack([box.vertices, second.vertices]),
                            np.vstack([box.tetrahedra, second.tetrahedra + box.vertex_count]))
    with pytest.raises(PatientMeshError, match=r"1 of 2 connected parts of the mesh \(8 vertices\)"):
        prepare_mesh(two_parts, FixedSelection(boxes=(Box((0, 0, 0), (0.1, 0.1, 0.0)),)))  # the first's bottom
    held = prepare_mesh(two_parts, FixedSelection(planes=(Plane((0, 0, 0), (0, 0, 1), 0.0),)))
    assert held.fixed_vertices.size == 9 + 4


def test_inverted_and_degenerate_elements_fail_naming_how_many(tmp_path):
    box = structured_box_mesh((0.1, 0.1, 0.1), (2, 2, 2))
    tangled = box.tetrahedra.copy()
    tangled[:5, [2, 3]] = tangled[:5, [3, 2]]
    with pytest.raises(PatientMeshError, match=r"5 of 48 tetrahedra are inverted against the others"):
        read_patient_mesh(write_plain(tmp_path / "tangled.vtu", box.vertices, tangled))
    all_reversed = box.tetrahedra[:, [0, 1, 3, 2]]  # another ordering convention: fine
    assert read_patient_mesh(write_plain(tmp_path / "reversed.vtu", box.vertices, all_reversed)).mesh.flipped_count == 48
    flat = np.vstack([box.vertices, [[0.05, 0.05, 0.2], [0.06, 0.05, 0.2], [0.07, 0.05, 0.2], [0.05, 0.06, 0.2]]])
    flat_tets = np.vstack([box.tetrahedra, [[27, 28, 29, 30]]])
    with pytest.raises(PatientMeshError, match=r"1 degenerate tetrahedra"):
        read_patient_mesh(write_plain(tmp_path / "flat.vtu", flat, flat_tets))


def test_unreadable_file_is_a_one_line_error(tmp_path):
    (tmp_path / "bad.msh").write_text("$MeshFormat\ngarbage\n")
    with pytest.raises(MeshFileError, match="could not be read by meshio"):
        read_patient_mesh(tmp_path / "bad.msh")
    with pytest.raises(MeshFileError, match="does not exist"):
        read_patient_mesh(tmp_path / "missing.vtu")
    with pytest.raises(MeshFileError, match="is a folder, not a mesh file"):
        read_patient_mesh(tmp_path)


# --------------------------------------------------------------------------- against the clouds
def liver_in(tmp_path, unit_per_liver_unit: float, name: str):
    """The SOFA liver written in another unit (1 liver unit = 3 cm), with no fixed data."""
    liver = load_mesh(LIVER_FILE)
    return write_plain(tmp_path / f"{name}.vtu", liver.vertices * unit_per_liver_unit, liver.tetrahedra), liver


def top_view_cloud(liver, metres_per_unit=LIVER_METRES_PER_UNIT, share=0.3):
    """What a camera above sees: the upper `share` of the liver's surface, in metres, with noise."""
    surface = liver.vertices[liver.surface_vertices] * metres_per_unit
    top = surface[surface[:, 2] >= np.quantile(surface[:, 2], 1.0 - share)]
    return top + np.random.default_rng(0).normal(scale=5e-4, size=top.shape)


def lowest_vertices(liver):
    return FixedSelection(indices=tuple(np.flatnonzero(liver.vertices[:, 2] <= np.quantile(liver.vertices[:, 2], 0.15))))


def test_mesh_in_millimetres_against_clouds_in_metres_fails_in_one_line(tmp_path):
    path, liver = liver_in(tmp_path, 30.0, "liver-mm")
    cloud = top_view_cloud(liver)
    mesh = prepare_mesh(path, lowest_vertices(liver))
    with pytest.raises(PatientMeshError) as error:
        check_against_clouds(mesh, [cloud])
    message = str(error.value)
    assert message.startswith("the mesh is ~") and "x larger than the clouds (bounding-box diagonals" in message
    assert message.endswith("is it in millimetres? set mesh_scale 0.001") and "\n" not in message
    check_against_clouds(prepare_mesh(path, lowest_vertices(liver), scale=0.001), [cloud])  # a partial view passes


def test_mesh_in_centimetres_and_too_small_meshes_are_named(tmp_path):
    path, liver = liver_in(tmp_path, 3.0, "liver-cm")
    cloud = top_view_cloud(liver)
    with pytest.raises(PatientMeshError, match="is it in centimetres\\? set mesh_scale 0.01$"):
        check_against_clouds(prepare_mesh(path, lowest_vertices(liver)), [cloud])
    with pytest.raises(PatientMeshError, match="x smaller than the clouds .*is mesh_scale too small"):
        check_against_clouds(prepare_mesh(path, lowest_vertices(liver), scale=1e-4), [cloud])
    check_against_clouds(prepare_mesh(path, lowest_vertices(liver), scale=0.01), [cloud[::2], cloud[1::2]])


def test_unregistered_mesh_fails_saying_how_far_and_to_set_mesh_pose(tmp_path):
    path, liver = liver_in(tmp_path, 30.0, "liver-mm")
    cloud = top_view_cloud(liver)
    shifted = prepare_mesh(path, lowest_vertices(liver), scale=0.001, pose=[0.0, 0.5, 0.0, 0, 0, 0, 1])
    mesh_top = shifted.vertices[:, 1].min()
    expected_gap = mesh_top - np.percentile(cloud[:, 1], 99.5)
    with pytest.raises(PatientMeshError) as error:
        check_against_clouds(shifted, [cloud])
    assert f"bounding boxes are {expected_gap:.3g} m apart" in str(error.value)
    assert str(error.value).endswith("set mesh_pose to the registration of the mesh's frame to the world frame")
    nudged = prepare_mesh(path, lowest_vertices(liver), scale=0.001, pose=[0.0, 0.01, 0.0, 0, 0, 0, 1])
    check_against_clouds(nudged, [cloud])  # a registration error of 1 cm is within tolerance


def test_units_guess_from_organ_size():
    assert plausible_units(6.5) == [("cm", 0.01)]  # the SOFA liver's 6.5 units
    assert plausible_units(190.0) == [("mm", 0.001)]
    assert plausible_units(0.15) == [("m", 1.0)]
    assert plausible_units(5000.0) == []
    # the bundled airway in millimetres (16.5 units): an airway segment in mm, or a kidney in cm
    assert plausible_units(16.5) == [("cm", 0.01), ("mm", 0.001)]


def test_a_millimetre_mesh_read_as_centimetres_is_told_to_check_mesh_scale_not_mesh_pose(tmp_path):
    """10x too large and away from the origin: within the size factor, but not overlapping the
    clouds; at a tenth of the scale (about the mesh frame's origin, mesh_pose's position) it would."""
    liver = load_mesh(LIVER_FILE)
    pose = [0.02, -0.01, 0.0, 0.0, 0.0, 0.0, 1.0]
    lifted = write_plain(tmp_path / "lifted.vtu", liver.vertices * 30.0 + [0.0, 0.0, 150.0], liver.tetrahedra)
    cloud = top_view_cloud(load_mesh(lifted), metres_per_unit=0.001) + pose[:3]
    as_centimetres = prepare_mesh(lifted, lowest_vertices(liver), scale=0.01, pose=pose)
    with pytest.raises(PatientMeshError) as error:
        check_against_clouds(as_centimetres, [cloud], scale_origin=pose[:3])
    assert str(error.value).startswith("the clouds do not overlap the mesh, but would with mesh_scale 0.1 times its "
                                       "value: is mesh_scale right for the mesh file's units?")
    with pytest.raises(PatientMeshError, match="set mesh_pose"):  # without the origin: registration, as before
        check_against_clouds(as_centimetres, [cloud])
    check_against_clouds(prepare_mesh(lifted, lowest_vertices(liver), scale=0.001, pose=pose), [cloud],
                         scale_origin=pose[:3])


def test_a_fixed_box_or_plane_in_the_files_millimetres_fails_saying_what_it_would_select(tmp_path):
    box = structured_box_mesh((100.0, 60.0, 40.0), (5, 3, 2))  # millimetres
    path = write_plain(tmp_path / "mm.vtu", box.vertices + [0.0, 0.0, 50.0], box.tetrahedra)
    bottom = np.flatnonzero(box.vertices[:, 2] == 0.0)
    in_millimetres = Box((-1.0, -1.0, 49.0), (101.0, 61.0, 51.0))
    with pytest.raises(PatientMeshError) as error:
        prepare_mesh(path, FixedSelection(boxes=(in_millimetres,)), scale=0.001)
    message = str(error.value)
    assert "fixed_box selects no vertex of the mesh, which spans [0, 0, 0.05] to [0.1, 0.06, 0.09] m" in message
    assert f"read in the mesh file's units it would select {bottom.size}" in message
    assert message.endswith("e.g. [-0.001, -0.001, 0.049, 0.101, 0.061, 0.051]") and "\n" not in message
    in_metres = prepare_mesh(path, FixedSelection(boxes=(Box((-0.001, -0.001, 0.049), (0.101, 0.061, 0.051)),)),
                             scale=0.001)
    np.testing.assert_array_equal(in_metres.fixed_vertices, bottom)
    plane_in_millimetres = Plane((0.0, 0.0, 50.0), (0.0, 0.0, 1.0), 1.0)
    with pytest.raises(PatientMeshError, match=rf"fixed_plane selects no vertex .* it would select {bottom.size}: "):
        prepare_mesh(path, FixedSelection(planes=(plane_in_millimetres,)), scale=0.001)
    everything = Box((-1e3, -1e3, -1e3), (1e3, 1e3, 1e3))
    with pytest.raises(PatientMeshError, match=f"fixed_box selects all {box.vertex_count} vertices of the mesh"):
        prepare_mesh(path, FixedSelection(indices=tuple(bottom), boxes=(everything,)), scale=0.001)


def test_simulatable_check_names_inverted_elements_and_a_fully_fixed_mesh():
    box = structured_box_mesh((0.1, 0.1, 0.1), (2, 2, 2))
    held = box.with_fixed(np.flatnonzero(box.vertices[:, 2] == 0.0))
    check_simulatable(held)
    with pytest.raises(PatientMeshError, match="^48 of 48 tetrahedra are flat or inverted$"):
        check_simulatable(held.with_vertices(box.vertices * [1.0, 1.0, -1.0]))
    with pytest.raises(PatientMeshError, match="^all 27 vertices are fixed: nothing is left to deform$"):
        check_simulatable(box.with_fixed(np.arange(27)))
