"""An external simulator's state and stiffness as the estimator's prior (core/physics/external_prior.py):
the checks of an answer, the frame change, the information made of an indefinite, asymmetric
stiffness with held dofs, and the estimator's use of it (the same estimate as its own K when it
is given its own K)."""
import numpy as np
import pytest
import scipy.sparse
from scipy.spatial.transform import Rotation

from meshfg_ros.core.estimation.estimator import EstimatorConfig, SlidingWindowEstimator
from meshfg_ros.core.physics.external_prior import (
    FIXED_DIAGONAL,
    REPAIR_SHIFTS,
    BridgeAnswer,
    ExternalPriorError,
    ExternalStiffness,
    bridge_state,
)
from meshfg_ros.core.physics.fem import ElasticModel
from meshfg_ros.synthetic.meshing import cube_mesh

SIDE = 0.05


@pytest.fixture(scope="module")
def mesh():
    mesh = cube_mesh(side=SIDE, divisions=3)
    return mesh.with_fixed(np.flatnonzero(np.isclose(mesh.vertices[:, 2], 0.0)))


@pytest.fixture(scope="module")
def model(mesh):
    return ElasticModel(mesh.vertices, mesh.tetrahedra, 3000.0, 0.45)


def answer_of(mesh, positions=None, stiffness=None, **changes):
    positions = mesh.vertices if positions is None else positions
    fields = dict(positions=positions.reshape(-1), valid_vertex_count=mesh.vertex_count,
                  invalid_vertices=np.zeros(0, np.int32), elements=mesh.tetrahedra[:, ::-1].reshape(-1),
                  invalid_elements=np.zeros(0, np.int32), stiffness=stiffness)
    fields.update(changes)
    return BridgeAnswer(**fields)


def coo(matrix):
    matrix = scipy.sparse.coo_matrix(matrix)
    return matrix.row, matrix.col, matrix.data.astype(np.float32), matrix.shape


def free_dofs(mesh):
    free = np.setdiff1d(np.arange(mesh.vertex_count), mesh.fixed_vertices)
    return (3 * free[:, None] + np.arange(3)).reshape(-1)


def test_positions_and_stiffness_are_moved_into_the_world_frame(mesh, model):
    rotation = Rotation.from_euler("xyz", [0.3, -0.2, 1.1]).as_matrix()
    to_world = np.eye(4)
    to_world[:3, :3], to_world[:3, 3] = rotation, [0.1, -0.2, 0.3]
    stiffness = model.stiffness(None, kind="linear")
    positions, external, removed = bridge_state(answer_of(mesh, stiffness=coo(stiffness)), mesh, to_world)
    assert removed is None
    np.testing.assert_allclose(positions, mesh.vertices @ rotation.T + [0.1, -0.2, 0.3], atol=1e-12)
    blocks = scipy.sparse.kron(scipy.sparse.identity(mesh.vertex_count), rotation).toarray()
    sent = stiffness.toarray().astype(np.float32).astype(np.float64)
    expected = blocks @ sent @ blocks.T
    got = scipy.sparse.coo_matrix((external.values, (external.rows, external.cols)), shape=expected.shape).toarray()
    np.testing.assert_allclose(got, expected, atol=1e-9 * np.abs(expected).max())


@pytest.mark.parametrize("changes, counter, words", [
    ({"positions": np.zeros(3 * 10)}, "sim_bridge_rejected_mesh", "10 vertex slots"),
    ({"invalid_elements": np.array([3, 999], np.int32)}, "sim_bridge_rejected_malformed", "outside"),
    ({"invalid_vertices": np.array([3], np.int32)}, "sim_bridge_rejected_malformed", "vertex size 64"),
    ({"elements": np.arange(8)}, "sim_bridge_rejected_mesh", "2 element slots, the initial mesh 162"),
    ({"elements": np.concatenate([[0, 1, 2, 63], np.zeros(4 * 161, int)])}, "sim_bridge_rejected_mesh",
     "not those of the initial mesh"),
    ({"stiffness": (np.array([0]), np.array([0]), np.array([1.0]), (3, 3))}, "sim_bridge_rejected_malformed",
     "expected"),
    ({"stiffness": (np.array([0, 1]), np.array([0]), np.array([1.0]), None)}, "sim_bridge_rejected_malformed",
     "equal counts"),
])
def test_answers_that_do_not_fit_are_refused_with_the_reason(mesh, changes, counter, words):
    if "stiffness" in changes and changes["stiffness"][3] is None:
        size = 3 * mesh.vertex_count
        changes["stiffness"] = (*changes["stiffness"][:3], (size, size))
    with pytest.raises(ExternalPriorError, match=words) as error:
        bridge_state(answer_of(mesh, **changes), mesh, np.eye(4))
    assert error.value.counter == counter


def test_a_cut_comes_as_the_mesh_own_element_slots_and_removed_vertices_are_held(mesh):
    # The simulator's slots in another order than the mesh's: slot k of the answer is mesh slot order[k].
    order = np.random.default_rng(5).permutation(len(mesh.tetrahedra))
    corner = 0  # a corner vertex of the cube: removing its elements leaves it without one
    around = np.flatnonzero((mesh.tetrahedra == corner).any(axis=1))
    theirs = np.flatnonzero(np.isin(order, around))
    positions = mesh.vertices.copy()
    positions[corner] = np.nan  # a removed vertex's slot may hold anything
    answer = answer_of(mesh, positions, elements=mesh.tetrahedra[order].reshape(-1), invalid_elements=theirs,
                       invalid_vertices=np.array([corner]), valid_vertex_count=mesh.vertex_count - 1)
    world, _, removed = bridge_state(answer, mesh, np.eye(4))
    np.testing.assert_array_equal(removed, np.sort(around))
    assert np.isfinite(world).all() and np.array_equal(world[corner], mesh.vertices[corner])
    cut = mesh.without_elements(removed)
    assert corner in cut.invalid_vertices and len(cut.tetrahedra) == len(mesh.tetrahedra) - len(around)
    still_used = answer_of(mesh, positions, invalid_vertices=np.array([corner]),
                           valid_vertex_count=mesh.vertex_count - 1)
    with pytest.raises(ExternalPriorError, match="remaining elements use"):
        bridge_state(still_used, mesh, np.eye(4))


def test_non_finite_answers_are_refused(mesh, model):
    positions = mesh.vertices.copy()
    positions[4, 1] = np.nan
    with pytest.raises(ExternalPriorError) as error:
        bridge_state(answer_of(mesh, positions), mesh, np.eye(4))
    assert error.value.counter == "sim_bridge_rejected_malformed"
    rows, cols, values, shape = coo(model.stiffness(None, kind="linear"))
    values[7] = np.inf
    with pytest.raises(ExternalPriorError, match="not all finite"):
        bridge_state(answer_of(mesh, stiffness=(rows, cols, values, shape)), mesh, np.eye(4))


def test_information_is_symmetric_definite_on_the_pattern_with_held_dofs_cleared(mesh, model):
    template = model.stiffness(None, kind="linear")
    stiffness = template.toarray()
    rng = np.random.default_rng(0)
    asymmetry = np.zeros_like(stiffness)
    on_pattern = stiffness != 0
    asymmetry[on_pattern] = rng.normal(scale=0.01 * np.abs(stiffness).max(), size=np.count_nonzero(on_pattern))
    given = stiffness + asymmetry
    held_vertex = int(np.flatnonzero(np.isclose(mesh.vertices[:, 2], SIDE))[5])  # free in the mesh
    held = 3 * held_vertex + np.arange(3)
    given[held, :] = given[:, held] = 0.0
    given[held, held] = 1e9
    far = (0, 3 * (mesh.vertex_count - 1))  # two corners of the cube: no shared element
    given[far], given[far[::-1]] = 5.0, 5.0
    information = ExternalStiffness(*coo(given)[:3]).information(template, free_dofs(mesh))
    matrix = information.matrix
    assert np.array_equal(matrix.indptr, template.indptr) and np.array_equal(matrix.indices, template.indices)
    dense = matrix.toarray()
    np.testing.assert_allclose(dense, dense.T)
    symmetric = 0.5 * (given + given.T)
    symmetric[far], symmetric[far[::-1]] = 0.0, 0.0
    free = free_dofs(mesh)
    others = np.setdiff1d(free, held)
    symmetric[held, held] = np.diag(symmetric)[others].max()  # held by the prior as the stiffest free dof
    shift = np.diag(dense)[others] - np.diag(symmetric)[others]
    np.testing.assert_allclose(dense - np.diag(np.diag(dense)), symmetric - np.diag(np.diag(symmetric)),
                               atol=1e-6 * np.abs(stiffness).max())
    np.testing.assert_allclose(shift, shift[0], atol=1e-6 * np.abs(stiffness).max())  # a uniform shift, if any
    assert "couples vertices sharing no element" in information.note
    assert "1 vertices the simulator holds are free in the mesh" in information.note
    assert np.abs(dense[np.ix_(held, others)]).max() == 0.0 and dense[held, held].max() < FIXED_DIAGONAL
    assert np.linalg.eigvalsh(dense[np.ix_(free, free)]).min() > 0.0


def test_a_slightly_indefinite_stiffness_is_shifted_a_strongly_indefinite_one_refused(mesh, model):
    template = model.stiffness(None, kind="linear")
    free = free_dofs(mesh)
    stiffness = template.toarray()
    lowest = np.linalg.eigvalsh(stiffness[np.ix_(free, free)]).min()
    mean_diagonal = np.mean(np.diag(stiffness)[free])
    slightly = stiffness - (lowest + 1e-3 * mean_diagonal) * np.eye(len(stiffness))  # lowest eigenvalue -1e-3 mean
    information = ExternalStiffness(*coo(slightly)[:3]).information(template, free)
    assert "made positive definite by a shift of 0.01" in information.note
    assert np.linalg.eigvalsh(information.matrix.toarray()[np.ix_(free, free)]).min() > 0.0
    with pytest.raises(ExternalPriorError, match=f"indefinite beyond a shift of {REPAIR_SHIFTS[-1]:g}") as error:
        strongly = stiffness - (lowest + 0.3 * mean_diagonal) * np.eye(len(stiffness))  # diagonal still positive
        ExternalStiffness(*coo(strongly)[:3]).information(template, free)
    assert error.value.counter == "sim_bridge_stiffness_rejected"


def _run(mesh, stiffness_for_step, steps=4):
    config = EstimatorConfig(stiffness_kind="linear", window_size=3)
    estimator = SlidingWindowEstimator(mesh, config)
    rng = np.random.default_rng(3)
    top = np.flatnonzero(np.isclose(mesh.vertices[:, 2], SIDE))
    estimates = []
    for step in range(1, steps + 1):
        predicted = mesh.vertices.copy()
        predicted[top, 2] -= 0.001 * step
        points = np.column_stack([rng.uniform(0.005, SIDE - 0.005, (200, 2)),
                                  SIDE - 0.0015 * step + rng.normal(scale=5e-4, size=200)])
        result = estimator.update(step * 100_000_000, points, predicted, None, None, stiffness_for_step(step))
        estimates.append(result.positions)
    return np.array(estimates)


def test_the_estimator_given_its_own_stiffness_estimates_as_with_its_model(mesh, model):
    own = _run(mesh, lambda step: None)
    template = model.stiffness(None, kind="linear")
    given = _run(mesh, lambda step: 7.0 * template)  # the scale does not matter: normalised like the model's
    np.testing.assert_allclose(given, own, atol=1e-9)
    softer_top = template.copy()  # on the model's pattern, as the hook requires
    rows = np.repeat(np.arange(template.shape[0]), np.diff(template.indptr))
    top = np.flatnonzero(mesh.vertices[:, 2] > 0.6 * SIDE)
    softer_top.data[np.isin(rows // 3, top) & np.isin(template.indices // 3, top)] *= 0.05
    other = _run(mesh, lambda step: softer_top)
    assert np.abs(other - own).max() > 1e-5


def test_a_cut_and_the_simulators_stiffness_reach_the_estimator_through_the_scheduler(mesh):
    from meshfg_ros.core.scheduler import EstimationScheduler, Prediction

    corner = int(np.flatnonzero(np.all(np.isclose(mesh.vertices, [SIDE, SIDE, SIDE]), axis=1))[0])
    around = np.flatnonzero((mesh.tetrahedra == corner).any(axis=1))
    keep = np.setdiff1d(np.arange(len(mesh.tetrahedra)), around)
    scheduler = EstimationScheduler(mesh, EstimatorConfig(window_size=3))
    rng = np.random.default_rng(2)
    for step in (1, 2, 3):
        cut = step >= 2
        positions = mesh.vertices.copy()
        positions[:, 2] -= 4e-4 * step * positions[:, 2] / SIDE
        elements = mesh.tetrahedra[keep] if cut else mesh.tetrahedra
        stiffness = ElasticModel(mesh.vertices, elements, 3000.0, 0.45).stiffness(positions, kind="corotational")
        answer = answer_of(mesh, positions, stiffness=coo(stiffness), invalid_elements=around if cut else np.zeros(0),
                           invalid_vertices=np.array([corner] if cut else [], dtype=np.int64),
                           valid_vertex_count=mesh.vertex_count - int(cut))
        world, external, removed = bridge_state(answer, mesh, np.eye(4))
        points = np.column_stack([rng.uniform(0.005, SIDE - 0.005, (300, 2)),
                                  SIDE - 4e-4 * step + rng.normal(scale=5e-4, size=300)])
        scheduler.add_cloud(step * 100_000_000, points)
        scheduler.add_prediction(Prediction(step * 100_000_000, world, stiffness=external, removed_elements=removed))
        outcome = scheduler.run(scheduler.next_step(0.0, flush=True))
        assert outcome.result is not None and not outcome.result.degraded, outcome.error
        assert not [note for note in outcome.notes if note.counter == "sim_bridge_stiffness_rejected"], outcome.notes
    assert len(scheduler.estimator.mesh.tetrahedra) == len(keep) and corner in scheduler.estimator.mesh.invalid_vertices
    valid = np.setdiff1d(np.arange(mesh.vertex_count), [corner])
    assert np.abs(outcome.result.positions[valid] - world[valid]).max() < 2e-3


def test_a_kept_projection_gives_what_a_fresh_one_gives_answer_after_answer(mesh, model):
    from meshfg_ros.core.physics.external_prior import StiffnessProjection

    template, free = model.stiffness(None, kind="linear"), free_dofs(mesh)
    projection = StiffnessProjection(template, free)
    stiffness = template.toarray()
    lowest = np.linalg.eigvalsh(stiffness[np.ix_(free, free)]).min()
    mean_diagonal = np.mean(np.diag(stiffness)[free])
    answers = [stiffness, stiffness - (lowest + 1e-3 * mean_diagonal) * np.eye(len(stiffness)), 2.0 * stiffness]
    for given in answers:
        external = ExternalStiffness(*coo(given)[:3])
        kept, fresh = projection.information(external), external.information(template, free)
        np.testing.assert_allclose(kept.matrix.toarray(), fresh.matrix.toarray(), rtol=1e-12, atol=0)
        assert kept.note == fresh.note
    assert "shift" in projection.information(ExternalStiffness(*coo(answers[1])[:3])).note
