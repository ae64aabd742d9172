"""Virtual endoscope: ray-cast a pinhole camera's pixel grid onto triangle surfaces.

It produces what segmented monocular depth estimation gives the estimator: world points on the
target surface only, with depth-dependent noise along each pixel ray, fewer returns at grazing
incidence and, optionally, segmentation leaks (points on occluders such as the tool or the
airway wall that the mask failed to remove). Camera frame follows the ROS optical convention:
x right, y down, z forward (the viewing direction).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple, Sequence

import numpy as np
import scipy.ndimage
from scipy.spatial.transform import Rotation

# Upper bound on (triangle, ray) candidate pairs tested at once, to bound memory (~100 MB).
_PAIR_CHUNK = 1_000_000
# Barycentric slack so that rays through a shared edge or vertex hit at least one triangle.
_BARYCENTRIC_SLACK = 1e-9


def as_point_array(name: str, points) -> np.ndarray:
    """Return `points` as a finite (K, 3) float64 array or raise ValueError naming it."""
    array = np.asarray(points, dtype=np.float64)
    if array.ndim != 2 or array.shape[1] != 3:
        raise ValueError(f"{name} must have shape (K, 3), got {array.shape}")
    if not np.isfinite(array).all():
        raise ValueError(f"{name} contains non-finite values")
    return array


def as_triangle_array(name: str, triangles, vertex_count: int) -> np.ndarray:
    """Return `triangles` as an (F, 3) int64 array of valid vertex indices or raise ValueError."""
    array = np.asarray(triangles)
    if array.ndim != 2 or array.shape[1] != 3:
        raise ValueError(f"{name} must have shape (F, 3), got {array.shape}")
    if array.size and not np.issubdtype(array.dtype, np.integer):
        raise ValueError(f"{name} must hold integer vertex indices, got dtype {array.dtype}")
    array = array.astype(np.int64)
    if array.size and (array.min() < 0 or array.max() >= vertex_count):
        raise ValueError(f"{name} index vertices outside [0, {vertex_count})")
    return array


class RayHits(NamedTuple):
    """First hit per ray: triangle index (-1 on a miss) and distance along the unit ray (inf)."""

    triangles: np.ndarray
    distances: np.ndarray


def first_ray_hits(origin, directions, vertices, triangles) -> RayHits:
    """First intersection of rays sharing one origin with a triangle soup.

    Hand-written because trimesh's RayMeshIntersector (rtree per ray) took ~20 s for 10^4 rays
    on a 2x10^4-face sphere and embree is unavailable. Rays from one point admit a cheap broad
    phase: centrally project ray directions and triangles onto a plane facing the mean
    direction, bin the ray images in a uniform grid and pair each triangle with the rays in the
    cells its projected bounding box covers (unbounded on a side where the triangle crosses
    the plane through the origin). The narrow phase is the exact Moeller-Trumbore test.
    Every direction must be less than 90 degrees from the mean direction (true of any pinhole
    camera's rays).
    """
    origin = np.asarray(origin, dtype=np.float64)
    if origin.shape != (3,) or not np.isfinite(origin).all():
        raise ValueError(f"origin must be a finite (3,) array, got shape {origin.shape}")
    directions = as_point_array("directions", directions)
    vertices = as_point_array("vertices", vertices)
    triangles = as_triangle_array("triangles", triangles, len(vertices))
    lengths = np.linalg.norm(directions, axis=1)
    if (lengths == 0).any():
        raise ValueError("directions contains zero-length vectors")
    unit = directions / lengths[:, None]
    ray_count = len(unit)
    best_triangle = np.full(ray_count, -1, dtype=np.int64)
    best_distance = np.full(ray_count, np.inf)
    if ray_count == 0 or len(triangles) == 0:
        return RayHits(best_triangle, best_distance)

    axis = unit.mean(axis=0)
    axis_norm = np.linalg.norm(axis)
    if axis_norm == 0 or (unit @ (axis / axis_norm)).min() <= 1e-9:
        raise ValueError("ray directions must all lie within 90 degrees of their mean direction")
    frame = _orthonormal_frame(axis / axis_norm)  # columns: e1, e2, axis

    ray_images = (unit @ frame[:, :2]) / (unit @ frame[:, 2])[:, None]
    grid = _RayGrid(ray_images)

    corners = ((vertices - origin) @ frame)[triangles]  # (F, 3, 3) in the ray frame
    low, high = _projected_bounds(corners)
    candidate = np.flatnonzero((corners[:, :, 2] > 0).any(axis=1))  # others lie behind
    cell_low, cell_high = grid.cell_of(low), grid.cell_of(high)
    pair_counts = grid.rays_in_boxes(cell_low[candidate], cell_high[candidate])
    candidate, pair_counts = candidate[pair_counts > 0], pair_counts[pair_counts > 0]

    chunk_marks = np.arange(0, pair_counts.sum(), _PAIR_CHUNK)
    chunk_starts = np.unique(np.searchsorted(np.cumsum(pair_counts), chunk_marks, side="right"))
    for chunk in np.split(candidate, chunk_starts[1:]):
        pair_triangle, pair_ray = grid.pairs(chunk, cell_low[chunk], cell_high[chunk])
        distance = _moller_trumbore(origin, unit[pair_ray], vertices[triangles[pair_triangle]])
        hit = np.isfinite(distance)
        pair_triangle, pair_ray, distance = pair_triangle[hit], pair_ray[hit], distance[hit]
        order = np.lexsort((distance, pair_ray))
        first = order[np.r_[True, np.diff(pair_ray[order]) != 0]] if len(order) else order
        closer = distance[first] < best_distance[pair_ray[first]]
        rays = pair_ray[first][closer]
        best_distance[rays] = distance[first][closer]
        best_triangle[rays] = pair_triangle[first][closer]
    return RayHits(best_triangle, best_distance)


def _orthonormal_frame(axis: np.ndarray) -> np.ndarray:
    """3x3 rotation whose third column is `axis` (unit)."""
    helper = np.eye(3)[np.argmin(np.abs(axis))]
    first = np.cross(helper, axis)
    first /= np.linalg.norm(first)
    return np.column_stack((first, np.cross(axis, first), axis))


def _projected_bounds(corners: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Bounding box of each triangle's central projection onto the plane z = 1, restricted to
    its part with z > 0. An edge crossing z = 0 makes the image unbounded on the side of the
    crossing point (x/z -> +-inf as z -> 0+), so that side of the box becomes infinite."""
    heights = corners[:, :, 2]
    ahead = heights > 0
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        images = corners[:, :, :2] / heights[:, :, None]
    low = np.where(ahead[:, :, None], images, np.inf).min(axis=1)
    high = np.where(ahead[:, :, None], images, -np.inf).max(axis=1)
    following = np.roll(corners, -1, axis=1)
    crossing = ahead != np.roll(ahead, -1, axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(crossing, heights / (heights - following[:, :, 2]), 0.0)
    along = following[:, :, :2] - corners[:, :, :2]
    crossing_points = corners[:, :, :2] + ratio[:, :, None] * along
    crossing = crossing[:, :, None]
    high[(crossing & (crossing_points >= 0)).any(axis=1)] = np.inf
    low[(crossing & (crossing_points <= 0)).any(axis=1)] = -np.inf
    return low, high


def _moller_trumbore(origin: np.ndarray, unit: np.ndarray, corners: np.ndarray) -> np.ndarray:
    """Distance along each unit ray to its paired triangle, inf where it misses."""
    edge1 = corners[:, 1] - corners[:, 0]
    edge2 = corners[:, 2] - corners[:, 0]
    p = np.cross(unit, edge2)
    determinant = np.einsum("ij,ij->i", edge1, p)
    with np.errstate(divide="ignore", invalid="ignore"):
        inverse = 1.0 / determinant
        offset = origin - corners[:, 0]
        u = np.einsum("ij,ij->i", offset, p) * inverse
        q = np.cross(offset, edge1)
        v = np.einsum("ij,ij->i", unit, q) * inverse
        distance = np.einsum("ij,ij->i", edge2, q) * inverse
        # Rays parallel to a triangle give inf/nan barycentrics: they compare False (a miss).
        hit = (
            (determinant != 0)
            & (u >= -_BARYCENTRIC_SLACK)
            & (v >= -_BARYCENTRIC_SLACK)
            & (u + v <= 1 + _BARYCENTRIC_SLACK)
            & (distance > 0)
        )
    return np.where(hit, distance, np.inf)


class _RayGrid:
    """Uniform 2-D grid over ray images, about one ray per cell, with rays sorted by cell."""

    def __init__(self, images: np.ndarray):
        self.low = images.min(axis=0)
        extent = images.max(axis=0) - self.low
        area = extent.prod()
        size = np.sqrt(area / len(images)) if area > 0 else extent.max() / len(images)
        self.cell_size = size if size > 0 else 1.0
        self.shape = np.floor(extent / self.cell_size).astype(np.int64) + 1
        cells = self.cell_of(images)
        flat = cells[:, 0] * self.shape[1] + cells[:, 1]
        self.ray_order = np.argsort(flat, kind="stable")
        counts = np.bincount(flat, minlength=int(self.shape.prod()))
        self.cell_start = np.concatenate(([0], np.cumsum(counts)[:-1]))
        self.cell_count = counts
        table = np.zeros(self.shape + 1, dtype=np.int64)  # summed-area table of ray counts
        table[1:, 1:] = counts.reshape(self.shape).cumsum(axis=0).cumsum(axis=1)
        self.summed = table

    def cell_of(self, images: np.ndarray) -> np.ndarray:
        """Cell (i, j) of each image point, clamped into the grid (monotone, so boxes stay
        conservative)."""
        with np.errstate(invalid="ignore", over="ignore"):
            scaled = np.floor((images - self.low) / self.cell_size)
        return np.clip(np.nan_to_num(scaled), 0, self.shape - 1).astype(np.int64)

    def rays_in_boxes(self, low: np.ndarray, high: np.ndarray) -> np.ndarray:
        """Number of rays in each inclusive cell box."""
        s = self.summed
        return (
            s[high[:, 0] + 1, high[:, 1] + 1]
            - s[low[:, 0], high[:, 1] + 1]
            - s[high[:, 0] + 1, low[:, 1]]
            + s[low[:, 0], low[:, 1]]
        )

    def pairs(self, triangle_ids, low, high) -> tuple[np.ndarray, np.ndarray]:
        """All (triangle, ray) pairs with the ray in the triangle's cell box."""
        width = high[:, 1] - low[:, 1] + 1
        box_cells = (high[:, 0] - low[:, 0] + 1) * width
        owner = np.repeat(np.arange(len(triangle_ids)), box_cells)
        rank = np.arange(len(owner)) - np.repeat(np.cumsum(box_cells) - box_cells, box_cells)
        row = low[owner, 0] + rank // width[owner]
        column = low[owner, 1] + rank % width[owner]
        cell = row * self.shape[1] + column
        counts = self.cell_count[cell]
        pair_owner = np.repeat(owner, counts)
        rank = np.arange(len(pair_owner)) - np.repeat(np.cumsum(counts) - counts, counts)
        rays = self.ray_order[np.repeat(self.cell_start[cell], counts) + rank]
        return triangle_ids[pair_owner], rays


@dataclass(frozen=True)
class PinholeCamera:
    """Pinhole camera: pose in the world (position, quaternion [qx, qy, qz, qw] of the
    camera-to-world rotation) and intrinsics in pixels. Pixel (u, v) has its centre at integer
    coordinates, u along image columns (camera x), v along rows (camera y)."""

    position: np.ndarray
    orientation: np.ndarray
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    def __post_init__(self):
        position = np.asarray(self.position, dtype=np.float64)
        orientation = np.asarray(self.orientation, dtype=np.float64)
        if position.shape != (3,) or not np.isfinite(position).all():
            raise ValueError(f"position must be a finite (3,) array, got {position.shape}")
        if orientation.shape != (4,) or not np.isfinite(orientation).all():
            raise ValueError(f"orientation must be finite [qx, qy, qz, qw], got {orientation.shape}")
        norm = np.linalg.norm(orientation)
        if norm < 1e-9:
            raise ValueError("orientation quaternion has zero norm")
        if int(self.width) != self.width or int(self.height) != self.height:
            raise ValueError("width and height must be integers")
        if self.width < 1 or self.height < 1:
            raise ValueError(f"image size must be positive, got {self.width}x{self.height}")
        if not (self.fx > 0 and self.fy > 0):
            raise ValueError(f"focal lengths must be positive, got fx={self.fx}, fy={self.fy}")
        if not (np.isfinite(self.cx) and np.isfinite(self.cy)):
            raise ValueError("principal point must be finite")
        object.__setattr__(self, "position", position)
        object.__setattr__(self, "orientation", orientation / norm)
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))
        for name in ("fx", "fy", "cx", "cy"):
            object.__setattr__(self, name, float(getattr(self, name)))

    @classmethod
    def look_at(cls, position, target, up, width, height, fx, fy=None, cx=None, cy=None):
        """Camera at `position` whose optical axis points at `target`, image y pointing away
        from world `up`. fy defaults to fx, the principal point to the image centre."""
        position = np.asarray(position, dtype=np.float64)
        forward = np.asarray(target, dtype=np.float64) - position
        if np.linalg.norm(forward) == 0:
            raise ValueError("target coincides with the camera position")
        forward /= np.linalg.norm(forward)
        right = np.cross(forward, np.asarray(up, dtype=np.float64))
        if np.linalg.norm(right) < 1e-9:
            raise ValueError("up is parallel to the viewing direction")
        right /= np.linalg.norm(right)
        down = np.cross(forward, right)
        rotation = np.column_stack((right, down, forward))
        return cls(
            position,
            Rotation.from_matrix(rotation).as_quat(),
            width,
            height,
            fx,
            fx if fy is None else fy,
            (width - 1) / 2 if cx is None else cx,
            (height - 1) / 2 if cy is None else cy,
        )

    @property
    def rotation(self) -> np.ndarray:
        """3x3 camera-to-world rotation; its columns are the camera axes in the world."""
        return Rotation.from_quat(self.orientation).as_matrix()

    @property
    def pose(self) -> np.ndarray:
        """(7,) pose [x, y, z, qx, qy, qz, qw]."""
        return np.concatenate((self.position, self.orientation))

    def world_to_camera(self, points) -> np.ndarray:
        """World points (K, 3) expressed in the camera frame."""
        return (as_point_array("points", points) - self.position) @ self.rotation

    def camera_to_world(self, points) -> np.ndarray:
        """Camera-frame points (K, 3) expressed in the world frame."""
        return as_point_array("points", points) @ self.rotation.T + self.position

    def pixel_grid(self, stride: int = 1) -> np.ndarray:
        """(P, 2) int64 pixels [u, v] of every `stride`-th column and row, row-major."""
        if int(stride) != stride or stride < 1:
            raise ValueError(f"stride must be a positive integer, got {stride}")
        rows, columns = np.mgrid[0 : self.height : stride, 0 : self.width : stride]
        return np.column_stack((columns.ravel(), rows.ravel())).astype(np.int64)

    def pixel_rays(self, pixels) -> np.ndarray:
        """Camera-frame rays (P, 3) through pixels [u, v], scaled to unit depth (z = 1)."""
        pixels = np.asarray(pixels, dtype=np.float64)
        if pixels.ndim != 2 or pixels.shape[1] != 2:
            raise ValueError(f"pixels must have shape (P, 2), got {pixels.shape}")
        x = (pixels[:, 0] - self.cx) / self.fx
        y = (pixels[:, 1] - self.cy) / self.fy
        return np.column_stack((x, y, np.ones(len(pixels))))

    def project(self, points) -> tuple[np.ndarray, np.ndarray]:
        """Pixel coordinates (K, 2) float and depths (K,) (camera z) of world points."""
        local = self.world_to_camera(points)
        with np.errstate(divide="ignore", invalid="ignore"):
            u = self.fx * local[:, 0] / local[:, 2] + self.cx
            v = self.fy * local[:, 1] / local[:, 2] + self.cy
        return np.column_stack((u, v)), local[:, 2]


@dataclass(frozen=True)
class CaptureOptions:
    """Sensor model of `capture`.

    stride: keep every stride-th pixel column and row.
    noise_constant, noise_quadratic: depth noise sigma(z) = noise_constant + noise_quadratic*z^2
        (metres, 1/metres), Gaussian along the pixel ray, as for stereo or monocular depth.
    grazing_exponent: a hit is kept with probability |cos(incidence)|^grazing_exponent
        (0 keeps all), thinning returns where the surface is seen edge-on.
    leak_fraction: probability that a hit on an occluder survives segmentation.
    leak_dilation_pixels: 0 lets every occluder hit leak (with probability leak_fraction);
        a positive value restricts leaks to occluder hits within that many pixels (Euclidean,
        full-resolution pixels) of a pixel whose ray hits the target, as a segmentation mask
        that bleeds over the tissue's silhouette and the tool's contour does.
    """

    stride: int = 1
    noise_constant: float = 0.0
    noise_quadratic: float = 0.0
    grazing_exponent: float = 0.0
    leak_fraction: float = 0.0
    leak_dilation_pixels: float = 0.0

    def __post_init__(self):
        if int(self.stride) != self.stride or self.stride < 1:
            raise ValueError(f"stride must be a positive integer, got {self.stride}")
        for name in ("noise_constant", "noise_quadratic", "grazing_exponent", "leak_dilation_pixels"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value >= 0):
                raise ValueError(f"{name} must be finite and non-negative, got {value}")
        if not 0 <= self.leak_fraction <= 1:
            raise ValueError(f"leak_fraction must lie in [0, 1], got {self.leak_fraction}")


@dataclass(frozen=True)
class DepthCapture:
    """One segmented depth frame as world points.

    points (K, 3) world; labels (K,) int64: 0 target, otherwise the occluder's label (a leak);
    pixels (K, 2) int64 [u, v]; depths (K,) measured camera-z depth (noise included);
    triangle_ids (K,) int64 hit triangle within the labelled surface's own triangle array.
    """

    points: np.ndarray
    labels: np.ndarray
    pixels: np.ndarray
    depths: np.ndarray
    triangle_ids: np.ndarray


def capture(
    camera: PinholeCamera,
    target_vertices,
    target_triangles,
    occluders: Sequence[tuple] = (),
    rng: np.random.Generator | int | None = None,
    options: CaptureOptions = CaptureOptions(),
) -> DepthCapture:
    """Ray-cast the camera's pixel grid against target and occluders (first hit wins).

    Target hits are kept; occluder hits are kept with probability options.leak_fraction (only
    within options.leak_dilation_pixels of a target hit, when that is positive) and labelled
    with their occluder's label. Every hit is then thinned by incidence angle and its
    depth perturbed along its pixel ray; points whose noisy depth is not positive are dropped.
    `occluders` holds (vertices, triangles, label) triples; `rng` is a Generator or a seed.
    """
    rng = np.random.default_rng(rng)
    surfaces = [("target", target_vertices, target_triangles, 0)]
    for index, (vertices, triangles, label) in enumerate(occluders):
        if int(label) != label or label < 1:
            raise ValueError(f"occluders[{index}] label must be an integer >= 1, got {label}")
        surfaces.append((f"occluders[{index}]", vertices, triangles, int(label)))
    vertex_arrays, triangle_arrays, offset = [], [], 0
    for name, vertices, triangles, _ in surfaces:
        vertices = as_point_array(f"{name} vertices", vertices)
        triangles = as_triangle_array(f"{name} triangles", triangles, len(vertices))
        triangle_arrays.append(triangles + offset)
        vertex_arrays.append(vertices)
        offset += len(vertices)
    all_vertices, all_triangles = np.concatenate(vertex_arrays), np.concatenate(triangle_arrays)
    sizes = [len(triangles) for triangles in triangle_arrays]
    triangle_label = np.repeat([label for *_, label in surfaces], sizes).astype(np.int64)
    triangle_local = np.concatenate([np.arange(size, dtype=np.int64) for size in sizes])

    pixels = camera.pixel_grid(options.stride)
    camera_rays = camera.pixel_rays(pixels)
    world_rays = camera_rays @ camera.rotation.T
    ray_lengths = np.linalg.norm(world_rays, axis=1)
    hits = first_ray_hits(camera.position, world_rays, all_vertices, all_triangles)
    hit_rays = np.flatnonzero(hits.triangles >= 0)
    hit_triangles = hits.triangles[hit_rays]
    depths = hits.distances[hit_rays] / ray_lengths[hit_rays]

    corners = all_vertices[all_triangles[hit_triangles]]
    normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    normals /= np.linalg.norm(normals, axis=1)[:, None]
    unit_rays = world_rays[hit_rays] / ray_lengths[hit_rays, None]
    cosine = np.abs(np.einsum("ij,ij->i", normals, unit_rays))

    labels = triangle_label[hit_triangles]
    keep_by_angle = rng.random(len(hit_rays)) < cosine**options.grazing_exponent
    keep_by_mask = (labels == 0) | (rng.random(len(hit_rays)) < options.leak_fraction)
    if options.leak_dilation_pixels > 0:
        keep_by_mask &= (labels == 0) | _near_target(pixels[hit_rays], labels == 0, options)
    kept = np.flatnonzero(keep_by_angle & keep_by_mask)
    sigma = options.noise_constant + options.noise_quadratic * depths[kept] ** 2
    noisy_depths = depths[kept] + sigma * rng.standard_normal(len(kept))
    kept, noisy_depths = kept[noisy_depths > 0], noisy_depths[noisy_depths > 0]

    points = camera.camera_to_world(camera_rays[hit_rays[kept]] * noisy_depths[:, None])
    return DepthCapture(
        points=points,
        labels=labels[kept],
        pixels=pixels[hit_rays[kept]],
        depths=noisy_depths,
        triangle_ids=triangle_local[hit_triangles[kept]],
    )


def _near_target(hit_pixels: np.ndarray, on_target: np.ndarray, options: CaptureOptions) -> np.ndarray:
    """Whether each hit pixel [u, v] lies within options.leak_dilation_pixels (full-resolution
    pixels) of a target hit: Euclidean distance transform of the strided image's target mask."""
    if not on_target.any():
        return np.zeros(len(hit_pixels), dtype=bool)
    stride = options.stride
    grid = hit_pixels // stride
    outside_target = np.ones(tuple(grid.max(axis=0)[::-1] + 1), dtype=bool)  # rows v, columns u
    outside_target[grid[on_target, 1], grid[on_target, 0]] = False
    distance = scipy.ndimage.distance_transform_edt(outside_target) * stride
    return distance[grid[:, 1], grid[:, 0]] <= options.leak_dilation_pixels
