"""Synthetic scenes with ground truth: deforming cubes (paper Table I), airway push, liver push,
the five mismatch scenes of `meshfg_ros.synthetic.mismatch_scenes` (truth from an
independent hyperelastic model) and the cutting scene of `meshfg_ros.synthetic.cut_scene`.

A scenario is what a recording holds (initial mesh, tool poses, measured clouds, camera pose)
plus the ground truth per step and the estimator's nominal model. The ground truth is
simulated with a *different* model than the estimator's simulator (material parameters,
heterogeneity, loads the model does not know, tool shape), because real tissue never matches
the model; see shared notes on modelling.
"""
from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator
from contextvars import ContextVar
from dataclasses import dataclass, field, replace
from functools import lru_cache
from pathlib import Path

import numpy as np

from meshfg_ros.synthetic.camera import CaptureOptions, PinholeCamera, capture
from meshfg_ros.core.geometry.mesh import TetMesh, load_mesh
from meshfg_ros.synthetic.meshing import airway_phantom, cube_mesh
from meshfg_ros.evaluation.metrics import sample_surface
from meshfg_ros.core.physics.simulator import ElasticSimulator, SimulatorConfig

MISMATCH_SCENARIOS = ("slab-inclusion", "dome-tilted", "liver-gravity", "kidney-drag", "flap-bend")
CUT_SCENARIOS = ("sheet-cut",)  # meshfg_ros.synthetic.cut_scene
ORGAN_SCALE_SCENARIOS = ("organ-slab",)  # slab-inclusion at organ scale, for `meshfg bench`
SCENARIOS = ("cube-translate", "cube-shear-spd", "cube-shear-nonspd", "cao-push", "liver-push", *MISMATCH_SCENARIOS,
             *CUT_SCENARIOS, *ORGAN_SCALE_SCENARIOS)
STEP_PERIOD_NS = 1_000_000_000  # 1 Hz, as the paper's capture
FIRST_STAMP_NS = 1_000_000_000
LIVER_PATH_CANDIDATES = (
    Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "liver.msh",
    Path(__file__).resolve().parents[2] / "data" / "liver.msh",
)
LIVER_METRES_PER_UNIT = 0.03  # the file states no unit; 0.03 m/unit gives a ~19 cm adult liver


class ScenarioError(ValueError):
    """Unknown scenario name or unusable scenario input."""


@dataclass(frozen=True)
class ScenarioStep:
    """One 1 Hz step: what the sensors give (tool pose, cloud) and the hidden truth."""

    stamp_ns: int
    tool_pose: np.ndarray      # (7,) x y z qx qy qz qw, world frame
    points: np.ndarray         # (K, 3) measured cloud, world frame
    point_labels: np.ndarray   # (K,) 0 = target tissue, >0 = segmentation leak (occluder id)
    truth: np.ndarray          # (N, 3) ground-truth vertex positions
    # slots of the initial mesh's elements a cut has removed by this step (TetMesh.without_elements)
    removed_elements: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))


@dataclass(frozen=True)
class Scenario:
    """A complete synthetic recording with ground truth."""

    name: str
    seed: int
    initial_mesh: TetMesh
    steps: tuple[ScenarioStep, ...]
    initial_tool_pose: np.ndarray              # (7,) tool pose at step 0 (the initial mesh's stamp)
    simulator_config: SimulatorConfig          # the estimator's nominal model
    grasped_vertices: np.ndarray               # (G,) driven by the tool in "grasp" mode
    noise_sigma_m: float                       # measurement noise (std, metres)
    camera_pose: np.ndarray | None = None      # (7,) camera in world, optical frame
    observed_triangles: np.ndarray | None = None  # (F,) bool mask: faces measurements come from
    estimator_overrides: dict = field(default_factory=dict)  # e.g. the non-SPD prior
    description: str = ""

    def events(self) -> Iterator[tuple[str, int, np.ndarray]]:
        """What the nodes would receive, in order, as core.scheduler.run_offline takes it: the
        initial tool pose, then each step's tool pose and cloud (world frame)."""
        yield "pose", FIRST_STAMP_NS, self.initial_tool_pose
        for step in self.steps:
            yield "pose", step.stamp_ns, step.tool_pose
            yield "cloud", step.stamp_ns, step.points


# Where the scene being generated reports its truth's steps (`generate`'s `progress`), so that
# the scene builders and their truth simulations need not pass it down to one another.
_TRUTH_PROGRESS: ContextVar[Callable | None] = ContextVar("truth_progress", default=None)


def truth_steps(steps: Iterable, total: int) -> Iterable:
    """`steps` of a truth simulation, reported to the progress of the `generate` call it runs in."""
    progress = _TRUTH_PROGRESS.get()
    return steps if progress is None else progress(steps, total)


def generate(name: str, seed: int = 0, steps: int | None = None, progress: Callable | None = None) -> Scenario:
    """Build scenario `name` deterministically from `seed`. `progress`: a progress(iterable,
    total) wrapper (a tqdm bar in the CLI) that the truth's simulation reports its steps to."""
    builders = {
        "cube-translate": lambda: _cube(seed, steps or 15, motion="translate", prior="spd"),
        "cube-shear-spd": lambda: _cube(seed, steps or 15, motion="shear", prior="spd"),
        "cube-shear-nonspd": lambda: _cube(seed, steps or 15, motion="shear", prior="nonspd"),
        "cao-push": lambda: _airway_push(seed, steps or 10),
        "liver-push": lambda: _liver_push(seed, steps or 10),
        **{name: (lambda name=name: _mismatch_scene(name, seed, steps or 10))
           for name in (*MISMATCH_SCENARIOS, *ORGAN_SCALE_SCENARIOS)},
        "sheet-cut": lambda: _cut_scene(seed, steps or 10),
    }
    if name not in builders:
        raise ScenarioError(f"unknown scenario {name!r}; choose one of {', '.join(SCENARIOS)}")
    token = _TRUTH_PROGRESS.set(progress)
    try:
        return builders[name]()
    finally:
        _TRUTH_PROGRESS.reset(token)


def _mismatch_scene(name: str, seed: int, steps: int) -> Scenario:
    """A scene of meshfg_ros.synthetic (imported on use: it needs scikit-fem and gmsh)."""
    from meshfg_ros.synthetic.mismatch_scenes import build_scene

    return build_scene(name, seed, steps)


def _cut_scene(seed: int, steps: int) -> Scenario:
    """The cutting scene of meshfg_ros.synthetic.cut_scene (imported on use, as the mismatch scenes)."""
    from meshfg_ros.synthetic.cut_scene import build_cut_scene

    return build_cut_scene(seed, steps)


def pose(position, quaternion=(0.0, 0.0, 0.0, 1.0)) -> np.ndarray:
    """Pose array [x, y, z, qx, qy, qz, qw]."""
    return np.concatenate([np.asarray(position, float), np.asarray(quaternion, float)])


def _stamp(step: int) -> int:
    return FIRST_STAMP_NS + step * STEP_PERIOD_NS


def _simulate_truth(mesh: TetMesh, config: SimulatorConfig, tool_poses, grasped=None) -> list[np.ndarray]:
    """Run the ground-truth simulator through the tool poses (one 1 s step each)."""
    simulator = ElasticSimulator(mesh, config, grasped_vertices=grasped)
    simulator.reset(tool_poses[0])
    state, states = mesh.vertices.copy(), []
    for tool_pose in truth_steps(tool_poses[1:], len(tool_poses) - 1):
        state = simulator.predict(state, tool_pose, STEP_PERIOD_NS * 1e-9)
        states.append(state)
    return states


# --------------------------------------------------------------------------- cubes (Table I)
CUBE_NOISE_SIGMA_M = 1e-3
CUBE_POINTS_PER_STEP = 2000
CUBE_OBSERVED_FACE_NORMALS = ((0.0, 0.0, 1.0), (1.0, 0.0, 0.0), (0.0, 1.0, 0.0))  # +z, +x, +y


def _cube(seed: int, steps: int, motion: str, prior: str) -> Scenario:
    """Unit cube (1 m) driven through its top face: rigid translation or shear (bottom fixed).

    Measurements are noisy samples of the true surface on the +z, +x and +y faces only, so the
    -x and -y faces are external but unobserved.
    """
    rng = np.random.default_rng(seed)
    mesh = cube_mesh(side=1.0, divisions=7)
    z = mesh.vertices[:, 2]
    top = np.flatnonzero(np.isclose(z, 1.0))
    bottom = np.flatnonzero(np.isclose(z, 0.0))
    nominal = SimulatorConfig(youngs_modulus=5e3, poisson_ratio=0.45, tool_mode="grasp")
    if motion == "translate":
        # The tool holds the top face and carries the free cube along +x.
        displacement_per_step = np.array([0.6e-3, 0.3e-3, 0.0])
        truth_config = replace(nominal, poisson_ratio=0.40)
    else:
        mesh = mesh.with_fixed(bottom)
        displacement_per_step = np.array([1.5e-3, 0.0, 0.0])
        truth_config = replace(nominal, poisson_ratio=0.40, youngs_modulus=8e3)
    start = pose(mesh.vertices[top].mean(axis=0))
    tool_poses = [start + np.concatenate([k * displacement_per_step, np.zeros(4)]) for k in range(steps + 1)]
    truths = _simulate_truth(mesh, _ground_truth_solver(truth_config), tool_poses, grasped=top)

    normals = mesh.triangle_normals()
    observed = np.zeros(len(mesh.surface_triangles), bool)
    for direction in CUBE_OBSERVED_FACE_NORMALS:
        observed |= normals @ np.asarray(direction) > 0.99
    observed_triangles = mesh.surface_triangles[observed]
    scenario_steps = []
    for k, truth in enumerate(truths, start=1):
        clean = sample_surface(truth, observed_triangles, CUBE_POINTS_PER_STEP, seed=int(rng.integers(2**31)))
        noisy = clean + rng.normal(scale=CUBE_NOISE_SIGMA_M, size=clean.shape)
        scenario_steps.append(ScenarioStep(_stamp(k), tool_poses[k], noisy,
                                           np.zeros(len(noisy), np.int32), truth))
    # The scene's prior (the paper's SPD or non-SPD stiffness) is part of what Table I compares;
    # the weights are the estimator's defaults.
    overrides = {"stiffness_kind": "corotational", "spd_projection": False}
    if prior == "nonspd":
        overrides = {**overrides, "stiffness_kind": "neo_hookean"}
    return Scenario(
        name=f"cube-{motion}-{prior}" if motion == "shear" else "cube-translate",
        seed=seed, initial_mesh=mesh, steps=tuple(scenario_steps), initial_tool_pose=tool_poses[0],
        simulator_config=nominal,
        grasped_vertices=top, noise_sigma_m=CUBE_NOISE_SIGMA_M, observed_triangles=observed,
        estimator_overrides=overrides,
        description=f"1 m cube, top face driven by the tool ({motion}), {steps} steps at 1 Hz, "
                    f"{CUBE_POINTS_PER_STEP} points/step on +x/+y/+z faces, sigma {CUBE_NOISE_SIGMA_M * 1e3:g} mm",
    )


def _ground_truth_solver(config: SimulatorConfig) -> SimulatorConfig:
    """The truth is integrated more finely than the estimator's predictor."""
    return replace(config, substeps=config.substeps * 2, solver_iterations=config.solver_iterations * 2)


# --------------------------------------------------------------------------- airway (CAO)
AIRWAY_TOOL_RADIUS = 2.0e-3
AIRWAY_TOOL_CALIBRATION_ERROR = np.array([0.6e-3, 0.5e-3, -0.5e-3])  # reported minus true tool position (m)
# Monocular depth: sigma = 0.3 mm + 0.4 mm at 0.1 m depth^2 scale (~0.33 mm at 25 mm), thinned at
# grazing angles, 2% of the occluder hits leak through segmentation.
AIRWAY_CAPTURE = CaptureOptions(stride=2, noise_constant=0.3e-3, noise_quadratic=0.04, grazing_exponent=1.0,
                                leak_fraction=0.02)


@lru_cache(maxsize=1)
def _airway_geometry():
    return airway_phantom()


def _airway_push(seed: int, steps: int) -> Scenario:
    """Central-airway-obstruction phantom: a tool pushes the tumour towards the wall at 1 Hz.

    The truth differs from the estimator's model as a real procedure would: less compressible
    tissue, a sag under gravity the model ignores, a larger effective tool tip, and a robot
    whose reported tool pose is off by a constant calibration error (continuum robots are
    millimetre-accurate at best). Only the reported poses are recorded.
    """
    rng = np.random.default_rng(seed)
    phantom = _airway_geometry()
    mesh = phantom.tumour
    centre = phantom.tumour_centre
    # Push direction: from the lumen centre line towards the tumour's attachment.
    radial = np.array([centre[0], centre[1], 0.0])
    radial /= np.linalg.norm(radial)
    # Start with the sphere touching the tumour's free surface on the lumen side.
    free_surface = np.setdiff1d(mesh.surface_vertices, mesh.fixed_vertices)
    reach = (mesh.vertices[free_surface] - np.array([0.0, 0.0, centre[2]])) @ radial
    contact = np.array([0.0, 0.0, centre[2]]) + radial * (reach.min() - AIRWAY_TOOL_RADIUS)
    push_per_step = 0.5e-3
    true_tool_poses = [pose(contact + radial * push_per_step * k) for k in range(steps + 1)]
    tool_poses = [p + np.concatenate([AIRWAY_TOOL_CALIBRATION_ERROR, np.zeros(4)]) for p in true_tool_poses]

    nominal = SimulatorConfig(youngs_modulus=3e3, poisson_ratio=0.45, tool_radius=AIRWAY_TOOL_RADIUS,
                              tool_mode="sphere")
    truth_config = replace(nominal, youngs_modulus=6e3, poisson_ratio=0.49,
                           tool_radius=AIRWAY_TOOL_RADIUS * 1.25, gravity=(0.0, -9.81, 0.0))
    truths = _simulate_truth(mesh, _ground_truth_solver(truth_config), true_tool_poses)

    camera = _airway_camera(phantom)
    scenario_steps = []
    for k, truth in enumerate(truths, start=1):
        tool_sphere = _sphere_surface(true_tool_poses[k][:3], truth_config.tool_radius)
        result = capture(camera, truth, mesh.surface_triangles,
                         occluders=[(phantom.wall_vertices, phantom.wall_triangles, 1), (*tool_sphere, 2)],
                         rng=rng, options=AIRWAY_CAPTURE)
        scenario_steps.append(ScenarioStep(_stamp(k), tool_poses[k], result.points, result.labels, truth))
    return Scenario(
        name="cao-push", seed=seed, initial_mesh=mesh, steps=tuple(scenario_steps),
        initial_tool_pose=tool_poses[0],
        simulator_config=nominal, grasped_vertices=np.zeros(0, np.int64),
        noise_sigma_m=AIRWAY_CAPTURE.noise_constant, camera_pose=camera.pose,
        description=f"airway (r={phantom.inner_radius * 1e3:.1f} mm) tumour pushed {push_per_step * 1e3:g} mm/step "
                    f"for {steps} steps; endoscope depth points, 2% segmentation leaks",
    )


def _airway_camera(phantom) -> PinholeCamera:
    """Endoscope on the airway axis, upstream of the tumour, looking down the lumen (+z)."""
    position = phantom.axis_origin + phantom.axis_direction * (phantom.tumour_centre[2] - 0.02)
    return PinholeCamera(position=position, orientation=np.array([0.0, 0.0, 0.0, 1.0]),
                         width=160, height=120, fx=110.0, fy=110.0, cx=80.0, cy=60.0)


def _sphere_surface(centre, radius):
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions=2, radius=radius)
    return np.asarray(sphere.vertices) + np.asarray(centre), np.asarray(sphere.faces, dtype=np.int64)


# --------------------------------------------------------------------------- liver
def liver_mesh(path: str | Path | None = None) -> TetMesh:
    """The SOFA liver (legacy Gmsh v1), scaled to metres; the lowest 15% (posterior) fixed."""
    candidates = [Path(path)] if path else list(LIVER_PATH_CANDIDATES)
    for candidate in candidates:
        if candidate.is_file():
            raw = load_mesh(candidate)
            break
    else:
        raise ScenarioError(f"liver mesh not found (looked in {', '.join(str(c) for c in candidates)})")
    vertices = raw.vertices * LIVER_METRES_PER_UNIT
    y = vertices[:, 1]
    surface = raw.surface_vertices
    fixed = surface[y[surface] <= y.min() + 0.15 * np.ptp(y)]
    return TetMesh(vertices, raw.tetrahedra, fixed, name="liver")


def _liver_push(seed: int, steps: int) -> Scenario:
    """A laparoscopic tool indents the top of the liver; a camera above sees the upper surface."""
    rng = np.random.default_rng(seed)
    mesh = liver_mesh()
    tool_radius = 8e-3
    top = mesh.surface_vertices[np.argmax(mesh.vertices[mesh.surface_vertices, 1])]
    down = np.array([0.0, -1.0, 0.0])
    contact = mesh.vertices[top] - down * tool_radius
    push_per_step = 1.5e-3
    tool_poses = [pose(contact + down * push_per_step * k) for k in range(steps + 1)]
    nominal = SimulatorConfig(youngs_modulus=4e3, poisson_ratio=0.45, tool_radius=tool_radius, tool_mode="sphere")
    # The truth: less compressible, stiffer, a larger effective tool tip (no gravity: the liver
    # rests on the organs below, which the fixed posterior region stands in for).
    truth_config = replace(nominal, poisson_ratio=0.48, youngs_modulus=6e3, tool_radius=tool_radius * 1.1)
    truths = _simulate_truth(mesh, _ground_truth_solver(truth_config), tool_poses)
    centre = mesh.vertices.mean(axis=0)
    camera_position = centre + np.array([0.05, 0.25, 0.0])
    camera = PinholeCamera.look_at(camera_position, centre, up=np.array([0.0, 0.0, 1.0]),
                                   width=160, height=120, fx=140.0, fy=140.0, cx=80.0, cy=60.0)
    options = CaptureOptions(stride=2, noise_constant=0.5e-3, noise_quadratic=0.02, grazing_exponent=1.0,
                             leak_fraction=0.01)
    scenario_steps = []
    for k, truth in enumerate(truths, start=1):
        tool_sphere = _sphere_surface(tool_poses[k][:3], truth_config.tool_radius)
        result = capture(camera, truth, mesh.surface_triangles, occluders=[(*tool_sphere, 2)], rng=rng,
                         options=options)
        scenario_steps.append(ScenarioStep(_stamp(k), tool_poses[k], result.points, result.labels, truth))
    return Scenario(
        name="liver-push", seed=seed, initial_mesh=mesh, steps=tuple(scenario_steps),
        initial_tool_pose=tool_poses[0],
        simulator_config=nominal, grasped_vertices=np.zeros(0, np.int64), noise_sigma_m=options.noise_constant,
        camera_pose=camera.pose,
        description=f"SOFA liver ({mesh.vertex_count} vertices) indented {push_per_step * 1e3:g} mm/step, {steps} steps",
    )
