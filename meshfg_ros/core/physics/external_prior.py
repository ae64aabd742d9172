"""A physics prior from an external simulator (the authors' XPBD simulator through its
sim_bridge service, nodes/sim_bridge_client.py): its state and stiffness as the estimator's
prediction and prior information, checked and made usable, without ROS.

The simulator answers with every vertex and element slot (removed ones listed as invalid, the
indices stable) and, on request, its stiffness: a symmetric COO matrix in float32 over 3 dofs
per vertex slot, from the constraint Hessian, so it may be indefinite, and the dofs the
simulator holds carry FIXED_DIAGONAL-sized entries (it writes 1e9) on the diagonal.

`bridge_state` checks an answer against the estimator's mesh (slot counts, finite values, the
same elements) and moves it into the world frame: positions (N, 3) and, when given, the
stiffness as an `ExternalStiffness` (COO, rotated: K_world = B K B^T with B = diag(R, ..., R)),
with the element slots the simulator removed (a cut) as slots of the mesh's own elements, which
the estimator follows (SlidingWindowEstimator.remove_elements, core/geometry/topology.py).
Each failure is an `ExternalPriorError` with the diagnostics counter it counts in.

`ExternalStiffness.information(template, free_dofs)` makes the prior's information of it, on the
estimator's own stiffness pattern (the window's block pattern only holds pairs of vertices
sharing a tetrahedron):
- symmetrised, (K + K^T) / 2;
- entries coupling vertices that share no tetrahedron (a contact constraint's) dropped;
- the dofs the simulator holds (diagonal >= FIXED_DIAGONAL): their rows and columns cleared;
  where the estimator's mesh leaves such a vertex free, its diagonal block is set to the largest
  diagonal entry of the free dofs, so that the prior holds it at the simulator's position as
  firmly as the stiffest free dof (the estimator keeps its own fixed vertices fixed);
- made positive definite on the estimator's free dofs by the smallest added multiple of the
  identity that lets a sparse Cholesky factorisation through (Nocedal & Wright, Numerical
  Optimization, Alg. 3.3: shifts of REPAIR_SHIFTS times the mean free diagonal, tried in
  order). A uniform shift keeps the pattern and the ratios of the simulator's stiffness
  between vertices, and a Cholesky that succeeds proves definiteness, at the cost of a few
  factorisations; a per-vertex-block eigenvalue clip does neither (the off-diagonal blocks can
  keep the whole matrix indefinite), and a full eigen-decomposition costs O((3N)^3). A matrix
  that needs more than the largest shift is indefinite beyond a repair that keeps its meaning:
  refused (ExternalPriorError "sim_bridge_stiffness_rejected"), and the step uses the
  estimator's own FEM stiffness.
The estimator scales the result as it scales its own stiffness (core/factors.prior_scale: mean
free diagonal = 1 / simulation_sigma^2), so only the simulator's stiffness ratios enter.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse

from meshfg_ros.core.geometry.mesh import TetMesh
from meshfg_ros.core.solvers.sparse_cholesky import NotPositiveDefiniteError, SparseCholesky

__all__ = ["FIXED_DIAGONAL", "HELD_DOF_STIFFNESS", "REPAIR_SHIFTS", "BridgeAnswer", "ExternalPriorError",
           "ExternalStiffness", "StiffnessInformation", "StiffnessProjection", "bridge_state", "held_dof_stiffness"]

# A dof whose diagonal stiffness reaches this is held by the simulator (it writes 1e9 [N/m]; a
# tissue's own diagonal stays below ~1e4 N/m at millimetre elements and 1e5 Pa).
FIXED_DIAGONAL = 1e8
# What the authors' bridge writes on the diagonal of a held dof [N/m].
HELD_DOF_STIFFNESS = 1e9
# Shifts tried, relative to the mean free diagonal: none first, then the size of the estimator's
# ridge (PRIOR_RIDGE, which makes a free body's rigid modes definite); beyond the last the matrix
# is refused.
REPAIR_SHIFTS = (0.0, 1e-6, 1e-4, 1e-3, 1e-2, 3e-2, 1e-1)


class ExternalPriorError(ValueError):
    """An answer of the external simulator that cannot be used, with its diagnostics counter."""

    def __init__(self, counter: str, reason: str) -> None:
        super().__init__(reason)
        self.counter = counter


@dataclass(frozen=True)
class BridgeAnswer:
    """A sim_bridge answer as arrays (nodes/sim_bridge_client.py makes it from the message).

    positions: every vertex slot's xyz, flat (3S,); valid_vertex_count: the `size` field;
    invalid_vertices: removed slots; elements: every element slot's 4 indices, flat (4E,);
    invalid_elements: removed slots; stiffness: (rows, cols, values, shape) or None."""

    positions: np.ndarray
    valid_vertex_count: int
    invalid_vertices: np.ndarray
    elements: np.ndarray
    invalid_elements: np.ndarray
    stiffness: tuple[np.ndarray, np.ndarray, np.ndarray, tuple[int, int]] | None = None


@dataclass(frozen=True, eq=False)
class StiffnessInformation:
    """The prior information made of a simulator's stiffness: `matrix` (3N, 3N) csr on the
    template's pattern [N/m], and what was changed to make it usable (one line, "" if nothing)."""

    matrix: scipy.sparse.csr_matrix
    note: str = ""


@dataclass(frozen=True, eq=False)
class ExternalStiffness:
    """The simulator's stiffness in the world frame as COO triplets over 3N dofs."""

    rows: np.ndarray
    cols: np.ndarray
    values: np.ndarray

    def information(self, template: scipy.sparse.csr_matrix, free_dofs: np.ndarray) -> StiffnessInformation:
        """The prior's information on `template`'s pattern (module docstring), or
        ExternalPriorError("sim_bridge_stiffness_rejected", why). A caller with many answers
        for one mesh keeps a `StiffnessProjection` instead (its analysis is made once)."""
        return StiffnessProjection(template, free_dofs).information(self)


class StiffnessProjection:
    """`ExternalStiffness.information` for one template (the estimator's K pattern, csr with
    sorted indices) and set of free dofs, with what does not change between answers made once:
    the pattern's keys and diagonal, the free block's positions and its Cholesky analysis (METIS
    ordering, symbolic factorisation), and the slots of the last answer's (row, col) pattern:
    most of a fresh one's cost is that analysis, not the numeric factorisation an answer needs."""

    def __init__(self, template: scipy.sparse.csr_matrix, free_dofs: np.ndarray) -> None:
        template = scipy.sparse.csr_matrix(template)
        template.sort_indices()
        self.size = size = template.shape[0]
        self._indptr, self._indices = template.indptr.copy(), template.indices.copy()
        rows = np.repeat(np.arange(size, dtype=np.int64), np.diff(template.indptr))
        self._keys = rows * size + template.indices.astype(np.int64)
        self._diagonal_slots = np.searchsorted(self._keys, np.arange(size, dtype=np.int64) * (size + 1))
        # Each entry's mirror (col, row): the template's pattern is symmetric.
        self._mirror_slots = np.searchsorted(self._keys, template.indices.astype(np.int64) * size + rows)
        self._is_free = np.zeros(size, dtype=bool)
        self._is_free[free_dofs] = True
        block_index = np.full(size, -1, dtype=np.int64)
        block_index[free_dofs] = np.arange(len(free_dofs))
        in_block = self._is_free[rows] & self._is_free[template.indices]
        block_rows, block_cols = block_index[rows[in_block]], block_index[template.indices[in_block]]
        block_size = len(free_dofs)
        order = np.lexsort((block_cols, block_rows))
        self._block_entries = np.flatnonzero(in_block)[order]  # template data positions, in csr order of the block
        block_indptr = np.searchsorted(block_rows[order], np.arange(block_size + 1)).astype(np.int32)
        self._block_pattern = (block_cols[order].astype(np.int32), block_indptr)
        self._block_diagonal = np.flatnonzero(block_rows[order] == block_cols[order])
        self._factor: SparseCholesky | None = None  # analysed on first use
        self._last_pattern: tuple | None = None  # (rows, cols, slots, inside) of the last answer

    def information(self, stiffness: ExternalStiffness) -> StiffnessInformation:
        """See ExternalStiffness.information."""
        size, rows, cols, values = self.size, stiffness.rows, stiffness.cols, stiffness.values
        on_diagonal = rows == cols
        diagonal = np.bincount(rows[on_diagonal], weights=values[on_diagonal], minlength=size)
        held_dofs = diagonal >= FIXED_DIAGONAL
        notes = []
        # Symmetrise: each entry and its mirror, halved, on the template; the held dofs' rows and
        # columns cleared.
        slots, inside = self._slots(rows, cols)
        kept = inside & ~(held_dofs[rows] | held_dofs[cols])
        outside = ~inside & (np.abs(values) > 0.0)
        if outside.any():
            dropped = float(np.abs(values[outside]).sum() / max(np.abs(values).sum(), 1e-300))
            notes.append(f"{dropped:.1%} of the stiffness (by magnitude) couples vertices sharing no element: dropped")
        upper = np.bincount(slots[kept], weights=values[kept], minlength=self._keys.size)
        data = 0.5 * (upper + upper[self._mirror_slots])
        matrix = scipy.sparse.csr_matrix((data, self._indices.copy(), self._indptr.copy()), shape=(size, size))
        free_diagonal = data[self._diagonal_slots][self._is_free & ~held_dofs]
        if free_diagonal.size == 0 or not np.mean(free_diagonal) > 0.0:
            raise ExternalPriorError("sim_bridge_stiffness_rejected", "the simulator's stiffness has no positive "
                                     "diagonal on the free vertices: the estimator's own stiffness is used")
        held_free = np.flatnonzero(held_dofs & self._is_free)
        if held_free.size:
            matrix.data[self._diagonal_slots[held_free]] = float(free_diagonal.max())
            notes.append(f"{held_free.size // 3} vertices the simulator holds are free in the mesh: held by the prior")
        mean_diagonal = float(np.mean(free_diagonal))
        shift = self._definite_shift(matrix.data, mean_diagonal)
        if shift is None:
            raise ExternalPriorError("sim_bridge_stiffness_rejected", (
                f"the simulator's stiffness is indefinite beyond a shift of {REPAIR_SHIFTS[-1]:g} of its mean "
                "diagonal: "
                "the estimator's own stiffness is used (check the simulator's state for inverted elements)"))
        if shift > 0.0:
            matrix.data[self._diagonal_slots] += shift
            notes.append(f"made positive definite by a shift of {shift / mean_diagonal:.2g} of its mean diagonal")
        return StiffnessInformation(matrix, "; ".join(notes))

    def _slots(self, rows: np.ndarray, cols: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Template data positions of the entries (rows, cols) and which lie on the template;
        the last answer's, when its pattern is this one (a simulator sends one pattern)."""
        last = self._last_pattern
        if last is not None and np.array_equal(last[0], rows) and np.array_equal(last[1], cols):
            return last[2], last[3]
        keys = rows * self.size + cols
        slots = np.minimum(np.searchsorted(self._keys, keys), self._keys.size - 1)
        inside = self._keys[slots] == keys
        self._last_pattern = (rows.copy(), cols.copy(), slots, inside)
        return slots, inside

    def _definite_shift(self, data: np.ndarray, mean_diagonal: float) -> float | None:
        """The first of REPAIR_SHIFTS x mean_diagonal that makes the free block positive definite."""
        block = data[self._block_entries]
        for relative in REPAIR_SHIFTS:
            shifted = block.copy()
            shifted[self._block_diagonal] += relative * mean_diagonal
            try:
                if self._factor is None:
                    indices, indptr = self._block_pattern
                    self._factor = SparseCholesky(scipy.sparse.csr_matrix(
                        (shifted, indices, indptr), shape=(indptr.size - 1,) * 2), node_size=3)
                else:
                    self._factor.refactor(shifted)
            except NotPositiveDefiniteError:
                continue
            return relative * mean_diagonal
        return None


def held_dof_stiffness(stiffness, held_vertices: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, tuple]:
    """A stiffness matrix as the authors' bridge sends it: (rows, columns, float32 values, shape)
    of its entries, the held vertices' rows and columns cleared and HELD_DOF_STIFFNESS on their
    diagonal (what bridge_state reads back as held dofs)."""
    matrix = scipy.sparse.coo_matrix(stiffness)
    held = np.zeros(matrix.shape[0], dtype=bool)
    held[(3 * np.asarray(held_vertices, dtype=np.int64)[:, None] + np.arange(3)).reshape(-1)] = True
    keep = ~(held[matrix.row] | held[matrix.col])
    dofs = np.flatnonzero(held)
    return (np.concatenate([matrix.row[keep], dofs]), np.concatenate([matrix.col[keep], dofs]),
            np.concatenate([matrix.data[keep], np.full(dofs.size, HELD_DOF_STIFFNESS)]).astype(np.float32),
            matrix.shape)


def bridge_state(answer: BridgeAnswer, mesh: TetMesh, to_world: np.ndarray
                 ) -> tuple[np.ndarray, ExternalStiffness | None, np.ndarray | None]:
    """(positions (N, 3) in the world frame, the stiffness or None, the removed element slots
    or None) of a sim_bridge answer for `mesh` (the estimator's initial mesh, before any cut, in
    the simulator's vertex order); `to_world` (4, 4): the simulator frame's points into the world
    frame. The removed slots are those of `mesh.all_tetrahedra` (core/geometry/topology.py), the
    simulator's element slots matched to them once by their vertices; a removed vertex's slot is
    given its initial position (the estimator holds it). ExternalPriorError with the counter
    "sim_bridge_rejected_malformed" (sizes, indices, non-finite values) or
    "sim_bridge_rejected_mesh" (another mesh, or slots added: refinement is not followed)."""
    positions = np.array(answer.positions, dtype=np.float64)
    if positions.size % 3 or positions.size // 3 != mesh.vertex_count:
        raise ExternalPriorError("sim_bridge_rejected_mesh", (
            f"the simulator's mesh has {positions.size / 3:g} vertex slots, the initial mesh {mesh.vertex_count}: "
            "set mesh_file to the simulator's mesh, in its vertex order (refined meshes are not followed)"))
    positions = positions.reshape(-1, 3)
    invalid_vertices = _slots(answer.invalid_vertices, mesh.vertex_count, "vertex")
    valid = np.ones(mesh.vertex_count, dtype=bool)
    valid[invalid_vertices] = False
    if answer.valid_vertex_count != np.count_nonzero(valid):
        raise ExternalPriorError("sim_bridge_rejected_malformed", (
            f"the simulator's vertex size {answer.valid_vertex_count} is not its {mesh.vertex_count} slots less "
            f"the {invalid_vertices.size} invalid ones"))
    if not np.isfinite(positions[valid]).all():
        raise ExternalPriorError("sim_bridge_rejected_malformed", "the simulator's positions are not all finite")
    positions[~valid] = mesh.vertices[~valid]
    slots_of_ours = _element_slots(np.asarray(answer.elements, dtype=np.int64), mesh.all_tetrahedra)
    invalid_elements = _slots(answer.invalid_elements, len(mesh.all_tetrahedra), "element")
    removed = np.sort(slots_of_ours[invalid_elements]) if invalid_elements.size else None
    remaining = np.ones(len(mesh.all_tetrahedra), dtype=bool)
    remaining[slots_of_ours[invalid_elements]] = False
    if not valid[mesh.all_tetrahedra[remaining]].all():
        raise ExternalPriorError("sim_bridge_rejected_malformed", "the simulator lists as invalid vertices that its "
                                 "remaining elements use")
    rotation, translation = to_world[:3, :3], to_world[:3, 3]
    world = positions @ rotation.T + translation
    if answer.stiffness is None:
        return world, None, removed
    return world, _rotated_stiffness(answer.stiffness, mesh.vertex_count, rotation), removed


def _slots(indices, count: int, kind: str) -> np.ndarray:
    """Unique slot indices, or ExternalPriorError for one outside [0, count)."""
    indices = np.unique(np.asarray(indices, dtype=np.int64))
    if indices.size and (indices[0] < 0 or indices[-1] >= count):
        raise ExternalPriorError("sim_bridge_rejected_malformed", f"an invalid {kind} index outside the simulator's "
                                 f"{count} {kind} slots")
    return indices


def _element_slots(elements: np.ndarray, tetrahedra: np.ndarray) -> np.ndarray:
    """For each of the simulator's element slots (flat indices, 4 per slot) the slot of the same
    tetrahedron in `tetrahedra` (M, 4), in any order of slots and of corners (a mesh file's
    tetrahedra may be reoriented); ExternalPriorError("sim_bridge_rejected_mesh") when they are
    not the same tetrahedra."""
    if elements.size % 4 or elements.size // 4 != len(tetrahedra):
        raise ExternalPriorError("sim_bridge_rejected_mesh", (
            f"the simulator has {elements.size / 4:g} element slots, the initial mesh {len(tetrahedra)}: set "
            "mesh_file to the simulator's mesh, in its vertex order (refined meshes are not followed)"))
    ours = np.sort(np.asarray(tetrahedra, dtype=np.int64), axis=1)
    theirs = np.sort(elements.reshape(-1, 4), axis=1)
    our_order, their_order = np.lexsort(ours.T[::-1]), np.lexsort(theirs.T[::-1])
    if not np.array_equal(ours[our_order], theirs[their_order]):
        raise ExternalPriorError("sim_bridge_rejected_mesh", (
            f"the simulator's {len(theirs)} elements are not those of the initial mesh: set mesh_file to the "
            "simulator's mesh, in its vertex order"))
    slots = np.empty(len(theirs), dtype=np.int64)
    slots[their_order] = our_order
    return slots


def _rotated_stiffness(stiffness, vertex_count: int, rotation: np.ndarray) -> ExternalStiffness:
    rows, cols, values, shape = stiffness
    rows, cols = np.asarray(rows, dtype=np.int64), np.asarray(cols, dtype=np.int64)
    values = np.asarray(values, dtype=np.float64)
    size = 3 * vertex_count
    if tuple(shape) != (size, size) or not (rows.shape == cols.shape == values.shape):
        raise ExternalPriorError("sim_bridge_rejected_malformed", (
            f"the simulator's stiffness is {shape[0]} x {shape[1]} with {rows.size}/{cols.size}/{values.size} "
            f"row/column/value entries; expected {size} x {size} (3 dofs per vertex) and equal counts"))
    if rows.size and (min(rows.min(), cols.min()) < 0 or max(rows.max(), cols.max()) >= size):
        raise ExternalPriorError("sim_bridge_rejected_malformed", "the simulator's stiffness has indices outside "
                                 f"its {size} x {size} shape")
    if not np.isfinite(values).all():
        raise ExternalPriorError("sim_bridge_rejected_malformed", "the simulator's stiffness is not all finite")
    if np.allclose(rotation, np.eye(3)):
        return ExternalStiffness(rows, cols, values)
    blocks = scipy.sparse.kron(scipy.sparse.identity(vertex_count, format="csr"), rotation, format="csr")
    rotated = (blocks @ scipy.sparse.csr_matrix((values, (rows, cols)), shape=(size, size)) @ blocks.T).tocoo()
    return ExternalStiffness(rotated.row.astype(np.int64), rotated.col.astype(np.int64), rotated.data)
