"""The window's factor graph: states, factors and the normal equations LM solves.

`FactorGraph` holds the states of a window (in time order), their factors and the fixed
(boundary) vertices, and is the problem Levenberg-Marquardt solves: unknowns are the free
vertex coordinates of every state; fixed vertices are eliminated (held at their known
positions), which is exact and keeps the system well conditioned, unlike a stiff prior.
It owns the block sparsity pattern, the per-state relinearisation cache, the linearised
window system (linear_system.WindowSystem) and LM's inversion guard (`step_fraction`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np
import scipy.sparse
from numba.types import float64, int64

from meshfg_ros.core.estimation.factors import Factor, FactorError, FactorLinearization, checked_state
from meshfg_ros.core.geometry.kernel_types import read_only, writable
from meshfg_ros.core.solvers.linear_system import WindowSystem, diagonal_positions
import meshfg_ros.core.worker_threads as worker_threads
from meshfg_ros.core.geometry.mesh import DofPattern, ElementVolumes, cross3, dot3, element_ranges

__all__ = ["MIN_VOLUME_RATIO_PER_STEP", "FactorGraph"]

# LM's inversion guard: one step may shrink a tetrahedron to no less than this fraction of its
# volume (FactorGraph.step_fraction). A quarter leaves room for the real compression of tissue
# (volume ratios near 1: nearly incompressible) while no step can flatten or invert an element.
MIN_VOLUME_RATIO_PER_STEP = 0.25
# step_fraction brackets a volume's first crossing of the margin on this many equal fractions
# of the step, then bisects; the result is verified on exact volumes, halving if needed.
_STEP_FRACTION_GRID = 16
_STEP_FRACTION_BISECTIONS = 20
_STEP_FRACTION_HALVINGS = 30


@dataclass
class _StateLinearization:
    """Cached normal-equation terms of the single-state factors of one state at x_lin."""

    x_lin: np.ndarray        # (N, 3) linearisation point
    data: np.ndarray         # (nnz + 1,) block values on the pattern (last: sink)
    gradient: np.ndarray     # (3N,)
    cost: float
    block: scipy.sparse.csr_matrix | None = None  # block over the free dofs (for the model)
    revision: int = 0        # FactorGraph.relinearizations when it was made: names its values
    rebased: bool = False    # FactorGraph.gradient moved x_lin, cost, gradient; data is older
    model_at: tuple | None = None  # (state, cost, gradient) of the last model evaluation


# A linearisation's factor classes go to the worker threads side by side (FactorGraph._relinearize)
# from this many renewed unknowns: at organ scale (32k per state) the prior's stiffness takes
# about 45 ms beside the points' 20 ms; at paper scale (1.5k) the classes take about a millisecond
# each, and the hand-offs and the GIL that their Python parts contend for cost more than they save.
# Between, on boxes of the bench's kind (W=5, 20,000 points), three interleaved pairs of runs:
# 17.5k unknowns, update p95 356-390 ms side by side against 401-435 ms in turn; 10.1k, alike
# (p95 113-140 against 111-140 ms).
PARALLEL_MIN_LINEARIZATION_DOFS = 10_000


def _linearize_classes(groups: list, states: dict) -> list:
    """`linearize_batch` of each (factor class, factors) of `groups` in turn: one worker
    thread's part of FactorGraph._relinearize."""
    return [factor_class.linearize_batch(factors, states) for factor_class, factors in groups]


class FactorGraph:
    """States of a window (time order), their factors and fixed vertices; the LM problem.

    vertex_count N, tetrahedra (M, 4) (sparsity pattern and inversion checks), surface
    triangles (F, 3), fixed vertices (held at fixed_positions). Unknown vector x: the free
    vertex coordinates of every state, concatenated in window order.

    Relinearisation (as iSAM2's): the single-state factors of a state (physics prior,
    measurements) are re-linearised when it moved more than `relinearize_threshold` [m] (RMS
    vertex displacement) from where they were last linearised; otherwise their cached
    Gauss-Newton quadratic c + g.d + 0.5 d.H d (d = X - X_lin) stands in for them, in the
    gradient and in the cost, until the next linearisation. States that are re-linearised are
    "active": `cost` evaluates their factors exactly. Old window states, which get no new
    measurements, thus cost nothing until they really move. threshold 0 re-linearises every
    state at every iteration (exact Levenberg-Marquardt on the window). Factors with
    identity_blocks (the temporal ones) are exact quadratics and always evaluated directly. States in `exact_keys` (the estimator's
    newest state, the one its new measurements and prediction act on) ignore the threshold.
    """

    def __init__(self, vertex_count: int, tetrahedra, surface_triangles, fixed_vertices=(), fixed_positions=None,
                 relinearize_threshold: float = 0.0):
        self.vertex_count = int(vertex_count)
        self.tetrahedra = np.ascontiguousarray(tetrahedra, dtype=np.int64)
        self.surface_triangles = np.asarray(surface_triangles, dtype=np.int64)
        fixed = np.unique(np.asarray(fixed_vertices, dtype=np.int64))
        self.fixed_vertices = fixed
        is_free = np.ones(self.vertex_count, dtype=bool)
        is_free[fixed] = False
        self.free_vertices = np.flatnonzero(is_free)
        self.fixed_positions = None if fixed_positions is None else checked_state(fixed_positions, self.vertex_count, "fixed positions")[fixed]
        self.free_dofs = (3 * self.free_vertices[:, None] + np.arange(3)).reshape(-1)
        self.dof_count = 3 * self.vertex_count
        self.block_size = self.free_dofs.size
        self._free_index = np.full(self.dof_count, -1, dtype=np.int64)
        self._free_index[self.free_dofs] = np.arange(self.block_size)
        self.relinearize_threshold = float(relinearize_threshold)
        self._build_pattern()
        self.keys: list = []
        self.states: dict = {}
        self.factors: list[Factor] = []
        # The states' element volumes, shared with their volume barriers (the estimator's).
        self.element_volumes = ElementVolumes(self.tetrahedra)
        self._cache: dict = {}
        self._active: set = set()
        self.exact_keys: set = set()  # states re-linearised whenever they move at all
        self.relinearizations = 0

    # ------------------------------------------------------------------------ pattern
    @property
    def block_pattern(self) -> scipy.sparse.csr_matrix:
        """The sparsity pattern of every state's block of the linearised system (csr over the
        free dofs, sorted indices; its values are zeros and not to be written)."""
        return self._pattern

    def _build_pattern(self) -> None:
        """Block pattern over free dofs: every pair of dofs of vertices sharing a tetrahedron
        (the stiffness pattern, geometry.mesh.DofPattern, without the fixed dofs; free dofs
        keep their order, so its keys stay sorted)."""
        full = DofPattern(self.tetrahedra, self.vertex_count)
        free_rows, free_cols = self._free_index[full.rows()], self._free_index[full.indices]
        keep = (free_rows >= 0) & (free_cols >= 0)
        n = self.block_size
        keys = free_rows[keep] * n + free_cols[keep]
        self._pattern_keys = keys
        pattern_rows, pattern_cols = np.divmod(keys, n)
        indptr = np.searchsorted(pattern_rows, np.arange(n + 1)).astype(np.int32)
        self._pattern = scipy.sparse.csr_matrix(
            (np.zeros(keys.size), pattern_cols.astype(np.int32), indptr), shape=(n, n)
        )
        self._diagonal_index = diagonal_positions(self._pattern)
        # Positions of every triangle's 9x9 dof pairs (row major) in the pattern (or the sink).
        triangle_dofs = (3 * self.surface_triangles[:, :, None] + np.arange(3)).reshape(-1, 9)
        self._triangle_dofs = triangle_dofs
        self._tetrahedron_dofs = (3 * self.tetrahedra[:, :, None] + np.arange(3)).reshape(-1, 12)
        self._triangle_slots = self._slots(
            np.repeat(triangle_dofs, 9, axis=1), np.tile(triangle_dofs, (1, 9))
        ).reshape(-1, 81)
        free_vertex_dofs = 3 * np.arange(n // 3)[:, None, None] + np.arange(3)
        self._vertex_block_slots = np.searchsorted(
            keys, (free_vertex_dofs * n + free_vertex_dofs.transpose(0, 2, 1)).reshape(-1)
        ).reshape(-1, 3, 3)
        self._csr_slot_cache: tuple | None = None
        self._scattered_hessians: dict = {}  # factor -> (its Hessian matrix, values on the pattern)

    def _slots(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """Pattern data positions of full-dof pairs (rows, cols); nnz (a sink slot) where a dof
        is fixed."""
        free_rows, free_cols = self._free_index[rows], self._free_index[cols]
        inside = (free_rows >= 0) & (free_cols >= 0)
        keys = free_rows * self.block_size + free_cols
        slots = np.searchsorted(self._pattern_keys, np.where(inside, keys, 0))
        slots = np.where(inside, slots, self._pattern_keys.size)
        hit = slots[inside]
        if np.any(hit >= self._pattern_keys.size) or np.any(self._pattern_keys[hit] != keys[inside]):
            raise FactorError("a factor couples dofs of vertices that share no tetrahedron")
        return slots

    def locate_hessian_pattern(self, matrix) -> None:
        """Find where the entries of sparse `matrix`'s pattern (one state's dofs, a factor's
        Hessian: the physics prior's stiffness) lie in the block pattern, for the linearisations
        of Hessians of that pattern, which otherwise find them at the first one (about 50 ms at
        6,859 vertices, in the first update's time)."""
        self._csr_slots(scipy.sparse.csr_matrix(matrix))

    def _csr_slots(self, matrix: scipy.sparse.csr_matrix) -> np.ndarray:
        cache = self._csr_slot_cache
        if cache is not None and np.array_equal(cache[0], matrix.indptr) and np.array_equal(cache[1], matrix.indices):
            return cache[2]
        rows = np.repeat(np.arange(matrix.shape[0]), np.diff(matrix.indptr))
        slots = self._slots(rows, matrix.indices.astype(np.int64))
        self._csr_slot_cache = (matrix.indptr.copy(), matrix.indices.copy(), slots)
        return slots

    def newest_information(self) -> scipy.sparse.csr_matrix:
        """The newest state's information over its free dofs (block_pattern): its single-state
        factors at their last linearisation plus its temporal terms, conditioned on the other
        states of the window."""
        cached, temporal = self._newest_terms()
        block = cached.block.copy()
        block.data[self._diagonal_index] += temporal
        return block

    def newest_vertex_information(self) -> np.ndarray:
        """3x3 information blocks (free vertices, 3, 3) of the newest state: its single-state
        factors at their last linearisation plus its temporal terms."""
        cached, temporal = self._newest_terms()
        return cached.data[self._vertex_block_slots] + temporal * np.eye(3)

    def _newest_terms(self) -> tuple:
        """(the newest state's single-state factors at their last linearisation, the weight of
        its temporal terms on its diagonal)."""
        key = self.keys[-1]
        cached = self._cache.get(key) or self._relinearize([key], self.states)[key]
        return cached, sum(factor.identity_terms().get((key, key), 0.0) for factor in self._identity_factors())

    # ------------------------------------------------------------------------ states
    def add_state(self, key, initial) -> None:
        """Append state `key` (newest) with initial positions (N, 3); fixed vertices are reset."""
        if key in self.states:
            raise FactorError(f"state {key!r} is already in the graph")
        state = self._held(initial, f"initial state {key!r}")
        self.keys.append(key)
        self.states[key] = state

    def remove_state(self, key) -> np.ndarray:
        """Drop state `key` and every factor touching it; returns its positions."""
        state = self.states.pop(key)
        self.keys.remove(key)
        self.element_volumes.forget(key)
        self._cache.pop(key, None)
        self._active.discard(key)
        self.factors = [factor for factor in self.factors if key not in factor.keys]
        return state

    def add_factor(self, factor: Factor) -> None:
        """Add `factor`; one without identity_blocks must act on one state (whose cached
        linearisation it invalidates)."""
        unknown = [key for key in factor.keys if key not in self.states]
        if unknown:
            raise FactorError(f"factor touches unknown state {unknown[0]!r}")
        if not factor.identity_blocks and len(factor.keys) != 1:
            raise FactorError("factors across states must give scaled-identity terms only (identity_blocks)")
        self.factors.append(factor)
        if not factor.identity_blocks:
            self._cache.pop(factor.keys[0], None)

    def get_x(self) -> np.ndarray:
        return np.concatenate([self.states[key].reshape(-1)[self.free_dofs] for key in self.keys])

    def states_from_x(self, x: np.ndarray) -> dict:
        parts = np.asarray(x, dtype=np.float64).reshape(len(self.keys), self.block_size)
        states = {}
        for key, part in zip(self.keys, parts):
            flat = self.states[key].reshape(-1).copy()
            flat[self.free_dofs] = part
            states[key] = flat.reshape(-1, 3)
        return states

    def set_x(self, x: np.ndarray) -> None:
        self.states = self.states_from_x(x)

    def set_state(self, key, positions) -> None:
        """Move state `key` to positions (N, 3); fixed vertices are reset."""
        if key not in self.states:
            raise FactorError(f"state {key!r} is not in the graph")
        self.states[key] = self._held(positions, f"state {key!r}")

    def _held(self, positions, name: str) -> np.ndarray:
        """A checked copy of positions (N, 3) with the fixed vertices at their fixed positions."""
        state = checked_state(positions, self.vertex_count, name).copy()
        if self.fixed_positions is not None:
            state[self.fixed_vertices] = self.fixed_positions
        return state

    # ------------------------------------------------------------------------ problem
    def state_factors(self, key) -> list:
        """The factors linearised into state `key`'s block and cached with it: those on `key`
        alone without identity_blocks (identity-block factors are exact quadratics, never cached)."""
        return [factor for factor in self.factors if factor.keys == (key,) and not factor.identity_blocks]

    def replace_state_factors(self, key, factors) -> None:
        """Put `factors` in place of state `key`'s `state_factors` (the estimator re-weights its
        newest state); the state's cached linearisation goes with the old ones."""
        old = self.state_factors(key)
        self.factors = [factor for factor in self.factors if not any(factor is o for o in old)]
        for factor in old:
            self._scattered_hessians.pop(factor, None)
        self._cache.pop(key, None)
        for factor in factors:
            self.add_factor(factor)

    def _grouped_state_factors(self, keys) -> list[tuple[type, list]]:
        """The `state_factors` of states `keys`, grouped by class (in order of appearance), for
        the classes' batch evaluations (Factor.cost_batch, Factor.linearize_batch)."""
        groups: dict = {}
        for key in keys:
            for factor in self.state_factors(key):
                groups.setdefault(type(factor), []).append(factor)
        return list(groups.items())

    def _relinearize(self, keys, states: dict) -> dict:
        """Fresh linearisations of the single-state factors of states `keys` at `states`:
        key -> _StateLinearization. Each class's factors on those states are linearised
        together; from PARALLEL_MIN_LINEARIZATION_DOFS renewed unknowns the classes run in
        contiguous groups side by side on the worker threads (one group per thread: the physics
        prior, then the volume barrier and the points; the prior's corotational stiffness and the
        points' closest-point search, the two largest, release the GIL). A state's terms are then
        added in its factors' order whatever the batching."""
        nnz = self._pattern_keys.size
        out = {key: _StateLinearization(states[key].copy(), np.zeros(nnz + 1), np.zeros(self.dof_count), 0.0)
               for key in keys}
        groups = self._grouped_state_factors(keys)
        most = len(groups) if self.dof_count * len(keys) >= PARALLEL_MIN_LINEARIZATION_DOFS else 1
        parts = worker_threads.run_parts(_linearize_classes,
                                         [(part, states) for part in worker_threads.split(groups, most)])
        batches = [batch for part in parts for batch in part]
        for (_, factors), linearizations in zip(groups, batches):
            for factor, terms in zip(factors, linearizations):
                linearization = out[factor.keys[0]]
                linearization.cost += terms.cost
                self._accumulate(terms, factor, linearization.data, linearization.gradient)
        pattern = self._pattern
        for linearization in out.values():
            self.relinearizations += 1
            linearization.revision = self.relinearizations
            linearization.block = scipy.sparse.csr_matrix((linearization.data[:nnz], pattern.indices, pattern.indptr),
                                                          shape=pattern.shape)
        return out

    def _scattered_hessian(self, factor, matrix) -> np.ndarray:
        """A factor's sparse Hessian as values on the block pattern (nnz + 1,). Kept while the
        factor hands back the same matrix object: the physics prior's information is one matrix
        for a whole update (factors replace, never modify, a Hessian they returned)."""
        cached = self._scattered_hessians.get(factor)
        if cached is not None and cached[0] is matrix:
            return cached[1]
        csr = scipy.sparse.csr_matrix(matrix)
        scattered = np.bincount(self._csr_slots(csr), weights=csr.data, minlength=self._pattern_keys.size + 1)
        self._scattered_hessians[factor] = (matrix, scattered)
        return scattered

    def _accumulate(self, terms: FactorLinearization, factor, data: np.ndarray | None, gradient: np.ndarray) -> None:
        """Add a factor's terms to a state's gradient and block values `data` (None: gradient only)."""
        for values in terms.gradients.values():
            gradient += values
        for blocks in terms.point_blocks.values():
            _scatter_add(gradient, self._triangle_dofs[blocks.triangle], blocks.gradient)
        for blocks in terms.element_blocks.values():
            _scatter_add(gradient, self._tetrahedron_dofs[blocks.tetrahedron], blocks.gradient)
        if data is None:
            return
        for matrix in terms.hessians.values():
            data += self._scattered_hessian(factor, matrix)
        for blocks in terms.point_blocks.values():
            if blocks.hessian is not None:
                _scatter_add(data, self._triangle_slots[blocks.hessian_triangle], blocks.hessian)
        for blocks in terms.element_blocks.values():
            if blocks.hessian is not None:
                dofs = self._tetrahedron_dofs[blocks.tetrahedron]
                _scatter_add(data, self._slots(np.repeat(dofs, 12, axis=1), np.tile(dofs, (1, 12))), blocks.hessian)

    def _model(self, cached: _StateLinearization, state: np.ndarray):
        """(cost, gradient (3N,)) of the cached quadratic at `state`; the last evaluation is
        kept (LM's trial cost and its convergence test ask at one x)."""
        if cached.model_at is not None and np.array_equal(cached.model_at[0], state):
            return cached.model_at[1], cached.model_at[2]
        delta = (state - cached.x_lin).reshape(-1)
        free_delta = delta[self.free_dofs]
        product = np.zeros(self.dof_count)
        product[self.free_dofs] = cached.block @ free_delta
        cost = cached.cost + float(cached.gradient @ delta) + 0.5 * float(free_delta @ product[self.free_dofs])
        gradient = cached.gradient + product
        cached.model_at = (state.copy(), cost, gradient)
        return cost, gradient

    def _moved(self, cached: _StateLinearization, state: np.ndarray) -> float:
        """RMS vertex displacement since the linearisation (a max would let the few vertices at
        sharp surface edges, where the closest triangle flips, re-linearise every state)."""
        return float(np.sqrt(np.mean(np.sum((state - cached.x_lin) ** 2, axis=1))))

    def _outdated(self, key, cached: _StateLinearization, state: np.ndarray) -> bool:
        """Whether `linearize` must re-linearise state `key` (its cached quadratic stands in otherwise)."""
        threshold = 0.0 if key in self.exact_keys else self.relinearize_threshold
        return (cached.rebased and threshold == 0.0) or self._moved(cached, state) > threshold

    def _identity_factors(self) -> list:
        """The identity_blocks factors: evaluated directly, their terms go into the diagonal
        shift and the couplings of the window system."""
        return [factor for factor in self.factors if factor.identity_blocks]

    def cost(self, x: np.ndarray) -> float:
        """Total cost: exact for active states and identity-block factors, cached model for the rest."""
        states = self.states_from_x(x)
        total = 0.0
        exact = []
        for key in self.keys:
            cached = self._cache.get(key)
            if key in self._active or cached is None:
                exact.append(key)
            else:
                total += self._model(cached, states[key])[0]
        for factor_class, factors in self._grouped_state_factors(exact):
            total += sum(factor_class.cost_batch(factors, states))
        total += sum(factor.cost(states) for factor in self._identity_factors())
        return float(total)

    def gradient(self, x: np.ndarray):
        """(gradient over the free dofs, cost) at x, as `linearize` gives them, without new
        Hessians: a state `linearize` would re-linearise gets its exact cost and gradient and
        its cached quadratic re-based at x (cost and gradient exact there, Hessian kept, same
        revision). LM calls this after an accepted step to test for convergence before paying
        for Hessians it may not need. A re-based state whose threshold is 0 (the estimator's
        newest, or exact LM) is re-linearised by the next `linearize`; the others follow the
        threshold rule from x, their quadratic exact to first order there (so the estimator's
        next update does not re-linearise the state it just finished)."""
        states = self.states_from_x(x)
        gradient = np.zeros((len(self.keys), self.dof_count))
        cost = 0.0
        position = {key: t for t, key in enumerate(self.keys)}
        new = [key for key in self.keys if key not in self._cache]
        rebased = [key for key in self.keys
                   if key in self._cache and self._outdated(key, self._cache[key], states[key])]
        self._cache.update(self._relinearize(new, states))
        for key in rebased:
            cached = self._cache[key]
            cached.cost, cached.gradient = 0.0, np.zeros(self.dof_count)  # cached.data (the Hessian) is kept
        for factor_class, factors in self._grouped_state_factors(rebased):
            for factor, terms in zip(factors, factor_class.linearize_batch(factors, states, hessian=False)):
                cached = self._cache[factor.keys[0]]
                cached.cost += terms.cost
                self._accumulate(terms, factor, None, cached.gradient)
        for key in rebased:
            cached = self._cache[key]
            cached.x_lin = states[key].copy()
            cached.rebased = True
            cached.model_at = None
        self._active.update(new, rebased)
        for t, key in enumerate(self.keys):
            cost_t, gradient[t] = self._model(self._cache[key], states[key])
            cost += cost_t
        for factor in self._identity_factors():
            terms = factor.linearize(states, hessian=False)
            cost += terms.cost
            for key, values in terms.gradients.items():
                gradient[position[key]] += values
        return gradient[:, self.free_dofs].reshape(-1), float(cost)

    def linearize(self, x: np.ndarray):
        """(WindowSystem of J^T W J, gradient J^T W r over the free dofs, cost) at x.

        The system's blocks are the states' cached linearisations themselves (not copied: at
        organ scale, W copies of 1.4M values cost ~60 ms an update); the identity-block
        factors' terms go into its diagonal shift and its couplings."""
        states = self.states_from_x(x)
        window = len(self.keys)
        gradient = np.zeros((window, self.dof_count))
        couplings = np.zeros(max(window - 1, 0))
        coupling_diagonal = np.zeros(window)
        cost = 0.0
        self._active = {key for key in self.keys
                        if key not in self._cache or self._outdated(key, self._cache[key], states[key])}
        self._cache.update(self._relinearize([key for key in self.keys if key in self._active], states))
        blocks, revisions = [], []
        for t, key in enumerate(self.keys):
            cached = self._cache[key]
            if key in self._active:
                cost += cached.cost
                gradient[t] = cached.gradient
            else:
                model_cost, model_gradient = self._model(cached, states[key])
                cost += model_cost
                gradient[t] = model_gradient
            blocks.append(cached.block)
            revisions.append(cached.revision)
        position = {key: t for t, key in enumerate(self.keys)}
        for factor in self._identity_factors():
            terms = factor.linearize(states)
            cost += terms.cost
            for key, values in terms.gradients.items():
                gradient[position[key]] += values
            for (key_i, key_j), value in factor.identity_terms().items():
                t, s = position[key_i], position[key_j]
                if t == s:
                    coupling_diagonal[t] += value
                elif abs(t - s) == 1:
                    couplings[min(t, s)] += value
                else:
                    raise FactorError("identity terms may only couple consecutive states")
            if terms.hessians or terms.point_blocks or terms.element_blocks:
                raise FactorError(f"{type(factor).__name__} declares identity_blocks but gave other terms")
        shift = np.repeat(coupling_diagonal[:, None], self.block_size, axis=1) if coupling_diagonal.any() else None
        system = WindowSystem(blocks, couplings, list(self.keys), self._diagonal_index, coupling_diagonal,
                              self._vertex_block_slots, revisions, shift)
        # Scattered Hessians serve states that get re-linearised; keep only those of the states
        # this linearisation re-linearised (memory stays bounded by the active states).
        self._scattered_hessians = {factor: kept for factor, kept in self._scattered_hessians.items()
                                    if factor.keys[0] in self._active}
        return system, gradient[:, self.free_dofs].reshape(-1), cost

    def step_fraction(self, x: np.ndarray, step: np.ndarray) -> np.ndarray:
        """Per unknown (the shape of x), the fraction alpha_t in [0, 1] of its state t's part of
        the step: the largest such that every tetrahedron of the state with a positive volume at
        x keeps at least MIN_VOLUME_RATIO_PER_STEP of it at x + alpha_t * step_t (LM's inversion
        guard). Each state is cut on its own (a state's volumes depend on its own positions
        only), so that one state that cannot move, such as one holding an element the simulator
        nearly flattened, does not stop the steps of the others.

        Along the step a volume is the cubic 6 V(alpha) = (u + a du) x (v + a dv) . (w + a dw) in
        the edge vectors at corner 0. With L the longest of u, v, w and delta the largest move of
        the element's corners, |6 V(alpha) - 6 V(0)| <= (L + 2 delta)^3 - L^3, which clears most
        elements at once; for the rest the cubic's first crossing of the margin is bracketed on a
        grid of alpha and refined by bisection, and the result is checked on exact volumes. States
        the step leaves alone (PCGSolver's left-out blocks) are not looked at."""
        step = np.asarray(step, dtype=np.float64)
        fractions = np.ones(len(self.keys))
        moved = np.flatnonzero(step.reshape(len(self.keys), self.block_size).any(axis=1))
        fractions[moved] = self._state_fractions(x, step, moved)
        return np.repeat(fractions, self.block_size)

    def _state_fractions(self, x: np.ndarray, step: np.ndarray, moved: np.ndarray) -> np.ndarray:
        """step_fraction's alpha_t of the states `moved` (indices into keys), (len(moved),)."""
        if not moved.size:
            return np.ones(0)
        keys = [self.keys[t] for t in moved]
        states = self.states_from_x(x)
        volumes, longest = self.element_volumes.of(states, keys)
        moves = np.zeros((len(keys), self.dof_count))
        moves[:, self.free_dofs] = step.reshape(len(self.keys), self.block_size)[moved]
        moves = moves.reshape(len(keys), -1, 3)
        window = np.stack([states[key] for key in keys])
        fractions = np.min(worker_threads.run_parts(_first_crossings, [
            (window, moves, self.tetrahedra[part], np.ascontiguousarray(volumes[:, part]),
             np.ascontiguousarray(longest[:, part]), MIN_VOLUME_RATIO_PER_STEP, _STEP_FRACTION_GRID,
             _STEP_FRACTION_BISECTIONS) for part in element_ranges(len(self.tetrahedra), len(keys))]), axis=0)
        if np.all(fractions == 1.0):
            return fractions
        margin = MIN_VOLUME_RATIO_PER_STEP * 6.0 * volumes
        positive = volumes > 0.0
        blocks = step.reshape(len(self.keys), self.block_size)
        for _ in range(_STEP_FRACTION_HALVINGS):
            scaled = np.zeros_like(blocks)
            scaled[moved] = fractions[:, None] * blocks[moved]
            trial_volumes = self.element_volumes.of(self.states_from_x(x + scaled.reshape(-1)), keys)[0]
            short = np.any(positive & (6.0 * trial_volumes < margin), axis=1)
            if not short.any():
                return fractions
            fractions[short] *= 0.5
        fractions[short] = 0.0
        return fractions


def _scatter_add(target: np.ndarray, index: np.ndarray, values: np.ndarray) -> None:
    """target[index[k]] += values[k] for every k, repeated indices summed (index and values of
    one shape, flattened)."""
    _scatter_add_flat(target, np.ascontiguousarray(index, dtype=np.int64).reshape(-1),
                      np.ascontiguousarray(values, dtype=np.float64).reshape(-1))


@numba.njit((writable(float64, 1), read_only(int64, 1), read_only(float64, 1)), cache=True, boundscheck=True)
def _scatter_add_flat(target, index, values):
    """Compiled (numba): a bincount over the whole target allocates and adds a target-sized
    array for each factor's few hundred terms (18k block values on a small window's state)."""
    for k in range(index.size):
        target[index[k]] += values[k]


@numba.njit((read_only(float64, 3), read_only(float64, 3), read_only(int64, 2), read_only(float64, 2),
             read_only(float64, 2), float64, int64, int64), cache=True, boundscheck=True, nogil=True)
def _first_crossings(states, moves, tetrahedra, volumes, longest, ratio, grid_count, bisections):
    """Per state s, the smallest fraction alpha in [0, 1] of its move at which one of its
    elements with a positive volume first falls below `ratio` of it (1 where none does), to
    1/grid_count then bisected `bisections` times from below: FactorGraph.step_fraction's
    bracketing (its docstring), before the check on exact volumes.

    Compiled (numba): as numpy passes over the elements the bound cannot clear, LM's inversion
    guard (step_fraction) costs two to three times as much (docs/design-notes.md, "Compiled kernels")."""
    fractions = np.ones(states.shape[0])
    for s in range(states.shape[0]):
        x, move = states[s], moves[s]
        for e in range(tetrahedra.shape[0]):
            volume = volumes[s, e]
            if not volume > 0.0:
                continue
            largest = 0.0
            for k in range(4):
                vertex = tetrahedra[e, k]
                largest = max(largest, move[vertex, 0] ** 2 + move[vertex, 1] ** 2 + move[vertex, 2] ** 2)
            largest = np.sqrt(largest)
            bound = ratio * 6.0 * volume
            if (longest[s, e] + 2.0 * largest) ** 3 - longest[s, e] ** 3 < 6.0 * volume - bound:
                continue
            i0, i1, i2, i3 = tetrahedra[e, 0], tetrahedra[e, 1], tetrahedra[e, 2], tetrahedra[e, 3]
            u, v, w = x[i1] - x[i0], x[i2] - x[i0], x[i3] - x[i0]
            du, dv, dw = move[i1] - move[i0], move[i2] - move[i0], move[i3] - move[i0]
            # 6 V(alpha) = (u + a du) . ((v + a dv) x (w + a dw)) = c0 + c1 a + c2 a^2 + c3 a^3.
            vw, dvdw = cross3(v, w), cross3(dv, dw)
            mixed = cross3(dv, w) + cross3(v, dw)
            c0 = dot3(u, vw)
            c1 = dot3(du, vw) + dot3(u, mixed)
            c2 = dot3(du, mixed) + dot3(u, dvdw)
            c3 = dot3(du, dvdw)
            for g in range(1, grid_count + 1):
                high = g / grid_count
                if c0 + high * (c1 + high * (c2 + high * c3)) < bound:
                    low = (g - 1) / grid_count
                    for _ in range(bisections):
                        middle = 0.5 * (low + high)
                        if c0 + middle * (c1 + middle * (c2 + middle * c3)) < bound:
                            high = middle
                        else:
                            low = middle
                    fractions[s] = min(fractions[s], low)
                    break
    return fractions
