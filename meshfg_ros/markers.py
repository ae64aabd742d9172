"""visualization_msgs/MarkerArray of an estimate, built through a MessageFactory (no rclpy).

The same builder serves recordings (RosbagsMessageFactory: the offline replay) and live
publishing (RclpyMessageFactory): it only names message types and fields. Three markers: the
surface as a TRIANGLE_LIST coloured by posterior standard deviation (blue = certain, red =
uncertain; grey when unknown), its edges as a LINE_LIST wireframe, and the measured points as
POINTS. Every marker is ADD with an identity pose, a non-zero scale and opaque colours, in
fixed namespaces and ids, so a new array replaces the previous one in RViz and Foxglove.
"""

from __future__ import annotations

import numpy as np

from meshfg_ros.io.messages import MessageFactory, RosbagsMessageFactory, header_msg

MARKER_ARRAY = "visualization_msgs/msg/MarkerArray"
NAMESPACE_SURFACE = "meshfg/surface"
NAMESPACE_WIREFRAME = "meshfg/wireframe"
NAMESPACE_POINTS = "meshfg/points"
# visualization_msgs/Marker constants.
LINE_LIST, POINTS, TRIANGLE_LIST, ADD = 5, 8, 11, 0
# Line width and point size as fractions of the mesh's bounding-box diagonal.
_LINE_WIDTH_FRACTION = 2e-3
_POINT_SIZE_FRACTION = 4e-3
_MIN_SIZE = 1e-5  # metres: RViz rejects a zero scale
# Diverging cool-to-warm colour map (endpoints and mid-point of Moreland's "coolwarm").
_COLOUR_STOPS = np.array([0.0, 0.5, 1.0])
_COLOUR_VALUES = np.array([[0.230, 0.299, 0.754], [0.865, 0.865, 0.865], [0.706, 0.016, 0.150]])
_WIREFRAME_COLOUR = (0.1, 0.1, 0.1, 1.0)
_POINTS_COLOUR = (0.1, 0.8, 0.2, 1.0)
_UNKNOWN_STD_COLOUR = (0.6, 0.6, 0.6, 1.0)


def surface_edges(surface_triangles: np.ndarray) -> np.ndarray:
    """Unique edges (E, 2), i < j, of the triangles (F, 3)."""
    triangles = np.asarray(surface_triangles, dtype=np.int64).reshape(-1, 3)
    pairs = np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]])
    return np.unique(np.sort(pairs, axis=1), axis=0)


def std_colours(position_std: np.ndarray, std_max: float = 0.0) -> np.ndarray:
    """RGBA colours (N, 4) for per-vertex std: 0 -> blue, std_max (or the largest std if 0) -> red."""
    position_std = np.asarray(position_std, dtype=np.float64)
    scale = std_max if std_max > 0.0 else float(position_std.max(initial=0.0))
    fraction = np.clip(position_std / scale, 0.0, 1.0) if scale > 0.0 else np.zeros_like(position_std)
    rgb = np.stack([np.interp(fraction, _COLOUR_STOPS, _COLOUR_VALUES[:, c]) for c in range(3)], axis=1)
    return np.concatenate([rgb, np.ones((rgb.shape[0], 1))], axis=1)


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

    def marker(self, header, namespace: str, marker_type: int, scale: float, colour, points: list,
               colours: list) -> object:
        make = self.factory.make
        pose = make("geometry_msgs/msg/Pose",
                    position=make("geometry_msgs/msg/Point", x=0.0, y=0.0, z=0.0),
                    orientation=make("geometry_msgs/msg/Quaternion", x=0.0, y=0.0, z=0.0, w=1.0))
        return make(
            "visualization_msgs/msg/Marker", header=header, ns=namespace, id=0, type=marker_type, action=ADD,
            pose=pose, scale=make("geometry_msgs/msg/Vector3", x=float(scale), y=float(scale), z=float(scale)),
            color=self.colour(colour), lifetime=make("builtin_interfaces/msg/Duration", sec=0, nanosec=0),
            frame_locked=False, points=points, colors=colours, texture_resource="", texture=self._empty_image,
            uv_coordinates=[], text="", mesh_resource="", mesh_file=self._empty_mesh_file,
            mesh_use_embedded_materials=False,
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
):
    """MarkerArray: surface (TRIANGLE_LIST, std colours), wireframe (LINE_LIST), points (POINTS).

    positions (N, 3) metres; surface_triangles (F, 3); position_std (N,) or None/empty (grey
    surface); points (K, 3) or None (empty points marker); edges (E, 2) from surface_edges
    (computed if None); factory: rosbags messages by default, or RclpyMessageFactory().
    """
    build = _MarkerBuilder(RosbagsMessageFactory() if factory is None else factory)
    positions = np.asarray(positions, dtype=np.float64)
    triangles = np.asarray(surface_triangles, dtype=np.int64).reshape(-1, 3)
    edges = surface_edges(triangles) if edges is None else np.asarray(edges, dtype=np.int64)
    header = header_msg(stamp_ns, frame_id, build.factory)
    extent = float(np.linalg.norm(np.ptp(positions, axis=0))) if positions.size else 0.0
    corners = triangles.reshape(-1)
    has_std = position_std is not None and np.size(position_std) > 0
    surface = build.marker(header, NAMESPACE_SURFACE, TRIANGLE_LIST, 1.0, _UNKNOWN_STD_COLOUR,
                           build.points(positions[corners]),
                           build.colours(std_colours(position_std, std_max)[corners]) if has_std else [])
    wireframe = build.marker(header, NAMESPACE_WIREFRAME, LINE_LIST, max(_LINE_WIDTH_FRACTION * extent, _MIN_SIZE),
                             _WIREFRAME_COLOUR, build.points(positions[edges.reshape(-1)]), [])
    cloud_points = [] if points is None else build.points(np.asarray(points, dtype=np.float64).reshape(-1, 3))
    cloud = build.marker(header, NAMESPACE_POINTS, POINTS, max(_POINT_SIZE_FRACTION * extent, _MIN_SIZE),
                         _POINTS_COLOUR, cloud_points, [])
    return build.factory.make(MARKER_ARRAY, markers=[surface, wireframe, cloud])
