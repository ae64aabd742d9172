"""Cuts (topology changes): the mesh after a cut keeps its indices, the simulator and the estimator
follow it, the published mesh says what was removed, and on a small cutting scene (a sheet under
tension cut mid-sequence, the wound pulled open by a pre-stress the model does not know) the
estimates follow the truth's topology from the cut's step on, none inverted, and beat the
simulation alone over the vertices left."""

import numpy as np
import pytest

from meshfg_ros.core.estimation.estimator import EstimatorConfig, EstimatorInputError, SlidingWindowEstimator
from meshfg_ros.core.geometry.mesh import InvalidMeshError, inverted_elements
from meshfg_ros.core.scheduler import OfflinePipeline, run_offline
from meshfg_ros.core.physics.simulator import ElasticSimulator, SimulatorConfig
from meshfg_ros.core.geometry.topology import cut_elements, detached_elements, elements_in_box
from meshfg_ros.evaluation.accuracy import scene_result
from meshfg_ros.io.messages import MeshState, mesh_state_from_msg, mesh_state_to_msg
from meshfg_ros.io.recording import RecordingReader
from meshfg_ros.replay import write_replay
from meshfg_ros.synthetic.cut_scene import build_cut_scene
from meshfg_ros.synthetic.meshing import cube_mesh
from meshfg_ros.synthetic.recordings import write_scenario
from meshfg_ros.topics import ESTIMATED_MESH_TOPIC, GROUND_TRUTH_TOPIC, REMOVE_ELEMENTS_TOPIC

SIDE = 0.03
TOOL_RADIUS = 4e-3


@pytest.fixture(scope="module")
def block():
    """A 30 mm cube held at its base."""
    mesh = cube_mesh(SIDE, 4)
    return mesh.with_fixed(np.flatnonzero(mesh.vertices[:, 2] < 1e-9))


@pytest.fixture(scope="module")
def wound(block):
    """A blade box 8 mm wide across the top half of the cube, off its middle."""
    return cut_elements(block, [0.0075, SIDE / 2, 0.022], [0.004, 0.01, 0.008])


def test_a_cut_keeps_indices_makes_the_wound_surface_and_invalidates_vertices_left_alone(block, wound):
    cut = block.without_elements(wound)
    kept = np.setdiff1d(np.arange(block.tetrahedron_count), wound)
    np.testing.assert_array_equal(cut.vertices, block.vertices)  # the same vertex rows
    np.testing.assert_array_equal(cut.tetrahedra, block.tetrahedra[kept])  # the others, in slot order
    np.testing.assert_array_equal(cut.all_tetrahedra, block.tetrahedra)
    np.testing.assert_array_equal(cut.removed_elements, wound)
    used = np.unique(cut.tetrahedra)
    np.testing.assert_array_equal(cut.invalid_vertices, np.setdiff1d(np.arange(block.vertex_count), used))
    assert cut.invalid_vertices.size  # the blade box holds whole vertices' neighbourhoods
    assert set(cut.invalid_vertices) <= set(cut.fixed_vertices)  # held, not estimated
    np.testing.assert_array_equal(cut.boundary_vertices, block.fixed_vertices)
    # The wound's faces are surface: faces of removed elements shared with kept ones.
    kept_faces = {tuple(sorted(face)) for face in cut.surface_triangles.tolist()}
    removed_faces = {tuple(sorted(face)) for tet in block.tetrahedra[wound].tolist()
                     for face in ([tet[1], tet[2], tet[3]], [tet[0], tet[2], tet[3]], [tet[0], tet[1], tet[3]],
                                  [tet[0], tet[1], tet[2]])}
    uncut_faces = {tuple(sorted(face)) for face in block.surface_triangles.tolist()}
    assert (removed_faces & kept_faces) - uncut_faces  # new surface inside the body
    assert not set(cut.invalid_vertices) & (set(cut.surface_vertices) | set(cut.internal_vertices))
    # Outward orientation: the cut body's surface encloses its remaining volume.
    corners = cut.vertices[cut.surface_triangles]
    enclosed = np.einsum("ij,ij->i", corners[:, 0], np.cross(corners[:, 1], corners[:, 2])).sum() / 6.0
    assert enclosed == pytest.approx(cut.volume(), rel=1e-9)
    # Cuts compose, by slots of the uncut mesh.
    first, second = wound[: wound.size // 2], wound[wound.size // 2:]
    np.testing.assert_array_equal(block.without_elements(first).without_elements(second).tetrahedra, cut.tetrahedra)
    assert cut.without_elements(wound[:3]) is cut
    with pytest.raises(InvalidMeshError, match="out of range"):
        block.without_elements([block.tetrahedron_count])
    with pytest.raises(InvalidMeshError, match="every element"):
        block.without_elements(np.arange(block.tetrahedron_count))


def test_a_blade_takes_the_pieces_it_leaves_hanging():
    mesh = cube_mesh(SIDE, 4)
    held = mesh.vertices
    mesh = mesh.with_fixed(np.flatnonzero((held[:, 2] < 1e-9) & (held[:, 0] > SIDE / 2)))  # base, right half
    centre, half = [0.009, SIDE / 2, SIDE / 2], [0.0, SIDE, SIDE]  # a plane through the whole cube
    in_box = elements_in_box(mesh, centre, half)
    crossing = mesh.vertices[mesh.tetrahedra][:, :, 0]
    np.testing.assert_array_equal(in_box, np.flatnonzero((crossing.min(axis=1) <= 0.009)
                                                         & (crossing.max(axis=1) >= 0.009)))
    hanging = detached_elements(mesh.without_elements(in_box))
    # the piece left of the plane holds no fixed vertex: it fell off
    np.testing.assert_array_equal(hanging, np.flatnonzero(crossing.max(axis=1) < 0.009))
    removed = cut_elements(mesh, centre, half)
    np.testing.assert_array_equal(removed, np.union1d(in_box, hanging))
    np.testing.assert_array_equal(detached_elements(mesh.without_elements(removed)), [])
    simulator = ElasticSimulator(mesh, SimulatorConfig(tool_radius=TOOL_RADIUS))
    with pytest.raises(ValueError, match="not positive"):  # rigid modes: the simulator refuses, unchanged
        simulator.remove_elements(in_box)
    assert simulator.rest_mesh is mesh
    assert simulator.remove_elements(removed) and simulator.rest_mesh.removed_elements.size == removed.size


def test_simulator_and_estimator_follow_a_cut_and_never_estimate_a_removed_vertex(block, wound):
    config = SimulatorConfig(tool_radius=TOOL_RADIUS)
    simulator = ElasticSimulator(block, config)
    estimator = SlidingWindowEstimator(block, EstimatorConfig(tool_radius=TOOL_RADIUS))
    tool = np.array([0.02, 0.015, SIDE + TOOL_RADIUS, 0.0, 0.0, 0.0, 1.0])
    simulator.reset(tool)
    rng = np.random.default_rng(0)
    state = block.vertices.copy()
    for step in range(1, 6):
        if step == 3:
            assert simulator.remove_elements(wound) and estimator.remove_elements(wound)
            assert not estimator.remove_elements(wound)  # the same slots again: nothing changes
            invalid = estimator.mesh.invalid_vertices
            held = state[invalid].copy()
        tool = tool - np.array([0, 0, 5e-4, 0, 0, 0, 0])
        predicted = simulator.predict(state, tool, 1.0)
        truth = predicted + np.array([0.0, 0.0, 3e-4])  # the tissue sits higher than predicted
        truth[estimator.mesh.fixed_vertices] = predicted[estimator.mesh.fixed_vertices]
        surface = estimator.mesh.surface_vertices
        points = truth[surface] + rng.normal(0.0, 2e-4, (surface.size, 3))
        result = estimator.update(step * 10**9, points, predicted, tool)
        state = result.positions
        assert inverted_elements(state, estimator.mesh.tetrahedra).size == 0
        if step >= 3:
            assert result.window_size == step - 2  # the window restarted at the cut
            np.testing.assert_array_equal(estimator.mesh.removed_elements, wound)
            np.testing.assert_array_equal(state[invalid], held)  # not estimated: held where they were
            assert np.all(result.position_std[invalid] == 0.0)
            free = np.setdiff1d(np.arange(block.vertex_count), estimator.mesh.fixed_vertices)
            assert np.all(result.position_std[free] > 0.0)
    # The points are projected on the cut surface, the prior is the remaining elements' stiffness.
    cut = block.without_elements(wound)
    np.testing.assert_array_equal(estimator.graph.surface_triangles, cut.surface_triangles)
    np.testing.assert_array_equal(estimator.model.tetrahedra, cut.tetrahedra)
    with pytest.raises(EstimatorInputError, match="removed_elements"):
        estimator.remove_elements([block.tetrahedron_count + 7])
    np.testing.assert_array_equal(estimator.mesh.removed_elements, wound)


def test_the_published_mesh_says_what_a_cut_removed_and_reads_back(block, wound):
    cut = block.without_elements(wound)
    state = MeshState.of_mesh(cut, 5, "world", 3)
    back = mesh_state_from_msg(mesh_state_to_msg(state))
    np.testing.assert_array_equal(back.tetrahedra, cut.tetrahedra)
    np.testing.assert_array_equal(back.surface_triangles, cut.surface_triangles)
    np.testing.assert_array_equal(back.invalid_vertices, cut.invalid_vertices)
    np.testing.assert_array_equal(back.removed_elements, wound)
    np.testing.assert_array_equal(back.fixed_vertices, block.fixed_vertices)  # the boundary condition only
    uncut = mesh_state_from_msg(mesh_state_to_msg(MeshState.of_mesh(block, 5, "world", 0)))
    assert uncut.invalid_vertices.size == uncut.removed_elements.size == 0
    with pytest.raises(ValueError, match="invalid vertex"):
        MeshState(5, "world", 0, cut.vertices, block.tetrahedra, invalid_vertices=cut.invalid_vertices)


def test_the_offline_pipeline_carries_a_cut_from_the_simulator_to_the_estimator(block, wound):
    pipeline = OfflinePipeline(block, SimulatorConfig(tool_radius=TOOL_RADIUS),
                               EstimatorConfig(tool_radius=TOOL_RADIUS))
    tool = np.array([0.02, 0.015, SIDE + TOOL_RADIUS, 0.0, 0.0, 0.0, 1.0])
    top = block.vertices[block.surface_vertices]
    events = [("pose", 10**9, tool)]
    for step in range(2, 6):
        events.append(("pose", step * 10**9, tool - [0, 0, 4e-4 * step, 0, 0, 0, 0]))
        if step == 4:
            events.append(("cut", step * 10**9, wound))
        events.append(("cloud", step * 10**9, top))
    steps = list(run_offline(pipeline, iter(events)))
    assert [step.stamp_ns for step in steps] == [2 * 10**9, 3 * 10**9, 4 * 10**9, 5 * 10**9]
    for step in steps:
        expected = wound if step.stamp_ns >= 4 * 10**9 else []
        np.testing.assert_array_equal(step.mesh.removed_elements, expected)
    invalid = steps[-1].mesh.invalid_vertices
    np.testing.assert_array_equal(steps[-1].result.positions[invalid], steps[1].result.positions[invalid])


@pytest.fixture(scope="module")
def cut_replay(tmp_path_factory):
    """A small sheet-cut scene (coarse mesh, six steps, cut at the fourth), recorded and replayed."""
    folder = tmp_path_factory.mktemp("cut")
    write_scenario(build_cut_scene(seed=0, steps=6, mesh_size=4.5e-3), folder / "scene")
    write_replay(folder / "scene", folder / "replay")
    return folder / "scene", folder / "replay"


def test_the_estimates_follow_the_cut_and_beat_the_simulation_alone_over_the_vertices_left(cut_replay):
    recording, replay = cut_replay
    with RecordingReader(recording) as reader:
        truths = list(reader.records(GROUND_TRUTH_TOPIC, MeshState))
        requests = [message.data.data for message in reader.messages([REMOVE_ELEMENTS_TOPIC])]
    with RecordingReader(replay) as reader:
        estimates = {state.stamp_ns: state for state in reader.records(ESTIMATED_MESH_TOPIC, MeshState)}
    assert len(requests) == 1 and len(requests[0])  # one cut, requested at its step
    cut_stamps = [truth.stamp_ns for truth in truths if truth.removed_elements.size]
    assert len(cut_stamps) == 3 and len(estimates) == 6
    for truth in truths[1:]:
        estimate = estimates[truth.stamp_ns]
        np.testing.assert_array_equal(estimate.removed_elements, truth.removed_elements)
        np.testing.assert_array_equal(estimate.tetrahedra, truth.tetrahedra)
        np.testing.assert_array_equal(estimate.surface_triangles, truth.surface_triangles)
        np.testing.assert_array_equal(estimate.invalid_vertices, truth.invalid_vertices)
        assert inverted_elements(estimate.positions, estimate.tetrahedra).size == 0
        if truth.invalid_vertices.size:  # a removed vertex is neither estimated nor drawn
            assert np.all(estimate.position_std[truth.invalid_vertices] == 0.0)
            assert not np.isin(estimate.surface_triangles, truth.invalid_vertices).any()
    assert truths[-1].invalid_vertices.size
    row = scene_result("sheet-cut", recording, replay, 0.0)
    assert row["cut_steps"] == 3 and row["topology_mismatches"] == 0 and row["inverted_elements"] == 0
    assert row["ratio_all_final"] <= 0.8
    assert row["ratio_unobserved_external_final"] <= 0.8
