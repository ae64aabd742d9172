"""Measurement selection: the front end that decides what reaches the factors.

Before an update's factors are made, the estimator's inputs pass these tests, each reported in
the update's status message:
- far input (`set_aside_far_input`): points far outside the scene are dropped, a far tool pose
  is ignored, a far or inverted prediction is set aside (core/inputs/input_checks.py);
- the tool gate (`drop_points_on_tool`): in sphere mode, points inside the tool sphere are the
  segmentation's leaks onto the tool;
- the innovation test (`innovation_test`): a prediction the cloud contradicts far beyond the
  measurement noise is set aside (the step then runs degraded on the copy-forward);
- the point selection (`select_points`): of the points the measurement factor is to take, those
  farther from the predicted surface than the gate and those against faces turned away from
  the sensor are dropped; each remaining point gets its noise from its ray's incidence on the
  surface (noise.RayNoise), and the points are ordered by their closest triangles.
The measurement factor (factors.PointToSurfaceFactor) then takes the selected points and their
noise model as they are, as GTSAM's and Theseus' factors take their measurements.

Every test is made once per update, at the prediction, so that the objective does not change
while Levenberg-Marquardt iterates.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from meshfg_ros.core.estimation.noise import PointNoise, RayNoise
from meshfg_ros.core.estimation.weights import MIN_POINTS
from meshfg_ros.core.geometry.closest_point import Association, ClosestPointIndex, triangle_corners
from meshfg_ros.core.geometry.mesh import TetMesh, cross
from meshfg_ros.core.inputs.input_checks import (
    REJECTIONS,
    Scene,
    flat_elements,
    innovation_sample,
    innovation_spread,
)

__all__ = [
    "GATE_SIGMAS",
    "GATE_SPREAD_CAP",
    "INNOVATION_DIAGONALS",
    "INNOVATION_RATIO",
    "INNOVATION_SIGMAS",
    "MAX_BACK_FACING_SHARE",
    "TOOL_MARGIN_SIGMAS",
    "InnovationTest",
    "SelectedPoints",
    "drop_points_on_tool",
    "innovation_test",
    "select_points",
    "set_aside_far_input",
]

# The data-driven gate (gating_distance 0), in estimated sigmas: points farther from the predicted
# surface than GATE_SIGMAS robust spreads of their distances to it are dropped ...
GATE_SIGMAS = 5.0
# ... a spread taken between 1 and GATE_SPREAD_CAP measurement sigmas: a cloud that is mostly
# leaks or garbage must not widen the gate to its own scale.
GATE_SPREAD_CAP = 10.0
# The tool gate's margin around the tool sphere, in estimated sigmas (at most a radius).
TOOL_MARGIN_SIGMAS = 3.0
# The back-face test drops up to this share of a cloud's gated points; a larger share means the
# viewpoint is not the sensor's. Measured on the accuracy suite's camera scenes at the predicted
# surface: 0-1 % of the points on the tissue and 49-100 % of the leaks onto the surroundings lie
# against back faces; the leaks are 10-20 % of a cloud.
MAX_BACK_FACING_SHARE = 0.5
# Innovation test: a prediction is rejected when the robust spread of the cloud's distances to its
# surface exceeds INNOVATION_SIGMAS nominal measurement sigmas, INNOVATION_DIAGONALS of the scene's
# diagonal (against a sigma set far too small), and INNOVATION_RATIO times the spread about the
# copy-forward state that replaces it (a prediction that explains the cloud about as well as the
# copy-forward is never worse to keep). The nominal sigma (the measurement_sigma parameter, the
# sensor's datasheet value) is the scale, not the estimated one, which learns from the very clouds
# the test judges. On the bundled scenes (cao-push, liver-push, cube-shear-spd) the spread about the
# prediction is 1.0-2.9 nominal sigmas and at most 1.2 times the one about the copy-forward; a
# prediction shifted by 1 m gives hundreds of sigmas.
INNOVATION_SIGMAS = 20.0
INNOVATION_DIAGONALS = 0.05
INNOVATION_RATIO = 4.0


def set_aside_far_input(scene: Scene, mesh: TetMesh, points, predicted, tool_pose, messages: list):
    """Far cloud points dropped, a far or inverted prediction and a far tool pose set aside
    (core/inputs/input_checks.py), each reported in `messages`: (points, predicted, tool pose,
    count of points dropped)."""
    dropped = 0
    if points is not None:
        far = scene.far(points)
        dropped = int(np.count_nonzero(far))
        if dropped:
            messages.append(f"{dropped} {REJECTIONS['clouds_with_far_points']} ({scene.describe(points)})")
            points = points[~far]
    if tool_pose is not None and scene.far(tool_pose[None, :3])[0]:
        messages.append(f"{REJECTIONS['tool_poses_ignored_far']} ({scene.describe(tool_pose[None, :3])})")
        tool_pose = None
    if predicted is not None and scene.far(predicted).any():
        messages.append(f"{REJECTIONS['predictions_rejected_far']} (a vertex {scene.describe(predicted)})")
        predicted = None
    if predicted is not None:
        # The simulator never returns an inverted element (it reports a failure instead), and
        # the prior's volume barrier is relative to the prediction's volumes, fixed vertices
        # held where they are (as the new state gets it).
        held = predicted.copy()
        held[mesh.fixed_vertices] = mesh.vertices[mesh.fixed_vertices]
        flat = flat_elements(held, mesh.tetrahedra)
        if flat:
            messages.append(f"{REJECTIONS['predictions_rejected_inverted']} ({flat} of {mesh.tetrahedron_count})")
            predicted = None
    return points, predicted, tool_pose, dropped


def drop_points_on_tool(points, tool_pose, tool_mode: str, tool_radius: float, sigma: float):
    """(points outside the tool, count dropped). In sphere mode, points inside the tool sphere,
    grown by TOOL_MARGIN_SIGMAS measurement sigmas but by at most its radius, are leaks of the
    segmentation onto the tool (the commonest leak). A point farther than a radius off the
    sphere is no noisy point of it; without the bound a nominal sigma ten times too large drops
    most of the cloud around the tool, and the noise estimate, made from what is left (mostly
    leaks), takes seven updates to come down instead of one (docs/design-notes.md, "Weights")."""
    if points is None or tool_pose is None or tool_mode != "sphere":
        return points, 0
    centre = np.asarray(tool_pose, dtype=np.float64).reshape(-1)[:3]
    reach = tool_radius + min(TOOL_MARGIN_SIGMAS * sigma, tool_radius)
    inside = np.einsum("ij,ij->i", points - centre, points - centre) <= reach**2
    return points[~inside], int(np.count_nonzero(inside))


@dataclass
class InnovationTest:
    """The outcome of `innovation_test`: the prediction kept (None: set aside, `rejection` says
    why), and the cloud's association on its surface where the test made one and kept it."""

    prediction: np.ndarray | None
    association: Association | None = None
    rejection: str | None = None


def innovation_test(points, predicted, copy_forward: np.ndarray, surface_triangles: np.ndarray,
                    nominal_sigma: float, scene: Scene) -> InnovationTest:
    """Whether the cloud `points` contradicts the prediction `predicted` far beyond the
    measurement noise: the robust spread of the cloud's distances to the predicted surface is
    above max(INNOVATION_SIGMAS nominal sigmas, INNOVATION_DIAGONALS scene diagonals) and
    INNOVATION_RATIO times its spread about `copy_forward`, the state that would replace the
    prediction. The whole cloud is associated (the point selection reuses it), the test judges
    a sample. Clouds of fewer than MIN_POINTS points (weights.py) do not judge."""
    if predicted is None or points is None or len(points) < MIN_POINTS:
        return InnovationTest(predicted)
    association = ClosestPointIndex(predicted, surface_triangles).associate(points)
    spread = innovation_spread(innovation_sample(association.distance))
    limit = max(INNOVATION_SIGMAS * nominal_sigma, INNOVATION_DIAGONALS * scene.diagonal)
    if spread > limit:
        sample = innovation_sample(points)
        about_copy_forward = innovation_spread(
            ClosestPointIndex(copy_forward, surface_triangles).associate(sample).distance)
        if spread > INNOVATION_RATIO * about_copy_forward:
            return InnovationTest(None, rejection=(
                f"{REJECTIONS['predictions_rejected_innovation']} (spread {1e3 * spread:.3g} mm about it, "
                f"{1e3 * about_copy_forward:.3g} mm about the copy-forward, limit {1e3 * limit:.3g} mm)"))
    return InnovationTest(predicted, association)


@dataclass
class SelectedPoints:
    """The measurement factor's points and their noise model (`select_points`).

    points (K, 3), in the order of their closest triangles at `vertices`, where `association`
    (of these points, in this order) found them: consecutive points then read the same surface
    grid cells, or libigl's tree paths, in every later query. num_gated: points dropped, the
    back-facing ones included; back_facing_test_skipped: the viewpoint was found not to be the
    sensor's (more than MAX_BACK_FACING_SHARE of the points facing away), and nothing was
    dropped or weighted by it.
    """

    points: np.ndarray
    noise: PointNoise
    vertices: np.ndarray
    association: Association
    num_gated: int = 0
    num_back_facing: int = 0
    back_facing_test_skipped: bool = False


def select_points(points: np.ndarray, surface_triangles: np.ndarray, vertices: np.ndarray, sigma: float,
                  gating_distance: float, viewpoint: np.ndarray | None = None,
                  association: Association | None = None) -> SelectedPoints:
    """The points (K, 3), finite and K > 0, that a measurement factor on the surface `surface_triangles` of
    `vertices` (the prediction) takes, with their noise model, each test made once at `vertices`.

    The gate: points farther than `gating_distance` [m] from the surface are dropped; 0: GATE_SIGMAS
    times the robust spread of the points' distances, taken between 1 and GATE_SPREAD_CAP times
    `sigma` (the estimated measurement sigma). With a `viewpoint` (the sensor's centre, (3,)),
    points whose closest triangle faces away from it are dropped too: a camera cannot see a back
    face, and such points are the segmentation's leaks onto what lies behind the silhouette (the
    table, neighbouring tissue), close enough to the surface to pass a distance gate; when more
    than MAX_BACK_FACING_SHARE of the gated points would go, the viewpoint is not the sensor's (a
    camera pose left at a default) and the test is skipped. The noise: noise.RayNoise(sigma),
    each point's sigma following its ray's incidence on its face where the viewpoint is the
    sensor's (the implausible one's rays say nothing of the points' noise either), `sigma` for
    every point otherwise. `association`, the points' Association at `vertices` where the caller
    has it (the innovation test made it), saves that query."""
    if association is None:
        association = ClosestPointIndex(vertices, surface_triangles).associate(points)
    distance = association.distance
    gate = gating_distance or GATE_SIGMAS * float(np.clip(innovation_spread(distance), sigma, GATE_SPREAD_CAP * sigma))
    accepted = distance <= gate
    normals, num_back_facing, skipped = None, 0, False
    if viewpoint is not None:
        normals = _unit_normals(vertices, surface_triangles, association.triangle)
        # A degenerate triangle's NaN normal never counts as facing away.
        back = accepted & (np.einsum("ij,ij->i", normals, viewpoint - association.closest) < 0.0)
        num_back_facing = int(np.count_nonzero(back))
        skipped = num_back_facing > MAX_BACK_FACING_SHARE * max(int(np.count_nonzero(accepted)), 1)
        if skipped:
            num_back_facing = 0
        else:
            accepted &= ~back
    kept = np.flatnonzero(accepted)
    kept = kept[np.argsort(association.triangle[kept], kind="stable")]
    selected = points[kept]
    noise: PointNoise = RayNoise(sigma)
    if normals is not None and not skipped:
        noise = noise.on_surface(selected, normals[kept], viewpoint)
    return SelectedPoints(
        selected, noise, vertices,
        Association(*(getattr(association, name)[kept] for name in (
            "triangle", "closest", "barycentric", "region", "distance"))),
        num_gated=int(np.count_nonzero(~accepted)), num_back_facing=num_back_facing,
        back_facing_test_skipped=skipped)


def _unit_normals(vertices: np.ndarray, triangles: np.ndarray, index: np.ndarray) -> np.ndarray:
    """Unit normals (K, 3) of the triangles triangles[index] of `vertices` (NaN: degenerate)."""
    a, b, c = triangle_corners(vertices, triangles, index)
    normals = cross(b - a, c - a)
    with np.errstate(invalid="ignore", divide="ignore"):
        normals /= np.linalg.norm(normals, axis=1)[:, None]
    return normals
