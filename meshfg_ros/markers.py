"""visualization_msgs/MarkerArray of an estimate, built through a MessageFactory (no rclpy).

The same builder serves recordings (RosbagsMessageFactory: the offline replay) and live
publishing (RclpyMessageFactory): it only names message types and fields. Markers, in this order:
- the surface as a TRIANGLE_LIST coloured by posterior standard deviation (blue = certain, red =
  uncertain; grey when unknown), its edges as a LINE_LIST wireframe, the measured points as POINTS;
- with a std, its legend beside the mesh: the colour scale as a CUBE_LIST bar, TEXT_VIEW_FACING
  ticks giving its values in mm (each in its colour) and a title;
- with the covariance, uncertainty ellipsoids: one SPHERE per vertex of a bounded, evenly spread
  sample of the free surface vertices (MAX_ELLIPSOIDS), posed and scaled by the eigenvectors and
  eigenvalues of its 3x3 covariance to the region holding 95 % of its position's probability, at
  true scale, translucent in its std's colour; and a text saying so.
Every marker is ADD, with a non-zero scale and visible colours, in fixed namespaces and ids (the
legend's and the ellipsoids' numbered from 0): a stream of arrays with the same mesh and the same
kinds of uncertainty replaces the previous array in RViz and Foxglove.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from meshfg_ros.core.estimation.covariance import chi_squared_quantile
from meshfg_ros.io.messages import MessageFactory, RosbagsMessageFactory, header_msg

MARKER_ARRAY = "visualization_msgs/msg/MarkerArray"
NAMESPACE_SURFACE = "meshfg/surface"
NAMESPACE_WIREFRAME = "meshfg/wireframe"
NAMESPACE_POINTS = "meshfg/points"
NAMESPACE_LEGEND = "meshfg/legend"
NAMESPACE_ELLIPSOIDS = "meshfg/uncertainty_ellipsoids"
# visualization_msgs/Marker constants.
SPHERE, LINE_LIST, CUBE_LIST, POINTS, TEXT_VIEW_FACING, TRIANGLE_LIST, ADD = 2, 5, 6, 8, 9, 11, 0
# At most this many ellipsoids (one Marker each): the array stays small for any mesh.
MAX_ELLIPSOIDS = 200
# The ellipsoid {d : d^T Sigma^-1 d <= r^2} holds 95 % of a 3-D Gaussian's probability for r^2 the
# chi-square quantile with 3 degrees of freedom (7.8147: semi-axes 2.80 sqrt(eigenvalues)).
_CHI2_3DOF_95 = float(chi_squared_quantile(0.95, 3))
_ELLIPSOID_ALPHA = 0.6
# Line width, point size and legend text height as fractions of the mesh's bounding-box diagonal.
_LINE_WIDTH_FRACTION = 2e-3
_POINT_SIZE_FRACTION = 4e-3
_TEXT_HEIGHT_FRACTION = 0.04
_LEGEND_GAP_FRACTION = 0.15  # between the mesh's bounding box and the legend's bar
_LEGEND_BAR_CELLS = 16
_LEGEND_TICKS = 5  # 0, 1/4, 1/2, 3/4 and all of the scale
_MIN_SIZE = 1e-5  # metres: RViz rejects a zero scale
_M_TO_MM = 1e3
# Diverging cool-to-warm colour map (endpoints and mid-point of Moreland's "coolwarm").
_COLOUR_STOPS = np.array([0.0, 0.5, 1.0])
_COLOUR_VALUES = np.array([[0.230, 0.299, 0.754], [0.865, 0.865, 0.865], [0.706, 0.016, 0.150]])
_WIREFRAME_COLOUR = (0.1, 0.1, 0.1, 1.0)
_POINTS_COLOUR = (0.1, 0.8, 0.2, 1.0)
_UNKNOWN_STD_COLOUR = (0.6, 0.6, 0.6, 1.0)
_LEGEND_TEXT_COLOUR = (0.9, 0.9, 0.9, 1.0)


def surface_edges(surface_triangles: np.ndarray) -> np.ndarray:
    """Unique edges (E, 2), i < j, of the triangles (F, 3)."""
    triangles = np.asarray(surface_triangles, dtype=np.int64).reshape(-1, 3)
    pairs = np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]])
    return np.unique(np.sort(pairs, axis=1), axis=0)


def std_colours(position_std: np.ndarray, std_max: float = 0.0) -> np.ndarray:
    """RGBA colours (N, 4) for per-vertex std: 0 -> blue, std_max (or the largest std if 0) -> red."""
    position_std = np.asarray(position_std, dtype=np.float64)
    scale = std_scale(position_std, std_max)
    fraction = np.clip(position_std / scale, 0.0, 1.0) if scale > 0.0 else np.zeros_like(position_std)
    rgb = np.stack([np.interp(fraction, _COLOUR_STOPS, _COLOUR_VALUES[:, c]) for c in range(3)], axis=1)
    return np.concatenate([rgb, np.ones((rgb.shape[0], 1))], axis=1)


def std_scale(position_std: np.ndarray, std_max: float = 0.0) -> float:
    """The std (m) the colour scale ends at: std_max, or the largest std if std_max is 0."""
    return std_max if std_max > 0.0 else float(np.max(position_std, initial=0.0))


def spread_surface_sample(positions: np.ndarray, surface_triangles: np.ndarray, excluded: np.ndarray = (),
                          count: int = MAX_ELLIPSOIDS) -> np.ndarray:
    """Indices of up to `count` surface vertices spread evenly over the surface (farthest-point
    sampling, from the one farthest from their centroid), `excluded` ones (fixed: certain) left
    out; sorted. One pass per sample, each vectorised over the candidates."""
    candidates = np.setdiff1d(np.unique(np.asarray(surface_triangles, dtype=np.int64)),
                              np.asarray(excluded, dtype=np.int64))
    if len(candidates) <= count:
        return candidates
    where = np.asarray(positions, dtype=np.float64)[candidates]
    chosen = [int(np.argmax(np.linalg.norm(where - where.mean(axis=0), axis=1)))]
    distance = np.linalg.norm(where - where[chosen[0]], axis=1)
    while len(chosen) < count:
        chosen.append(int(np.argmax(distance)))
        distance = np.minimum(distance, np.linalg.norm(where - where[chosen[-1]], axis=1))
    return np.sort(candidates[chosen])


def ellipsoid_axes(covariance: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Full axis lengths (K, 3) of the 95 % ellipsoids of covariance blocks (K, 3, 3) (m^2), and
    quaternions (K, 4) [x, y, z, w] turning the x, y, z axes onto them (a SPHERE marker's scale
    and orientation). Eigenvalues below zero (rounding of a singular block) count as zero."""
    eigenvalues, eigenvectors = np.linalg.eigh(np.asarray(covariance, dtype=np.float64))
    eigenvectors[:, :, 2] *= np.sign(np.linalg.det(eigenvectors))[:, None]  # a rotation: right-handed
    lengths = 2.0 * np.sqrt(_CHI2_3DOF_95 * np.clip(eigenvalues, 0.0, None))
    return lengths, Rotation.from_matrix(eigenvectors).as_quat()


class _MarkerBuilder:
    """Makes the nested messages of a Marker with one factory."""

    def __init__(self, factory: MessageFactory) -> None:
        self.factory = factory
        self._empty_image = factory.make(
            "sensor_msgs/msg/CompressedImage", header=header_msg(0, "", factory), format="",
            data=factory.sequence(np.zeros(0, np.uint8), np.uint8))
        self._empty_mesh_file = factory.make(
            "visualization_msgs/msg/MeshFile", filename="", data=factory.sequence(np.zeros(0, np.uint8), np.uint8))

    def points(self, coordinates: np.ndarray) -> list:
        # Nested message sequences have no bulk form in either flavour: one object per point.
        make = self.factory.make
        return [make("geometry_msgs/msg/Point", x=x, y=y, z=z) for x, y, z in coordinates.tolist()]

    def colour(self, rgba) -> object:
        r, g, b, a = (float(c) for c in rgba)
        return self.factory.make("std_msgs/msg/ColorRGBA", r=r, g=g, b=b, a=a)

    def colours(self, rgba: np.ndarray) -> list:
        return [self.colour(c) for c in rgba.tolist()]

    def marker(self, header, namespace: str, marker_type: int, scale, colour, points: list = (),
               colours: list = (), marker_id: int = 0, position=(0.0, 0.0, 0.0),
               orientation=(0.0, 0.0, 0.0, 1.0), text: str = "") -> object:
        """A Marker; scale: one size for x, y, z, or three."""
        make = self.factory.make
        x, y, z = (float(c) for c in position)
        qx, qy, qz, qw = (float(c) for c in orientation)
        sx, sy, sz = (float(c) for c in np.broadcast_to(scale, 3))
        pose = make("geometry_msgs/msg/Pose", position=make("geometry_msgs/msg/Point", x=x, y=y, z=z),
                    orientation=make("geometry_msgs/msg/Quaternion", x=qx, y=qy, z=qz, w=qw))
        return make(
            "visualization_msgs/msg/Marker", header=header, ns=namespace, id=int(marker_id), type=marker_type,
            action=ADD, pose=pose, scale=make("geometry_msgs/msg/Vector3", x=sx, y=sy, z=sz),
            color=self.colour(colour), lifetime=make("builtin_interfaces/msg/Duration", sec=0, nanosec=0),
            frame_locked=False, points=list(points), colors=list(colours), texture_resource="",
            texture=self._empty_image, uv_coordinates=[], text=text, mesh_resource="",
            mesh_file=self._empty_mesh_file, mesh_use_embedded_materials=False,
        )


def mesh_markers(
    positions: np.ndarray,
    surface_triangles: np.ndarray,
    position_std: np.ndarray | None,
    points: np.ndarray | None,
    frame_id: str,
    stamp_ns: int,
    std_max: float = 0.0,
    edges: np.ndarray | None = None,
    factory: MessageFactory | None = None,
    position_covariance: np.ndarray | None = None,
    ellipsoid_vertices: np.ndarray | None = None,
):
    """MarkerArray: surface (TRIANGLE_LIST, std colours), wireframe (LINE_LIST), points (POINTS),
    then the std's legend and the covariance's ellipsoids (module docstring).

    positions (N, 3) metres; surface_triangles (F, 3); position_std (N,) or None/empty (grey
    surface, no legend); points (K, 3) or None (empty points marker); std_max: the std at the
    colour scale's red end (0: the largest std); edges (E, 2) from surface_edges (computed if
    None); factory: rosbags messages by default, or RclpyMessageFactory(); position_covariance
    (N, 3, 3) m^2 or None/empty (no ellipsoids); ellipsoid_vertices: the vertices given
    ellipsoids, from spread_surface_sample (None: computed, leaving out the vertices whose
    covariance is zero).
    """
    build = _MarkerBuilder(RosbagsMessageFactory() if factory is None else factory)
    positions = np.asarray(positions, dtype=np.float64)
    triangles = np.asarray(surface_triangles, dtype=np.int64).reshape(-1, 3)
    edges = surface_edges(triangles) if edges is None else np.asarray(edges, dtype=np.int64)
    header = header_msg(stamp_ns, frame_id, build.factory)
    extent = float(np.linalg.norm(np.ptp(positions, axis=0))) if positions.size else 0.0
    corners = triangles.reshape(-1)
    has_std = position_std is not None and np.size(position_std) > 0
    if has_std:
        position_std = np.asarray(position_std, dtype=np.float64)
    surface = build.marker(header, NAMESPACE_SURFACE, TRIANGLE_LIST, 1.0, _UNKNOWN_STD_COLOUR,
                           build.points(positions[corners]),
                           build.colours(std_colours(position_std, std_max)[corners]) if has_std else [])
    wireframe = build.marker(header, NAMESPACE_WIREFRAME, LINE_LIST, max(_LINE_WIDTH_FRACTION * extent, _MIN_SIZE),
                             _WIREFRAME_COLOUR, build.points(positions[edges.reshape(-1)]), [])
    cloud_points = [] if points is None else build.points(np.asarray(points, dtype=np.float64).reshape(-1, 3))
    cloud = build.marker(header, NAMESPACE_POINTS, POINTS, max(_POINT_SIZE_FRACTION * extent, _MIN_SIZE),
                         _POINTS_COLOUR, cloud_points, [])
    markers = [surface, wireframe, cloud]
    has_covariance = position_covariance is not None and np.size(position_covariance) > 0
    if has_std and positions.size:
        markers += _legend(build, header, positions, extent, std_scale(position_std, std_max), std_max > 0.0,
                           has_covariance)
    if has_covariance:
        covariance = np.asarray(position_covariance, dtype=np.float64).reshape(-1, 3, 3)
        if ellipsoid_vertices is None:
            certain = np.flatnonzero(~covariance.any(axis=(1, 2)))
            ellipsoid_vertices = spread_surface_sample(positions, triangles, certain)
        std = position_std if has_std else np.sqrt(np.einsum("vii->v", covariance) / 3.0)
        markers += _ellipsoids(build, header, positions, covariance, std, std_max,
                               np.asarray(ellipsoid_vertices, dtype=np.int64))
    return build.factory.make(MARKER_ARRAY, markers=markers)


def _legend(build: _MarkerBuilder, header, positions: np.ndarray, extent: float, scale: float, clipped: bool,
            with_ellipsoids: bool) -> list:
    """The colour scale beside the mesh (+x of its bounding box, along z): a CUBE_LIST bar from 0
    (bottom) to `scale` (top), ticks in mm in their colours (the top one '>=' when stds beyond it
    are `clipped` to red), a title, and with_ellipsoids what the ellipsoids show."""
    low, high = positions.min(axis=0), positions.max(axis=0)
    text_height = max(_TEXT_HEIGHT_FRACTION * extent, _MIN_SIZE)
    bar_x, middle_y = high[0] + _LEGEND_GAP_FRACTION * extent, 0.5 * (low[1] + high[1])
    bar_height = max(high[2] - low[2], 0.5 * extent, _MIN_SIZE)
    cell = bar_height / _LEGEND_BAR_CELLS
    cell_fractions = (np.arange(_LEGEND_BAR_CELLS) + 0.5) / _LEGEND_BAR_CELLS
    cell_centres = np.column_stack([np.full(_LEGEND_BAR_CELLS, bar_x), np.full(_LEGEND_BAR_CELLS, middle_y),
                                    low[2] + bar_height * cell_fractions])
    bar = build.marker(header, NAMESPACE_LEGEND, CUBE_LIST, cell, _UNKNOWN_STD_COLOUR, build.points(cell_centres),
                       build.colours(std_colours(cell_fractions, 1.0)))
    markers = [bar]
    tick_fractions = np.linspace(0.0, 1.0, _LEGEND_TICKS)
    tick_colours = std_colours(tick_fractions, 1.0)
    for index, fraction in enumerate(tick_fractions):  # a handful of labels
        label = f"{_M_TO_MM * scale * fraction:.3g} mm"
        if clipped and index == _LEGEND_TICKS - 1:
            label = ">= " + label
        markers.append(build.marker(header, NAMESPACE_LEGEND, TEXT_VIEW_FACING, text_height, tick_colours[index],
                                    marker_id=1 + index, text=label,
                                    position=(bar_x + 3.0 * text_height, middle_y, low[2] + bar_height * fraction)))
    lines = ["posterior std (position)"]
    if with_ellipsoids:
        lines.append("ellipsoids: 95 % regions, true scale")
    for index, line in enumerate(lines):
        markers.append(build.marker(header, NAMESPACE_LEGEND, TEXT_VIEW_FACING, text_height, _LEGEND_TEXT_COLOUR,
                                    marker_id=1 + _LEGEND_TICKS + index, text=line,
                                    position=(bar_x, middle_y,
                                              low[2] + bar_height + (1.5 + 1.5 * index) * text_height)))
    return markers


def _ellipsoids(build: _MarkerBuilder, header, positions: np.ndarray, covariance: np.ndarray, std: np.ndarray,
                std_max: float, vertices: np.ndarray) -> list:
    """One SPHERE per vertex of `vertices`, posed and scaled as its 95 % ellipsoid, in its std's
    colour (translucent)."""
    lengths, orientations = ellipsoid_axes(covariance[vertices])
    colours = std_colours(std, std_max)[vertices]
    colours[:, 3] = _ELLIPSOID_ALPHA
    centres = positions[vertices]
    # One Marker object per ellipsoid (a SPHERE_LIST has a single scale and no orientation): a
    # loop over at most MAX_ELLIPSOIDS, with everything numeric computed above for all at once.
    return [build.marker(header, NAMESPACE_ELLIPSOIDS, SPHERE, np.maximum(lengths[k], _MIN_SIZE), colours[k],
                         marker_id=k, position=centres[k], orientation=orientations[k])
            for k in range(len(vertices))]
