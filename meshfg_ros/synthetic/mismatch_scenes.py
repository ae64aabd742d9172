"""Five scenes whose ground truth differs from the estimator's model the way real tissue does.

The truth of every scene is the static equilibrium of a heterogeneous compressible neo-Hookean
solid (`hyperelastic.py`, scikit-fem), not the package's own simulator: another constitutive
law, stiff inclusions or layers and smooth stiffness variations the model does not know,
nearly incompressible tissue (nu 0.47-0.49 against the nominal 0.45), loads the model does not
know (a lateral pull, a change of gravity direction), adhesive tool contact that never
releases, and a robot whose reported tool position is off by a calibration error. The nominal
model (`Scenario.simulator_config`) holds only what a user would know: a Young's modulus, the
usual Poisson ratio and the tool's radius. The estimator runs with its default settings
(`estimator_overrides` is empty) and the datasheet noise sigma (the depth-dependent term makes
the real spread larger).

Meshes come from gmsh with its default (light) optimisation only, so element quality is what
a real segmentation-to-mesh pipeline gives; measurements from a pinhole depth camera with
noise along the rays, thinning at grazing incidence, occlusion by the tool (sphere and shaft)
and segmentation leaks onto the tool and the surroundings at the mask boundary.

Scenes (10 steps at 1 Hz; every random choice from `seed`):
  slab-inclusion  tissue slab on a table with a 5x stiffer spherical inclusion under the
                  indentation site, indented vertically.
  dome-tilted     dome with +-40 % smooth stiffness variation about twice the nominal
                  modulus, indented 35 degrees off its normal while a lateral body load ramps up.
  liver-gravity   the SOFA liver re-meshed, a 5x stiffer tumour under the indentation site,
                  gravity turning by 10 degrees as the table tilts.
  kidney-drag     ellipsoidal kidney with a 3x stiffer capsule, pushed in and then dragged
                  sideways by a sticky tool with a calibration error.
  flap-bend       tissue flap attached at one end, with a 4x stiffer vessel along it, bent
                  down near its free end by an oblique push while a tether load ramps up.
                  Added after the estimator's defaults were settled, as a design they were
                  not tuned on.
  organ-slab      slab-inclusion meshed to organ scale (~6,400 vertices), every pixel
                  captured (about 7,000 points per cloud): the organ-scale live figure of
                  `meshfg bench`, not an accuracy scene.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from functools import lru_cache

import numpy as np
from scipy.spatial.transform import Rotation

from meshfg_ros.synthetic.camera import CaptureOptions, PinholeCamera, capture
from meshfg_ros.core.geometry.mesh import TetMesh, signed_volumes
from meshfg_ros.synthetic.meshing import MeshingError, compact_tetrahedra, gmsh_model
from meshfg_ros.synthetic.scenarios import (Scenario, ScenarioError, ScenarioStep, _stamp, liver_mesh, pose,
                                             truth_steps)
from meshfg_ros.core.physics.simulator import SimulatorConfig

from meshfg_ros.synthetic.hyperelastic import NeoHookeanSolid, StickySphereContact

__all__ = ["build_scene", "radius_ratios"]

NOMINAL_POISSON_RATIO = 0.45
TRUTH_SUBSTEPS = 4  # tool increments per step in the truth solver
SURROUNDINGS_LABEL = 1  # point label of leaks onto the table or neighbouring tissue
TOOL_LABEL = 2  # point label of leaks onto the tool (sphere and shaft)
SHAFT_RADIUS = 1.5e-3
SHAFT_LENGTH = 0.08
SURROUNDINGS_HALF_SIZE = 0.4  # half side of the square table / tissue plane around a body
SMOOTH_FIELD_MODES = 6  # plane waves of a smooth stiffness variation
SMOOTH_FIELD_WAVELENGTHS = (0.025, 0.05)  # m: a variation over an organ of a few centimetres
_GMSH_TETRAHEDRON = 4
_GMSH_TRIANGLE = 2


# ------------------------------------------------------------------------------- meshing


def _gmsh_mesh(model_name: str, build, options: dict[str, float]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Vertices (N, 3), tetrahedra (M, 4) and a marked-region flag (M,) of a gmsh model.

    build(gmsh) creates and synchronises the geometry (and any size field) and returns the tags
    of the volumes to mark (the session: core.meshing.gmsh_model).
    """
    with gmsh_model(model_name, options) as gmsh:
        marked_volumes = set(build(gmsh))
        gmsh.model.mesh.generate(3)
        node_tags, coordinates, _ = gmsh.model.mesh.getNodes()
        blocks, marked_blocks = [], []
        for _, volume in gmsh.model.getEntities(3):
            types, _, nodes = gmsh.model.mesh.getElements(3, volume)
            if _GMSH_TETRAHEDRON in list(types):
                block = np.asarray(nodes[list(types).index(_GMSH_TETRAHEDRON)], dtype=np.int64).reshape(-1, 4)
                blocks.append(block)
                marked_blocks.append(np.full(len(block), volume in marked_volumes))
    if not blocks:
        raise MeshingError(f"gmsh produced no tetrahedra for {model_name}")
    vertices, tetrahedra = compact_tetrahedra(node_tags, coordinates, np.concatenate(blocks))
    return vertices, tetrahedra, np.concatenate(marked_blocks)


def radius_ratios(vertices, tetrahedra) -> np.ndarray:
    """Element quality 3 r_in / r_circ (M,): 1 for the regular tetrahedron, 0 for a flat one."""
    corners = np.asarray(vertices, dtype=np.float64)[np.asarray(tetrahedra)]
    a, b, c = (corners[:, k] - corners[:, 0] for k in (1, 2, 3))
    six_volumes = np.abs(np.einsum("ij,ij->i", a, np.cross(b, c)))
    faces = corners[:, [[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]]]  # (M, 4, 3, 3)
    face_areas = 0.5 * np.linalg.norm(np.cross(faces[:, :, 1] - faces[:, :, 0], faces[:, :, 2] - faces[:, :, 0]),
                                      axis=2)
    inradius = six_volumes / (2.0 * face_areas.sum(axis=1))
    squared = [np.einsum("ij,ij->i", edge, edge) for edge in (a, b, c)]
    circumcentre = (squared[0][:, None] * np.cross(b, c) + squared[1][:, None] * np.cross(c, a)
                    + squared[2][:, None] * np.cross(a, b))
    circumradius = np.linalg.norm(circumcentre, axis=1) / (2.0 * six_volumes)
    return 3.0 * inradius / circumradius


@dataclass(frozen=True)
class _SceneMesh:
    """A scene's mesh, its marked (stiffer) elements and its quality figures."""

    mesh: TetMesh
    marked: np.ndarray  # (M,) bool
    min_quality: float
    median_quality: float


def _scene_mesh(vertices, tetrahedra, marked, fixed_rule, name: str) -> _SceneMesh:
    """TetMesh with the fixed vertices fixed_rule(mesh) picks, and its radius-ratio figures."""
    mesh = TetMesh(vertices, tetrahedra, name=name)
    mesh = mesh.with_fixed(fixed_rule(mesh))
    quality = radius_ratios(mesh.vertices, mesh.tetrahedra)
    return _SceneMesh(mesh, np.asarray(marked, dtype=bool), float(quality.min()), float(np.median(quality)))


# ----------------------------------------------------------------------- shared scene parts


def _first_contact(vertices: np.ndarray, aim: np.ndarray, approach: np.ndarray, radius: float) -> np.ndarray:
    """Centre of a sphere of `radius` moving along unit `approach` towards `aim` where it first
    touches a vertex (no vertex inside it)."""
    start = aim - approach * (np.ptp(vertices, axis=0).max() + 2.0 * radius)
    offsets = vertices - start
    along = offsets @ approach
    across_squared = np.einsum("ij,ij->i", offsets, offsets) - along**2
    reachable = across_squared < radius**2
    travel = along[reachable] - np.sqrt(radius**2 - across_squared[reachable])
    return start + approach * travel.min()


def _tool_orientation(approach: np.ndarray) -> np.ndarray:
    """Quaternion [qx qy qz qw] turning the tool frame's z axis onto the approach direction."""
    rotation, _ = Rotation.align_vectors([approach], [[0.0, 0.0, 1.0]])
    return rotation.as_quat()


def _tool_surfaces(centre: np.ndarray, approach: np.ndarray, radius: float) -> list[tuple]:
    """Occluders of the tool: its sphere and a thin shaft from the sphere back along the approach."""
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions=2, radius=radius)
    shaft = trimesh.creation.cylinder(radius=SHAFT_RADIUS, segment=[centre, centre - approach * SHAFT_LENGTH],
                                      sections=16)
    return [
        (np.asarray(sphere.vertices) + centre, np.asarray(sphere.faces, dtype=np.int64), TOOL_LABEL),
        (np.asarray(shaft.vertices), np.asarray(shaft.faces, dtype=np.int64), TOOL_LABEL),
    ]


def _plane(point, normal) -> tuple:
    """Square of half side SURROUNDINGS_HALF_SIZE through `point`, facing `normal`: the table or
    the tissue around a body, a background for the camera and a target of leaks."""
    normal = np.asarray(normal, dtype=np.float64) / np.linalg.norm(normal)
    first = np.cross(normal, np.eye(3)[np.argmin(np.abs(normal))])
    first /= np.linalg.norm(first)
    second = np.cross(normal, first)
    signs = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], dtype=np.float64) * SURROUNDINGS_HALF_SIZE
    corners = np.asarray(point, dtype=np.float64) + signs[:, :1] * first + signs[:, 1:] * second
    return corners, np.array([[0, 1, 2], [0, 2, 3]], dtype=np.int64), SURROUNDINGS_LABEL


def _smooth_field(points: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A smooth random field over `points` (K, 3) scaled to max |value| = 1: a sum of
    SMOOTH_FIELD_MODES plane waves with random directions, wavelengths in
    SMOOTH_FIELD_WAVELENGTHS and phases."""
    directions = rng.normal(size=(SMOOTH_FIELD_MODES, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    wavenumbers = 2.0 * np.pi / rng.uniform(*SMOOTH_FIELD_WAVELENGTHS, size=SMOOTH_FIELD_MODES)
    phases = rng.uniform(0.0, 2.0 * np.pi, size=SMOOTH_FIELD_MODES)
    field = np.cos(points @ (directions * wavenumbers[:, None]).T + phases).sum(axis=1)
    return field / np.abs(field).max()


@dataclass(frozen=True)
class _Loading:
    """The truth's material and loads, and what the robot and camera do."""

    youngs_modulus: np.ndarray  # (M,) Pa
    poisson_ratio: float
    true_tool_centres: np.ndarray  # (steps + 1, 3)
    body_forces: np.ndarray  # (steps + 1, 3) N/m^3
    tool_radius: float
    approach: np.ndarray  # (3,) unit: the tool's axis, from the shaft towards the tip
    calibration_error: np.ndarray  # (3,) reported minus true tool position
    camera: PinholeCamera
    capture_options: CaptureOptions
    surroundings: tuple  # (vertices, triangles, label) of the table or neighbouring tissue


def _simulate_truth(scene_mesh: _SceneMesh, loading: _Loading) -> list[np.ndarray]:
    """Truth positions after each step (the initial mesh is step 0)."""
    solid = NeoHookeanSolid(scene_mesh.mesh, loading.youngs_modulus, loading.poisson_ratio)
    contact = StickySphereContact(solid, loading.tool_radius, loading.true_tool_centres[0], TRUTH_SUBSTEPS,
                                  loading.body_forces[0])
    return [contact.advance(centre, force)
            for centre, force in truth_steps(zip(loading.true_tool_centres[1:], loading.body_forces[1:]),
                                             len(loading.true_tool_centres) - 1)]


def _assemble(name: str, seed: int, rng: np.random.Generator, scene_mesh: _SceneMesh, loading: _Loading,
              nominal_youngs_modulus: float, summary: str, truths: list[np.ndarray] | None = None,
              removed: list[np.ndarray] | None = None) -> Scenario:
    """Simulate the truth (unless `truths` gives it), capture a cloud per step and package the
    Scenario; `removed`: each step's element slots a cut has removed (core/geometry/topology.py), whose
    surface the camera sees then."""
    mesh = scene_mesh.mesh
    truths = _simulate_truth(scene_mesh, loading) if truths is None else truths
    removed = [np.zeros(0, np.int64)] * len(truths) if removed is None else removed
    orientation = _tool_orientation(loading.approach)
    reported = [pose(centre + loading.calibration_error, orientation) for centre in loading.true_tool_centres]
    steps, leak_shares, counts = [], [], []
    for k, (truth, slots) in enumerate(zip(truths, removed), start=1):
        occluders = [loading.surroundings, *_tool_surfaces(loading.true_tool_centres[k], loading.approach,
                                                          loading.tool_radius)]
        result = capture(loading.camera, truth, mesh.without_elements(slots).surface_triangles, occluders=occluders,
                         rng=rng, options=loading.capture_options)
        steps.append(ScenarioStep(_stamp(k), reported[k], result.points, result.labels, truth, slots))
        leak_shares.append(float(np.mean(result.labels > 0)))
        counts.append(len(result.points))
    nominal = SimulatorConfig(youngs_modulus=nominal_youngs_modulus, poisson_ratio=NOMINAL_POISSON_RATIO,
                              tool_radius=loading.tool_radius, tool_mode="sphere", tool_contact="stick")
    mean_youngs_modulus = np.average(loading.youngs_modulus, weights=signed_volumes(mesh.vertices, mesh.tetrahedra))
    description = (
        f"{summary}; {mesh.vertex_count} vertices, {mesh.tetrahedron_count} tetrahedra, radius ratio "
        f"min {scene_mesh.min_quality:.2f} median {scene_mesh.median_quality:.2f}; {len(truths)} steps; "
        f"{np.mean(counts):.0f} points per cloud, {100 * np.mean(leak_shares):.0f}% leaks; truth: compressible "
        f"neo-Hookean, E {mean_youngs_modulus / 1e3:.1f} kPa volume mean "
        f"(nominal {nominal_youngs_modulus / 1e3:g} kPa), nu {loading.poisson_ratio:g}"
    )
    return Scenario(
        name=name, seed=seed, initial_mesh=mesh, steps=tuple(steps), initial_tool_pose=reported[0],
        simulator_config=nominal, grasped_vertices=np.zeros(0, np.int64),
        noise_sigma_m=loading.capture_options.noise_constant, camera_pose=loading.camera.pose,
        description=description,
    )


def _straight_path(start: np.ndarray, direction: np.ndarray, per_step: float, steps: int) -> np.ndarray:
    """Tool centres (steps + 1, 3) moving `per_step` along unit `direction` from `start` per step."""
    return start + np.arange(steps + 1)[:, None] * per_step * direction


# ------------------------------------------------------------------------ slab-inclusion
SLAB_SIZE = (0.06, 0.04, 0.02)  # x, y, thickness at the crown (m)
SLAB_CROWN_RADIUS = 0.1  # top: a cylinder along x; the long edges sit 2 mm lower than the crown
SLAB_MESH_SIZE = 3.4e-3
SLAB_INDENT_SITE = np.array([0.005, 0.003])  # x, y of the tool's aim on the top
SLAB_INCLUSION_RADIUS = 6e-3
SLAB_INCLUSION_COVER = 3e-3  # tissue between the top and the inclusion
SLAB_TOOL_RADIUS = 4e-3
SLAB_PUSH_PER_STEP = 0.8e-3
SLAB_NOMINAL_E = 4e3
SLAB_TISSUE_E = 4e3
SLAB_INCLUSION_STIFFNESS_RATIO = 5.0
SLAB_POISSON_RATIO = 0.49
SLAB_CALIBRATION_ERROR = np.array([0.4e-3, -0.3e-3, 0.0])
# Stereo depth at ~0.13 m: sigma 0.35 mm (datasheet) + 0.01 z^2 (0.52 mm at 0.13 m).
SLAB_CAPTURE = CaptureOptions(stride=2, noise_constant=0.35e-3, noise_quadratic=0.01, grazing_exponent=1.0,
                              leak_fraction=0.7, leak_dilation_pixels=4.0)
# organ-slab: the same scene at organ scale, for `meshfg bench` (~6,400 vertices, every pixel:
# about 7,000 points per cloud).
ORGAN_SLAB_MESH_SIZE = SLAB_MESH_SIZE / 1.75
ORGAN_SLAB_CAPTURE = replace(SLAB_CAPTURE, stride=1)


def _slab_crown_height(y):
    """Height of the slab's curved top above the table at lateral coordinate y."""
    return SLAB_SIZE[2] - SLAB_CROWN_RADIUS + np.sqrt(SLAB_CROWN_RADIUS**2 - np.asarray(y) ** 2)


def _slab_inclusion_centre() -> np.ndarray:
    """Centre of the inclusion: SLAB_INCLUSION_COVER of tissue between it and the top at the site."""
    x, y = SLAB_INDENT_SITE
    return np.array([x, y, _slab_crown_height(y) - SLAB_INCLUSION_COVER - SLAB_INCLUSION_RADIUS])


@lru_cache(maxsize=2)
def _slab_mesh(mesh_size: float = SLAB_MESH_SIZE) -> _SceneMesh:
    length, width, thickness = SLAB_SIZE

    def build(gmsh):
        occ = gmsh.model.occ
        box = occ.addBox(-length / 2, -width / 2, 0.0, length, width, thickness + 1e-3)
        crown = occ.addCylinder(-length / 2, 0.0, thickness - SLAB_CROWN_RADIUS, length, 0.0, 0.0,
                                SLAB_CROWN_RADIUS)
        slab, _ = occ.intersect([(3, box)], [(3, crown)])
        inclusion = occ.addSphere(*_slab_inclusion_centre(), SLAB_INCLUSION_RADIUS)
        _, pieces = occ.fragment(slab, [(3, inclusion)])
        occ.synchronize()
        return [tag for _, tag in pieces[1]]

    vertices, tetrahedra, marked = _gmsh_mesh(
        "meshfg_slab", build, {"Mesh.MeshSizeMin": mesh_size, "Mesh.MeshSizeMax": mesh_size})
    return _scene_mesh(vertices, tetrahedra, marked,
                       lambda mesh: mesh.surface_vertices[mesh.vertices[mesh.surface_vertices, 2] < 1e-9],
                       "slab_inclusion")


def _slab_inclusion(seed: int, steps: int, name: str = "slab-inclusion", mesh_size: float = SLAB_MESH_SIZE,
                    capture_options: CaptureOptions = SLAB_CAPTURE) -> Scenario:
    """A tissue slab on a table, fixed at its bottom, indented from above over a stiff inclusion.

    Unmodelled: the 5x stiffer inclusion 3 mm under the tool, near incompressibility, adhesive
    contact, a 0.5 mm tool calibration error. Camera above the slab, tilted 30 degrees.
    """
    rng = np.random.default_rng(seed)
    scene_mesh = _slab_mesh(mesh_size)
    mesh = scene_mesh.mesh
    youngs = np.where(scene_mesh.marked, SLAB_INCLUSION_STIFFNESS_RATIO * SLAB_TISSUE_E, SLAB_TISSUE_E)
    approach = np.array([0.0, 0.0, -1.0])
    aim = np.array([*SLAB_INDENT_SITE, _slab_crown_height(SLAB_INDENT_SITE[1])])
    start = _first_contact(mesh.vertices, aim, approach, SLAB_TOOL_RADIUS)
    tilt = np.deg2rad(30.0)
    sideways = np.array([-0.8, -0.6, 0.0])
    camera = PinholeCamera.look_at(aim + 0.13 * (np.sin(tilt) * sideways + np.cos(tilt) * np.array([0, 0, 1.0])),
                                   aim, up=np.array([0.0, 1.0, 0.0]), width=200, height=150, fx=230.0)
    loading = _Loading(
        youngs_modulus=youngs, poisson_ratio=SLAB_POISSON_RATIO,
        true_tool_centres=_straight_path(start, approach, SLAB_PUSH_PER_STEP, steps),
        body_forces=np.zeros((steps + 1, 3)), tool_radius=SLAB_TOOL_RADIUS, approach=approach,
        calibration_error=SLAB_CALIBRATION_ERROR, camera=camera, capture_options=capture_options,
        surroundings=_plane([0.0, 0.0, -1e-4], [0.0, 0.0, 1.0]),
    )
    return _assemble(name, seed, rng, scene_mesh, loading, SLAB_NOMINAL_E,
                     f"60x40x20 mm slab, 5x stiff inclusion (r 6 mm) 3 mm under a 4 mm tool pushing "
                     f"{SLAB_PUSH_PER_STEP * 1e3:g} mm/step, table leaks, tool calibration error 0.5 mm")


# ------------------------------------------------------------------------- dome-tilted
DOME_SEMI_AXES = np.array([0.03, 0.03, 0.024])
DOME_MESH_SIZE = 3.6e-3
DOME_SITE_POLAR_ANGLE = np.deg2rad(30.0)  # from the apex, towards +x
DOME_TILT = np.deg2rad(35.0)  # between the push and the inward surface normal, towards +y
DOME_TOOL_RADIUS = 5e-3
# 0.6 mm/step: at 1 mm/step (and 0.8) the nominal simulator inverts an element under the tool
# after about 7 mm of tilted travel.
DOME_PUSH_PER_STEP = 0.6e-3
DOME_NOMINAL_E = 3e3
DOME_TRUTH_MEAN_E = 6e3
DOME_HETEROGENEITY = 0.4
DOME_POISSON_RATIO = 0.47
DOME_LATERAL_LOAD = np.array([0.0, -1.2e4, 0.0])  # N/m^3 at the last step, from 0 at step 0
DOME_CAPTURE = CaptureOptions(stride=2, noise_constant=0.6e-3, noise_quadratic=0.018, grazing_exponent=1.0,
                              leak_fraction=0.8, leak_dilation_pixels=6.0)


@lru_cache(maxsize=1)
def _dome_mesh() -> _SceneMesh:
    def build(gmsh):
        occ = gmsh.model.occ
        ellipsoid = occ.addSphere(0.0, 0.0, 0.0, 1.0)
        occ.dilate([(3, ellipsoid)], 0.0, 0.0, 0.0, *DOME_SEMI_AXES)
        extent = 2.0 * DOME_SEMI_AXES.max()
        upper = occ.addBox(-extent, -extent, 0.0, 2 * extent, 2 * extent, extent)
        occ.intersect([(3, ellipsoid)], [(3, upper)])
        occ.synchronize()
        return []

    vertices, tetrahedra, marked = _gmsh_mesh(
        "meshfg_dome", build, {"Mesh.MeshSizeMin": DOME_MESH_SIZE, "Mesh.MeshSizeMax": DOME_MESH_SIZE})
    return _scene_mesh(vertices, tetrahedra, marked,
                       lambda mesh: mesh.surface_vertices[mesh.vertices[mesh.surface_vertices, 2] < 1e-9],
                       "dome_tilted")


def _dome_tilted(seed: int, steps: int) -> Scenario:
    """A dome fixed at its base, indented 35 degrees off its normal while pulled sideways.

    Unmodelled: a stiffness twice the nominal with a smooth +-40 % variation, a lateral body
    load ramping up over the steps (the organ pulled sideways), near incompressibility,
    adhesive contact.
    """
    rng = np.random.default_rng(seed)
    scene_mesh = _dome_mesh()
    mesh = scene_mesh.mesh
    centroids = mesh.vertices[mesh.tetrahedra].mean(axis=1)
    youngs = DOME_TRUTH_MEAN_E * (1.0 + DOME_HETEROGENEITY * _smooth_field(centroids, rng))
    a, _, c = DOME_SEMI_AXES
    site = np.array([a * np.sin(DOME_SITE_POLAR_ANGLE), 0.0, c * np.cos(DOME_SITE_POLAR_ANGLE)])
    normal = site / DOME_SEMI_AXES**2
    normal /= np.linalg.norm(normal)
    sideways = np.array([0.0, 1.0, 0.0])  # tangent at the site (the site lies in y = 0)
    approach = -np.cos(DOME_TILT) * normal + np.sin(DOME_TILT) * sideways
    start = _first_contact(mesh.vertices, site, approach, DOME_TOOL_RADIUS)
    camera = PinholeCamera.look_at(np.array([0.09, -0.06, 0.12]), np.array([0.0, 0.0, 0.012]),
                                   up=np.array([0.0, 0.0, 1.0]), width=200, height=150, fx=300.0)
    loading = _Loading(
        youngs_modulus=youngs, poisson_ratio=DOME_POISSON_RATIO,
        true_tool_centres=_straight_path(start, approach, DOME_PUSH_PER_STEP, steps),
        body_forces=np.linspace(0.0, 1.0, steps + 1)[:, None] * DOME_LATERAL_LOAD,
        tool_radius=DOME_TOOL_RADIUS, approach=approach, calibration_error=np.zeros(3), camera=camera,
        capture_options=DOME_CAPTURE, surroundings=_plane([0.0, 0.0, -1e-4], [0.0, 0.0, 1.0]),
    )
    return _assemble("dome-tilted", seed, rng, scene_mesh, loading, DOME_NOMINAL_E,
                     f"dome (semi-axes 30/30/24 mm) indented {DOME_PUSH_PER_STEP * 1e3:g} mm/step 35 deg off "
                     f"its normal by a 5 mm tool, lateral load ramping to {np.linalg.norm(DOME_LATERAL_LOAD):g} N/m^3, "
                     f"+-40% smooth stiffness variation")


# ------------------------------------------------------------------------ liver-gravity
# gmsh splits the re-meshed liver surface into patches at edges sharper than this; at 40 (60)
# degrees the patch borders pin flat elements to the SOFA surface's creases: radius ratio 0.06
# (0.17) against 0.22 at 70.
LIVER_CLASSIFY_ANGLE = np.deg2rad(70.0)
LIVER_MESH_SIZE = 0.013
LIVER_FINE_MESH_SIZE = 0.005  # within LIVER_FINE_RADIUS of the indentation site
LIVER_FINE_RADIUS = 0.03
LIVER_FIXED_FRACTION = 0.15  # as core.scenarios.liver_mesh: the lowest 15% (posterior) fixed
LIVER_TOOL_RADIUS = 6e-3
LIVER_PUSH_PER_STEP = 1.2e-3
LIVER_TUMOUR_RADIUS = 0.012
LIVER_TUMOUR_DEPTH = 0.022  # tumour centre under the indentation site
LIVER_TUMOUR_STIFFNESS_RATIO = 5.0
LIVER_NOMINAL_E = 4e3
LIVER_TRUTH_E = 8e3
LIVER_POISSON_RATIO = 0.48
# The liver lies among organs and fluid of nearly its density (1060 against about 1030 kg/m^3):
# a change of gravity moves it by the density excess only, as buoyancy cancels the rest.
LIVER_DENSITY_EXCESS = 30.0  # kg/m^3
GRAVITY = 9.81
LIVER_TABLE_TILT = np.deg2rad(10.0)  # head-down tilt at the last step, about the world x axis
# Laparoscopic stereo at ~0.23 m: sigma 1 mm (datasheet) + 0.015 z^2 (1.8 mm at 0.23 m).
LIVER_CAPTURE = CaptureOptions(stride=2, noise_constant=1.0e-3, noise_quadratic=0.015, grazing_exponent=1.0,
                               leak_fraction=0.8, leak_dilation_pixels=4.0)


def _liver_site(mesh: TetMesh) -> np.ndarray:
    """The highest surface point of the liver (world y is up): where the tool aims."""
    surface = mesh.surface_vertices
    return mesh.vertices[surface[np.argmax(mesh.vertices[surface, 1])]]


@lru_cache(maxsize=1)
def _liver_mesh() -> _SceneMesh:
    import trimesh

    source = liver_mesh()
    # Midpoint subdivision keeps the SOFA surface exactly and gives gmsh's classification
    # patches it can parametrise.
    surface_vertices, surface_triangles = trimesh.remesh.subdivide(source.vertices, source.surface_triangles)
    site = _liver_site(source)

    def build(gmsh):
        surface = gmsh.model.addDiscreteEntity(2)
        gmsh.model.mesh.addNodes(2, surface, np.arange(1, len(surface_vertices) + 1), surface_vertices.reshape(-1))
        gmsh.model.mesh.addElementsByType(surface, _GMSH_TRIANGLE, [], (surface_triangles + 1).reshape(-1))
        gmsh.model.mesh.classifySurfaces(LIVER_CLASSIFY_ANGLE, True, True, math.pi)
        gmsh.model.mesh.createGeometry()
        loop = gmsh.model.geo.addSurfaceLoop([tag for _, tag in gmsh.model.getEntities(2)])
        gmsh.model.geo.addVolume([loop])
        gmsh.model.geo.synchronize()
        fine = gmsh.model.mesh.field.add("Ball")
        for key, value in (("Radius", LIVER_FINE_RADIUS), ("Thickness", LIVER_FINE_RADIUS),
                           ("VIn", LIVER_FINE_MESH_SIZE), ("VOut", LIVER_MESH_SIZE),
                           ("XCenter", site[0]), ("YCenter", site[1]), ("ZCenter", site[2])):
            gmsh.model.mesh.field.setNumber(fine, key, value)
        gmsh.model.mesh.field.setAsBackgroundMesh(fine)
        return []

    vertices, tetrahedra, marked = _gmsh_mesh("meshfg_liver", build, {
        "Mesh.MeshSizeMin": LIVER_FINE_MESH_SIZE, "Mesh.MeshSizeMax": LIVER_MESH_SIZE,
        "Mesh.MeshSizeExtendFromBoundary": 0, "Mesh.MeshSizeFromPoints": 0, "Mesh.MeshSizeFromCurvature": 0,
    })

    def posterior(mesh):
        y = mesh.vertices[:, 1]
        surface = mesh.surface_vertices
        return surface[y[surface] <= y.min() + LIVER_FIXED_FRACTION * np.ptp(y)]

    return _scene_mesh(vertices, tetrahedra, marked, posterior, "liver_gravity")


def _liver_gravity(seed: int, steps: int) -> Scenario:
    """The SOFA liver indented over a stiff tumour while the table tilts by 10 degrees.

    Unmodelled: a 5x stiffer tumour under the tool, a stiffness twice the nominal, the change of
    gravity as the table tilts (the initial mesh is the liver under the initial gravity; the
    truth loads it with the difference times the density excess over the surrounding organs,
    (rho - rho_surroundings) (g(t) - g(0))), adhesive contact.
    """
    rng = np.random.default_rng(seed)
    scene_mesh = _liver_mesh()
    mesh = scene_mesh.mesh
    site = _liver_site(mesh)
    approach = np.array([0.0, -1.0, 0.0])
    tumour_centre = site + approach * LIVER_TUMOUR_DEPTH
    centroids = mesh.vertices[mesh.tetrahedra].mean(axis=1)
    in_tumour = np.linalg.norm(centroids - tumour_centre, axis=1) < LIVER_TUMOUR_RADIUS
    youngs = np.where(in_tumour, LIVER_TUMOUR_STIFFNESS_RATIO * LIVER_TRUTH_E, LIVER_TRUTH_E)
    angles = np.linspace(0.0, LIVER_TABLE_TILT, steps + 1)
    gravity = GRAVITY * np.column_stack([np.zeros(steps + 1), -np.cos(angles), np.sin(angles)])
    start = _first_contact(mesh.vertices, site, approach, LIVER_TOOL_RADIUS)
    centre = mesh.vertices.mean(axis=0)
    camera = PinholeCamera.look_at(centre + np.array([0.06, 0.22, 0.03]), centre, up=np.array([0.0, 0.0, 1.0]),
                                   width=200, height=150, fx=170.0)
    y = mesh.vertices[:, 1]
    loading = _Loading(
        youngs_modulus=youngs, poisson_ratio=LIVER_POISSON_RATIO,
        true_tool_centres=_straight_path(start, approach, LIVER_PUSH_PER_STEP, steps),
        body_forces=LIVER_DENSITY_EXCESS * (gravity - gravity[0]), tool_radius=LIVER_TOOL_RADIUS, approach=approach,
        calibration_error=np.zeros(3), camera=camera, capture_options=LIVER_CAPTURE,
        surroundings=_plane([0.0, y.min() + LIVER_FIXED_FRACTION * np.ptp(y), 0.0], [0.0, 1.0, 0.0]),
    )
    return _assemble("liver-gravity", seed, rng, scene_mesh, loading, LIVER_NOMINAL_E,
                     f"SOFA liver re-meshed, 6 mm tool pushing {LIVER_PUSH_PER_STEP * 1e3:g} mm/step over a 5x stiff "
                     f"tumour (r 12 mm), gravity turning by 10 deg, surrounding tissue at the fixed region's level")


# -------------------------------------------------------------------------- kidney-drag
KIDNEY_SEMI_AXES = np.array([0.02, 0.0125, 0.01])
KIDNEY_CAPSULE_THICKNESS = 2e-3
KIDNEY_MESH_SIZE = 2.2e-3
KIDNEY_FIXED_BELOW = -0.4  # surface vertices with z below this fraction of the z semi-axis are fixed
KIDNEY_SURROUNDINGS_LEVEL = -0.5  # the surrounding tissue's plane, as a fraction of the z semi-axis
KIDNEY_SITE = np.array([-0.006, 0.0])  # x, y of the tool's aim on the top
KIDNEY_TOOL_RADIUS = 4e-3
KIDNEY_PUSH_STEPS = 3
KIDNEY_PUSH_PER_STEP = 1.0e-3
KIDNEY_DRAG_PER_STEP = 0.8e-3  # along +x, after the push
KIDNEY_NOMINAL_E = 5e3
KIDNEY_PARENCHYMA_E = 5e3
KIDNEY_CAPSULE_STIFFNESS_RATIO = 3.0
KIDNEY_POISSON_RATIO = 0.48
KIDNEY_CALIBRATION_ERROR = np.array([0.5e-3, -0.4e-3, 0.3e-3])
# sigma 1 mm (datasheet) + 0.035 z^2 (1.5 mm at 0.12 m).
KIDNEY_CAPTURE = CaptureOptions(stride=2, noise_constant=1.0e-3, noise_quadratic=0.035, grazing_exponent=1.0,
                                leak_fraction=0.85, leak_dilation_pixels=6.0)


@lru_cache(maxsize=1)
def _kidney_mesh() -> _SceneMesh:
    def build(gmsh):
        occ = gmsh.model.occ
        outer = occ.addSphere(0.0, 0.0, 0.0, 1.0)
        occ.dilate([(3, outer)], 0.0, 0.0, 0.0, *KIDNEY_SEMI_AXES)
        inner = occ.addSphere(0.0, 0.0, 0.0, 1.0)
        occ.dilate([(3, inner)], 0.0, 0.0, 0.0, *(KIDNEY_SEMI_AXES - KIDNEY_CAPSULE_THICKNESS))
        _, pieces = occ.fragment([(3, outer)], [(3, inner)])
        occ.synchronize()
        return sorted({tag for _, tag in pieces[0]} - {tag for _, tag in pieces[1]})

    # HXT: gmsh's default Delaunay leaves slivers (radius ratio 0.002) on the capsule's inner face.
    vertices, tetrahedra, marked = _gmsh_mesh("meshfg_kidney", build, {
        "Mesh.MeshSizeMin": KIDNEY_MESH_SIZE, "Mesh.MeshSizeMax": KIDNEY_MESH_SIZE, "Mesh.Algorithm3D": 10})
    limit = KIDNEY_FIXED_BELOW * KIDNEY_SEMI_AXES[2]
    return _scene_mesh(vertices, tetrahedra, marked,
                       lambda mesh: mesh.surface_vertices[mesh.vertices[mesh.surface_vertices, 2] < limit],
                       "kidney_drag")


def _kidney_drag(seed: int, steps: int) -> Scenario:
    """An ellipsoidal kidney fixed on its back, pushed in by a sticky tool and then dragged sideways.

    Unmodelled: a 3x stiffer capsule, adhesive contact that drags the surface along, near
    incompressibility, a 0.7 mm tool calibration error.
    """
    rng = np.random.default_rng(seed)
    scene_mesh = _kidney_mesh()
    mesh = scene_mesh.mesh
    youngs = np.where(scene_mesh.marked, KIDNEY_CAPSULE_STIFFNESS_RATIO * KIDNEY_PARENCHYMA_E, KIDNEY_PARENCHYMA_E)
    x, y = KIDNEY_SITE
    a, b, c = KIDNEY_SEMI_AXES
    site = np.array([x, y, c * np.sqrt(1.0 - (x / a) ** 2 - (y / b) ** 2)])
    normal = site / KIDNEY_SEMI_AXES**2
    approach = -normal / np.linalg.norm(normal)
    start = _first_contact(mesh.vertices, site, approach, KIDNEY_TOOL_RADIUS)
    pushes = np.minimum(np.arange(steps + 1), KIDNEY_PUSH_STEPS) * KIDNEY_PUSH_PER_STEP
    drags = np.maximum(np.arange(steps + 1) - KIDNEY_PUSH_STEPS, 0) * KIDNEY_DRAG_PER_STEP
    centres = start + pushes[:, None] * approach + drags[:, None] * np.array([1.0, 0.0, 0.0])
    camera = PinholeCamera.look_at(np.array([-0.02, -0.07, 0.1]), np.array([0.0, 0.0, 0.0]),
                                   up=np.array([0.0, 0.0, 1.0]), width=320, height=240, fx=400.0)
    loading = _Loading(
        youngs_modulus=youngs, poisson_ratio=KIDNEY_POISSON_RATIO, true_tool_centres=centres,
        body_forces=np.zeros((steps + 1, 3)), tool_radius=KIDNEY_TOOL_RADIUS, approach=approach,
        calibration_error=KIDNEY_CALIBRATION_ERROR, camera=camera, capture_options=KIDNEY_CAPTURE,
        surroundings=_plane([0.0, 0.0, KIDNEY_SURROUNDINGS_LEVEL * c], [0.0, 0.0, 1.0]),
    )
    return _assemble("kidney-drag", seed, rng, scene_mesh, loading, KIDNEY_NOMINAL_E,
                     f"40x25x20 mm kidney, 3x stiff 2 mm capsule, 4 mm tool pushing {KIDNEY_PUSH_STEPS} steps "
                     f"then dragging {KIDNEY_DRAG_PER_STEP * 1e3:g} mm/step, tool calibration error 0.7 mm")


# ---------------------------------------------------------------------------- flap-bend
FLAP_SIZE = (0.05, 0.03, 0.008)  # x (from its attached end), y, thickness (m)
FLAP_MESH_SIZE = 2.6e-3
FLAP_ATTACHED_LENGTH = 0.01  # the bottom face is attached to the tissue below up to this x
FLAP_VESSEL_RADIUS = 2.5e-3
FLAP_VESSEL_OFFSET = np.array([0.006, 0.004])  # y, z of the vessel's axis (along x)
FLAP_VESSEL_STIFFNESS_RATIO = 4.0
FLAP_SITE = np.array([0.038, -0.004])  # x, y of the tool's aim on the top face
FLAP_TILT = np.deg2rad(20.0)  # of the push from the vertical, towards the free end
FLAP_TOOL_RADIUS = 4e-3
FLAP_PUSH_PER_STEP = 0.6e-3
FLAP_NOMINAL_E = 3e3
FLAP_TISSUE_E = 5e3
FLAP_POISSON_RATIO = 0.49
FLAP_TETHER_LOAD = 1.0e3 * np.array([0.0, -0.6, -0.8])  # N/m^3 at the last step, from 0 at step 0
FLAP_BED_GAP = 0.014  # the tissue bed under the flap's free part, below its lowest reach
FLAP_CALIBRATION_ERROR = np.array([-0.3e-3, 0.4e-3, 0.3e-3])
# Laparoscopic stereo at ~0.12 m: sigma 0.8 mm (datasheet) + 0.02 z^2 (1.1 mm at 0.12 m).
FLAP_CAPTURE = CaptureOptions(stride=2, noise_constant=0.8e-3, noise_quadratic=0.02, grazing_exponent=1.0,
                              leak_fraction=0.8, leak_dilation_pixels=5.0)


@lru_cache(maxsize=1)
def _flap_mesh() -> _SceneMesh:
    length, width, thickness = FLAP_SIZE

    def build(gmsh):
        occ = gmsh.model.occ
        flap = occ.addBox(0.0, -width / 2, 0.0, length, width, thickness)
        vessel = occ.addCylinder(0.0, *FLAP_VESSEL_OFFSET, length, 0.0, 0.0, FLAP_VESSEL_RADIUS)
        _, pieces = occ.fragment([(3, flap)], [(3, vessel)])
        occ.synchronize()
        return [tag for _, tag in pieces[1]]

    # HXT, as for the kidney: the default Delaunay leaves slivers (radius ratio 0.07) along the vessel.
    vertices, tetrahedra, marked = _gmsh_mesh("meshfg_flap", build, {
        "Mesh.MeshSizeMin": FLAP_MESH_SIZE, "Mesh.MeshSizeMax": FLAP_MESH_SIZE, "Mesh.Algorithm3D": 10})

    def attached(mesh):
        x, z = mesh.vertices[mesh.surface_vertices, 0], mesh.vertices[mesh.surface_vertices, 2]
        return mesh.surface_vertices[(x < 1e-9) | ((z < 1e-9) & (x <= FLAP_ATTACHED_LENGTH))]

    return _scene_mesh(vertices, tetrahedra, marked, attached, "flap_bend")


def _flap_bend(seed: int, steps: int) -> Scenario:
    """A tissue flap attached at one end, bent down near its free end by an oblique push.

    Unmodelled: a 4x stiffer vessel along the flap, tissue 1.7x stiffer than the nominal (2x in
    the volume mean, with the vessel), near incompressibility, a tether load ramping up (the
    flap's connections pulling it down and sideways), adhesive contact, a 0.6 mm tool
    calibration error. Unlike the other scenes the
    flap bends as a plate, with large rotations, rather than being indented. Camera above the
    flap, to the side of the vessel; the tool and its shaft occlude it.
    """
    rng = np.random.default_rng(seed)
    scene_mesh = _flap_mesh()
    mesh = scene_mesh.mesh
    youngs = np.where(scene_mesh.marked, FLAP_VESSEL_STIFFNESS_RATIO * FLAP_TISSUE_E, FLAP_TISSUE_E)
    approach = np.array([np.sin(FLAP_TILT), 0.0, -np.cos(FLAP_TILT)])
    aim = np.array([*FLAP_SITE, FLAP_SIZE[2]])
    start = _first_contact(mesh.vertices, aim, approach, FLAP_TOOL_RADIUS)
    camera = PinholeCamera.look_at(np.array([0.04, 0.06, 0.11]), np.array([0.025, 0.0, 0.002]),
                                   up=np.array([1.0, 0.0, 0.0]), width=200, height=150, fx=260.0)
    loading = _Loading(
        youngs_modulus=youngs, poisson_ratio=FLAP_POISSON_RATIO,
        true_tool_centres=_straight_path(start, approach, FLAP_PUSH_PER_STEP, steps),
        body_forces=np.linspace(0.0, 1.0, steps + 1)[:, None] * FLAP_TETHER_LOAD, tool_radius=FLAP_TOOL_RADIUS,
        approach=approach, calibration_error=FLAP_CALIBRATION_ERROR, camera=camera, capture_options=FLAP_CAPTURE,
        surroundings=_plane([0.0, 0.0, -FLAP_BED_GAP], [0.0, 0.0, 1.0]),
    )
    return _assemble("flap-bend", seed, rng, scene_mesh, loading, FLAP_NOMINAL_E,
                     f"50x30x8 mm flap attached at one end, 4x stiff vessel (r 2.5 mm) along it, bent by a 4 mm tool "
                     f"pushing {FLAP_PUSH_PER_STEP * 1e3:g} mm/step {np.rad2deg(FLAP_TILT):g} deg off the vertical near its "
                     f"free end, tether load ramping to {np.linalg.norm(FLAP_TETHER_LOAD):g} N/m^3, tool calibration "
                     f"error 0.6 mm")


_BUILDERS = {
    "slab-inclusion": _slab_inclusion,
    "organ-slab": lambda seed, steps: _slab_inclusion(seed, steps, "organ-slab", ORGAN_SLAB_MESH_SIZE,
                                                      ORGAN_SLAB_CAPTURE),
    "dome-tilted": _dome_tilted,
    "liver-gravity": _liver_gravity,
    "kidney-drag": _kidney_drag,
    "flap-bend": _flap_bend,
}


def build_scene(name: str, seed: int = 0, steps: int = 10) -> Scenario:
    """Scene `name` (core.scenarios.MISMATCH_SCENARIOS) with `steps` 1 Hz steps, deterministic from `seed`."""
    if name not in _BUILDERS:
        raise ScenarioError(f"unknown mismatch scene {name!r}; choose one of {', '.join(_BUILDERS)}")
    if int(steps) != steps or steps < 1:
        raise ScenarioError(f"steps must be a positive integer, got {steps}")
    return _BUILDERS[name](seed, int(steps))
