"""`meshfg mesh info`, `meshfg mesh export` and `meshfg params`, run in-process through cli.main."""
import meshio
import numpy as np
import pytest
from offline_helpers import BAGS

from meshfg_ros import cli
from meshfg_ros.core.geometry.mesh import load_mesh, save_mesh
from meshfg_ros.io.messages import MeshState
from meshfg_ros.io.recording import RecordingReader
from meshfg_ros.parameters import read_parameters_file
from meshfg_ros.replay import load_inputs, replay_parameters, scenario_parameters
from meshfg_ros.synthetic.meshing import gmsh_model, structured_box_mesh
from meshfg_ros.synthetic.scenarios import LIVER_PATH_CANDIDATES
from meshfg_ros.topics import INITIAL_MESH_TOPIC

LIVER_FILE = next(path for path in LIVER_PATH_CANDIDATES if path.is_file())
RECORDINGS = ("cao-push", "liver-push")


def run(capsys, *argv) -> tuple[int, str, str]:
    code = cli.main(list(argv))
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def info_rows(output: str) -> dict[str, str]:
    rows = {}
    for line in output.splitlines()[1:]:
        label, _, text = line.strip().partition(":")
        rows[label] = text.strip()
    return rows


def test_mesh_info_of_the_sofa_liver(capsys):
    code, out, _ = run(capsys, "mesh", "info", str(LIVER_FILE))
    assert code == 0
    rows = info_rows(out)
    assert rows["vertices"] == "181"  # the SOFA liver, in centimetres
    assert rows["tetrahedra"].startswith("596 (surface: 276 triangles)")
    assert rows["bounding box"].startswith("6.483 x 4.939 x 4.421 (file units)")
    assert rows["units (guess)"].startswith("cm: the largest side is 0.0648 m at mesh_scale 0.01")
    assert rows["fixed vertices"] == "0 (point data 'fixed')"
    assert rows["groups"] == "none"


def test_mesh_info_lets_the_clouds_decide_between_two_plausible_units(capsys, tmp_path):
    """The bundled airway in millimetres (16.5 units across) is an organ's size in mm and in cm;
    the recording's clouds agree with millimetres only, and say why centimetres do not fit."""
    airway = load_inputs(BAGS / "cao-push").initial_mesh
    path = tmp_path / "airway_mm.vtu"
    save_mesh(airway.with_vertices(1e3 * airway.vertices), path)
    code, out, _ = run(capsys, "mesh", "info", str(path))
    rows = info_rows(out)
    assert code == 0 and rows["units (guess)"].startswith("cm: the largest side is 0.165 m at mesh_scale 0.01 or mm: "
                                                          "the largest side is 0.0165 m at mesh_scale 0.001")
    assert rows["units (guess)"].endswith("only the clouds tell which (--clouds BAG, or the estimator's check of its "
                                          "first clouds)")
    assert "units (clouds)" not in rows
    code, out, _ = run(capsys, "mesh", "info", str(path), "--clouds", str(BAGS / "cao-push"))
    rows = info_rows(out)
    assert code == 0 and rows["units (clouds)"].startswith("mm (mesh_scale 0.001) agrees with the first 3 clouds of ")
    assert ("cm: the clouds do not overlap the mesh, but would with mesh_scale 0.1 times its value"
            in rows["units (clouds)"])
    assert "m: the mesh is ~1100x larger than the clouds" in rows["units (clouds)"]


def test_mesh_info_quality_groups_and_fixed_vertices(capsys, tmp_path):
    """Kuhn tetrahedra of cubic cells: radius ratio 3 r_in / r_circ = 3 (1/2)/(1 + sqrt 2) / (sqrt 3 / 2)."""
    box = structured_box_mesh((0.1, 0.1, 0.1), (3, 3, 3))
    path = tmp_path / "box.msh"
    with gmsh_model("info", {}) as gmsh:  # a file with groups, written the way gmsh users write them
        gmsh.model.add("info")
        gmsh.model.addDiscreteEntity(3, 1)
        gmsh.model.mesh.addNodes(3, 1, np.arange(1, box.vertex_count + 1), box.vertices.reshape(-1))
        gmsh.model.mesh.addElementsByType(1, 4, [], (box.tetrahedra + 1).reshape(-1))
        gmsh.model.addPhysicalGroup(3, [1], name="tissue")
        gmsh.write(str(path))
    code, out, _ = run(capsys, "mesh", "info", str(path))
    assert code == 0
    rows = info_rows(out)
    kuhn = 3 * (0.5 / (1 + np.sqrt(2))) / (np.sqrt(3) / 2)
    assert rows["element quality"].startswith(f"radius ratio min {kuhn:.3f}, median {kuhn:.3f}")
    assert rows["units (guess)"].startswith("m: the largest side is 0.1 m at mesh_scale 1")
    assert rows["groups"] == "tissue (64 vertices)"
    meshio.write(tmp_path / "fixed.vtu", meshio.Mesh(box.vertices, [("tetra", box.tetrahedra)],
                                                     point_data={"fixed": (box.vertices[:, 2] == 0).astype(np.int32)}))
    assert info_rows(run(capsys, "mesh", "info", str(tmp_path / "fixed.vtu"))[1])["fixed vertices"].startswith("16 ")


def test_mesh_info_errors_are_one_line(capsys, tmp_path):
    code, out, err = run(capsys, "mesh", "info", str(tmp_path / "missing.msh"))
    assert (code, out) == (1, "")
    assert err == f"meshfg mesh: error: {tmp_path / 'missing.msh'} does not exist\n"
    meshio.write(tmp_path / "surface.vtu", meshio.Mesh(np.eye(3), [("triangle", np.array([[0, 1, 2]]))]))
    code, _, err = run(capsys, "mesh", "info", str(tmp_path / "surface.vtu"))
    assert code == 1 and err.endswith("is not a tetrahedral mesh (no tetra cells)\n") and err.count("\n") == 1


@pytest.mark.parametrize("recording", RECORDINGS)
@pytest.mark.parametrize("suffix", [".msh", ".vtu"])
def test_mesh_export_round_trips_through_load_mesh(capsys, tmp_path, recording, suffix):
    out = tmp_path / f"initial{suffix}"
    code, stdout, _ = run(capsys, "mesh", "export", str(BAGS / recording), "--out", str(out))
    assert code == 0 and stdout.startswith(f"wrote {out}: ")
    with RecordingReader(BAGS / recording) as reader:
        state = next(iter(reader.records(INITIAL_MESH_TOPIC, MeshState)))
    loaded = load_mesh(out)
    assert loaded.fixed_vertices.size > 0
    np.testing.assert_array_equal(loaded.vertices, state.positions)
    np.testing.assert_array_equal(loaded.tetrahedra, state.tetrahedra)
    np.testing.assert_array_equal(loaded.fixed_vertices, np.sort(state.fixed_vertices))
    assert loaded.flipped_count == 0


def test_mesh_export_never_overwrites(capsys, tmp_path):
    out = tmp_path / "initial.vtu"
    out.write_text("keep me")
    code, _, err = run(capsys, "mesh", "export", str(BAGS / "cao-push"), "--out", str(out))
    assert code == 1 and "File exists (never overwritten)" in err
    assert out.read_text() == "keep me"


@pytest.mark.parametrize("recording", RECORDINGS)
def test_params_file_gives_the_replay_parameters(capsys, tmp_path, recording):
    out = tmp_path / "params.yaml"
    code, stdout, _ = run(capsys, "params", str(BAGS / recording), "--out", str(out))
    assert (code, stdout) == (0, f"wrote {out}\n")
    expected = replay_parameters(load_inputs(BAGS / recording))
    assert read_parameters_file(out) == expected
    assert read_parameters_file(out, node_name="estimator_node") == expected
    code, printed, _ = run(capsys, "params", str(BAGS / recording))
    assert code == 0 and printed == out.read_text()


def test_params_differ_between_recordings(capsys, tmp_path):
    """The file carries each recording's own model: the test above would not pass on defaults."""
    files = {name: tmp_path / f"{name}.yaml" for name in RECORDINGS}
    for name, path in files.items():
        run(capsys, "params", str(BAGS / name), "--out", str(path))
    airway, liver = (read_parameters_file(files[name]) for name in RECORDINGS)
    assert airway["youngs_modulus"] != liver["youngs_modulus"] or airway["measurement_sigma"] != liver["measurement_sigma"]


@pytest.mark.slow  # a node of rclpy (DDS participant) parses the file as the live nodes do
@pytest.mark.parametrize("recording", RECORDINGS)
def test_params_file_through_rcl_as_the_nodes_read_it(capsys, tmp_path, recording):
    import rclpy
    from rclpy.context import Context

    from meshfg_ros.nodes.ros_parameters import declare_parameters

    out = tmp_path / "params.yaml"
    run(capsys, "params", str(BAGS / recording), "--out", str(out))
    context = Context()
    rclpy.init(args=["--ros-args", "--params-file", str(out)], context=context)
    values = {}
    try:
        for name in ("simulation_node", "estimator_node"):
            node = rclpy.create_node(name, context=context)
            values.update(declare_parameters(node, name))
            node.destroy_node()
    finally:
        rclpy.shutdown(context=context)
    inputs = load_inputs(BAGS / recording)
    replayed = replay_parameters(inputs)
    assert set(scenario_parameters(inputs.metadata, inputs.camera_pose)) <= set(values)
    assert values == {name: replayed[name] for name in values}
