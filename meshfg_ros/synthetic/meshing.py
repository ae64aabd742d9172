"""Mesh generators: structured cube / box meshes and the airway + tumour phantom (gmsh).

Everything here runs at scene set-up, never in an estimation loop. gmsh runs single-threaded
with user configuration files ignored so that the same arguments give the same mesh.
"""

from __future__ import annotations

import itertools
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np

from meshfg_ros.core.geometry.mesh import TetMesh

__all__ = [
    "AirwayPhantom",
    "MeshingError",
    "MeshingParameterError",
    "airway_phantom",
    "compact_tetrahedra",
    "gmsh_model",
    "box_mesh",
    "cross_section_area",
    "cube_mesh",
    "structured_box_mesh",
]

_GMSH_TETRAHEDRON = 4


class MeshingParameterError(ValueError):
    """A generator argument outside its valid range."""


class MeshingError(RuntimeError):
    """gmsh failed or produced an unusable mesh."""


def _kuhn_tetrahedra() -> np.ndarray:
    """Corner indices (bit x=1, y=2, z=4) of the 6 positive Kuhn tetrahedra of a unit cell.

    Every tetrahedron runs from corner 0 to corner 7 along one axis permutation, so all cells
    split their faces along the same diagonals and neighbouring cells conform.
    """
    tetrahedra = []
    for permutation in itertools.permutations(range(3)):
        path = [0]
        for axis in permutation:
            path.append(path[-1] | (1 << axis))
        inversions = sum(a > b for a, b in itertools.combinations(permutation, 2))
        if inversions % 2:  # odd permutation: negative determinant, swap to orient positively
            path[2], path[3] = path[3], path[2]
        tetrahedra.append(path)
    return np.array(tetrahedra, dtype=np.int64)


def structured_box_mesh(size, divisions, origin=(0.0, 0.0, 0.0), name: str = "box") -> TetMesh:
    """Axis-aligned box `size` (3,) from corner `origin`, `divisions` (3,) cells per axis, 6 tets per cell."""
    size = np.asarray(size, dtype=np.float64).reshape(-1)
    divisions = np.asarray(divisions).reshape(-1)
    origin = np.asarray(origin, dtype=np.float64).reshape(-1)
    if size.shape != (3,) or not np.all(size > 0.0) or not np.all(np.isfinite(size)):
        raise MeshingParameterError(f"size must be 3 positive lengths, got {size.tolist()}")
    if divisions.shape != (3,) or not np.issubdtype(divisions.dtype, np.integer) or np.any(divisions < 1):
        raise MeshingParameterError(f"divisions must be 3 integers >= 1, got {divisions.tolist()}")
    if origin.shape != (3,) or not np.all(np.isfinite(origin)):
        raise MeshingParameterError(f"origin must be a finite 3-vector, got {origin.tolist()}")
    nx, ny, nz = (int(d) for d in divisions)
    axes = [origin[a] + size[a] * np.arange(divisions[a] + 1) / divisions[a] for a in range(3)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)
    vertices = grid.reshape(-1, 3)

    def vertex_index(i, j, k):
        return (i * (ny + 1) + j) * (nz + 1) + k

    i, j, k = (a.reshape(-1) for a in np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz), indexing="ij"))
    corners = np.stack(
        [vertex_index(i + (c & 1), j + ((c >> 1) & 1), k + ((c >> 2) & 1)) for c in range(8)], axis=1
    )
    tetrahedra = corners[:, _kuhn_tetrahedra()].reshape(-1, 4)
    return TetMesh(vertices, tetrahedra, name=name)


def cube_mesh(side: float = 1.0, divisions: int = 7, origin=(0.0, 0.0, 0.0)) -> TetMesh:
    """Cube of edge `side` from corner `origin`: (divisions+1)^3 vertices, 6 * divisions^3 tets."""
    if not isinstance(divisions, (int, np.integer)):
        raise MeshingParameterError(f"divisions must be an integer, got {divisions!r}")
    return structured_box_mesh((side, side, side), (divisions,) * 3, origin, name="cube")


def box_mesh(target_vertices: int = 10000, size=(0.1, 0.1, 0.1), origin=(0.0, 0.0, 0.0)) -> TetMesh:
    """Box of `size` with near-cubic cells and about `target_vertices` vertices, for scaling benchmarks."""
    size = np.asarray(size, dtype=np.float64).reshape(-1)
    if size.shape != (3,) or not np.all(size > 0.0):
        raise MeshingParameterError(f"size must be 3 positive lengths, got {size.tolist()}")
    if target_vertices < 8:
        raise MeshingParameterError(f"target_vertices must be >= 8, got {target_vertices}")
    # Cell edge h with prod(size / h + 1) = target, by bisection on the monotone count.
    low, high = 1e-9 * size.max(), size.max()
    for _ in range(100):
        h = np.sqrt(low * high)
        if np.prod(size / h + 1.0) > target_vertices:
            low = h
        else:
            high = h
    divisions = np.maximum(1, np.rint(size / h)).astype(np.int64)
    return structured_box_mesh(size, divisions, origin, name="box")


def cross_section_area(mesh: TetMesh, plane_origin, plane_normal) -> float:
    """Area of the mesh's cross-section with a plane, from its closed outward surface.

    trimesh cuts the surface into segments; each is oriented along plane_normal x face_normal
    (counter-clockwise around the section) and the shoelace sum gives the enclosed area.
    """
    import trimesh
    import trimesh.intersections

    plane_normal = np.asarray(plane_normal, dtype=np.float64)
    plane_normal = plane_normal / np.linalg.norm(plane_normal)
    surface = trimesh.Trimesh(mesh.vertices, mesh.surface_triangles, process=False)
    segments, faces = trimesh.intersections.mesh_plane(
        surface, plane_normal, np.asarray(plane_origin, dtype=np.float64), return_faces=True
    )
    if len(segments) == 0:
        return 0.0
    forward = np.cross(plane_normal, mesh.triangle_normals()[faces])
    reversed_segment = np.einsum("ij,ij->i", segments[:, 1] - segments[:, 0], forward) < 0.0
    starts = np.where(reversed_segment[:, None], segments[:, 1], segments[:, 0])
    ends = np.where(reversed_segment[:, None], segments[:, 0], segments[:, 1])
    return float(0.5 * np.cross(starts, ends).sum(axis=0) @ plane_normal)


@dataclass(frozen=True)
class AirwayPhantom:
    """Straight airway (lumen along +z from `axis_origin`) with a tumour attached to its inner wall.

    tumour: tetrahedral mesh of the tumour; its fixed_vertices are those on the tumour-wall
        interface (the cylinder r = inner_radius).
    wall_vertices (P, 3), wall_triangles (Q, 3): the lumen's inner wall surface, normals
        pointing into the lumen, for the camera's ray casting and for segmentation leaks.
    occluded_fraction: tumour cross-section area / lumen area on the slice through
        tumour_centre, measured on the mesh.
    """

    tumour: TetMesh
    wall_vertices: np.ndarray
    wall_triangles: np.ndarray
    inner_radius: float
    length: float
    axis_origin: np.ndarray
    axis_direction: np.ndarray
    tumour_centre: np.ndarray
    tumour_semi_axes: np.ndarray
    occluded_fraction: float


def _cylinder_wall(radius: float, length: float, angular_segments: int, axial_segments: int):
    """Structured triangulation of the side of the cylinder r = radius, 0 <= z <= length, normals inward."""
    angles = 2.0 * np.pi * np.arange(angular_segments) / angular_segments
    heights = np.linspace(0.0, length, axial_segments + 1)
    angle_grid, height_grid = np.meshgrid(angles, heights, indexing="ij")
    vertices = np.stack(
        [radius * np.cos(angle_grid), radius * np.sin(angle_grid), height_grid], axis=-1
    ).reshape(-1, 3)
    j, k = (
        a.reshape(-1)
        for a in np.meshgrid(np.arange(angular_segments), np.arange(axial_segments), indexing="ij")
    )
    j_next = (j + 1) % angular_segments
    rows = axial_segments + 1
    a, b = j * rows + k, j_next * rows + k
    c, d = j_next * rows + k + 1, j * rows + k + 1
    # (a, b, c) would face outward (e_theta x e_z = e_r); reversed order faces the lumen.
    triangles = np.concatenate([np.stack([a, c, b], axis=1), np.stack([a, d, c], axis=1)])
    return vertices, triangles.astype(np.int64)


@contextmanager
def gmsh_model(name: str, options: dict[str, float]):
    """gmsh with a new model `name` and `options` set: in a new single-threaded session without
    configuration files (the same arguments give the same mesh), or in the caller's session,
    whose options and current model are restored afterwards. Errors become MeshingError."""
    import gmsh

    options = {"General.Terminal": 0, "General.NumThreads": 1, **options}
    owns_session = not gmsh.isInitialized()
    if owns_session:
        gmsh.initialize(["", "-nt", "1"], readConfigFiles=False, interruptible=False)
    else:
        previous_options = {key: gmsh.option.getNumber(key) for key in options}
        previous_model = gmsh.model.getCurrent()
    try:
        for key, value in options.items():
            gmsh.option.setNumber(key, value)
        gmsh.model.add(name)
        yield gmsh
    except MeshingError:
        raise
    except Exception as error:
        raise MeshingError(f"gmsh failed to mesh {name}: {error}") from None
    finally:
        if owns_session:
            gmsh.finalize()
        else:
            gmsh.model.remove()
            gmsh.model.setCurrent(previous_model)
            for key, value in previous_options.items():
                gmsh.option.setNumber(key, value)


def compact_tetrahedra(node_tags, coordinates, tet_node_tags) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (N, 3) and tetrahedra (M, 4) from gmsh's node tags, coordinates and the
    tetrahedra's node tags: only nodes used by tetrahedra are kept, in gmsh's node order."""
    node_tags = np.asarray(node_tags, dtype=np.int64)
    coordinates = np.asarray(coordinates, dtype=np.float64).reshape(-1, 3)
    tet_node_tags = np.asarray(tet_node_tags, dtype=np.int64).reshape(-1, 4)
    used_tags = np.unique(tet_node_tags)
    order = np.argsort(node_tags)
    vertices = coordinates[order[np.searchsorted(node_tags, used_tags, sorter=order)]]
    return vertices, np.searchsorted(used_tags, tet_node_tags)


def _gmsh_tumour(inner_radius, length, centre, semi_axes, mesh_size) -> tuple[np.ndarray, np.ndarray]:
    """Tetrahedralise (ellipsoid at `centre` with `semi_axes`) intersected with the lumen cylinder."""
    with gmsh_model("meshfg_airway_tumour", {"Mesh.MeshSizeMin": mesh_size, "Mesh.MeshSizeMax": mesh_size}) as gmsh:
        occ = gmsh.model.occ
        lumen = occ.addCylinder(0.0, 0.0, 0.0, 0.0, 0.0, length, inner_radius)
        ellipsoid = occ.addSphere(*centre, 1.0)
        occ.dilate([(3, ellipsoid)], *centre, *semi_axes)
        pieces, _ = occ.intersect([(3, ellipsoid)], [(3, lumen)])
        if len(pieces) != 1:
            raise MeshingError(f"ellipsoid and lumen intersect in {len(pieces)} volumes, expected 1")
        occ.synchronize()
        gmsh.model.mesh.generate(3)
        node_tags, coordinates, _ = gmsh.model.mesh.getNodes()
        element_types, _, element_nodes = gmsh.model.mesh.getElements(dim=3)
    if _GMSH_TETRAHEDRON not in list(element_types):
        raise MeshingError("gmsh produced no tetrahedra for the tumour")
    return compact_tetrahedra(node_tags, coordinates, element_nodes[list(element_types).index(_GMSH_TETRAHEDRON)])


def airway_phantom(
    inner_radius: float = 0.009,
    length: float = 0.04,
    tumour_centre_radius: float = 0.0072,
    tumour_semi_axes=(0.009, 0.009, 0.008),
    mesh_size: float = 0.0015,
    wall_angular_segments: int = 64,
    interface_tolerance: float = 1e-6,
) -> AirwayPhantom:
    """Airway tube along +z (z in [0, length]) with a tumour on its inner wall at +x, mid-length.

    The tumour is an ellipsoid (semi-axes along x, y, z) centred `tumour_centre_radius` from the
    axis, intersected with the lumen r <= inner_radius by gmsh/OpenCASCADE and meshed at
    `mesh_size`. Its surface vertices with r >= inner_radius - interface_tolerance lie on the
    airway wall and are fixed. The defaults occlude about half of the lumen cross-section.
    """
    semi_axes = np.asarray(tumour_semi_axes, dtype=np.float64).reshape(-1)
    if inner_radius <= 0.0 or length <= 0.0 or mesh_size <= 0.0:
        raise MeshingParameterError(
            f"inner_radius, length and mesh_size must be positive, got {inner_radius}, {length}, {mesh_size}"
        )
    if semi_axes.shape != (3,) or np.any(semi_axes <= 0.0):
        raise MeshingParameterError(f"tumour_semi_axes must be 3 positive lengths, got {semi_axes.tolist()}")
    if not abs(tumour_centre_radius - inner_radius) < semi_axes[0]:
        raise MeshingParameterError(
            f"the tumour centred {tumour_centre_radius} m from the axis with radial semi-axis "
            f"{semi_axes[0]} m does not cross the wall r = {inner_radius} m"
        )
    if semi_axes[2] >= length / 2:
        raise MeshingParameterError(f"tumour axial semi-axis {semi_axes[2]} m must be below length / 2")
    centre = np.array([tumour_centre_radius, 0.0, length / 2])
    vertices, tetrahedra = _gmsh_tumour(inner_radius, length, centre, semi_axes, mesh_size)
    tumour = TetMesh(vertices, tetrahedra, name="airway_tumour")
    surface = tumour.surface_vertices
    radii = np.linalg.norm(tumour.vertices[surface, :2], axis=1)
    tumour = tumour.with_fixed(surface[radii >= inner_radius - interface_tolerance])
    wall_vertices, wall_triangles = _cylinder_wall(
        inner_radius, length, wall_angular_segments, max(1, int(np.ceil(length / mesh_size)))
    )
    occluded = cross_section_area(tumour, centre, (0.0, 0.0, 1.0)) / (np.pi * inner_radius**2)
    return AirwayPhantom(
        tumour=tumour,
        wall_vertices=wall_vertices,
        wall_triangles=wall_triangles,
        inner_radius=float(inner_radius),
        length=float(length),
        axis_origin=np.zeros(3),
        axis_direction=np.array([0.0, 0.0, 1.0]),
        tumour_centre=centre,
        tumour_semi_axes=semi_axes,
        occluded_fraction=float(occluded),
    )
