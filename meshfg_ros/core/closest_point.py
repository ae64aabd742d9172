"""Closest points on triangles: closed-form projection, its exact Jacobian, and association.

`project_onto_triangles` is Ericson's closest-point-on-triangle ("Real-Time Collision
Detection", 5.1.5) evaluated for many (point, triangle) pairs at once: it classifies each
point into one of the 7 Voronoi regions of its triangle (3 vertices, 3 edges, the face) and
returns the closest point with its barycentric coordinates.

`projection_jacobian` is the derivative of that closed-form closest point q(a, b, c) with
respect to the 9 triangle vertex coordinates, region by region (the barycentrics depend on
the vertices too):
  vertex region v:        dq/dv = I, other vertices 0.
  edge u->v, q = u + t e: e = v - u, d = p - u, t = d.e / e.e
                          dq/du = (1 - t) I + e (dt/du)^T,  dt/du = (2 t e - e - d) / e.e
                          dq/dv = t I + e (dt/dv)^T,        dt/dv = (d - 2 t e) / e.e
  face, q = p - n s / n.n with n = (b - a) x (c - a), s = n.(p - a):
                          dq/dn = -(s / n.n) I - n (p - a)^T / n.n + 2 s n n^T / (n.n)^2
                          dq/da = n n^T / n.n + dq/dn [c - b]x,  dq/db = -dq/dn [c - a]x,
                          dq/dc = dq/dn [b - a]x.
On a region boundary both one-sided derivatives exist; the formula of the region the point
was classified into is used (the same choice as autograd through the closed form).

`ClosestPointIndex` finds, for each measured point, the exact closest surface triangle with
libigl's AABB tree (a bounding-volume hierarchy over the triangles, built per surface state),
then re-projects the point on that triangle with `project_onto_triangles`, so association,
residual and Jacobian all come from the one closed form above. Measured on the paper-scale
surface (588 triangles, 2,000 points): tree and query 1.6 ms, against 9 ms for the k-d tree
over centroids with an exact candidate screen that it replaced; organ scale (5,292 triangles,
20,000 points) 14 ms against about 100 ms.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import igl

from meshfg_ros.core.mesh import cross

__all__ = [
    "REGION_EDGE_AB",
    "REGION_EDGE_AC",
    "REGION_EDGE_BC",
    "REGION_FACE",
    "REGION_VERTEX_A",
    "REGION_VERTEX_B",
    "REGION_VERTEX_C",
    "Association",
    "ClosestPointIndex",
    "InvalidGeometryError",
    "MAX_COORDINATE",
    "TriangleProjection",
    "brute_force_closest",
    "project_onto_triangles",
    "projection_jacobian",
    "triangle_corners",
]

REGION_FACE, REGION_VERTEX_A, REGION_VERTEX_B, REGION_VERTEX_C = 0, 1, 2, 3
REGION_EDGE_AB, REGION_EDGE_AC, REGION_EDGE_BC = 4, 5, 6

# Guards divisions for (numerically) degenerate triangles; valid meshes never reach it.
_TINY = 1e-300
# Largest |coordinate| of a point or vertex that can be projected: the closed form multiplies four
# coordinate differences (vc = d1 d4 - d3 d2, each d a dot product of two differences), at most
# 144 (1e75)^4 = 1.4e302 < 1.8e308, and libigl's squared distances stay far from overflow, where
# its tree returns triangle indices out of range.
MAX_COORDINATE = 1e75


class InvalidGeometryError(ValueError):
    """Points, vertices or triangles with a wrong shape, non-finite values or bad indices."""


@dataclass(frozen=True)
class TriangleProjection:
    """Closest points of P points on P triangles: closest (P, 3), barycentric (P, 3) weights of
    (a, b, c), region (P,) Voronoi region code, squared_distance (P,)."""

    closest: np.ndarray
    barycentric: np.ndarray
    region: np.ndarray
    squared_distance: np.ndarray


def _dot(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    return np.einsum("...i,...i->...", u, v)


def project_onto_triangles(points, a, b, c) -> TriangleProjection:
    """Closest point on triangle (a[i], b[i], c[i]) to points[i], all arrays (P, 3) float64."""
    p = np.asarray(points, dtype=np.float64)
    a, b, c = (np.asarray(x, dtype=np.float64) for x in (a, b, c))
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = _dot(ab, ap), _dot(ac, ap)
    bp = p - b
    d3, d4 = _dot(ab, bp), _dot(ac, bp)
    cp = p - c
    d5, d6 = _dot(ab, cp), _dot(ac, cp)
    vc = d1 * d4 - d3 * d2
    vb = d5 * d2 - d1 * d6
    va = d3 * d6 - d5 * d4
    # Ericson's tests in his order: the first region whose test passes wins, so they are
    # written last to first, each overwriting the later ones (a third faster than np.select).
    region = np.full(d1.shape, REGION_FACE, dtype=np.int8)
    region[(va <= 0.0) & (d4 - d3 >= 0.0) & (d5 - d6 >= 0.0)] = REGION_EDGE_BC
    region[(vb <= 0.0) & (d2 >= 0.0) & (d6 <= 0.0)] = REGION_EDGE_AC
    region[(d6 >= 0.0) & (d5 <= d6)] = REGION_VERTEX_C
    region[(vc <= 0.0) & (d1 >= 0.0) & (d3 <= 0.0)] = REGION_EDGE_AB
    region[(d3 >= 0.0) & (d4 <= d3)] = REGION_VERTEX_B
    region[(d1 <= 0.0) & (d2 <= 0.0)] = REGION_VERTEX_A

    def safe(x):
        return np.where(np.abs(x) > _TINY, x, _TINY)

    # The face's barycentrics for every point (most lie inside a face), then the other regions'
    # on the points outside their face, all at once: each edge's parameter is computed for all
    # of them and kept where the point lies in that edge's region (elsewhere it may overflow
    # and is dropped).
    inverse = 1.0 / safe(va + vb + vc)
    beta, gamma = vb * inverse, vc * inverse
    outside = region != REGION_FACE
    if outside.any():
        o1, o2, o3, o4, o5, o6 = (d[outside] for d in (d1, d2, d3, d4, d5, d6))
        with np.errstate(divide="ignore", over="ignore", invalid="ignore"):
            t_ab = o1 / safe(o1 - o3)
            t_ac = o2 / safe(o2 - o6)
            t_bc = (o4 - o3) / safe((o4 - o3) + (o5 - o6))
        # Choices by region code minus one: vertex a, b, c, edge ab, ac, bc.
        code = region[outside] - REGION_VERTEX_A
        beta[outside] = np.choose(code, (0.0, 1.0, 0.0, t_ab, 0.0, 1.0 - t_bc))
        gamma[outside] = np.choose(code, (0.0, 0.0, 1.0, 0.0, t_ac, t_bc))
    alpha = 1.0 - beta - gamma
    barycentric = np.stack([alpha, beta, gamma], axis=-1)
    closest = alpha[..., None] * a + beta[..., None] * b + gamma[..., None] * c
    difference = closest - p
    return TriangleProjection(closest, barycentric, region, _dot(difference, difference))


def _skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrices [v]x, (..., 3, 3)."""
    s = np.zeros(v.shape[:-1] + (3, 3))
    s[..., 0, 1], s[..., 0, 2] = -v[..., 2], v[..., 1]
    s[..., 1, 0], s[..., 1, 2] = v[..., 2], -v[..., 0]
    s[..., 2, 0], s[..., 2, 1] = -v[..., 1], v[..., 0]
    return s


def _edge_blocks(p, u, v):
    """dq/du, dq/dv (..., 3, 3) for q = u + t (v - u), t = (p - u).e / e.e (unclamped)."""
    e, d = v - u, p - u
    ee = np.maximum(_dot(e, e), _TINY)
    t = _dot(d, e) / ee
    dt_du = (2.0 * t[..., None] * e - e - d) / ee[..., None]
    dt_dv = (d - 2.0 * t[..., None] * e) / ee[..., None]
    eye = np.eye(3)
    dq_du = (1.0 - t)[..., None, None] * eye + e[..., :, None] * dt_du[..., None, :]
    dq_dv = t[..., None, None] * eye + e[..., :, None] * dt_dv[..., None, :]
    return dq_du, dq_dv


def _face_blocks(p, a, b, c):
    """dq/da, dq/db, dq/dc (..., 3, 3) for q = p - n (n.(p - a)) / n.n (projection on the plane)."""
    e1, e2 = b - a, c - a
    n = cross(e1, e2)
    nn = np.maximum(_dot(n, n), _TINY)
    pa = p - a
    s = _dot(n, pa)
    outer_nn = n[..., :, None] * n[..., None, :]
    dq_dn = (
        -(s / nn)[..., None, None] * np.eye(3)
        - n[..., :, None] * pa[..., None, :] / nn[..., None, None]
        + 2.0 * (s / nn**2)[..., None, None] * outer_nn
    )
    dq_da = outer_nn / nn[..., None, None] + dq_dn @ _skew(c - b)
    dq_db = -(dq_dn @ _skew(e2))
    dq_dc = dq_dn @ _skew(e1)
    return dq_da, dq_db, dq_dc


# The corners an edge region's closest point moves with, (u, v) by region code (-1: no edge).
_EDGE_U = np.array([-1, -1, -1, -1, 0, 0, 1])
_EDGE_V = np.array([-1, -1, -1, -1, 1, 2, 2])


def projection_jacobian(points, a, b, c, region=None) -> np.ndarray:
    """d closest / d (a, b, c): (P, 3, 9), columns [a_x a_y a_z b_x .. c_z], see module doc.

    `region` (P,) from `project_onto_triangles` (computed when None). One pass per kind of
    region (vertex, edge, face), each corner's block placed by index.
    """
    p = np.asarray(points, dtype=np.float64)
    a, b, c = (np.asarray(x, dtype=np.float64) for x in (a, b, c))
    if region is None:
        region = project_onto_triangles(p, a, b, c).region
    region = np.asarray(region)
    jacobian = np.zeros((len(p), 3, 3, 3))  # point, row, corner, column
    vertex = np.flatnonzero((region >= REGION_VERTEX_A) & (region <= REGION_VERTEX_C))
    if vertex.size:
        jacobian[vertex, :, region[vertex] - REGION_VERTEX_A, :] = np.eye(3)
    edge = np.flatnonzero(region >= REGION_EDGE_AB)
    if edge.size:
        u_corner, v_corner = _EDGE_U[region[edge]], _EDGE_V[region[edge]]
        corners = np.stack((a[edge], b[edge], c[edge]), axis=1)
        rows = np.arange(edge.size)
        dq_du, dq_dv = _edge_blocks(p[edge], corners[rows, u_corner], corners[rows, v_corner])
        jacobian[edge, :, u_corner, :] = dq_du
        jacobian[edge, :, v_corner, :] = dq_dv
    jacobian = jacobian.reshape(len(p), 3, 9)
    face = np.flatnonzero(region == REGION_FACE)
    if face.size:
        jacobian[face] = np.concatenate(_face_blocks(p[face], a[face], b[face], c[face]), axis=-1)
    return jacobian


def _check_points(points) -> np.ndarray:
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise InvalidGeometryError(f"points must have shape (K, 3), got {points.shape}")
    if not np.all(np.isfinite(points)):
        raise InvalidGeometryError("points contain NaN or infinite coordinates")
    if points.size and np.abs(points).max() > MAX_COORDINATE:
        raise InvalidGeometryError(f"points have coordinates beyond {MAX_COORDINATE:g} m, which cannot be projected")
    return points


@dataclass(frozen=True)
class Association:
    """Closest surface triangle per point: triangle (K,) index into the triangle list (-1: none
    within the distance limit), closest (K, 3), barycentric (K, 3), region (K,), distance (K,)
    (inf where triangle is -1)."""

    triangle: np.ndarray
    closest: np.ndarray
    barycentric: np.ndarray
    region: np.ndarray
    distance: np.ndarray


class ClosestPointIndex:
    """Exact closest-triangle queries on one surface state (libigl AABB tree, see module doc).

    vertices (N, 3), triangles (F, 3) int indices into vertices.
    """

    def __init__(self, vertices, triangles):
        vertices = np.asarray(vertices, dtype=np.float64)
        triangles = np.asarray(triangles)
        if vertices.ndim != 2 or vertices.shape[1] != 3 or not np.all(np.isfinite(vertices)):
            raise InvalidGeometryError(f"vertices must be finite with shape (N, 3), got {vertices.shape}")
        if vertices.size and np.abs(vertices).max() > MAX_COORDINATE:
            raise InvalidGeometryError(f"vertices have coordinates beyond {MAX_COORDINATE:g} m, "
                                       "which cannot be projected")
        if triangles.ndim != 2 or triangles.shape[1] != 3 or triangles.shape[0] == 0:
            raise InvalidGeometryError(f"triangles must have shape (F>0, 3), got {triangles.shape}")
        if not np.issubdtype(triangles.dtype, np.integer) or triangles.min() < 0 or triangles.max() >= len(vertices):
            raise InvalidGeometryError(f"triangles must index vertices [0, {len(vertices)})")
        self.vertices = np.ascontiguousarray(vertices)
        self.triangles = np.ascontiguousarray(triangles, dtype=np.int64)
        self._tree = igl.AABB()
        self._tree.init(self.vertices, self.triangles)

    def associate(self, points, max_distance: float = np.inf) -> Association:
        """Closest triangle (exact) per point; points farther than max_distance get triangle -1."""
        points = _check_points(points)
        if not len(points):
            return _association(points, self.vertices, self.triangles, np.zeros(0, dtype=np.int64))
        _, triangle, _ = self._tree.squared_distance(self.vertices, self.triangles, np.ascontiguousarray(points))
        return _association(points, self.vertices, self.triangles, triangle, max_distance)


def triangle_corners(vertices: np.ndarray, triangles: np.ndarray, index: np.ndarray):
    """Corners (a, b, c), each (K, 3) and contiguous, of the triangles triangles[index] of
    `vertices`: the projection's arithmetic on them runs half again as fast as on the strided
    columns of one (K, 3, 3) gather."""
    corner_vertices = triangles[index]
    return tuple(vertices[corner_vertices[:, k]] for k in range(3))


def _association(points, vertices, triangles, triangle, max_distance=np.inf) -> Association:
    """Points associated with the given (closest) triangles by the closed-form projection."""
    projection = project_onto_triangles(points, *triangle_corners(vertices, triangles, triangle))
    distance = np.sqrt(projection.squared_distance)
    found = distance <= max_distance
    if found.all():
        return Association(triangle, projection.closest, projection.barycentric, projection.region, distance)
    return Association(
        np.where(found, triangle, -1),
        np.where(found[:, None], projection.closest, np.nan),
        np.where(found[:, None], projection.barycentric, np.nan),
        np.where(found, projection.region, np.int8(-1)).astype(np.int8),
        np.where(found, distance, np.inf),
    )


def brute_force_closest(points, vertices, triangles) -> Association:
    """All-pairs closest triangle, first minimiser on ties (reference for tests; O(K F) memory)."""
    points = _check_points(points)
    vertices = np.asarray(vertices, dtype=np.float64)
    triangles = np.asarray(triangles, dtype=np.int64)
    corners = vertices[triangles]
    count, faces = len(points), len(triangles)
    pair_points = np.repeat(points, faces, axis=0)
    pair_corners = np.tile(corners, (count, 1, 1))
    squared = project_onto_triangles(pair_points, pair_corners[:, 0], pair_corners[:, 1],
                                     pair_corners[:, 2]).squared_distance
    return _association(points, vertices, triangles, squared.reshape(count, faces).argmin(axis=1))
