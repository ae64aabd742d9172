"""The cutting scene: a tissue sheet under tension is cut mid-sequence, and the wound opens.

  sheet-cut  a 60x40x12 mm sheet of tissue bridging a gap, held at both ends, stretched 15 %
             along x by the tissue around it (its stress-free shape is shorter than the sheet)
             and loaded by the weight of what hangs from it. A 4 mm tool indents it on one
             side; halfway through the sequence a blade cuts a 24 mm long, 7 mm deep wound
             across it on the other side. The tension pulls the wound open (its lips retract)
             and the sheet, weaker at the wound, sags there.

The truth is the static equilibrium of a heterogeneous (smooth +-30 % Young's modulus)
compressible neo-Hookean solid (`hyperelastic.py`) with that pre-stress and load, cut by
removing the elements the blade reaches (core/geometry/topology.py: cut_elements, the pieces left hanging
removed too). The estimator's nominal model knows the cut (the recording's
/meshfg/remove_elements at the step's stamp: its simulator made it) but neither the pre-stress
nor the load: its simulator's rest shape is the sheet as the camera first sees it, so the
simulation alone keeps the wound closed and the sheet where it was, and only the clouds show
otherwise. Camera, noise, leaks, tool occlusion, adhesive contact and the tool's calibration
error as in the mismatch scenes (`mismatch_scenes.py`). A wound's retraction along the sheet is
tangential to its top, which point-to-plane measurements hardly see (docs/design-notes.md,
"Cuts").
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from meshfg_ros.core.geometry.topology import cut_elements
from meshfg_ros.synthetic.camera import CaptureOptions, PinholeCamera
from meshfg_ros.synthetic.hyperelastic import NeoHookeanSolid, StickySphereContact
from meshfg_ros.synthetic.mismatch_scenes import (
    TRUTH_SUBSTEPS,
    _assemble,
    _first_contact,
    _gmsh_mesh,
    _Loading,
    _plane,
    _scene_mesh,
    _SceneMesh,
    _smooth_field,
    _straight_path,
)
from meshfg_ros.synthetic.scenarios import Scenario, ScenarioError, truth_steps

__all__ = ["SHEET_MESH_SIZE", "build_cut_scene"]

SHEET_SIZE = (0.06, 0.04, 0.012)  # x, y, thickness (m), centred on x = y = 0, base at z = 0
SHEET_MESH_SIZE = 3.4e-3
SHEET_PRESTRETCH = 0.15  # the sheet is this much longer along x than its stress-free shape
SHEET_CUT_CENTRE = np.array([-0.012, 0.0])  # x, y of the wound's middle
SHEET_CUT_HALF_LENGTH = 0.012  # along y
SHEET_CUT_HALF_WIDTH = 1.5e-3  # along x: the tissue the blade (an electrosurgical one) takes away
SHEET_CUT_DEPTH = 7e-3
SHEET_BED_GAP = 0.01  # the tissue below the bridge
# The weight of what hangs from the sheet (N/m^3), which the model does not know.
SHEET_LOAD = np.array([0.0, 0.0, -1.0e4])
SHEET_SITE = np.array([0.014, 0.004])  # x, y of the tool's aim on the top
SHEET_TOOL_RADIUS = 4e-3
SHEET_PUSH_PER_STEP = 0.6e-3
SHEET_NOMINAL_E = 4e3
SHEET_TRUTH_E = 5e3
SHEET_HETEROGENEITY = 0.3
SHEET_POISSON_RATIO = 0.47
SHEET_CAMERA_TILT = 25.0  # degrees from the vertical, towards -y
SHEET_CALIBRATION_ERROR = np.array([0.3e-3, 0.3e-3, 0.0])
SHEET_CAPTURE = CaptureOptions(stride=2, noise_constant=0.35e-3, noise_quadratic=0.01, grazing_exponent=1.0,
                               leak_fraction=0.7, leak_dilation_pixels=4.0)


@lru_cache(maxsize=2)
def _sheet_mesh(mesh_size: float) -> _SceneMesh:
    length, width, thickness = SHEET_SIZE

    def build(gmsh):
        gmsh.model.occ.addBox(-length / 2, -width / 2, 0.0, length, width, thickness)
        gmsh.model.occ.synchronize()
        return []

    vertices, tetrahedra, marked = _gmsh_mesh("meshfg_sheet", build,
                                              {"Mesh.MeshSizeMin": mesh_size, "Mesh.MeshSizeMax": mesh_size})
    held = np.abs(vertices[:, 0]) > length / 2 - 1e-9
    return _scene_mesh(vertices, tetrahedra, marked, lambda mesh: np.flatnonzero(held), "sheet_cut")


def build_cut_scene(seed: int = 0, steps: int = 10, mesh_size: float = SHEET_MESH_SIZE) -> Scenario:
    """The sheet-cut scene (module doc) with `steps` 1 Hz steps, cut at step steps // 2 + 1
    (at the second step of a shorter sequence), deterministic from `seed`; `mesh_size` [m] (a
    coarser mesh makes a quicker scene for tests)."""
    if int(steps) != steps or steps < 2:
        raise ScenarioError(f"steps must be an integer >= 2 (one before the cut), got {steps}")
    rng = np.random.default_rng(seed)
    sheet = _sheet_mesh(float(mesh_size))
    unstressed = sheet.mesh.vertices * np.array([1.0 / (1.0 + SHEET_PRESTRETCH), 1.0, 1.0])
    centroids = sheet.mesh.vertices[sheet.mesh.tetrahedra].mean(axis=1)
    youngs = SHEET_TRUTH_E * (1.0 + SHEET_HETEROGENEITY * _smooth_field(centroids, rng))
    # The sheet as the camera sees it before the cut: the pre-stressed equilibrium (the
    # segmented mesh of the estimator and its simulator's rest shape).
    stretched = NeoHookeanSolid(sheet.mesh, youngs, SHEET_POISSON_RATIO, unstressed)
    mesh = sheet.mesh.with_vertices(stretched.equilibrium(sheet.mesh.vertices, body_force=SHEET_LOAD).positions)
    scene_mesh = _SceneMesh(mesh, sheet.marked, sheet.min_quality, sheet.median_quality)
    top = SHEET_SIZE[2]
    removed_at_cut = cut_elements(mesh, [*SHEET_CUT_CENTRE, top - SHEET_CUT_DEPTH / 2],
                                  [SHEET_CUT_HALF_WIDTH, SHEET_CUT_HALF_LENGTH, SHEET_CUT_DEPTH / 2])
    approach = np.array([0.0, 0.0, -1.0])
    aim = np.array([*SHEET_SITE, top])
    start = _first_contact(mesh.vertices, aim, approach, SHEET_TOOL_RADIUS)
    tilt = np.deg2rad(SHEET_CAMERA_TILT)
    eye = np.array([0.0, 0.0, top]) + 0.13 * np.array([0.0, -np.sin(tilt), np.cos(tilt)])
    camera = PinholeCamera.look_at(eye, np.array([0.0, 0.0, top]), up=np.array([1.0, 0.0, 0.0]), width=200,
                                   height=150, fx=200.0)
    loading = _Loading(
        youngs_modulus=youngs, poisson_ratio=SHEET_POISSON_RATIO,
        true_tool_centres=_straight_path(start, approach, SHEET_PUSH_PER_STEP, steps),
        body_forces=np.tile(SHEET_LOAD, (steps + 1, 1)), tool_radius=SHEET_TOOL_RADIUS, approach=approach,
        calibration_error=SHEET_CALIBRATION_ERROR, camera=camera, capture_options=SHEET_CAPTURE,
        surroundings=_plane([0.0, 0.0, -SHEET_BED_GAP], [0.0, 0.0, 1.0]),
    )
    cut_step = steps // 2 + 1
    removed = [removed_at_cut if k >= cut_step else np.zeros(0, np.int64) for k in range(1, steps + 1)]
    truths = _cut_truth(mesh, youngs, unstressed, loading, removed)
    return _assemble("sheet-cut", seed, rng, scene_mesh, loading, SHEET_NOMINAL_E,
                     f"60x40x12 mm sheet stretched {100 * SHEET_PRESTRETCH:g} % along x, a 4 mm tool pushing "
                     f"{SHEET_PUSH_PER_STEP * 1e3:g} mm/step, cut at step {cut_step}: {removed_at_cut.size} elements "
                     f"removed, a {2e3 * SHEET_CUT_HALF_LENGTH:g} mm long {SHEET_CUT_DEPTH * 1e3:g} mm deep wound "
                     f"the tension pulls open, an unmodelled load of {-SHEET_LOAD[2]:g} N/m^3; leaks onto the tissue "
                     "below, tool calibration error 0.4 mm",
                     truths=truths, removed=removed)


def _cut_truth(mesh, youngs: np.ndarray, unstressed: np.ndarray, loading: _Loading,
               removed: list[np.ndarray]) -> list[np.ndarray]:
    """Truth positions after each step: the pre-stressed solid under the sticky tool, cut (a
    new solid on the remaining elements, the vertices left without one held where they are)
    at the first step whose `removed` slots are not empty."""
    solid = NeoHookeanSolid(mesh, youngs, loading.poisson_ratio, unstressed)
    contact = StickySphereContact(solid, loading.tool_radius, loading.true_tool_centres[0], TRUTH_SUBSTEPS,
                                  loading.body_forces[0])
    truths, cut = [], False
    for centre, force, slots in truth_steps(zip(loading.true_tool_centres[1:], loading.body_forces[1:], removed),
                                            len(removed)):
        if slots.size and not cut:
            cut_mesh = mesh.without_elements(slots)
            held = cut_mesh.vertices.copy()
            held[cut_mesh.invalid_vertices] = contact.positions[cut_mesh.invalid_vertices]
            kept = np.setdiff1d(np.arange(mesh.tetrahedron_count), slots)
            contact.cut(NeoHookeanSolid(cut_mesh.with_vertices(held), youngs[kept], loading.poisson_ratio,
                                        unstressed))
            cut = True
        truths.append(contact.advance(centre, force))
    return truths
