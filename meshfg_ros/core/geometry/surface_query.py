"""What a planner asks of an estimate: for points, the closest surface point, the signed
distance (negative inside the tissue), the outward normal and the distance's standard deviation.

`SurfaceQuery(vertices, surface_triangles, position_covariance)` answers for one mesh state.
The closest point is the exact closest point on the surface triangles (core/geometry/closest_point.py:
its surface grid and libigl's AABB tree find the triangle, Ericson's closed form projects on it).

Inside or outside: the sign of (p - c) . n, with n the angle-weighted pseudo-normal of the
feature the closest point c lies on (the face's normal, an edge's sum of its two faces' normals,
a vertex's normals of its faces weighted by their angles there; libigl computes them). For a
closed, manifold, consistently oriented surface (a tetrahedral mesh's boundary) this sign is
exact (Baerentzen and Aanaes, "Signed distance computation using the angle weighted
pseudonormal", IEEE TVCG 2005), also where the closest point is an edge or a corner, where a
face normal's sign fails.

The normal returned is the signed distance's gradient, the unit direction (p - c) / d: the face's
normal where c lies inside a face, the direction away from an edge or a corner otherwise; for a
point on the surface (|d| below 1e-12 of the surface's extent) the feature's pseudo-normal.
Moving p along it changes d at rate 1.

The standard deviation: to first order the distance changes by -n . dc when the surface moves,
and c = sum_i w_i x_i (w: the barycentric weights of c on its triangle, x_i its corners; by the
envelope theorem the weights' own change does not enter), so var d = n^T Cov(sum_i w_i x_i) n.
The estimate publishes only each vertex's 3x3 block C_i, not the blocks between vertices.
By Cauchy-Schwarz |n^T C_ij n| <= s_i s_j with s_i = sqrt(n^T C_i n), so
    std d <= sum_i w_i s_i,
with equality when the corners' errors along n are fully correlated. That bound is returned: it
holds whatever the correlation is, so a planner keeping k standard deviations of clearance
keeps at least that many; and neighbouring vertices of an elastic mesh move together, so it is
close (taking them as independent, sqrt(sum_i w_i^2 s_i^2), would understate the std by up to
sqrt(3) at a triangle's centre when they are correlated). It is the surface's uncertainty only:
the queried point's own is not in it.

`query_timing` measures one query of many points on a surface, for `meshfg bench`.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import igl
import numpy as np

from meshfg_ros.core.geometry.closest_point import (
    REGION_EDGE_AB,
    REGION_EDGE_AC,
    REGION_EDGE_BC,
    REGION_FACE,
    REGION_VERTEX_A,
    REGION_VERTEX_C,
    ClosestPointIndex,
    InvalidGeometryError,
)
from meshfg_ros.core.geometry.mesh import cross

__all__ = ["SurfaceDistances", "SurfaceQuery", "query_timing"]

# A point nearer the surface than this share of the surface's extent is on it: its normal is the
# pseudo-normal, not the direction (p - c) / d that rounding makes arbitrary there.
_ON_SURFACE = 1e-12
# libigl's face-edge k (of F * 3) is the edge opposite corner k; the edge of each edge region.
_OPPOSITE_CORNER = {REGION_EDGE_BC: 0, REGION_EDGE_AC: 1, REGION_EDGE_AB: 2}


@dataclass(frozen=True)
class SurfaceDistances:
    """The answers for K points: closest (K, 3) surface points, signed_distance (K,) metres
    (negative inside), normal (K, 3) outward unit normals, distance_std (K,) metres or None (the
    estimate has no covariance), triangle (K,) the closest surface triangle (an index into the
    surface triangles), barycentric (K, 3) the closest point's weights on its corners."""

    closest: np.ndarray
    signed_distance: np.ndarray
    normal: np.ndarray
    distance_std: np.ndarray | None
    triangle: np.ndarray
    barycentric: np.ndarray


def _unit(vectors: np.ndarray) -> np.ndarray:
    length = np.linalg.norm(vectors, axis=-1, keepdims=True)
    return np.divide(vectors, length, out=np.zeros_like(vectors), where=length > 0.0)


class SurfaceQuery:
    """Signed distances to one mesh state's surface (module docstring).

    vertices (N, 3) metres; surface_triangles (F, 3), counter-clockwise seen from outside (as
    TetMesh and TetraMesh give them); position_covariance (N, 3, 3) per-vertex blocks (m^2), or
    None / empty: distance_std is then None. InvalidGeometryError for bad shapes or values.
    """

    def __init__(self, vertices, surface_triangles, position_covariance=None) -> None:
        self._index = ClosestPointIndex(vertices, surface_triangles)
        vertices, triangles = self._index.vertices, self._index.triangles
        self.vertices, self.surface_triangles = vertices, triangles
        covariance = None if position_covariance is None else np.asarray(position_covariance, dtype=np.float64)
        if covariance is not None and covariance.size == 0:
            covariance = None
        if covariance is not None and (covariance.shape != (len(vertices), 3, 3) or not np.isfinite(covariance).all()):
            raise InvalidGeometryError(f"position_covariance must be finite with shape ({len(vertices)}, 3, 3), "
                                       f"got {covariance.shape}")
        self.position_covariance = covariance
        corners = vertices[triangles]
        self._face_normals = _unit(cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]))
        # Unreferenced (interior) vertices get no normal from libigl (NaN): never read, zeroed.
        self._vertex_normals = np.nan_to_num(igl.per_vertex_normals(
            vertices, triangles, igl.PER_VERTEX_NORMALS_WEIGHTING_TYPE_ANGLE, self._face_normals))
        edge_normals, _, face_edges = igl.per_edge_normals(
            vertices, triangles, igl.PER_EDGE_NORMALS_WEIGHTING_TYPE_UNIFORM)
        self._edge_normals = edge_normals
        self._face_edges = face_edges.reshape(3, len(triangles)).T  # (F, 3): the edge opposite each corner
        self._on_surface = _ON_SURFACE * float(np.ptp(vertices[np.unique(triangles)], axis=0).max())

    def query(self, points) -> SurfaceDistances:
        """The closest point, signed distance, normal and distance std of each of `points` (K, 3)."""
        found = self._index.associate(points)
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        triangle, region = found.triangle, found.region
        pseudo_normal = self._pseudo_normals(triangle, region)
        offset = points - found.closest
        signed = np.where(np.einsum("ij,ij->i", offset, pseudo_normal) < 0.0, -found.distance, found.distance)
        normal = self._face_normals[triangle]
        off_face = np.flatnonzero(region != REGION_FACE)
        if off_face.size:
            away = np.abs(signed[off_face]) > self._on_surface
            normal[off_face] = np.where(away[:, None], offset[off_face] / np.where(away, signed[off_face], 1.0)[:, None],
                                        _unit(pseudo_normal[off_face]))
        return SurfaceDistances(found.closest, signed, normal, self._distance_std(triangle, found.barycentric, normal),
                                triangle, found.barycentric)

    def _pseudo_normals(self, triangle: np.ndarray, region: np.ndarray) -> np.ndarray:
        """(K, 3) pseudo-normal of the feature (face, edge, vertex) each closest point lies on."""
        pseudo = self._face_normals[triangle]
        vertex = np.flatnonzero((region >= REGION_VERTEX_A) & (region <= REGION_VERTEX_C))
        corners = self.surface_triangles[triangle[vertex], region[vertex] - REGION_VERTEX_A]
        pseudo[vertex] = self._vertex_normals[corners]
        edge = np.flatnonzero(region >= REGION_EDGE_AB)
        opposite = np.select([region[edge] == code for code in _OPPOSITE_CORNER], list(_OPPOSITE_CORNER.values()))
        pseudo[edge] = self._edge_normals[self._face_edges[triangle[edge], opposite]]
        return pseudo

    def _distance_std(self, triangle: np.ndarray, barycentric: np.ndarray, normal: np.ndarray) -> np.ndarray | None:
        """sum_i w_i sqrt(n^T C_i n) over the closest triangle's corners (module docstring)."""
        if self.position_covariance is None:
            return None
        blocks = self.position_covariance[self.surface_triangles[triangle]]  # (K, 3 corners, 3, 3)
        variance = np.einsum("ka,kcab,kb->kc", normal, blocks, normal)
        return np.einsum("kc,kc->k", barycentric, np.sqrt(np.maximum(variance, 0.0)))


def query_timing(vertices, surface_triangles, position_covariance, points, repeats: int = 20) -> tuple[float, float]:
    """(seconds to build a SurfaceQuery, median seconds of one query of all `points`) over
    `repeats` runs: what the planner service spends per estimate and per request."""
    builds, queries = [], []
    for _ in range(repeats):
        start = time.perf_counter()
        surface = SurfaceQuery(vertices, surface_triangles, position_covariance)
        built = time.perf_counter()
        surface.query(points)
        queries.append(time.perf_counter() - built)
        builds.append(built - start)
    return float(np.median(builds)), float(np.median(queries))
