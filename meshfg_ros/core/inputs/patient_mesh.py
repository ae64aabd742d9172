"""A user's own tetrahedral mesh (a CT segmentation, say) made ready for the simulator. ROS-free.

Such a mesh rarely carries the `fixed` point data of the project's meshes, is often in
millimetres, and lives in the CT's frame. `prepare_mesh(path, fixed, scale, pose)` reads it,
scales it to metres and places it in the world frame (world = R (scale x) + t, the CT-to-world
registration as [x, y, z, qx, qy, qz, qw]), marks the fixed vertices and checks that the
simulator can use it; the nodes call it with their parameters.

Fixed vertices are the union of the file's `fixed` point data and a `FixedSelection`: vertex
indices (of the mesh as loaded: tetrahedra's vertices in file order), vertices within a distance
of planes, vertices inside axis-aligned boxes (planes and boxes in the world frame, metres, after
scale and pose), and the vertices of named groups of the file (gmsh physical groups, meshio cell
and point sets). A plane or box that selects no vertex, or every one, fails with the selection
it would make read in the file's units (a box copied from the CT's millimetres).

`check_simulatable` turns what would fail deep inside the simulator ("Cholesky failed: pivot
... not positive", a singular stiffness) into one line naming the cause: no fixed vertex, a
connected part of the mesh held by fewer than three non-collinear fixed vertices, or elements
that are flat or inverted. `check_against_clouds` compares the placed mesh with the first
clouds (world frame): sizes orders of magnitude apart (a mesh in millimetres) or boxes that do
not meet (a missing registration, or a units mix-up the other units' scales resolve) fail in
one line that says which parameter to set. `plausible_units` lists the units that make a file's
mesh an organ's size.
"""

from __future__ import annotations

import contextlib
import io
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import scipy.sparse
from scipy.sparse.csgraph import connected_components

from meshfg_ros.core.geometry.mesh import (
    DegenerateMeshError,
    InvalidMeshError,
    MeshFileError,
    TetMesh,
    _is_gmsh_v1,  # the legacy format meshio cannot read, which load_mesh reads itself
    check_mesh_file,
    load_mesh,
)
from meshfg_ros.core.inputs.frames import transform_points
from meshfg_ros.core.inputs.input_checks import flat_elements
from meshfg_ros.core.inputs.pose_history import InvalidPoseError, as_pose, pose_matrix

__all__ = [
    "Box",
    "FixedSelection",
    "PatientMeshError",
    "PatientMeshFile",
    "Plane",
    "UNITS",
    "check_against_clouds",
    "check_simulatable",
    "plausible_units",
    "place_mesh",
    "prepare_mesh",
    "read_patient_mesh",
    "select_fixed",
]

# Candidate units of a mesh file, metres per unit, and the size range of the organs meshed
UNITS = {"m": 1.0, "cm": 0.01, "mm": 0.001}
# (largest bounding-box side: a kidney ~0.1 m, an adult liver ~0.2-0.3 m, an airway segment or a
# tumour ~0.01-0.02 m).
ORGAN_SIZE_RANGE_M = (0.01, 0.3)
# Mesh and clouds whose sizes (bounding-box diagonals) differ by more than this factor disagree
# on units. A partial view shows a part of the organ, down to a few centimetres of a liver
# (a factor ~10), and a wide one some background; a unit error is a factor of 100 or 1000.
SCALE_MISMATCH_FACTOR = 30.0
# The clouds' box may miss the mesh's by this fraction of the mesh's diagonal (deformation,
# noise, calibration) before they count as not overlapping.
OVERLAP_TOLERANCE = 0.1
# Percentiles of the clouds' coordinates that bound them: stray points do not stretch the box.
CLOUD_PERCENTILES = (0.5, 99.5)
# Fixed vertices spread less than this fraction of the mesh's size across a second axis lie on a line.
_SINGULAR_SPREAD = 1e-6


class PatientMeshError(ValueError):
    """A mesh the simulator cannot use, or that disagrees with the clouds; the message is one
    line and says what to change."""


@dataclass(frozen=True)
class Plane:
    """Vertices within `distance` (m) of the plane through `point` with `normal` (world frame)."""

    point: tuple[float, float, float]
    normal: tuple[float, float, float]
    distance: float

    def contains(self, vertices: np.ndarray) -> np.ndarray:
        normal = np.asarray(self.normal, dtype=np.float64)
        length = np.linalg.norm(normal)
        if not length > 0.0 or not self.distance >= 0.0:
            raise PatientMeshError(f"a fixed plane needs a non-zero normal and a distance >= 0, got {self}")
        return np.abs((vertices - np.asarray(self.point, dtype=np.float64)) @ (normal / length)) <= self.distance


@dataclass(frozen=True)
class Box:
    """Vertices inside the axis-aligned box [minimum, maximum] (world frame, m), faces included."""

    minimum: tuple[float, float, float]
    maximum: tuple[float, float, float]

    def contains(self, vertices: np.ndarray) -> np.ndarray:
        low, high = np.asarray(self.minimum, dtype=np.float64), np.asarray(self.maximum, dtype=np.float64)
        if np.any(low > high):
            raise PatientMeshError(f"a fixed box needs minimum <= maximum on every axis, got {self}")
        return np.all((vertices >= low) & (vertices <= high), axis=1)


@dataclass(frozen=True)
class FixedSelection:
    """Vertices held fixed: the union of every criterion given (module doc)."""

    indices: tuple[int, ...] = ()
    planes: tuple[Plane, ...] = ()
    boxes: tuple[Box, ...] = ()
    groups: tuple[str, ...] = ()


@dataclass(frozen=True)
class PatientMeshFile:
    """A mesh as read (file units and frame) and the vertex indices (of `mesh`) of its named groups."""

    mesh: TetMesh
    groups: Mapping[str, np.ndarray] = field(default_factory=dict)


def read_patient_mesh(path: str | Path) -> PatientMeshFile:
    """Read a tetrahedral mesh with meshio (.msh, .vtu, .vtk, ... ; legacy Gmsh v1 through
    core.geometry.mesh.load_mesh, without groups). Only tetrahedra are kept, vertices of no tetrahedron
    are dropped; the `fixed` point data and the named groups follow the kept vertices."""
    path = Path(path)
    check_mesh_file(path)
    if _is_gmsh_v1(path):
        return PatientMeshFile(load_mesh(path))
    data = _meshio_read(path)
    tetrahedra = [block.data for block in data.cells if block.type == "tetra"]
    if not tetrahedra:
        raise MeshFileError(f"{path} is not a tetrahedral mesh (no tetra cells)")
    tetrahedra = np.concatenate(tetrahedra).astype(np.int64)
    used = np.unique(tetrahedra)
    new_index = np.full(len(data.points), -1, dtype=np.int64)
    new_index[used] = np.arange(used.size)
    fixed = ()
    if "fixed" in data.point_data:
        fixed = np.flatnonzero(np.asarray(data.point_data["fixed"]).reshape(-1)[used] != 0)
    try:
        mesh = TetMesh(np.asarray(data.points, dtype=np.float64)[used, :3], new_index[tetrahedra], fixed,
                       name=path.stem)
    except (InvalidMeshError, DegenerateMeshError) as error:
        raise PatientMeshError(f"{path}: {error}") from None
    if 0 < mesh.flipped_count < mesh.tetrahedron_count:
        raise PatientMeshError(
            f"{path}: {mesh.flipped_count} of {mesh.tetrahedron_count} tetrahedra are inverted against the others "
            "(a tangled mesh, or mixed vertex orders): repair it in the mesher")
    groups = {}
    for name, vertex_indices in _named_vertex_sets(data).items():
        kept = new_index[vertex_indices]
        groups[name] = np.unique(kept[kept >= 0])
    return PatientMeshFile(mesh, groups)


def _meshio_read(path: Path):
    """meshio.read with every failure as MeshFileError. For a file that no reader of its
    extension accepts, meshio prints each reader's complaint and calls sys.exit: both are caught."""
    import meshio

    complaints = io.StringIO()
    try:
        with contextlib.redirect_stdout(complaints), contextlib.redirect_stderr(complaints):
            return meshio.read(path)
    except (Exception, SystemExit) as error:  # meshio raises many unrelated types for bad files
        reason = " ".join(complaints.getvalue().split()) or str(error)
        raise MeshFileError(f"{path} could not be read by meshio: {reason}") from None


def _named_vertex_sets(data) -> dict[str, np.ndarray]:
    """File point indices of each named cell set (gmsh physical groups) and point set."""
    sets = {}
    for name, per_block in data.cell_sets.items():
        if name.startswith("gmsh:"):  # meshio's bookkeeping of gmsh entities, not a user's group
            continue
        vertices = [np.asarray(block.data)[np.asarray(cells, dtype=np.int64)].reshape(-1)
                    for block, cells in zip(data.cells, per_block) if cells is not None and len(cells)]
        sets[name] = np.unique(np.concatenate(vertices)) if vertices else np.zeros(0, dtype=np.int64)
    for name, indices in data.point_sets.items():
        sets[name] = np.unique(np.asarray(indices, dtype=np.int64).reshape(-1))
    return sets


def place_mesh(mesh: TetMesh, scale: float = 1.0, pose: Sequence[float] = (0, 0, 0, 0, 0, 0, 1)) -> TetMesh:
    """The mesh in the world frame: vertices R (scale x) + t, with pose = [x, y, z, qx, qy, qz, qw]."""
    if not (np.isfinite(scale) and scale > 0.0):
        raise PatientMeshError(f"mesh_scale must be a positive number, got {scale}")
    try:
        matrix = pose_matrix(as_pose(pose))
    except InvalidPoseError as error:
        raise PatientMeshError(f"mesh_pose: {error}") from None
    return mesh.with_vertices(transform_points(matrix, scale * mesh.vertices))


def select_fixed(mesh: TetMesh, groups: Mapping[str, np.ndarray], selection: FixedSelection) -> np.ndarray:
    """Sorted vertex indices the selection picks (planes and boxes tested on `mesh`'s vertices)."""
    chosen = np.zeros(mesh.vertex_count, dtype=bool)
    indices = np.asarray(selection.indices, dtype=np.int64).reshape(-1)
    if indices.size and (indices.min() < 0 or indices.max() >= mesh.vertex_count):
        raise PatientMeshError(f"fixed vertex index out of range [0, {mesh.vertex_count}): "
                               f"min {indices.min()}, max {indices.max()}")
    chosen[indices] = True
    for region in (*selection.planes, *selection.boxes):
        chosen |= region.contains(mesh.vertices)
    for name in selection.groups:
        if name not in groups:
            found = ", ".join(sorted(groups)) or "none"
            raise PatientMeshError(f"the mesh has no group {name!r} (groups: {found})")
        chosen[groups[name]] = True
    return np.flatnonzero(chosen)


def check_simulatable(mesh: TetMesh) -> None:
    """PatientMeshError unless every connected part of the mesh is held by at least three
    non-collinear fixed vertices (else the stiffness is singular) and no element is flat or
    inverted."""
    if mesh.fixed_vertices.size == 0:
        raise PatientMeshError(
            "the mesh has no fixed vertices, so the simulator's stiffness is singular: select some "
            "(fixed vertex indices, a plane, a box or a group of the mesh file)")
    if mesh.fixed_vertices.size == mesh.vertex_count:
        raise PatientMeshError(f"all {mesh.vertex_count} vertices are fixed: nothing is left to deform")
    bad = flat_elements(mesh.vertices, mesh.tetrahedra)
    if bad:
        raise PatientMeshError(f"{bad} of {mesh.tetrahedron_count} tetrahedra are flat or inverted")
    part_count, part = _connected_parts(mesh)
    loose = np.flatnonzero(~_held_parts(mesh, part_count, part))
    if loose.size:
        sizes = np.bincount(part, minlength=part_count)[loose]
        shown = ", ".join(str(size) for size in sizes[:5]) + (", ..." if loose.size > 5 else "")
        raise PatientMeshError(
            f"{loose.size} of {part_count} connected parts of the mesh ({shown} vertices) are held by fewer than "
            "three non-collinear fixed vertices, so the simulator's stiffness is singular: fix more vertices "
            "there or remove those parts")


def check_against_clouds(mesh: TetMesh, clouds: Sequence[np.ndarray], scale_origin: Sequence[float] | None = None) -> None:
    """PatientMeshError when the placed mesh and the first clouds (points (K, 3), world frame)
    differ in size by more than SCALE_MISMATCH_FACTOR or their bounding boxes do not meet.

    Partial views pass: a cloud that sees one side of the organ lies inside the mesh's box and is
    smaller, within the factor. scale_origin: the world point mesh_scale scales the mesh about
    (mesh_pose's position) when the mesh comes from a scaled file; boxes that do not meet are then
    tested at the other units' scales, and one that makes them meet is named (a millimetre mesh
    read as centimetres is 10x too large and misplaced, within the size factor).
    """
    points = np.concatenate([np.asarray(cloud, dtype=np.float64).reshape(-1, 3) for cloud in clouds])
    points = points[np.isfinite(points).all(axis=1)]
    if not len(points):
        raise PatientMeshError("no finite cloud points to compare the mesh with")
    mesh_low, mesh_high = mesh.vertices.min(axis=0), mesh.vertices.max(axis=0)
    cloud_low, cloud_high = np.percentile(points, CLOUD_PERCENTILES, axis=0)
    mismatch = _box_mismatch(mesh_low, mesh_high, cloud_low, cloud_high)
    if mismatch is None:
        return
    if mismatch.startswith("the clouds do not overlap") and scale_origin is not None:
        origin = np.asarray(scale_origin, dtype=np.float64)
        for factor in _UNIT_FACTORS:
            if _box_mismatch(origin + factor * (mesh_low - origin), origin + factor * (mesh_high - origin),
                             cloud_low, cloud_high) is None:
                raise PatientMeshError(
                    f"the clouds do not overlap the mesh, but would with mesh_scale {factor:g} times its value: "
                    "is mesh_scale right for the mesh file's units? (0.001 for millimetres, 0.01 for centimetres)")
    raise PatientMeshError(mismatch)


# The ratios between the units of UNITS (nearest first): the scale errors a units mix-up makes.
_UNIT_FACTORS = (0.1, 10.0, 0.01, 100.0, 0.001, 1000.0)


def _box_mismatch(mesh_low: np.ndarray, mesh_high: np.ndarray, cloud_low: np.ndarray,
                  cloud_high: np.ndarray) -> str | None:
    """Why the mesh's and the clouds' bounding boxes disagree (check_against_clouds), or None."""
    mesh_size = float(np.linalg.norm(mesh_high - mesh_low))
    cloud_size = float(np.linalg.norm(cloud_high - cloud_low))
    sizes = f"bounding-box diagonals {mesh_size:.3g} m and {cloud_size:.3g} m"
    if mesh_size > SCALE_MISMATCH_FACTOR * cloud_size:
        ratio = mesh_size / max(cloud_size, np.finfo(float).tiny)
        return f"the mesh is ~{_rounded(ratio)}x larger than the clouds ({sizes}): {_unit_hint(ratio)}"
    if cloud_size > SCALE_MISMATCH_FACTOR * mesh_size:
        ratio = cloud_size / mesh_size
        return (f"the mesh is ~{_rounded(ratio)}x smaller than the clouds ({sizes}): "
                "is mesh_scale too small, or are the clouds not in metres?")
    gap = float(np.linalg.norm(np.maximum(0.0, np.maximum(cloud_low - mesh_high, mesh_low - cloud_high))))
    if gap > OVERLAP_TOLERANCE * mesh_size:
        offset = 0.5 * (cloud_low + cloud_high) - 0.5 * (mesh_low + mesh_high)
        return (f"the clouds do not overlap the mesh: their bounding boxes are {gap:.3g} m apart (clouds' centre "
                f"minus mesh's: [{offset[0]:.3g}, {offset[1]:.3g}, {offset[2]:.3g}] m): set mesh_pose to the "
                "registration of the mesh's frame to the world frame")
    return None


def _rounded(ratio: float) -> str:
    return f"{float(f'{ratio:.2g}'):g}"


def _unit_hint(ratio: float) -> str:
    """What a mesh `ratio` times larger than the clouds suggests about its unit."""
    for unit, name in (("mm", "millimetres"), ("cm", "centimetres")):
        if abs(np.log10(ratio * UNITS[unit])) < 0.5:
            return f"is it in {name}? set mesh_scale {UNITS[unit]:g}"
    return f"set mesh_scale to the mesh file's metres per unit (about {1.0 / ratio:.2g})"


def plausible_units(largest_side: float) -> list[tuple[str, float]]:
    """[(unit, metres per unit)] of UNITS that make a mesh's largest bounding-box side an organ's
    size (ORGAN_SIZE_RANGE_M), nearest the range's middle (log scale) first; empty if none does.
    Two of them fit a mesh of 3-30 file units: only the clouds tell which is right."""
    low, high = ORGAN_SIZE_RANGE_M
    fitting = sorted((abs(np.log(largest_side * scale / np.sqrt(low * high))), unit, scale)
                     for unit, scale in UNITS.items() if low <= largest_side * scale <= high)
    return [(unit, scale) for _, unit, scale in fitting]


def prepare_mesh(path: str | Path, fixed: FixedSelection = FixedSelection(), scale: float = 1.0,
                 pose: Sequence[float] = (0, 0, 0, 0, 0, 0, 1)) -> TetMesh:
    """The mesh file at `path`, scaled and placed in the world frame, with the file's fixed
    vertices and those `fixed` selects, checked for the simulator (module doc)."""
    read = read_patient_mesh(path)
    placed = place_mesh(read.mesh, scale, pose)
    chosen = np.union1d(read.mesh.fixed_vertices, select_fixed(placed, read.groups, fixed))
    mesh = placed.with_fixed(chosen)
    try:
        _check_regions(placed, fixed, scale, pose)
        check_simulatable(mesh)
    except PatientMeshError as error:
        raise PatientMeshError(f"{path}: {error}") from None
    return mesh


def _check_regions(placed: TetMesh, selection: FixedSelection, scale: float, pose: Sequence[float]) -> None:
    """PatientMeshError for a fixed plane or box that selects no vertex or every vertex of the
    placed mesh, saying whether it would select some read in the mesh file's units (planes and
    boxes are in the world frame, metres, after mesh_scale and mesh_pose; a user copying them from
    the CT's millimetres gets nothing, or everything)."""
    regions = [("fixed_plane", plane, _plane_in_file_units(plane, scale, pose)) for plane in selection.planes]
    regions += [("fixed_box", box, _box_in_file_units(box, scale, pose)) for box in selection.boxes]
    count = placed.vertex_count
    low, high = placed.vertices.min(axis=0), placed.vertices.max(axis=0)
    for name, region, in_file_units in regions:
        selected = int(np.count_nonzero(region.contains(placed.vertices)))
        if 0 < selected < count:
            continue
        what = "no vertex" if selected == 0 else f"all {count} vertices"
        message = (f"{name} selects {what} of the mesh, which spans [{low[0]:.4g}, {low[1]:.4g}, {low[2]:.4g}] to "
                   f"[{high[0]:.4g}, {high[1]:.4g}, {high[2]:.4g}] m in the world frame")
        in_file = int(np.count_nonzero(in_file_units.contains(placed.vertices)))
        if 0 < in_file < count:
            message += (f"; read in the mesh file's units it would select {in_file}: give it in the world frame, "
                        f"metres (after mesh_scale and mesh_pose), e.g. {_region_values(in_file_units)}")
        raise PatientMeshError(message)


def _plane_in_file_units(plane: Plane, scale: float, pose: Sequence[float]) -> Plane:
    """The plane whose values, read in the file's frame and units, are `plane`'s, in the world frame."""
    matrix = pose_matrix(as_pose(pose))
    point = transform_points(matrix, scale * np.asarray(plane.point, dtype=np.float64)[None])[0]
    normal = matrix[:3, :3] @ np.asarray(plane.normal, dtype=np.float64)
    return Plane(tuple(point), tuple(normal), scale * plane.distance)


def _box_in_file_units(box: Box, scale: float, pose: Sequence[float]) -> Box:
    """The world frame's axis-aligned bounds of the box whose values, read in the file's frame and
    units, are `box`'s (its corners placed as the mesh's vertices are)."""
    corners = np.array(np.meshgrid(*zip(box.minimum, box.maximum), indexing="ij")).reshape(3, -1).T
    placed = transform_points(pose_matrix(as_pose(pose)), scale * corners)
    return Box(tuple(placed.min(axis=0)), tuple(placed.max(axis=0)))


def _region_values(region: Plane | Box) -> str:
    values = ([*region.point, *region.normal, region.distance] if isinstance(region, Plane)
              else [*region.minimum, *region.maximum])
    return "[" + ", ".join(f"{value:.4g}" for value in values) + "]"


def _connected_parts(mesh: TetMesh) -> tuple[int, np.ndarray]:
    edges = mesh.edges
    adjacency = scipy.sparse.coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])),
                                        shape=(mesh.vertex_count,) * 2)
    return connected_components(adjacency, directed=False)


def _held_parts(mesh: TetMesh, part_count: int, part: np.ndarray) -> np.ndarray:
    """(parts,) whether each part's fixed vertices spread along two axes: the covariance of
    their positions has a second eigenvalue above rounding (one vertex, or a line of them,
    leaves a rotation free)."""
    fixed = mesh.fixed_vertices
    labels = part[fixed]
    positions = mesh.vertices[fixed] - mesh.vertices.mean(axis=0)
    counts = np.bincount(labels, minlength=part_count).astype(np.float64)
    means = np.stack([np.bincount(labels, positions[:, axis], part_count) for axis in range(3)], axis=1)
    means /= np.maximum(counts, 1.0)[:, None]
    products = (positions[:, :, None] * positions[:, None, :]).reshape(-1, 9)
    second_moments = np.stack([np.bincount(labels, products[:, k], part_count) for k in range(9)], axis=1)
    covariances = second_moments.reshape(-1, 3, 3) / np.maximum(counts, 1.0)[:, None, None]
    covariances -= means[:, :, None] * means[:, None, :]
    second_variance = np.linalg.eigvalsh(covariances)[:, 1]
    diagonal = np.linalg.norm(np.ptp(mesh.vertices, axis=0))
    return (counts >= 3) & (second_variance > (_SINGULAR_SPREAD * diagonal) ** 2)
