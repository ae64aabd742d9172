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

`ClosestPointIndex` finds, for each measured point, the exact closest surface triangle, then
re-projects the point on that triangle with `project_onto_triangles`, so association, residual
and Jacobian all come from the one closed form above. The measured points lie within a few
noise sigmas of the surface, a fraction of its edge length, and the search is made for every
state LM tries (three per paper-scale update), so it is answered first from a uniform grid of
the surface, made per state: each triangle is listed in the cells that its bounding box,
grown by a reach, overlaps, and a point whose closest listed triangle lies within the reach is
answered from its own cell's list, exactly (any triangle at least as close lies within the
reach, so its grown box holds the point and its cell lists it); ties go to the lowest triangle
index, as in the all-pairs search. libigl's AABB tree (a bounding-volume hierarchy over the
triangles) answers the points the grid cannot: outside it, or farther than the reach. With
`scan_beyond_reach` (the measurement factor's searches), a point a little beyond the reach (a
leak that the gate let through) is answered by the grid too, as exactly, from the lists of the
few cells around it that can hold a triangle as close as the best one within half a cell of
it; a search with no point far beyond builds no tree (on the organ-scale surface a tree per
state cost about a third of a trial's search, for the hundred or so gated points of a cloud of
20,000 beyond one edge).
libigl has no search bounded to a distance from the surface and builds its tree anew for each
state: near the paper-scale surface the grid answers in about half libigl's time, on the
organ-scale surface the two are alike (docs/design-notes.md, "Where an update's time goes",
with the alternatives measured).
"""

from __future__ import annotations

from dataclasses import dataclass

import igl
import numba
import numpy as np
from numba.types import float64, int64

import meshfg_ros.core.worker_threads as worker_threads
from meshfg_ros.core.geometry.kernel_types import read_only
from meshfg_ros.core.geometry.mesh import cross

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
    "project_onto_mesh_triangles",
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


@numba.njit(inline="always")
def _safe(x):
    """x, or _TINY where |x| is not above it (a degenerate triangle's divisor)."""
    return x if abs(x) > _TINY else _TINY


@numba.njit(inline="always")
def _closest_on_triangle(p, a, b, c):
    """(region code, beta, gamma) of the closest point of triangle (a, b, c) to p: Ericson's
    tests in his order (the first region whose test passes wins). The closest point is
    (1 - beta - gamma) a + beta b + gamma c."""
    ab0, ab1, ab2 = b[0] - a[0], b[1] - a[1], b[2] - a[2]
    ac0, ac1, ac2 = c[0] - a[0], c[1] - a[1], c[2] - a[2]
    ap0, ap1, ap2 = p[0] - a[0], p[1] - a[1], p[2] - a[2]
    bp0, bp1, bp2 = p[0] - b[0], p[1] - b[1], p[2] - b[2]
    cp0, cp1, cp2 = p[0] - c[0], p[1] - c[1], p[2] - c[2]
    d1, d2 = ab0 * ap0 + ab1 * ap1 + ab2 * ap2, ac0 * ap0 + ac1 * ap1 + ac2 * ap2
    d3, d4 = ab0 * bp0 + ab1 * bp1 + ab2 * bp2, ac0 * bp0 + ac1 * bp1 + ac2 * bp2
    d5, d6 = ab0 * cp0 + ab1 * cp1 + ab2 * cp2, ac0 * cp0 + ac1 * cp1 + ac2 * cp2
    vc = d1 * d4 - d3 * d2
    vb = d5 * d2 - d1 * d6
    va = d3 * d6 - d5 * d4
    if d1 <= 0.0 and d2 <= 0.0:
        return REGION_VERTEX_A, 0.0, 0.0
    if d3 >= 0.0 and d4 <= d3:
        return REGION_VERTEX_B, 1.0, 0.0
    if vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
        return REGION_EDGE_AB, d1 / _safe(d1 - d3), 0.0
    if d6 >= 0.0 and d5 <= d6:
        return REGION_VERTEX_C, 0.0, 1.0
    if vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
        return REGION_EDGE_AC, 0.0, d2 / _safe(d2 - d6)
    if va <= 0.0 and d4 - d3 >= 0.0 and d5 - d6 >= 0.0:
        t = (d4 - d3) / _safe((d4 - d3) + (d5 - d6))
        return REGION_EDGE_BC, 1.0 - t, t
    inverse = 1.0 / _safe(va + vb + vc)
    return REGION_FACE, vb * inverse, vc * inverse


@numba.njit(inline="always")
def _squared_distance(p, a, b, c, beta, gamma):
    """|q - p|^2 for q = (1 - beta - gamma) a + beta b + gamma c, summed as `_project` sums it."""
    alpha = 1.0 - beta - gamma
    distance = 0.0
    for k in range(3):
        distance += (alpha * a[k] + beta * b[k] + gamma * c[k] - p[k]) ** 2
    return distance


@numba.njit((read_only(float64, 2), read_only(float64, 2), read_only(int64, 2), read_only(int64, 1)), cache=True,
            boundscheck=True, error_model="numpy")
def _project(points, vertices, triangles, index):
    """Closest point on triangle triangles[index[i]] of `vertices` to points[i]: (closest,
    barycentric, region, squared distance).

    Compiled (numba) rather than numpy passes over all points, whose fixed cost would be most of
    their time on a window's clouds (docs/design-notes.md, "Compiled kernels")."""
    count = points.shape[0]
    closest = np.empty((count, 3))
    barycentric = np.empty((count, 3))
    region = np.empty(count, dtype=np.int8)
    squared = np.empty(count)
    for i in range(count):
        a, b, c = vertices[triangles[index[i], 0]], vertices[triangles[index[i], 1]], vertices[triangles[index[i], 2]]
        p = points[i]
        code, beta, gamma = _closest_on_triangle(p, a, b, c)
        alpha = 1.0 - beta - gamma
        region[i] = code
        barycentric[i, 0], barycentric[i, 1], barycentric[i, 2] = alpha, beta, gamma
        for k in range(3):
            closest[i, k] = alpha * a[k] + beta * b[k] + gamma * c[k]
        squared[i] = _squared_distance(p, a, b, c, beta, gamma)
    return closest, barycentric, region, squared


def project_onto_mesh_triangles(points, vertices, triangles, index) -> TriangleProjection:
    """Closest point on triangle triangles[index[i]] of `vertices` (N, 3) to points[i], points
    (P, 3) float64, index (P,) into triangles (F, 3)."""
    return TriangleProjection(*_project(np.ascontiguousarray(points, dtype=np.float64),
                                        np.ascontiguousarray(vertices, dtype=np.float64),
                                        np.ascontiguousarray(triangles, dtype=np.int64),
                                        np.ascontiguousarray(index, dtype=np.int64)))


def project_onto_triangles(points, a, b, c) -> TriangleProjection:
    """Closest point on triangle (a[i], b[i], c[i]) to points[i], all arrays (P, 3) float64."""
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise InvalidGeometryError(f"points must have shape (P, 3), got {points.shape}")
    corners = [np.broadcast_to(np.asarray(x, dtype=np.float64), points.shape) for x in (a, b, c)]
    count = len(points)
    return project_onto_mesh_triangles(points, np.concatenate(corners), np.arange(3 * count).reshape(3, count).T,
                                       np.arange(count))


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


# The surface grid (see the module doc), in the surface's median edge lengths: its cells (or its
# reach, where larger), its default reach, and the largest reach a caller may ask for (beyond it
# nearly every triangle is listed in every cell). The cells grow where a few far-flung or
# degenerate triangles would make more than _GRID_MAX_CELLS_PER_TRIANGLE per triangle. A point
# is answered from its cell's list within the reach less _GRID_ROUNDING of it and of the
# coordinates' magnitude, a margin that the listing's and the distances' rounding cannot cross.
GRID_CELL_EDGES = 0.5
GRID_REACH_EDGES = 0.33
GRID_MAX_REACH_EDGES = 1.0
_GRID_MAX_CELLS_PER_TRIANGLE = 64
# The grid's search runs on the worker threads (core/worker_threads.py) in parts of at least
# this many points: 20,000 points near the organ-scale surface take 10 ms on one thread.
PARALLEL_MIN_POINTS = 4000
_GRID_ROUNDING = 1e-9
# With `scan_beyond_reach`, a point beyond the reach is searched in the cells around it
# (`_grid_closest`) when they are at most this many; farther points go to libigl's tree.
_GRID_MAX_SCANNED_CELLS = 27


@numba.njit((read_only(float64, 2), read_only(int64, 2)), cache=True, boundscheck=True, error_model="numpy")
def _surface_extent(vertices, triangles):
    """(low (3,), high (3,)) corners of the triangles' bounding box and their median edge length."""
    low, high = np.full(3, np.inf), np.full(3, -np.inf)
    edges = np.empty(3 * triangles.shape[0])
    for f in range(triangles.shape[0]):
        for j in range(3):
            u, v = vertices[triangles[f, j]], vertices[triangles[f, (j + 1) % 3]]
            edges[3 * f + j] = np.sqrt((u[0] - v[0]) ** 2 + (u[1] - v[1]) ** 2 + (u[2] - v[2]) ** 2)
            for k in range(3):
                low[k], high[k] = min(low[k], u[k]), max(high[k], u[k])
    return low, high, np.median(edges)


@numba.njit((read_only(float64, 2), read_only(int64, 2), read_only(float64, 1), read_only(int64, 1), float64, float64),
            cache=True, boundscheck=True, error_model="numpy")
def _grid_listing(vertices, triangles, origin, dims, cell, reach):
    """(starts (cells + 1,), items): cell k = (x dims[1] + y) dims[2] + z lists the triangles
    items[starts[k]:starts[k + 1]], those whose bounding box grown by `reach` overlaps it."""
    count = triangles.shape[0]
    low = np.empty((count, 3), dtype=np.int64)
    high = np.empty((count, 3), dtype=np.int64)
    for f in range(count):
        for k in range(3):
            least, most = np.inf, -np.inf
            for j in range(3):
                value = vertices[triangles[f, j], k]
                least, most = min(least, value), max(most, value)
            low[f, k] = max(int(np.floor((least - reach - origin[k]) / cell)), 0)
            high[f, k] = min(int(np.floor((most + reach - origin[k]) / cell)), dims[k] - 1)
    starts = np.zeros(dims[0] * dims[1] * dims[2] + 1, dtype=np.int64)
    for f in range(count):
        for x in range(low[f, 0], high[f, 0] + 1):
            for y in range(low[f, 1], high[f, 1] + 1):
                for z in range(low[f, 2], high[f, 2] + 1):
                    starts[(x * dims[1] + y) * dims[2] + z + 1] += 1
    for k in range(starts.size - 1):
        starts[k + 1] += starts[k]
    filled = starts[:-1].copy()
    items = np.empty(starts[-1], dtype=np.int64)
    for f in range(count):
        for x in range(low[f, 0], high[f, 0] + 1):
            for y in range(low[f, 1], high[f, 1] + 1):
                for z in range(low[f, 2], high[f, 2] + 1):
                    k = (x * dims[1] + y) * dims[2] + z
                    items[filled[k]] = f
                    filled[k] += 1
    return starts, items


@numba.njit(inline="always")
def _scan_cell(p, vertices, triangles, starts, items, k, best, best_triangle):
    """(best squared distance, its triangle) over cell k's list and the given best: the lowest
    index among equal distances."""
    for j in range(starts[k], starts[k + 1]):
        f = items[j]
        a, b, c = vertices[triangles[f, 0]], vertices[triangles[f, 1]], vertices[triangles[f, 2]]
        _, beta, gamma = _closest_on_triangle(p, a, b, c)
        distance = _squared_distance(p, a, b, c, beta, gamma)
        if distance < best or (distance == best and f < best_triangle):
            best, best_triangle = distance, f
    return best, best_triangle


@numba.njit(inline="always")
def _scan_cells(p, vertices, triangles, starts, items, dims, low, high, done_low, done_high, best, best_triangle):
    """`_scan_cell` over the cells [low, high] (per axis) but those in [done_low, done_high],
    already scanned."""
    for x in range(low[0], high[0] + 1):
        for y in range(low[1], high[1] + 1):
            for z in range(low[2], high[2] + 1):
                if not (done_low[0] <= x <= done_high[0] and done_low[1] <= y <= done_high[1]
                        and done_low[2] <= z <= done_high[2]):
                    best, best_triangle = _scan_cell(p, vertices, triangles, starts, items,
                                                     (x * dims[1] + y) * dims[2] + z, best, best_triangle)
    return best, best_triangle


@numba.njit(inline="always")
def _cell_range(p, radius, origin, dims, cell, low, high):
    """The grid cells [low, high] (per axis, clamped to the grid) that the cube of half-width
    `radius` about p overlaps; returns their count (a float: far points must not overflow)."""
    count = 1.0
    for axis in range(3):
        least = min(max((p[axis] - radius - origin[axis]) / cell, 0.0), dims[axis] - 1.0)
        most = min(max((p[axis] + radius - origin[axis]) / cell, 0.0), dims[axis] - 1.0)
        low[axis], high[axis] = int(least), int(most)
        count *= high[axis] - low[axis] + 1.0
    return count


@numba.njit((read_only(float64, 2), read_only(float64, 2), read_only(int64, 2), read_only(float64, 1),
             read_only(int64, 1), float64, float64, float64, read_only(int64, 1), read_only(int64, 1), int64),
            cache=True, boundscheck=False, error_model="numpy", nogil=True)
def _grid_closest(points, vertices, triangles, origin, dims, cell, certified, slack, starts, items, most_scanned):
    """Closest triangle per point (the lowest index among equal distances), or -1 where the grid
    cannot answer.

    A point inside the grid whose closest triangle in its own cell's list lies within the
    certified reach r is answered from that list. Otherwise, with d the distance to the best
    triangle in the lists of the cells within half a cell of the point (or for a point outside
    the grid, of the grid's nearest cells), every triangle at most d away is listed in a cell
    within d - r of the point: a triangle's list cells cover the ball of radius r about each of
    its points, so about its closest point to p, which lies d - r or less from p along the way.
    Those cells are scanned when there are at most `most_scanned` of them (points a little
    beyond the reach: the leaks a measurement gate lets through; 0 scans none); the others are
    left to libigl. `slack` bounds the rounding of the cells' bounds (see `_make_grid`).

    Not bounds-checked, which halves its time (0.4 against 0.75 ms for 2,000 points near the
    paper-scale surface): it reads through cell indices it has clamped to `dims` and through the
    listing that `_grid_listing` (bounds-checked) made of validated triangles."""
    found = np.full(points.shape[0], -1, dtype=np.int64)
    certified_reach = np.sqrt(certified)
    nearest = np.empty(3, dtype=np.int64)
    near_low = np.empty(3, dtype=np.int64)
    near_high = np.empty(3, dtype=np.int64)
    low = np.empty(3, dtype=np.int64)
    high = np.empty(3, dtype=np.int64)
    for i in range(points.shape[0]):
        p = points[i]
        inside = True
        for axis in range(3):
            position = (p[axis] - origin[axis]) / cell  # compared as a float: far points must not overflow an int
            if not 0.0 <= position < dims[axis]:
                inside = False
            nearest[axis] = int(min(max(position, 0.0), dims[axis] - 1.0))
        if not inside and most_scanned == 0:
            continue
        k = (nearest[0] * dims[1] + nearest[1]) * dims[2] + nearest[2]
        best, best_triangle = _scan_cell(p, vertices, triangles, starts, items, k, np.inf, -1)
        if inside and best <= certified:
            found[i] = best_triangle
            continue
        if most_scanned == 0:
            continue
        # Beyond the reach: first the cells within half a cell of the point (a near candidate; they
        # hold the nearest cell, scanned above), then those within its best distance less the reach.
        _cell_range(p, 0.5 * cell, origin, dims, cell, near_low, near_high)
        best, best_triangle = _scan_cells(p, vertices, triangles, starts, items, dims, near_low, near_high,
                                          nearest, nearest, best, best_triangle)
        if best_triangle < 0:
            continue
        radius = max(np.sqrt(best) - certified_reach, 0.0) + 2.0 * slack
        if _cell_range(p, radius, origin, dims, cell, low, high) > most_scanned:
            continue
        best, best_triangle = _scan_cells(p, vertices, triangles, starts, items, dims, low, high,
                                          near_low, near_high, best, best_triangle)
        found[i] = best_triangle
    return found


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
    """Exact closest-triangle queries on one surface state: the surface grid, with libigl's AABB
    tree for the points the grid cannot answer (see the module doc).

    vertices (N, 3), triangles (F, 3) int indices into vertices. `reach` (m, optional): the
    distance from the surface within which most queried points lie (default GRID_REACH_EDGES
    median edges); the grid answers the points within it, libigl the others. With
    `scan_beyond_reach`, for queries of points nearly all within the reach (a measurement
    factor's gated points, searched once per state), the grid also answers the few a little
    beyond it, from the cells around them, where building libigl's tree for them would cost more
    than the search; points anywhere (a planner's, a whole cloud's outliers) are better left to
    the tree, which a query of many points amortises.
    """

    def __init__(self, vertices, triangles, reach: float | None = None, scan_beyond_reach: bool = False):
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
        self._tree = None  # libigl's, made when a point first needs it
        self._grid = self._make_grid(reach)
        self._most_scanned = _GRID_MAX_SCANNED_CELLS if scan_beyond_reach else 0

    def _make_grid(self, reach: float | None):
        """(origin, dims, cell, certified squared reach, its rounding slack, starts, items) of the
        surface grid."""
        low, high, edge = _surface_extent(self.vertices, self.triangles)
        if not edge > 0.0:  # every triangle a point: one cell holds them all
            edge = max(float(np.max(high - low)), 1.0)
        given = reach is not None and np.isfinite(reach) and reach > 0.0
        reach = min(float(reach), GRID_MAX_REACH_EDGES * edge) if given else GRID_REACH_EDGES * edge
        cell = max(GRID_CELL_EDGES * edge, reach)
        most_cells = _GRID_MAX_CELLS_PER_TRIANGLE * len(self.triangles)
        while np.prod((high - low + 2.0 * reach) / cell + 1.0) > most_cells:
            cell *= 2.0
        origin = low - reach
        dims = (np.floor((high + reach - origin) / cell) + 1.0).astype(np.int64)
        magnitude = float(np.max(np.abs(np.concatenate([low, high]))))
        slack = _GRID_ROUNDING * (reach + magnitude)
        certified = max(reach - slack, 0.0) ** 2
        return (origin, dims, cell, certified, slack,
                *_grid_listing(self.vertices, self.triangles, origin, dims, cell, reach))

    def associate(self, points, max_distance: float = np.inf) -> Association:
        """Closest triangle (exact) per point; points farther than max_distance get triangle -1."""
        points = np.ascontiguousarray(_check_points(points))
        if not len(points):
            return _association(points, self.vertices, self.triangles, np.zeros(0, dtype=np.int64))
        triangle = np.concatenate(worker_threads.run_parts(_grid_closest, [
            (share, self.vertices, self.triangles, *self._grid, self._most_scanned)
            for share in worker_threads.split(points, len(points) // PARALLEL_MIN_POINTS)]))
        unanswered = np.flatnonzero(triangle < 0)
        if unanswered.size:
            if self._tree is None:
                self._tree = igl.AABB()
                self._tree.init(self.vertices, self.triangles)
            _, triangle[unanswered], _ = self._tree.squared_distance(self.vertices, self.triangles,
                                                                     np.ascontiguousarray(points[unanswered]))
        return _association(points, self.vertices, self.triangles, triangle, max_distance)


def triangle_corners(vertices: np.ndarray, triangles: np.ndarray, index: np.ndarray):
    """Corners (a, b, c), each (K, 3) and contiguous, of the triangles triangles[index] of
    `vertices`: the projection's arithmetic on them runs half again as fast as on the strided
    columns of one (K, 3, 3) gather."""
    corner_vertices = triangles[index]
    return tuple(vertices[corner_vertices[:, k]] for k in range(3))


def _association(points, vertices, triangles, triangle, max_distance=np.inf) -> Association:
    """Points associated with the given (closest) triangles by the closed-form projection."""
    projection = project_onto_mesh_triangles(points, vertices, triangles, triangle)
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
