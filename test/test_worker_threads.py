"""Work split over the worker threads (core/worker_threads.py) gives what one thread gives: the
CHOLMOD solves without the GIL, the window's products, the association, the element kernels and
a whole estimator update."""

import threading
import time

import numpy as np
import pytest
from offline_helpers import box_stiffness

import meshfg_ros.core.worker_threads as worker_threads
from meshfg_ros.core.estimation import factor_graph, factors
from meshfg_ros.core.estimation.estimator import EstimatorConfig, SlidingWindowEstimator
from meshfg_ros.core.geometry import closest_point, mesh as mesh_module
from meshfg_ros.core.geometry.closest_point import ClosestPointIndex
from meshfg_ros.core.solvers import cholmod_without_gil, linear_system, sparse_cholesky
from meshfg_ros.core.solvers.linear_system import WindowSystem
from meshfg_ros.core.solvers.sparse_cholesky import SparseCholesky
from meshfg_ros.synthetic.meshing import box_mesh


@pytest.fixture
def two_threads(monkeypatch):
    """Two worker threads and every threshold at its least, so that the smallest test problem
    is split."""
    monkeypatch.setenv("MESHFG_WORKER_THREADS", "2")
    monkeypatch.setattr(sparse_cholesky, "PARALLEL_MIN_SIZE", 0)
    monkeypatch.setattr(linear_system, "PARALLEL_MIN_ENTRIES", 1)
    monkeypatch.setattr(closest_point, "PARALLEL_MIN_POINTS", 1)
    monkeypatch.setattr(mesh_module, "PARALLEL_MIN_ELEMENTS", 1)
    monkeypatch.setattr(factors, "PARALLEL_MIN_PRIOR_DOFS", 1)
    monkeypatch.setattr(factor_graph, "PARALLEL_MIN_LINEARIZATION_DOFS", 1)


@pytest.fixture(scope="module")
def stiffness():
    return box_stiffness(216)


def test_parts_run_at_once_on_two_threads_and_come_back_in_order(two_threads):
    both_started = threading.Barrier(2, timeout=5.0)  # only two threads at once can pass it

    def part(value):
        both_started.wait()
        return value, threading.get_ident()

    results = worker_threads.run_parts(part, [(1,), (2,)])
    assert [value for value, _ in results] == [1, 2]
    assert results[0][1] == threading.get_ident() != results[1][1]


def test_a_part_that_fails_is_raised_after_every_part_ended(two_threads):
    ended = []

    def part(fail):
        if fail:
            raise ValueError("the first part failed")
        time.sleep(0.05)
        ended.append(True)

    with pytest.raises(ValueError, match="first part failed"):
        worker_threads.run_parts(part, [(True,), (False,)])
    assert ended == [True]


def test_a_worker_splits_no_further_and_one_thread_splits_nothing(two_threads, monkeypatch):
    def inner(value):
        return threading.get_ident()

    def outer(value):
        return worker_threads.run_parts(inner, [(1,), (2,)])

    _, nested = worker_threads.run_parts(outer, [(0,), (1,)])
    assert nested[0] == nested[1]  # inline on the worker: no pool waits on itself
    monkeypatch.setenv("MESHFG_WORKER_THREADS", "1")
    assert worker_threads.split(list(range(5)), 4) == [[0, 1, 2, 3, 4]]


def test_background_work_runs_beside_the_caller_in_line_and_raises_at_its_result(two_threads, monkeypatch):
    """start_background: the function runs on a thread of its own while the caller goes on, its
    own splits run in line on that thread, and result() gives its value or raises its error;
    with one worker thread it runs on the calling thread, its error still raised by result()."""
    release = threading.Event()

    def work(value):
        release.wait(5.0)
        idents = worker_threads.run_parts(lambda part: threading.get_ident(), [(0,), (1,)])
        return value, threading.get_ident(), idents

    running = worker_threads.start_background(work, 7)
    release.set()  # the caller got here while the work waited: it runs beside the caller
    value, ident, idents = running.result()
    assert value == 7 and ident != threading.get_ident() and idents == [ident, ident]

    def fail():
        raise ValueError("the background work failed")

    with pytest.raises(ValueError, match="background work failed"):
        worker_threads.start_background(fail).result()
    monkeypatch.setenv("MESHFG_WORKER_THREADS", "1")  # one thread: now, on the caller's
    assert worker_threads.start_background(threading.get_ident).result() == threading.get_ident()
    failed = worker_threads.start_background(fail)  # raised by result(), not by the call
    with pytest.raises(ValueError, match="background work failed"):
        failed.result()


def test_a_forked_child_splits_on_a_pool_of_its_own(two_threads):
    import os
    import signal

    worker_threads.run_parts(lambda value: value, [(1,), (2,)])  # the parent's pool exists
    child = os.fork()
    if child == 0:  # the child: a split must not wait on the parent's threads
        signal.alarm(30)  # a child that hangs ends, and the test fails, instead of the suite hanging
        try:
            results = worker_threads.run_parts(lambda value: value * 2, [(1,), (2,)])
            os._exit(0 if results == [2, 4] else 1)
        finally:
            os._exit(2)
    _, status = os.waitpid(child, 0)
    assert os.WIFEXITED(status) and os.WEXITSTATUS(status) == 0


def test_thread_count_setting(monkeypatch):
    monkeypatch.delenv("MESHFG_WORKER_THREADS", raising=False)
    assert 1 <= worker_threads.count() <= worker_threads.DEFAULT_MAX_THREADS
    monkeypatch.setenv("MESHFG_WORKER_THREADS", "3")
    assert worker_threads.count() == 3
    assert worker_threads.split(list(range(7)), 5) == [[0, 1], [2, 3], [4, 5, 6]]
    for bad in ("0", "-1", "two"):
        monkeypatch.setenv("MESHFG_WORKER_THREADS", bad)
        with pytest.raises(worker_threads.WorkerThreadsSettingError, match="positive integer"):
            worker_threads.count()


def test_cholmod_solves_without_the_gil_equal_cvxopts(stiffness, two_threads, monkeypatch):
    assert cholmod_without_gil.available()
    rng = np.random.default_rng(3)
    columns = rng.normal(size=(stiffness.shape[0], 5))
    factor = SparseCholesky(stiffness, node_size=3)
    split = [factor.solve(columns), factor.forward_solve(columns), factor.back_solve(columns), factor.solve(columns[:, 0])]
    monkeypatch.setenv("MESHFG_WORKER_THREADS", "1")
    single = [factor.solve(columns), factor.forward_solve(columns), factor.back_solve(columns), factor.solve(columns[:, 0])]
    monkeypatch.setattr(cholmod_without_gil, "available", lambda: False)
    through_cvxopt = [factor.solve(columns), factor.forward_solve(columns), factor.back_solve(columns),
                      factor.solve(columns[:, 0])]
    expected = np.linalg.solve(stiffness.toarray(), columns)
    np.testing.assert_allclose(split[0], expected, rtol=1e-9, atol=1e-12 * np.abs(expected).max())
    for ours, theirs, one in zip(split, through_cvxopt, single):
        assert ours.shape == theirs.shape
        np.testing.assert_allclose(ours, theirs, rtol=1e-12, atol=1e-14 * np.abs(theirs).max())
        np.testing.assert_allclose(ours, one, rtol=1e-12, atol=1e-14 * np.abs(one).max())


def test_window_products_association_and_volumes_split_as_one_thread_gives(stiffness, two_threads, monkeypatch):
    rng = np.random.default_rng(4)
    size = stiffness.shape[0]
    blocks = [stiffness, 2.0 * stiffness, 3.0 * stiffness]
    system = WindowSystem(blocks, [0.5, 0.25], [0, 1, 2], linear_system.diagonal_positions(stiffness))
    x = rng.normal(size=3 * size)
    mesh = box_mesh(216, (0.1, 0.1, 0.1))
    surface = mesh.surface_triangles
    points = rng.uniform(-0.01, 0.11, size=(500, 3))
    states = np.stack([mesh.vertices, mesh.vertices + rng.normal(scale=1e-3, size=mesh.vertices.shape)])
    split = (system.matvec(x), ClosestPointIndex(mesh.vertices, surface).associate(points).triangle,
             mesh_module.signed_volumes(states, mesh.tetrahedra, longest_edges=True))
    monkeypatch.setenv("MESHFG_WORKER_THREADS", "1")
    single = (system.matvec(x), ClosestPointIndex(mesh.vertices, surface).associate(points).triangle,
              mesh_module.signed_volumes(states, mesh.tetrahedra, longest_edges=True))
    np.testing.assert_allclose(split[0], single[0], rtol=1e-13, atol=0)
    np.testing.assert_array_equal(split[1], single[1])
    for ours, one in zip(split[2], single[2]):
        np.testing.assert_array_equal(ours, one)


def test_an_estimator_update_split_over_two_threads_equals_one_threads(two_threads, monkeypatch):
    """The whole update (PCG with its block factors, the inversion guard, the priors, the
    association, the covariance draws) on two threads and on one: the same estimate."""
    box = box_mesh(343, (0.06, 0.06, 0.03))
    mesh = box.with_fixed(np.flatnonzero(box.vertices[:, 2] < 1e-9))
    rng = np.random.default_rng(6)
    surface_points = mesh.vertices[mesh.vertices[:, 2] > 0.029]

    def run():
        estimator = SlidingWindowEstimator(mesh, EstimatorConfig(window_size=3))
        outcomes = []
        for step in range(4):
            moved = mesh.vertices + np.array([0.0, 0.0, -1e-4 * step])
            points = surface_points + np.array([0.0, 0.0, -2e-4 * step]) + rng.normal(scale=5e-5, size=surface_points.shape)
            outcomes.append(estimator.update(step * 100_000_000, points, moved))
        return outcomes

    split = run()
    monkeypatch.setenv("MESHFG_WORKER_THREADS", "1")
    rng = np.random.default_rng(6)
    single = run()
    for ours, one in zip(split, single):
        assert ours.iterations == one.iterations
        np.testing.assert_allclose(ours.positions, one.positions, rtol=0, atol=1e-12)
        np.testing.assert_allclose(ours.position_std, one.position_std, rtol=1e-9, atol=1e-15)
    assert np.abs(split[-1].positions - mesh.vertices).max() > 1e-4  # the estimate moved with the data


def test_a_simulator_step_split_over_two_threads_equals_one_threads(two_threads, monkeypatch):
    """The vertex sweep's shares of a colour move as the whole colour does on one thread (the
    K0 solves, whose split columns differ in the last bits, kept on one thread here)."""
    from meshfg_ros.core.physics import simulator as simulator_module
    from meshfg_ros.core.physics.simulator import ElasticSimulator, SimulatorConfig
    from meshfg_ros.synthetic.scenarios import pose

    monkeypatch.setattr(simulator_module, "PARALLEL_MIN_INCIDENCES", 1)
    monkeypatch.setattr(sparse_cholesky, "PARALLEL_MIN_SIZE", 10**9)
    box = box_mesh(343, (0.05, 0.05, 0.05))
    mesh = box.with_fixed(np.flatnonzero(box.vertices[:, 2] < 1e-9))
    top = int(np.argmax(mesh.vertices[:, 2] + 1e-3 * mesh.vertices[:, 0]))
    start = mesh.vertices[top] + np.array([0.0, 0.0, 0.005])

    def predict():
        simulator = ElasticSimulator(mesh, SimulatorConfig(tool_radius=0.005))
        simulator.reset(pose(start))
        return simulator.predict(mesh.vertices, pose(start - np.array([0.0, 0.0, 0.004])), 1.0)

    split = predict()
    monkeypatch.setenv("MESHFG_WORKER_THREADS", "1")
    single = predict()
    np.testing.assert_array_equal(split, single)
    assert np.abs(split - mesh.vertices).max() > 1e-3  # the tool pushed the tissue


def test_a_linearisation_computes_its_factor_classes_side_by_side_as_one_thread_does(two_threads, monkeypatch):
    """The classes of a state's factors (physics prior; volume barrier and points) in one group
    per thread, and on one thread all on the calling thread: the same block values, gradient
    and cost to the bit (each class's terms are added in the same order)."""
    box = box_mesh(343, (0.06, 0.06, 0.03))
    mesh = box.with_fixed(np.flatnonzero(box.vertices[:, 2] < 1e-9))
    points = mesh.vertices[mesh.vertices[:, 2] > 0.029] + np.array([0.0, 0.0, -2e-4])
    estimator = SlidingWindowEstimator(mesh, EstimatorConfig(window_size=2))
    estimator.update(0, points, mesh.vertices + np.array([0.0, 0.0, -1e-4]))
    graph = estimator.graph
    key = graph.keys[-1]
    states = {key: graph.states[key] + 1e-5}
    threads = []
    original = factor_graph._linearize_classes

    def recording(groups, states_):
        threads.append((threading.current_thread().name, [factor_class.__name__ for factor_class, _ in groups]))
        return original(groups, states_)

    monkeypatch.setattr(factor_graph, "_linearize_classes", recording)
    split = graph._relinearize([key], states)[key]
    assert sorted(classes for _, classes in threads) == [
        ["PhysicsPriorFactor"], ["VolumeBarrierFactor", "PointToSurfaceFactor"]]
    assert len({name for name, _ in threads}) == 2
    threads.clear()
    monkeypatch.setenv("MESHFG_WORKER_THREADS", "1")
    single = graph._relinearize([key], states)[key]
    assert threads == [(threading.current_thread().name,
                        ["PhysicsPriorFactor", "VolumeBarrierFactor", "PointToSurfaceFactor"])]
    np.testing.assert_array_equal(split.data, single.data)
    np.testing.assert_array_equal(split.gradient, single.gradient)
    assert split.cost == single.cost and split.cost > 0.0
