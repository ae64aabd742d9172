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

`ClosestPointIndex` finds, for each measured point, the closest surface triangle with a
k-d tree over triangle centroids (scipy cKDTree) instead of all pairs, exactly: any triangle
at distance d from a point has its centroid within d + R of it (R: largest centroid-to-corner
distance), so after an upper bound U from nearby triangles only triangles whose centroid lies
within U + R can win. `CandidateCache` keeps, per point, every triangle within the best
distance + 2 * margin; while no surface vertex moves more than `margin`, the true closest
triangle stays in that set, so re-association is an exact projection on a few cached pairs
(up to 2 * margin when each point's new closest distance proves it, see CandidateCache).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

__all__ = [
    "REGION_EDGE_AB",
    "REGION_EDGE_AC",
    "REGION_EDGE_BC",
    "REGION_FACE",
    "REGION_VERTEX_A",
    "REGION_VERTEX_B",
    "REGION_VERTEX_C",
    "Association",
    "CandidateCache",
    "ClosestPointIndex",
    "InvalidGeometryError",
    "TriangleProjection",
    "brute_force_closest",
    "project_onto_triangles",
    "projection_jacobian",
]

REGION_FACE, REGION_VERTEX_A, REGION_VERTEX_B, REGION_VERTEX_C = 0, 1, 2, 3
REGION_EDGE_AB, REGION_EDGE_AC, REGION_EDGE_BC = 4, 5, 6

# Nearest centroids examined per point before the exactness check falls back to a ball query.
NEAREST_CENTROIDS = 16
# Guards divisions for (numerically) degenerate triangles; valid meshes never reach it.
_TINY = 1e-300


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
    # Ericson's tests in his order: the first region whose test passes wins.
    conditions = [
        (d1 <= 0.0) & (d2 <= 0.0),
        (d3 >= 0.0) & (d4 <= d3),
        (vc <= 0.0) & (d1 >= 0.0) & (d3 <= 0.0),
        (d6 >= 0.0) & (d5 <= d6),
        (vb <= 0.0) & (d2 >= 0.0) & (d6 <= 0.0),
        (va <= 0.0) & (d4 - d3 >= 0.0) & (d5 - d6 >= 0.0),
    ]
    codes = [REGION_VERTEX_A, REGION_VERTEX_B, REGION_EDGE_AB, REGION_VERTEX_C, REGION_EDGE_AC, REGION_EDGE_BC]
    region = np.select(conditions, codes, default=REGION_FACE).astype(np.int8)

    def safe(x):
        return np.where(np.abs(x) > _TINY, x, _TINY)

    t_ab = d1 / safe(d1 - d3)
    t_ac = d2 / safe(d2 - d6)
    t_bc = (d4 - d3) / safe((d4 - d3) + (d5 - d6))
    inverse = 1.0 / safe(va + vb + vc)
    face_v, face_w = vb * inverse, vc * inverse
    zero, one = np.zeros_like(d1), np.ones_like(d1)
    beta = np.select(
        [region == REGION_VERTEX_B, region == REGION_EDGE_AB, region == REGION_EDGE_BC, region == REGION_FACE],
        [one, t_ab, 1.0 - t_bc, face_v],
        default=zero,
    )
    gamma = np.select(
        [region == REGION_VERTEX_C, region == REGION_EDGE_AC, region == REGION_EDGE_BC, region == REGION_FACE],
        [one, t_ac, t_bc, face_w],
        default=zero,
    )
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
    n = np.cross(e1, e2)
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


def projection_jacobian(points, a, b, c, region=None) -> np.ndarray:
    """d closest / d (a, b, c): (P, 3, 9), columns [a_x a_y a_z b_x .. c_z], see module doc.

    `region` (P,) from `project_onto_triangles` (computed when None).
    """
    p = np.asarray(points, dtype=np.float64)
    a, b, c = (np.asarray(x, dtype=np.float64) for x in (a, b, c))
    if region is None:
        region = project_onto_triangles(p, a, b, c).region
    jacobian = np.zeros(p.shape[:-1] + (3, 9))
    eye = np.eye(3)
    for code, column in ((REGION_VERTEX_A, 0), (REGION_VERTEX_B, 3), (REGION_VERTEX_C, 6)):
        jacobian[region == code, :, column : column + 3] = eye
    for code, (u, v), (cu, cv) in (
        (REGION_EDGE_AB, (a, b), (0, 3)),
        (REGION_EDGE_AC, (a, c), (0, 6)),
        (REGION_EDGE_BC, (b, c), (3, 6)),
    ):
        mask = region == code
        if mask.any():
            dq_du, dq_dv = _edge_blocks(p[mask], u[mask], v[mask])
            jacobian[mask, :, cu : cu + 3] = dq_du
            jacobian[mask, :, cv : cv + 3] = dq_dv
    mask = region == REGION_FACE
    if mask.any():
        blocks = _face_blocks(p[mask], a[mask], b[mask], c[mask])
        jacobian[mask] = np.concatenate(blocks, axis=-1)
    return jacobian


def _check_points(points) -> np.ndarray:
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise InvalidGeometryError(f"points must have shape (K, 3), got {points.shape}")
    if not np.all(np.isfinite(points)):
        raise InvalidGeometryError("points contain NaN or infinite coordinates")
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


def _segment_argmin(owner: np.ndarray, values: np.ndarray, count: int):
    """Per owner in [0, count): (min value, index into values of its first minimiser); owners
    without entries get (inf, -1). `owner` must be sorted ascending."""
    best = np.full(count, np.inf)
    np.minimum.at(best, owner, values)
    winner = np.flatnonzero(values <= best[owner])
    first_owner, first_position = np.unique(owner[winner], return_index=True)
    argmin = np.full(count, -1, dtype=np.int64)
    argmin[first_owner] = winner[first_position]
    return best, argmin


class ClosestPointIndex:
    """Exact closest-triangle queries on one surface state through a k-d tree of centroids.

    vertices (N, 3), triangles (F, 3) int indices into vertices.
    """

    def __init__(self, vertices, triangles):
        vertices = np.asarray(vertices, dtype=np.float64)
        triangles = np.asarray(triangles)
        if vertices.ndim != 2 or vertices.shape[1] != 3 or not np.all(np.isfinite(vertices)):
            raise InvalidGeometryError(f"vertices must be finite with shape (N, 3), got {vertices.shape}")
        if triangles.ndim != 2 or triangles.shape[1] != 3 or triangles.shape[0] == 0:
            raise InvalidGeometryError(f"triangles must have shape (F>0, 3), got {triangles.shape}")
        if not np.issubdtype(triangles.dtype, np.integer) or triangles.min() < 0 or triangles.max() >= len(vertices):
            raise InvalidGeometryError(f"triangles must index vertices [0, {len(vertices)})")
        self.vertices = vertices
        self.triangles = triangles.astype(np.int64)
        corners = vertices[self.triangles]
        centroids = corners.mean(axis=1)
        self.radius = np.sqrt(((corners - centroids[:, None]) ** 2).sum(-1)).max(axis=1)
        self.max_radius = float(self.radius.max())
        self.tree = cKDTree(centroids)

    def _project(self, points: np.ndarray, triangle: np.ndarray) -> TriangleProjection:
        corners = self.vertices[self.triangles[triangle]]
        return project_onto_triangles(points, corners[:, 0], corners[:, 1], corners[:, 2])

    def candidate_pairs(self, points, slack: float = 0.0, max_distance: float = np.inf):
        """All (point, triangle) pairs whose exact distance is within `slack` of the point's
        closest distance, for points whose closest distance is <= max_distance.

        Triangles are screened with the lower bound |p - centroid| - radius of their distance
        before any exact projection. Returns (point (Q,) sorted, triangle (Q,), squared (Q,)).
        """
        points = _check_points(points)
        count = len(points)
        k = min(NEAREST_CENTROIDS, self.tree.n)
        centroid_distance, nearest = self.tree.query(points, k=k)
        centroid_distance = centroid_distance.reshape(count, k)
        nearest = nearest.reshape(count, k)
        # Upper bound: exact distance to the triangle of the nearest centroid.
        upper = np.sqrt(self._project(points, nearest[:, 0]).squared_distance)
        limit = np.minimum(upper, max_distance) + slack
        lower = centroid_distance - self.radius[nearest]
        rows, columns = np.nonzero(lower <= limit[:, None])
        pair_squared = self._project(points[rows], nearest[rows, columns]).squared_distance
        pair_triangle = nearest[rows, columns]
        best, _ = _segment_argmin(rows, pair_squared, count)
        limit = np.minimum(np.sqrt(best), max_distance) + slack
        # Exact when no triangle beyond the k nearest centroids can come within the limit.
        complete = (centroid_distance[:, -1] - self.max_radius > limit) | (k == self.tree.n)
        keep = (np.sqrt(pair_squared) <= limit[rows]) & complete[rows]
        pair_point, pair_triangle, pair_squared = [rows[keep]], [pair_triangle[keep]], [pair_squared[keep]]
        incomplete = np.flatnonzero(~complete)
        if incomplete.size:
            # Points far from the surface or next to large triangles: exact ball query.
            balls = self.tree.query_ball_point(points[incomplete], limit[incomplete] + self.max_radius)
            lengths = np.array([len(ball) for ball in balls], dtype=np.int64)
            ball_point = np.repeat(incomplete, lengths)
            ball_triangle = np.concatenate([np.asarray(ball, dtype=np.int64) for ball in balls])
            ball_squared = self._project(points[ball_point], ball_triangle).squared_distance
            best, _ = _segment_argmin(ball_point, ball_squared, count)
            inside = np.sqrt(ball_squared) <= np.minimum(np.sqrt(best[ball_point]), max_distance) + slack
            pair_point.append(ball_point[inside])
            pair_triangle.append(ball_triangle[inside])
            pair_squared.append(ball_squared[inside])
        pair_point = np.concatenate(pair_point)
        order = np.argsort(pair_point, kind="stable")
        return pair_point[order], np.concatenate(pair_triangle)[order], np.concatenate(pair_squared)[order]

    def associate(self, points, max_distance: float = np.inf) -> Association:
        """Closest triangle (exact) per point; points farther than max_distance get triangle -1."""
        points = _check_points(points)
        pair_point, pair_triangle, _ = self.candidate_pairs(points, 0.0, max_distance)
        return _associate_on_pairs(points, self.vertices, self.triangles, pair_point, pair_triangle, max_distance)


def _associate_on_pairs(points, vertices, triangles, pair_point, pair_triangle, max_distance=np.inf) -> Association:
    """Exact projection on the given candidate pairs and argmin per point."""
    count = len(points)
    corners = vertices[triangles[pair_triangle]]
    projection = project_onto_triangles(points[pair_point], corners[:, 0], corners[:, 1], corners[:, 2])
    best, argmin = _segment_argmin(pair_point, projection.squared_distance, count)
    found = (argmin >= 0) & (best <= max_distance**2)
    chosen = argmin[found]
    triangle = np.full(count, -1, dtype=np.int64)
    triangle[found] = pair_triangle[chosen]
    closest = np.full((count, 3), np.nan)
    closest[found] = projection.closest[chosen]
    barycentric = np.full((count, 3), np.nan)
    barycentric[found] = projection.barycentric[chosen]
    region = np.full(count, -1, dtype=np.int8)
    region[found] = projection.region[chosen]
    distance = np.full(count, np.inf)
    distance[found] = np.sqrt(best[found])
    return Association(triangle, closest, barycentric, region, distance)


class CandidateCache:
    """Closest-triangle association kept exact, with a k-d tree query only after large motion.

    The cache holds, per point, every triangle within reach = (closest distance + 2 * margin)
    of it at the vertices it was built on. Distances change by at most the largest vertex
    motion `moved`, so a triangle outside the set is now farther than reach - moved: the
    closest cached triangle is the true closest whenever its distance is below that bound
    (always so for moved <= margin). `associate` projects onto the cached pairs, checks the
    bound per point and rebuilds the cache only where it fails (or moved > 2 * margin).
    """

    def __init__(self, points, triangles, margin: float):
        if not margin > 0.0:
            raise InvalidGeometryError(f"margin must be > 0, got {margin}")
        self.points = _check_points(points)
        self.triangles = np.asarray(triangles, dtype=np.int64)
        self.margin = float(margin)
        self._surface_vertices = np.unique(self.triangles)
        self.rebuild_count = 0
        self._built_on: np.ndarray | None = None
        self._pair_point = self._pair_triangle = self._reach = None

    def _rebuild(self, vertices: np.ndarray) -> None:
        index = ClosestPointIndex(vertices, self.triangles)
        self._pair_point, self._pair_triangle, squared = index.candidate_pairs(self.points, 2.0 * self.margin)
        best, _ = _segment_argmin(self._pair_point, squared, len(self.points))
        # Every triangle outside the candidates was farther than this (candidate_pairs' limit).
        self._reach = np.sqrt(best) + 2.0 * self.margin
        self._built_on = vertices.copy()
        self.rebuild_count += 1

    def subset(self, mask: np.ndarray) -> CandidateCache:
        """The cache of the points selected by boolean `mask` (keeps their candidates)."""
        mask = np.asarray(mask, dtype=bool)
        out = CandidateCache(self.points[mask], self.triangles, self.margin)
        if self._built_on is not None:
            new_index = np.cumsum(mask) - 1
            keep = mask[self._pair_point]
            out._pair_point = new_index[self._pair_point[keep]]
            out._pair_triangle = self._pair_triangle[keep]
            out._reach = self._reach[mask]
            out._built_on = self._built_on
            out.rebuild_count = self.rebuild_count
        return out

    def associate(self, vertices) -> Association:
        """Exact closest triangle of every point on the surface at `vertices` (N, 3)."""
        vertices = np.asarray(vertices, dtype=np.float64)
        used = self._surface_vertices
        if self._built_on is not None:
            moved = float(np.max(np.linalg.norm(vertices[used] - self._built_on[used], axis=1)))
            if moved <= 2.0 * self.margin:
                association = _associate_on_pairs(self.points, vertices, self.triangles, self._pair_point,
                                                  self._pair_triangle)
                # Per-point proof instead of moved <= margin: saves ~half the k-d tree rebuilds
                # of an LM update (its first steps move the newest state by about a margin).
                if moved <= self.margin or np.all(association.distance < self._reach - moved):
                    return association
        self._rebuild(vertices)
        return _associate_on_pairs(self.points, vertices, self.triangles, self._pair_point, self._pair_triangle)


def brute_force_closest(points, vertices, triangles) -> Association:
    """All-pairs closest triangle (reference for tests; O(K F) memory)."""
    points = _check_points(points)
    triangles = np.asarray(triangles, dtype=np.int64)
    pair_point = np.repeat(np.arange(len(points)), len(triangles))
    pair_triangle = np.tile(np.arange(len(triangles)), len(points))
    return _associate_on_pairs(points, np.asarray(vertices, dtype=np.float64), triangles, pair_point, pair_triangle)
