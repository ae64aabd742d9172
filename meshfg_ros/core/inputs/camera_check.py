"""Whether a cloud can have been seen from the viewpoint the estimator is given. ROS-free.

A depth camera sees the surface it measures from the front, and hardly at grazing angles: a
point whose closest surface face is turned away from the camera's centre, or is met by the
camera's ray within GRAZING_LIMIT_DEGREES of grazing, is at an angle no real camera at that
centre returns. Segmentation leaks and noise put a few percent of a cloud there; a wrong centre
(a `camera_frame` whose origin is not the optical centre) puts many more. Measured on the
bundled recordings against their estimates, the points within 3 sigma of the surface:
cao-push 1.8 % at its camera, 7-12 % with the camera 10 mm off sideways or forwards, 4 % at 5 mm
(a camera moved back along its axis sees the same faces and cannot be told apart); liver-push
1.5 % (at most 2.6 % in a step). `implausible_view` counts them for the estimator node's health.
"""

from __future__ import annotations

import numpy as np

from meshfg_ros.core.geometry.closest_point import ClosestPointIndex, triangle_corners

__all__ = ["GRAZING_LIMIT_DEGREES", "IMPLAUSIBLE_SHARE", "implausible_view"]

GRAZING_LIMIT_DEGREES = 80.0
# More than this share of a cloud's points at implausible angles: the viewpoint is not the camera's.
IMPLAUSIBLE_SHARE = 0.05
_NEAR_SIGMAS = 3.0


def implausible_view(vertices: np.ndarray, triangles: np.ndarray, points: np.ndarray, viewpoint: np.ndarray,
                     sigma: float) -> tuple[int, int]:
    """(points at implausible angles, points considered): of the cloud `points` (K, 3) within
    3 `sigma` of the surface (`vertices` (N, 3), `triangles` (F, 3)), those whose closest face is
    turned away from `viewpoint` (3,) or is met by its ray within GRAZING_LIMIT_DEGREES of grazing."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if not len(points):
        return 0, 0
    association = ClosestPointIndex(vertices, triangles).associate(points, max_distance=_NEAR_SIGMAS * sigma)
    near = association.triangle >= 0
    if not near.any():
        return 0, 0
    a, b, c = triangle_corners(vertices, triangles, association.triangle[near])
    normals = np.cross(b - a, c - a)
    rays = np.asarray(viewpoint, dtype=np.float64) - association.closest[near]
    with np.errstate(invalid="ignore", divide="ignore"):
        cosine = np.einsum("ij,ij->i", normals, rays) / (np.linalg.norm(normals, axis=1) * np.linalg.norm(rays, axis=1))
    implausible = cosine < np.cos(np.radians(GRAZING_LIMIT_DEGREES))  # NaN (a degenerate face) never counts
    return int(np.count_nonzero(implausible)), int(np.count_nonzero(near))
