"""Cuts of a tetrahedral mesh: the element slots a blade removes, and the pieces a cut detaches.

A cut removes element slots of the uncut mesh with every index kept stable
(`TetMesh.without_elements`: the remaining elements, the surface with the wound's faces, the
vertices left without an element invalid and held). What follows a cut takes the slots:
`ElasticSimulator.remove_elements`, `SlidingWindowEstimator.remove_elements`,
`PredictionScheduler.remove_elements`, whose predictions carry them to the estimator.

`cut_elements` is what a blade removes: the elements reaching into its box (a thin box is the
blade's swept plane: every element it crosses goes, so the tissue parts), and then
every piece the cut leaves hanging by less than a face-connected body held at three or more
boundary vertices (a sliver joined by an edge, a flap cut off): such a piece has rigid modes no
elastic model can hold, and it is no longer the tissue the camera sees attached.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse
from scipy.sparse.csgraph import connected_components

from meshfg_ros.core.geometry.mesh import TetMesh

__all__ = ["MIN_HELD_VERTICES", "cut_elements", "detached_elements", "elements_in_box"]

# A face-connected piece needs this many boundary (fixed) vertices to be held without rigid modes.
MIN_HELD_VERTICES = 3
_TET_FACES = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]], dtype=np.int64)


def _remaining_slots(mesh: TetMesh) -> np.ndarray:
    """Slots (of mesh.all_tetrahedra) of the remaining elements, in the order of mesh.tetrahedra."""
    return np.setdiff1d(np.arange(mesh.all_tetrahedra.shape[0]), mesh.removed_elements)


def elements_in_box(mesh: TetMesh, centre, half_extents, rotation=np.eye(3)) -> np.ndarray:
    """Slots (of mesh.all_tetrahedra) of the remaining elements that reach into the box of
    `half_extents` (3,) about `centre` (3,), its axes the columns of `rotation` (3, 3): their
    corners' extent along each box axis overlaps the box's, at the mesh's vertices."""
    slots = _remaining_slots(mesh)
    local = (mesh.vertices[mesh.tetrahedra] - np.asarray(centre, dtype=np.float64)) @ np.asarray(
        rotation, dtype=np.float64)  # (M, 4, 3) corners in the box's frame
    half = np.asarray(half_extents, dtype=np.float64)
    overlaps = np.all((local.min(axis=1) <= half) & (local.max(axis=1) >= -half), axis=1)
    return slots[overlaps]


def detached_elements(mesh: TetMesh) -> np.ndarray:
    """Slots of the remaining elements in face-connected pieces with fewer than
    MIN_HELD_VERTICES boundary vertices (module doc)."""
    slots = _remaining_slots(mesh)
    tetrahedra = mesh.tetrahedra
    faces = np.sort(tetrahedra[:, _TET_FACES].reshape(-1, 3), axis=1)
    _, face_ids = np.unique(faces, axis=0, return_inverse=True)
    elements = np.repeat(np.arange(len(slots)), 4)
    incidence = scipy.sparse.csr_matrix((np.ones(elements.size), (elements, face_ids.reshape(-1))))
    _, piece = connected_components(incidence @ incidence.T, directed=False)
    held = np.zeros(mesh.vertex_count, dtype=bool)
    held[mesh.boundary_vertices] = True
    # Each piece's distinct held vertices: (piece, vertex) pairs of its elements' corners.
    pairs = np.unique(np.stack([np.repeat(piece, 4), tetrahedra.reshape(-1)], axis=1), axis=0)
    held_count = np.bincount(pairs[:, 0], held[pairs[:, 1]], minlength=piece.max() + 1)
    return slots[held_count[piece] < MIN_HELD_VERTICES]


def cut_elements(mesh: TetMesh, centre, half_extents, rotation=np.eye(3)) -> np.ndarray:
    """All slots a blade's box removes from `mesh`, those removed already included: the
    elements reaching into the box, then the pieces that leaves detached."""
    removed = np.union1d(mesh.removed_elements, elements_in_box(mesh, centre, half_extents, rotation))
    if removed.size == mesh.removed_elements.size:
        return mesh.removed_elements
    cut = mesh.without_elements(removed)
    return np.union1d(removed, detached_elements(cut)).astype(np.int64)
