"""Tetrahedral mesh: vertices + fixed connectivity, validation, topology and file IO.

A `TetMesh` holds one geometric state (`vertices`) of a fixed connectivity (`tetrahedra`)
plus the set of vertices that are held fixed (boundary conditions). The connectivity does not
change while tissue deforms, so the topology derived from it (boundary surface, edges,
vertex sets) is computed lazily once and shared by every mesh made with `with_vertices` or
`with_fixed`. A cut changes it (`without_elements`): element slots are removed with every
index kept stable, and the vertices left without an element become invalid.
"""

from __future__ import annotations

import contextlib
import io
from pathlib import Path

import numba
import numpy as np
from numba.types import float64, int64

import meshfg_ros.core.worker_threads as worker_threads
from meshfg_ros.core.geometry.kernel_types import read_only

__all__ = [
    "DegenerateMeshError",
    "DofPattern",
    "InvalidMeshError",
    "MeshFileError",
    "TetMesh",
    "check_degenerate",
    "check_mesh_file",
    "cross",
    "element_ranges",
    "inverted_elements",
    "load_mesh",
    "orient_tetrahedra",
    "save_mesh",
    "signed_volumes",
]

# |signed volume| below this times (mean edge length)^3 counts as a degenerate element.
DEGENERATE_VOLUME_TOLERANCE = 1e-12
# Per-element kernels run on the worker threads in parts of at least this many elements (times
# states): an element's volume takes about 8 ns, a hand-off to a thread about 0.1 ms.
PARALLEL_MIN_ELEMENTS = 20_000

# Faces of a positively oriented tetrahedron (v0, v1, v2, v3), each listed counter-clockwise
# seen from outside, i.e. with its normal pointing away from the opposite vertex.
_OUTWARD_TET_FACES = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]], dtype=np.int64)
_TET_EDGES = np.array([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]], dtype=np.int64)

_MAX_NAMED_ELEMENTS = 5


def name_elements(indices: np.ndarray) -> str:
    """'elements [i, j, ...]' naming the first few of `indices`, for one-line error messages."""
    shown = ", ".join(str(i) for i in indices[:_MAX_NAMED_ELEMENTS])
    more = ", ..." if len(indices) > _MAX_NAMED_ELEMENTS else ""
    return f"elements [{shown}{more}]"


class InvalidMeshError(ValueError):
    """Mesh arrays with a wrong shape, dtype, index range or unused vertices."""


class DegenerateMeshError(ValueError):
    """Tetrahedra with (near) zero volume or repeated vertex indices; names the elements."""

    def __init__(self, element_indices: np.ndarray, reason: str):
        self.element_indices = np.asarray(element_indices, dtype=np.int64)
        super().__init__(
            f"{self.element_indices.size} degenerate tetrahedra ({reason}): {name_elements(self.element_indices)}"
        )


class MeshFileError(ValueError):
    """A mesh file that cannot be read as (or written from) a tetrahedral mesh."""


def check_mesh_file(path: Path) -> None:
    """MeshFileError unless `path` is a file: it does not exist, or it is a folder (a rosbag2
    recording, whose initial mesh `meshfg mesh export` writes as a file, is named as one)."""
    if path.is_file():
        return
    if not path.is_dir():
        raise MeshFileError(f"{path} does not exist")
    if (path / "metadata.yaml").is_file():
        raise MeshFileError(f"{path} is a recording, not a mesh file: `meshfg mesh export {path} --out FILE` "
                            "writes its initial mesh as one")
    raise MeshFileError(f"{path} is a folder, not a mesh file")


def cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a x b of 3-vectors along the last axis, the very values of np.cross (the same products and
    differences), written into one array: np.cross's axis handling and copies cost more than
    its arithmetic on the estimator's arrays (2x on 600 vectors, 7x on 23,000)."""
    out = np.empty(np.broadcast_shapes(a.shape, b.shape))
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    np.subtract(a1 * b2, a2 * b1, out=out[..., 0])
    np.subtract(a2 * b0, a0 * b2, out=out[..., 1])
    np.subtract(a0 * b1, a1 * b0, out=out[..., 2])
    return out


def sorted_unique(keys: np.ndarray) -> np.ndarray:
    """The distinct values of integer `keys`, ascending: np.unique's, by a sort. np.unique hashes
    integers (numpy 2.4), which takes about ten times as long as a sort on the millions of pair keys
    of an organ-scale mesh."""
    ordered = np.sort(keys)
    return ordered[np.r_[True, ordered[1:] != ordered[:-1]]]


class DofPattern:
    """The CSR pattern over a tetrahedral mesh's vertex coordinates (vertex v's coordinate i is
    dof 3v+i) that a stiffness matrix has: every pair of dofs of two vertices sharing an element,
    and each vertex's own 3x3 block (also for a vertex of no element). Rows hold their columns
    in ascending order: a dof's row holds 3 columns per adjacent vertex, in the order of the
    vertex adjacency (`vertex_indptr`, `vertex_indices`).

    It is built from the vertex pairs (16 per element) and expanded to dofs by arithmetic, and
    positions are found per vertex pair: sorting and searching the 144 dof pairs of every element
    instead costs several times as much on an organ-scale mesh, where it was most of a node's
    start-up."""

    def __init__(self, tetrahedra: np.ndarray, vertex_count: int):
        tets = np.asarray(tetrahedra, dtype=np.int64).reshape(-1, 4)
        self.vertex_count = int(vertex_count)
        pairs = np.concatenate([(tets[:, :, None] * self.vertex_count + tets[:, None, :]).reshape(-1),
                                np.arange(self.vertex_count) * (self.vertex_count + 1)])
        self._vertex_keys = sorted_unique(pairs)
        vertex_rows, self.vertex_indices = np.divmod(self._vertex_keys, self.vertex_count)
        self.vertex_indptr = np.searchsorted(vertex_rows, np.arange(self.vertex_count + 1))
        row_lengths = np.repeat(3 * np.diff(self.vertex_indptr), 3)
        self.indptr = np.concatenate([[0], np.cumsum(row_lengths)])
        # Each vertex's columns (3 per adjacent vertex), then repeated for its three rows.
        vertex_block = (3 * self.vertex_indices[:, None] + np.arange(3)).reshape(-1)
        block_start = np.repeat(np.repeat(3 * self.vertex_indptr[:-1], 3), row_lengths)
        self._within_row = np.arange(self.indptr[-1]) - np.repeat(self.indptr[:-1], row_lengths)
        self.indices = vertex_block[block_start + self._within_row]

    @property
    def size(self) -> int:
        """The number of dofs (rows and columns)."""
        return 3 * self.vertex_count

    def rows(self) -> np.ndarray:
        """(nnz,) the row of each stored entry."""
        return np.repeat(np.arange(self.size), np.diff(self.indptr))

    def vertex_ranks(self, row_vertices: np.ndarray, column_vertices: np.ndarray) -> np.ndarray:
        """The place of each column vertex among its row vertex's adjacent vertices (the pairs
        must share an element, or be one vertex)."""
        keys = row_vertices * self.vertex_count + column_vertices
        return np.searchsorted(self._vertex_keys, keys) - self.vertex_indptr[row_vertices]

    def positions(self, rows: np.ndarray, ranks: np.ndarray, components: np.ndarray) -> np.ndarray:
        """Positions in `indices` of the entries in dof rows `rows` whose column is coordinate
        `components` of the row vertex's adjacent vertex number `ranks` (vertex_ranks)."""
        return self.indptr[rows] + 3 * ranks + components

    def transposed_positions(self) -> np.ndarray:
        """(nnz,) the position of each entry's mirror (its column's row, its row's column)."""
        rows = self.rows()
        row_vertices = np.repeat(np.arange(self.vertex_count), np.diff(self.vertex_indptr))
        mirror_ranks = self.vertex_ranks(self.vertex_indices, row_vertices)  # per vertex pair
        vertex_entry = self.vertex_indptr[rows // 3] + self._within_row // 3
        return self.positions(self.indices, mirror_ranks[vertex_entry], rows % 3)


@numba.njit(inline="always")
def cross3(a, b):
    """a x b of two 3-vectors inside a compiled kernel, the products and differences of `cross`."""
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])


@numba.njit(inline="always")
def dot3(a, b):
    """a . b of two 3-vectors inside a compiled kernel."""
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def signed_volumes(vertices: np.ndarray, tetrahedra: np.ndarray, longest_edges: bool = False):
    """Signed volume of each tetrahedron of a state (N, 3) -> (M,), or of states (W, N, 3) ->
    (W, M); positive when (v1-v0, v2-v0, v3-v0) is right-handed. With `longest_edges`, also the
    length of the longest of those three edges, in the same shape (the scale of an element's
    volume change along a step, FactorGraph.step_fraction)."""
    vertices = np.asarray(vertices, dtype=np.float64)
    stacked = np.ascontiguousarray(vertices.reshape((-1,) + vertices.shape[-2:]))
    tetrahedra = np.ascontiguousarray(tetrahedra, dtype=np.int64)
    parts = worker_threads.run_parts(_volumes_and_longest_edges,
                                     [(stacked, tetrahedra[part]) for part in element_ranges(len(tetrahedra), len(stacked))])
    volumes, longest = (np.concatenate([part[k] for part in parts], axis=1) for k in range(2))
    shape = vertices.shape[:-2] + (volumes.shape[1],)
    if not longest_edges:
        return volumes.reshape(shape)
    return volumes.reshape(shape), longest.reshape(shape)


def element_ranges(elements: int, states: int = 1) -> list[slice]:
    """`elements` split in contiguous ranges for the worker threads (core/worker_threads.py),
    each of at least PARALLEL_MIN_ELEMENTS elements times `states` (one range below that)."""
    return worker_threads.ranges(elements, states * elements // PARALLEL_MIN_ELEMENTS)


@numba.njit((read_only(float64, 3), read_only(int64, 2)), cache=True, boundscheck=True, nogil=True)
def _volumes_and_longest_edges(states, tetrahedra):
    """signed_volumes of states (W, N, 3): the triple product of the edge vectors u, v, w at
    corner 0, ((u x v) . w) / 6, and the longest of the three, each (W, M).

    Compiled (numba): the estimator evaluates it at every trial of its volume barrier and
    inversion guard, where numpy passes (two gathers per coordinate, then the products) cost
    several times as much (docs/design-notes.md, "Compiled kernels")."""
    volumes = np.empty((states.shape[0], tetrahedra.shape[0]))
    longest = np.empty((states.shape[0], tetrahedra.shape[0]))
    for s in range(states.shape[0]):
        x = states[s]
        for e in range(tetrahedra.shape[0]):
            i0, i1, i2, i3 = tetrahedra[e, 0], tetrahedra[e, 1], tetrahedra[e, 2], tetrahedra[e, 3]
            ux, uy, uz = x[i1, 0] - x[i0, 0], x[i1, 1] - x[i0, 1], x[i1, 2] - x[i0, 2]
            vx, vy, vz = x[i2, 0] - x[i0, 0], x[i2, 1] - x[i0, 1], x[i2, 2] - x[i0, 2]
            wx, wy, wz = x[i3, 0] - x[i0, 0], x[i3, 1] - x[i0, 1], x[i3, 2] - x[i0, 2]
            volumes[s, e] = ((uy * vz - uz * vy) * wx + (uz * vx - ux * vz) * wy + (ux * vy - uy * vx) * wz) / 6.0
            longest[s, e] = np.sqrt(max(ux * ux + uy * uy + uz * uz, vx * vx + vy * vy + vz * vz,
                                        wx * wx + wy * wy + wz * wz))
    return volumes, longest


class ElementVolumes:
    """Signed volumes and longest edges at corner 0 (signed_volumes with longest_edges) of the
    tetrahedra of a window's states, the last two states asked for each key kept.

    Levenberg-Marquardt asks at one x several times: its trial's cost (the volume barrier),
    then, once the trial is accepted, its inversion guard for the next step from there (or,
    after a rejected trial, again from the x before it); and a new update finds its older
    states where the last one left them. A FactorGraph and the volume barriers of its states
    share one, so that each state's volumes are made once."""

    def __init__(self, tetrahedra):
        self.tetrahedra = np.asarray(tetrahedra, dtype=np.int64)
        self._kept: dict = {}  # key -> [(state, (volumes, longest edges)), ...], newest last

    def of(self, states: dict, keys) -> tuple[np.ndarray, np.ndarray]:
        """(volumes, longest edges), each (len(keys), M), of states[key] for `keys`; the states
        not kept are evaluated together in one call."""
        values = [self._kept_values(key, states[key]) for key in keys]
        missing = [t for t, kept in enumerate(values) if kept is None]
        if missing:
            stacked = np.stack([states[keys[t]] for t in missing])
            volumes, longest = signed_volumes(stacked, self.tetrahedra, longest_edges=True)
            for t, state, state_volumes, state_longest in zip(missing, stacked, volumes, longest):
                values[t] = (state_volumes, state_longest)
                self._kept[keys[t]] = [*self._kept.get(keys[t], [])[-1:], (state, values[t])]
        return np.stack([v[0] for v in values]), np.stack([v[1] for v in values])

    def _kept_values(self, key, state: np.ndarray) -> tuple | None:
        for kept_state, kept in reversed(self._kept.get(key, ())):  # the newest first: most asks
            if np.array_equal(kept_state, state):
                return kept
        return None

    def forget(self, key) -> None:
        """Drop what is kept of state `key` (it left the window)."""
        self._kept.pop(key, None)


def inverted_elements(vertices: np.ndarray, tetrahedra: np.ndarray) -> np.ndarray:
    """Indices of the tetrahedra without a positive volume at `vertices` (NaN ones too)."""
    return np.flatnonzero(~(signed_volumes(vertices, tetrahedra) > 0.0))


def _mean_edge_length(vertices: np.ndarray, tetrahedra: np.ndarray) -> float:
    """Mean tetrahedron edge length (each edge counted once per element), the degeneracy scale."""
    corners = vertices[tetrahedra]
    edge_vectors = corners[:, _TET_EDGES[:, 1], :] - corners[:, _TET_EDGES[:, 0], :]
    return float(np.linalg.norm(edge_vectors, axis=2).mean())


def check_degenerate(vertices: np.ndarray, tetrahedra: np.ndarray) -> np.ndarray:
    """Raise DegenerateMeshError for repeated indices or |volume| < tol * mean_edge^3; return volumes."""
    sorted_tets = np.sort(tetrahedra, axis=1)
    repeated = np.flatnonzero(np.any(sorted_tets[:, 1:] == sorted_tets[:, :-1], axis=1))
    if repeated.size:
        raise DegenerateMeshError(repeated, "repeated vertex indices")
    volumes = signed_volumes(vertices, tetrahedra)
    tolerance = DEGENERATE_VOLUME_TOLERANCE * _mean_edge_length(vertices, tetrahedra) ** 3
    flat = np.flatnonzero(np.abs(volumes) <= tolerance)
    if flat.size:
        raise DegenerateMeshError(flat, f"|volume| <= {tolerance:.3g}")
    return volumes


def orient_tetrahedra(vertices: np.ndarray, tetrahedra: np.ndarray) -> tuple[np.ndarray, int]:
    """Swap two indices of every negatively oriented tetrahedron; return (tets, count fixed).

    Raises DegenerateMeshError first, as a flat element has no orientation to fix.
    """
    tetrahedra = np.array(tetrahedra, dtype=np.int64, copy=True)
    volumes = check_degenerate(np.asarray(vertices, dtype=np.float64), tetrahedra)
    inverted = volumes < 0.0
    tetrahedra[inverted, 2], tetrahedra[inverted, 3] = (
        tetrahedra[inverted, 3].copy(),
        tetrahedra[inverted, 2].copy(),
    )
    return tetrahedra, int(np.count_nonzero(inverted))


class _Topology:
    """Connectivity-derived data, computed on first use and shared between mesh states.

    `all_tetrahedra` are the element slots of the mesh before any cut; `tetrahedra` the
    remaining ones (all of them on a mesh that was never cut), `removed_elements` the slots
    removed and `invalid_vertices` the vertices no remaining element uses."""

    def __init__(self, tetrahedra: np.ndarray, vertex_count: int, all_tetrahedra: np.ndarray | None = None,
                 removed_elements: np.ndarray | None = None):
        self.tetrahedra = tetrahedra
        self.vertex_count = vertex_count
        self.all_tetrahedra = tetrahedra if all_tetrahedra is None else all_tetrahedra
        self.removed_elements = _read_only(np.zeros(0, np.int64) if removed_elements is None else removed_elements)
        used = np.zeros(vertex_count, dtype=bool)
        used[tetrahedra.reshape(-1)] = True
        self.invalid_vertices = _read_only(np.flatnonzero(~used).astype(np.int64))
        self._surface_triangles: np.ndarray | None = None
        self._surface_vertices: np.ndarray | None = None
        self._internal_vertices: np.ndarray | None = None
        self._edges: np.ndarray | None = None

    @property
    def surface_triangles(self) -> np.ndarray:
        if self._surface_triangles is None:
            faces = self.tetrahedra[:, _OUTWARD_TET_FACES].reshape(-1, 3)
            _, first_index, counts = np.unique(
                np.sort(faces, axis=1), axis=0, return_index=True, return_counts=True
            )
            if np.any(counts > 2):
                raise InvalidMeshError(
                    f"{np.count_nonzero(counts > 2)} faces are shared by more than two tetrahedra"
                )
            boundary = np.sort(first_index[counts == 1])
            self._surface_triangles = _read_only(faces[boundary])
        return self._surface_triangles

    @property
    def surface_vertices(self) -> np.ndarray:
        if self._surface_vertices is None:
            self._surface_vertices = _read_only(np.unique(self.surface_triangles))
        return self._surface_vertices

    @property
    def internal_vertices(self) -> np.ndarray:
        if self._internal_vertices is None:
            is_internal = np.ones(self.vertex_count, dtype=bool)
            is_internal[self.surface_vertices] = False
            is_internal[self.invalid_vertices] = False
            self._internal_vertices = _read_only(np.flatnonzero(is_internal).astype(np.int64))
        return self._internal_vertices

    @property
    def edges(self) -> np.ndarray:
        if self._edges is None:
            pairs = np.sort(self.tetrahedra[:, _TET_EDGES].reshape(-1, 2), axis=1)
            self._edges = _read_only(np.unique(pairs, axis=0))
        return self._edges


def _read_only(array: np.ndarray) -> np.ndarray:
    array.setflags(write=False)
    return array


def _as_vertices(vertices, expected_count: int | None = None) -> np.ndarray:
    array = np.array(vertices, dtype=np.float64, copy=True)
    if array.ndim != 2 or array.shape[1] != 3:
        raise InvalidMeshError(f"vertices must have shape (N, 3), got {array.shape}")
    if expected_count is not None and array.shape[0] != expected_count:
        raise InvalidMeshError(
            f"vertices must have {expected_count} rows to match the mesh, got {array.shape[0]}"
        )
    if not np.all(np.isfinite(array)):
        raise InvalidMeshError("vertices contain NaN or infinite coordinates")
    return _read_only(array)


def _as_index_array(values, vertex_count: int, what: str) -> np.ndarray:
    raw = np.asarray(values)
    if raw.size and not np.issubdtype(raw.dtype, np.integer):
        raise InvalidMeshError(f"{what} must be integer indices, got dtype {raw.dtype}")
    indices = raw.astype(np.int64)
    if indices.size and (indices.min() < 0 or indices.max() >= vertex_count):
        raise InvalidMeshError(
            f"{what} index out of range [0, {vertex_count}): min {indices.min()}, max {indices.max()}"
        )
    return indices


def _as_fixed(fixed_vertices, vertex_count: int) -> np.ndarray:
    fixed = _as_index_array(fixed_vertices, vertex_count, "fixed_vertices").reshape(-1)
    return _read_only(np.unique(fixed))


class TetMesh:
    """Immutable tetrahedral mesh state with positively oriented elements.

    The constructor validates, orients negative elements (counted in `flipped_count`) and
    rejects degenerate ones. `with_vertices` / `with_fixed` make new states sharing topology
    without re-checking orientation, since a deformed state may legitimately invert elements.
    """

    def __init__(self, vertices, tetrahedra, fixed_vertices=(), name: str = ""):
        vertices = _as_vertices(vertices)
        tets = _as_index_array(tetrahedra, vertices.shape[0], "tetrahedra")
        if tets.ndim != 2 or tets.shape[1] != 4 or tets.shape[0] == 0:
            raise InvalidMeshError(f"tetrahedra must have shape (M>0, 4), got {tets.shape}")
        used = np.zeros(vertices.shape[0], dtype=bool)
        used[tets.reshape(-1)] = True
        if not used.all():
            unused = np.flatnonzero(~used)
            raise InvalidMeshError(
                f"{unused.size} vertices belong to no tetrahedron, "
                f"first {unused[:_MAX_NAMED_ELEMENTS].tolist()}"
            )
        tets, self.flipped_count = orient_tetrahedra(vertices, tets)
        self._vertices = vertices
        self._fixed = _as_fixed(fixed_vertices, vertices.shape[0])
        self._topology = _Topology(_read_only(tets), vertices.shape[0])
        self.name = name

    @classmethod
    def _from_parts(cls, vertices, fixed, topology, name, flipped_count) -> TetMesh:
        mesh = cls.__new__(cls)
        mesh._vertices = vertices
        mesh._fixed = fixed
        mesh._topology = topology
        mesh.name = name
        mesh.flipped_count = flipped_count
        return mesh

    def with_vertices(self, vertices) -> TetMesh:
        """Same connectivity, fixed set and cached topology at new vertex positions (N, 3)."""
        new_vertices = _as_vertices(vertices, self.vertex_count)
        return TetMesh._from_parts(new_vertices, self._fixed, self._topology, self.name, 0)

    def with_fixed(self, fixed_vertices) -> TetMesh:
        """Same geometry and topology with a new set of fixed vertex indices (the invalid
        vertices of a cut mesh stay held)."""
        fixed = _read_only(np.union1d(_as_fixed(fixed_vertices, self.vertex_count), self.invalid_vertices))
        return TetMesh._from_parts(self._vertices, fixed, self._topology, self.name, 0)

    def without_elements(self, removed_elements) -> TetMesh:
        """The mesh after a cut: the element slots `removed_elements` (indices into
        `all_tetrahedra`, the elements before any cut) removed on top of those removed already.

        Indices stay stable: vertices keep their rows and `removed_elements` names slots of
        the uncut mesh, so that successive cuts (and a simulator's invalid indices) compose.
        `tetrahedra` holds the remaining elements in slot order, the surface is that of the
        remaining elements (the wound's faces become surface), and the vertices no remaining
        element uses become `invalid_vertices`: held like fixed vertices (they are in
        `fixed_vertices`, so simulator and estimator leave them where they are), never
        estimated, published as invalid. Raises InvalidMeshError for a slot out of range or a
        cut that leaves no element."""
        slots = _as_index_array(removed_elements, self.all_tetrahedra.shape[0], "removed_elements").reshape(-1)
        removed = np.union1d(self.removed_elements, slots).astype(np.int64)
        if removed.size == self.removed_elements.size:
            return self
        keep = np.ones(self.all_tetrahedra.shape[0], dtype=bool)
        keep[removed] = False
        if not keep.any():
            raise InvalidMeshError("the cut removes every element")
        topology = _Topology(_read_only(self.all_tetrahedra[keep]), self.vertex_count, self.all_tetrahedra,
                             removed)
        fixed = np.union1d(self._fixed, topology.invalid_vertices).astype(np.int64)
        return TetMesh._from_parts(self._vertices, _read_only(fixed), topology, self.name, 0)

    @property
    def vertices(self) -> np.ndarray:
        return self._vertices

    @property
    def tetrahedra(self) -> np.ndarray:
        return self._topology.tetrahedra

    @property
    def fixed_vertices(self) -> np.ndarray:
        """Vertices held where they are: the boundary condition, and the invalid vertices of a
        cut mesh (`boundary_vertices` without them)."""
        return self._fixed

    @property
    def boundary_vertices(self) -> np.ndarray:
        """The fixed vertices of the boundary condition (`fixed_vertices` but the invalid ones)."""
        return np.setdiff1d(self._fixed, self.invalid_vertices).astype(np.int64)

    @property
    def all_tetrahedra(self) -> np.ndarray:
        """Every element slot (M0, 4) of the mesh before any cut (`tetrahedra` when never cut)."""
        return self._topology.all_tetrahedra

    @property
    def removed_elements(self) -> np.ndarray:
        """Slots of `all_tetrahedra` a cut removed (sorted; empty when never cut)."""
        return self._topology.removed_elements

    @property
    def invalid_vertices(self) -> np.ndarray:
        """Vertices no remaining element uses (sorted; empty when never cut): not part of the body."""
        return self._topology.invalid_vertices

    @property
    def valid_vertices(self) -> np.ndarray:
        """Vertices of the remaining elements (all of them when never cut)."""
        return np.setdiff1d(np.arange(self.vertex_count), self.invalid_vertices).astype(np.int64)

    @property
    def free_vertices(self) -> np.ndarray:
        """Sorted indices of vertices that are not fixed."""
        is_free = np.ones(self.vertex_count, dtype=bool)
        is_free[self._fixed] = False
        return np.flatnonzero(is_free).astype(np.int64)

    @property
    def vertex_count(self) -> int:
        return self._vertices.shape[0]

    @property
    def tetrahedron_count(self) -> int:
        return self._topology.tetrahedra.shape[0]

    @property
    def surface_triangles(self) -> np.ndarray:
        return self._topology.surface_triangles

    @property
    def surface_vertices(self) -> np.ndarray:
        return self._topology.surface_vertices

    @property
    def internal_vertices(self) -> np.ndarray:
        return self._topology.internal_vertices

    @property
    def edges(self) -> np.ndarray:
        return self._topology.edges

    def signed_volumes(self, vertices=None) -> np.ndarray:
        """Per-element signed volumes (M,) at `vertices` (default: this state)."""
        return signed_volumes(self._state(vertices), self.tetrahedra)

    def volume(self, vertices=None) -> float:
        """Total signed volume at `vertices` (default: this state)."""
        return float(self.signed_volumes(vertices).sum())

    def triangle_normals(self, vertices=None) -> np.ndarray:
        """Unit outward normals (F, 3) of the surface triangles at `vertices` (default: this state)."""
        normals = self._triangle_area_normals(self._state(vertices))
        lengths = np.linalg.norm(normals, axis=1, keepdims=True)
        return normals / np.where(lengths > 0.0, lengths, 1.0)

    def vertex_normals(self, vertices=None) -> np.ndarray:
        """Unit outward area-weighted normals (N, 3) at surface vertices; zero rows for internal ones."""
        area_normals = self._triangle_area_normals(self._state(vertices))
        corner_vertices = self.surface_triangles.reshape(-1)
        corner_normals = np.repeat(area_normals, 3, axis=0)
        accumulated = np.stack(
            [np.bincount(corner_vertices, corner_normals[:, axis], self.vertex_count) for axis in range(3)],
            axis=1,
        )
        lengths = np.linalg.norm(accumulated, axis=1, keepdims=True)
        return accumulated / np.where(lengths > 0.0, lengths, 1.0)

    def _triangle_area_normals(self, vertices: np.ndarray) -> np.ndarray:
        corners = vertices[self.surface_triangles]
        return cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])

    def _state(self, vertices) -> np.ndarray:
        if vertices is None:
            return self._vertices
        return _as_vertices(vertices, self.vertex_count)

    def __repr__(self) -> str:
        return (
            f"TetMesh(name={self.name!r}, vertices={self.vertex_count}, "
            f"tetrahedra={self.tetrahedron_count}, fixed={self._fixed.size})"
        )


def _read_gmsh_v1(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Vertices and tetrahedra (type 4) of a legacy Gmsh v1 ($NOD/$ELM) file.

    Hand-written because meshio has no reader for the v1 format.
    """
    lines = path.read_text().split("\n")
    stripped = [line.strip() for line in lines]
    try:
        node_start = stripped.index("$NOD") + 1
        element_start = stripped.index("$ELM") + 1
        node_count = int(stripped[node_start])
        element_count = int(stripped[element_start])
        node_table = np.array(
            [line.split() for line in stripped[node_start + 1 : node_start + 1 + node_count]],
            dtype=np.float64,
        )
        element_tokens = [
            line.split() for line in stripped[element_start + 1 : element_start + 1 + element_count]
        ]
        # Tetra lines are 'id type reg_phys reg_elem 4 a b c d'; other element types differ in length.
        nine_token_rows = np.array([tokens for tokens in element_tokens if len(tokens) == 9], dtype=np.int64)
    except (ValueError, IndexError) as error:
        raise MeshFileError(f"{path} is not a readable Gmsh v1 mesh: {error}") from None
    if node_table.shape != (node_count, 4):
        raise MeshFileError(f"{path}: $NOD block must have {node_count} rows 'id x y z'")
    node_ids = node_table[:, 0].astype(np.int64)
    nine_token_rows = nine_token_rows.reshape(-1, 9)
    tet_rows = nine_token_rows[(nine_token_rows[:, 1] == 4) & (nine_token_rows[:, 4] == 4)]
    if tet_rows.shape[0] == 0:
        raise MeshFileError(f"{path} is not a tetrahedral mesh (no tetra cells)")
    tet_node_ids = tet_rows[:, 5:9]
    order = np.argsort(node_ids)
    positions = np.searchsorted(node_ids, tet_node_ids, sorter=order)
    positions = np.clip(positions, 0, node_ids.size - 1)
    tets = order[positions]
    if not np.array_equal(node_ids[tets], tet_node_ids):
        raise MeshFileError(f"{path}: $ELM references node ids missing from $NOD")
    return node_table[:, 1:], tets


def _is_gmsh_v1(path: Path) -> bool:
    if path.suffix.lower() != ".msh":
        return False
    with path.open("rb") as stream:
        for raw_line in stream:
            line = raw_line.strip()
            if line:
                return line == b"$NOD"
    return False


def _drop_unused_vertices(vertices, tetrahedra, fixed_flags):
    """Compact away vertices no tetrahedron uses (e.g. nodes of dropped non-tet cells)."""
    used = np.unique(tetrahedra)
    new_index = np.full(vertices.shape[0], -1, dtype=np.int64)
    new_index[used] = np.arange(used.size)
    fixed = np.flatnonzero(fixed_flags[used]) if fixed_flags is not None else ()
    return vertices[used], new_index[tetrahedra], fixed


def load_mesh(path) -> TetMesh:
    """Read a tetrahedral mesh (Gmsh v1/v2/v4 .msh, .vtu, .vtk); point data "fixed" marks fixed vertices.

    Only tetra cells are kept; vertices used by no tetrahedron are dropped.
    """
    import meshio

    path = Path(path)
    check_mesh_file(path)
    fixed_flags = None
    if _is_gmsh_v1(path):
        vertices, tets = _read_gmsh_v1(path)
    else:
        # meshio raises many unrelated types for bad files, and for some prints why and exits.
        try:
            with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()) as printed:
                data = meshio.read(path)
        except (Exception, SystemExit) as error:
            reason = " ".join(printed.getvalue().split()) or str(error)
            raise MeshFileError(f"{path} could not be read by meshio: {reason}") from None
        tet_blocks = [block.data for block in data.cells if block.type == "tetra"]
        if not tet_blocks:
            raise MeshFileError(f"{path} is not a tetrahedral mesh (no tetra cells)")
        vertices = np.asarray(data.points, dtype=np.float64)[:, :3]
        tets = np.concatenate(tet_blocks).astype(np.int64)
        if "fixed" in data.point_data:
            fixed_flags = np.asarray(data.point_data["fixed"]).reshape(-1) != 0
    vertices, tets, fixed = _drop_unused_vertices(vertices, tets, fixed_flags)
    return TetMesh(vertices, tets, fixed, name=path.stem)


def save_mesh(mesh: TetMesh, path) -> None:
    """Write `mesh` by extension: .msh (Gmsh 4.1 binary), .vtu or .vtk, with point data "fixed"."""
    import meshio

    path = Path(path)
    suffix = path.suffix.lower()
    fixed_flags = np.zeros(mesh.vertex_count, dtype=np.int32)
    fixed_flags[mesh.fixed_vertices] = 1
    cell_data = {}
    if suffix == ".msh":
        # Gmsh requires physical/geometrical tags on each element.
        element_tags = np.ones(mesh.tetrahedron_count, dtype=np.int32)
        cell_data = {"gmsh:physical": [element_tags], "gmsh:geometrical": [element_tags]}
    elif suffix not in (".vtu", ".vtk"):
        raise MeshFileError(f"{path}: unsupported mesh format {suffix!r} (use .msh, .vtu or .vtk)")
    data = meshio.Mesh(
        mesh.vertices,
        [("tetra", np.asarray(mesh.tetrahedra))],
        point_data={"fixed": fixed_flags},
        cell_data=cell_data,
    )
    if suffix == ".msh":
        # Binary: meshio's ASCII $NodeData writer prints numpy-2 scalar reprs it cannot read back.
        meshio.write(path, data, file_format="gmsh", binary=True)
    else:
        meshio.write(path, data)
