"""SparseCholesky: CHOLMOD factor with the symbolic analysis kept across numeric refactors."""

import sys
import threading
import time

import numpy as np
import pytest
import scipy.sparse

from offline_helpers import box_stiffness

from meshfg_ros.core.physics.fem import ElasticModel
from meshfg_ros.synthetic.meshing import box_mesh
from meshfg_ros.core.solvers.sparse_cholesky import NotPositiveDefiniteError
from meshfg_ros.core.solvers import cholmod_without_gil, sparse_cholesky
from meshfg_ros.core.solvers.sparse_cholesky import SparseCholesky, nested_dissection


@pytest.fixture(scope="module")
def stiffness():
    return box_stiffness(125)


def test_solves_vectors_and_matrices(stiffness):
    rng = np.random.default_rng(0)
    factor = SparseCholesky(stiffness)
    dense = stiffness.toarray()
    vector = rng.normal(size=stiffness.shape[0])
    columns = rng.normal(size=(stiffness.shape[0], 4))
    np.testing.assert_allclose(factor.solve(vector), np.linalg.solve(dense, vector), rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(factor.solve(columns), np.linalg.solve(dense, columns), rtol=1e-9, atol=1e-12)
    assert factor.solve(columns).shape == columns.shape


def test_forward_and_back_solves_are_the_halves_of_a_solve(stiffness):
    """forward_solve is L^-1 P and back_solve P^T L^-T, for A = P^T L L^T P: together a solve, the
    Gram matrix of forward-solved columns B^T A^-1 B, and forward_solve(A back_solve(z)) = z;
    one column or several (the multi-column path), sparse unit columns and zero columns too."""
    rng = np.random.default_rng(5)
    factor = SparseCholesky(stiffness)
    dense = stiffness.toarray()
    size = stiffness.shape[0]
    vector = rng.normal(size=size)
    columns = rng.normal(size=(size, 3))
    units = np.zeros((size, 4))
    units[[3, 4, 5, 200], np.arange(4)] = 1.0
    units[:, 3] = 0.0  # a zero column
    for rhs in (vector, columns, units):
        halves = factor.forward_solve(rhs)
        assert halves.shape == rhs.shape
        expected = np.linalg.solve(dense, rhs)
        np.testing.assert_allclose(factor.back_solve(halves), expected, rtol=0, atol=1e-10 * np.abs(expected).max())
        np.testing.assert_allclose(factor.forward_solve(dense @ factor.back_solve(rhs)), rhs, rtol=0, atol=1e-10)
    gram = factor.forward_solve(columns).T @ factor.forward_solve(columns)
    np.testing.assert_allclose(gram, columns.T @ np.linalg.solve(dense, columns), rtol=1e-9)
    assert not np.allclose(factor.forward_solve(columns), np.linalg.solve(dense, columns), rtol=1e-3)  # a half only
    np.testing.assert_array_equal(factor.forward_solve(units)[:, 3], 0.0)
    with pytest.raises(ValueError, match="rows"):
        factor.forward_solve(vector[:-1])


def test_refactor_uses_the_new_values(stiffness):
    rng = np.random.default_rng(1)
    factor = SparseCholesky(stiffness)
    scaled = stiffness.copy()
    scaled.data = scaled.data * 3.0
    scaled.data[scaled.indices == np.repeat(np.arange(scaled.shape[0]), np.diff(scaled.indptr))] += 5.0
    assert factor.same_pattern(scaled)
    factor.refactor(scaled.data)
    rhs = rng.normal(size=stiffness.shape[0])
    solution = factor.solve(rhs)
    np.testing.assert_allclose(scaled @ solution, rhs, rtol=1e-9, atol=1e-9)
    assert np.linalg.norm(stiffness @ solution - rhs) > 0.5 * np.linalg.norm(rhs)  # not the old factor


@pytest.mark.parametrize("threads", ["1", "2"])
def test_a_refactor_beside_the_caller_counts_at_once_and_gives_the_new_values(stiffness, monkeypatch, threads):
    """refactor_beside raises the revision before it returns (work queued behind it is judged
    against its values), factors on the background thread (or at once on one worker thread),
    and the factor then solves with the new values; non-finite values are refused at once and
    leave the last good factor."""
    monkeypatch.setenv("MESHFG_WORKER_THREADS", threads)
    rng = np.random.default_rng(7)
    factor = SparseCholesky(stiffness)
    revision = factor.revision
    tripled = 3.0 * stiffness.data
    done = factor.refactor_beside(tripled)
    assert factor.revision == revision + 1
    assert done.result() is None
    rhs = rng.normal(size=stiffness.shape[0])
    np.testing.assert_allclose(3.0 * (stiffness @ factor.solve(rhs)), rhs, rtol=1e-9, atol=1e-9)
    data = stiffness.data.copy()
    data[3] = np.inf
    with pytest.raises(NotPositiveDefiniteError, match="non-finite"):
        factor.refactor_beside(data)
    assert factor.revision == revision + 1
    np.testing.assert_allclose(3.0 * (stiffness @ factor.solve(rhs)), rhs, rtol=1e-9, atol=1e-9)


def test_sibling_factors_its_own_values_and_leaves_the_original(stiffness):
    rng = np.random.default_rng(2)
    factor = SparseCholesky(stiffness)
    doubled = stiffness.copy()
    doubled.data = doubled.data * 2.0
    twin = factor.sibling(doubled.data)
    rhs = rng.normal(size=stiffness.shape[0])
    np.testing.assert_allclose(doubled @ twin.solve(rhs), rhs, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(stiffness @ factor.solve(rhs), rhs, rtol=1e-9, atol=1e-9)
    twin.refactor(3.0 * stiffness.data)  # refactoring one leaves the other's values alone
    np.testing.assert_allclose(3.0 * (stiffness @ twin.solve(rhs)), rhs, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(stiffness @ factor.solve(rhs), rhs, rtol=1e-9, atol=1e-9)
    assert twin.same_pattern(stiffness)


def test_reads_only_the_lower_triangle(stiffness):
    lower_only = scipy.sparse.tril(stiffness).tocsr()
    rhs = np.arange(stiffness.shape[0], dtype=float)
    np.testing.assert_allclose(SparseCholesky(lower_only).solve(rhs), SparseCholesky(stiffness).solve(rhs),
                               rtol=1e-12, atol=0.0)


def test_indefinite_and_non_finite_matrices_are_rejected(stiffness):
    indefinite = (stiffness - 2.0 * stiffness.diagonal().max() * scipy.sparse.identity(stiffness.shape[0])).tocsr()
    with pytest.raises(NotPositiveDefiniteError, match="not positive"):
        SparseCholesky(indefinite)
    factor = SparseCholesky(stiffness)
    data = stiffness.data.copy()
    data[0] = np.nan
    with pytest.raises(NotPositiveDefiniteError, match="non-finite"):
        factor.refactor(data)
    vector = np.ones(stiffness.shape[0])
    np.testing.assert_allclose(stiffness @ factor.solve(vector), vector, rtol=1e-9)  # still the last good factor
    indefinite.sort_indices()
    with pytest.raises(NotPositiveDefiniteError, match="not positive"):
        factor.refactor(indefinite.data)
    for solve in (factor.solve, factor.forward_solve, factor.back_solve):  # never NaN from a failed factor
        with pytest.raises(NotPositiveDefiniteError, match="failed or was never made"):
            solve(vector)
    factor.refactor(stiffness.data)
    np.testing.assert_allclose(stiffness @ factor.solve(vector), vector, rtol=1e-9)
    with pytest.raises(NotPositiveDefiniteError, match="failed or was never made"):
        factor.sibling(None).solve(vector)  # its symbolic analysis only


def test_pattern_and_shape_checks(stiffness):
    factor = SparseCholesky(stiffness)
    other = scipy.sparse.identity(stiffness.shape[0], format="csr")
    assert not factor.same_pattern(other)
    with pytest.raises(ValueError, match="rows"):
        factor.solve(np.ones(3))
    with pytest.raises(ValueError, match="square"):
        SparseCholesky(scipy.sparse.csr_matrix(np.ones((2, 3))))


def test_nested_dissection_keeps_vertex_dofs_together(stiffness, monkeypatch):
    assert nested_dissection(stiffness, node_size=3) is None  # 125 vertices: below the threshold
    monkeypatch.setattr(sparse_cholesky, "NESTED_DISSECTION_MIN_NODES", 100)
    order = nested_dissection(stiffness, node_size=3)
    np.testing.assert_array_equal(np.sort(order), np.arange(stiffness.shape[0]))
    triples = order.reshape(-1, 3)
    assert np.all(triples[:, 0] % 3 == 0) and np.all(np.diff(triples, axis=1) == 1)
    assert nested_dissection(stiffness[:-1, :-1], node_size=3) is None  # not whole vertices
    # The ordered factor solves, from both triangles or the lower one (METIS needs the
    # symmetrised graph: one triangle alone crashed it).
    rng = np.random.default_rng(2)
    rhs = rng.normal(size=stiffness.shape[0])
    expected = np.linalg.solve(stiffness.toarray(), rhs)
    for matrix in (stiffness, scipy.sparse.tril(stiffness).tocsr()):
        np.testing.assert_allclose(SparseCholesky(matrix, node_size=3).solve(rhs), expected, rtol=1e-9, atol=1e-12)


def test_nested_dissection_fills_less_than_amd():
    """The reason for ordering by METIS: less fill than CHOLMOD's own AMD on a tet mesh."""
    from cvxopt import cholmod

    mesh = box_mesh(1331, (0.1, 0.1, 0.1))
    matrix = ElasticModel(mesh.vertices, mesh.tetrahedra, 3e3, 0.45).stiffness(kind="linear")
    matrix = (matrix + 1e-2 * scipy.sparse.identity(matrix.shape[0])).tocsr()
    assert mesh.vertex_count >= sparse_cholesky.NESTED_DISSECTION_MIN_NODES
    metis = SparseCholesky(matrix, node_size=3)
    amd = SparseCholesky(matrix)  # node_size 1 on 3,993 dofs: METIS too, so force AMD below
    amd._factor = cholmod.symbolic(amd._matrix, uplo="L")
    amd.refactor(matrix.data)
    rhs = np.ones(matrix.shape[0])
    np.testing.assert_allclose(metis.solve(rhs), amd.solve(rhs), rtol=1e-8)
    # getfactor last: it converts the factor in place.
    fill_metis, fill_amd = (len(cholmod.getfactor(factor._factor)) for factor in (metis, amd))
    assert fill_metis < 0.9 * fill_amd


def _python_passes_during_a_factorisation(factor, data, module, name, monkeypatch) -> int:
    """Passes of a Python loop on this thread while another thread is inside module.name, the
    C factorisation `factor.refactor(data)` calls. Threads hand over the GIL only where one
    blocks or releases it (the switch interval set beyond the test's length; each pass sleeps
    for 0 s, so that the other takes the GIL back when its call returns), so a factorisation
    that holds the GIL leaves none."""
    entered, left = threading.Event(), threading.Event()
    original = getattr(module, name)

    def factorisation(*args):
        entered.set()
        try:
            return original(*args)
        finally:
            left.set()

    monkeypatch.setattr(module, name, factorisation)
    interval = sys.getswitchinterval()
    sys.setswitchinterval(100.0)
    try:
        refactoring = threading.Thread(target=factor.refactor, args=(data,))
        refactoring.start()
        entered.wait()
        passes = 0
        while not left.is_set():
            passes += 1
            time.sleep(0.0)
        refactoring.join()
    finally:
        sys.setswitchinterval(interval)
        monkeypatch.setattr(module, name, original)
    return passes


def test_refactor_without_the_gil_matches_cvxopts_and_lets_python_run(monkeypatch):
    """Refactored through cholmod_without_gil (CHOLMOD's factorisation without the GIL), a factor
    solves as one refactored through cvxopt does, and another thread runs Python meanwhile,
    which cvxopt's factorisation does not let it."""
    if not cholmod_without_gil.available():
        pytest.skip("CHOLMOD cannot be bound here: refactors go through cvxopt")
    import cvxopt.cholmod

    stiffness = box_stiffness(3000)
    vector = np.random.default_rng(2).normal(size=stiffness.shape[0])
    factor = SparseCholesky(stiffness, node_size=3, numeric=False)
    assert _python_passes_during_a_factorisation(factor, stiffness.data, cholmod_without_gil, "factorize",
                                                 monkeypatch) > 0
    solution = factor.solve(vector)
    monkeypatch.setattr(cholmod_without_gil, "available", lambda: False)
    through_cvxopt = SparseCholesky(stiffness, node_size=3)
    assert _python_passes_during_a_factorisation(through_cvxopt, stiffness.data, cvxopt.cholmod, "numeric",
                                                 monkeypatch) == 0
    np.testing.assert_allclose(solution, through_cvxopt.solve(vector), rtol=1e-12, atol=0)
    np.testing.assert_allclose(stiffness @ solution, vector, rtol=1e-9)


def test_a_refactor_waits_for_the_solves_reading_the_factor(stiffness):
    """A refactor begun while another thread reads the factor (`reading`) starts once the
    reading ends, and counts in `revision`."""
    factor = SparseCholesky(stiffness)
    revision = factor.revision
    refactored = threading.Event()

    def refactor():
        factor.refactor(2.0 * stiffness.data)
        refactored.set()

    with factor.reading():
        refactoring = threading.Thread(target=refactor)
        refactoring.start()
        assert not refactored.wait(0.5)  # a few milliseconds' work, held back
        assert factor.revision == revision
    refactoring.join()
    assert factor.revision == revision + 1
    vector = np.ones(stiffness.shape[0])
    np.testing.assert_allclose(2.0 * (stiffness @ factor.solve(vector)), vector, rtol=1e-9)
