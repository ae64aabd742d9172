"""Sliding-window factor-graph estimator of a deforming tetrahedral mesh.

Each `update(stamp_ns, points, predicted, tool_pose, viewpoint)` appends a state X_t to the
window with the factors of the configuration (by name, FACTOR_CONFIGURATIONS): the physics prior (simulator
prediction Xhat_t, information scale * K(X_t)), the point-to-surface measurements of the
new cloud, and the temporal factor to the previous state; then Levenberg-Marquardt optimises
every state of the window jointly, and the newest state is returned with its per-vertex
posterior standard deviation.

Design decisions (see also factors.py, factor_graph.py, levenberg_marquardt.py, linear_solvers.py):
- Initial value of a new state: the prediction when given and the configuration has the
  physics prior, else the previous estimate (copy-forward). A configuration with the physics
  prior but no prediction uses the copy-forward state as the prediction and flags the step
  degraded.
- What leaves the window is *conditioned on*, not marginalised: the dropped state's estimate
  becomes a constant anchor of the temporal factor of the oldest remaining state (the
  initial mesh anchors the first state). Marginalisation would turn the dropped state's
  factors into a dense prior over a whole state (3N x 3N Schur complement, fill-in of the
  mesh's separators) at every update; conditioning keeps the window sparse and its cost
  fixed. test_estimator measures the difference to the full batch (a window as long as the
  sequence: the paper's offline graph).
- Fixed (boundary) vertices are eliminated: held at their initial positions.
- K_t(X_t) is evaluated at each state's linearisation point once per update, at the first LM
  iteration that re-linearises the state, and held for that update's remaining iterations;
  K is the information, not differentiated. Re-evaluating it at every LM iteration moves the
  objective itself between iterations (K(X) changes the cost at the same X), and on weakly
  determined (smooth, unobserved) modes the optimum moves by up to ~mm with it, and LM
  stalls at max_iterations rejecting steps (on the synthetic box). Held per update,
  the objective is fixed and LM provably decreases it, and K still follows X_t from one update
  to the next.
- Old states are re-linearised only when they moved more than RELINEARIZATION_SIGMAS nominal
  measurement sigmas (RMS over vertices) since their last linearisation
  (FactorGraph.relinearize_threshold, as iSAM2's relinearisation threshold): the quadratic
  model error that allows is second order, ~threshold^2 / edge length, far below the
  measurement noise; the newest state is re-linearised at every LM iteration. A threshold of 0
  is exact LM on the window (what the scipy / GTSAM cross-checks set on the graph).
- Weights (weights.py): with estimate_weights (default) the measurement sigma is estimated
  after every update from the residual distances (robust: 1.4826 median) and the physics
  prior is weighted as a simulation sigma of a tenth of it; the first update, which starts
  from the sensor's nominal sigma, is solved again while that estimate moves by more than 25 %.
  When the cloud's viewpoint is known, each point's sigma follows its ray's incidence on the
  predicted surface (noise.RayNoise: a depth sensor's noise lies along its rays), scaled so that
  the median point keeps the estimated sigma.
  Leaks: points on the tool sphere are dropped (the tool pose and radius are inputs), points
  far from the predicted surface are gated (TOOL_MARGIN_SIGMAS, GATE_SIGMAS, GATE_SPREAD_CAP),
  and the rest go through a Cauchy kernel of scale ROBUST_SCALE_SIGMAS sigmas. Which points
  reach the measurement factor, and their noise, is decided once per update before the factors
  are made, by the measurement front end (core/estimation/measurement_selection.py, in this
  order: far input, the tool gate, the innovation test, the gate, the back-face test, the rays'
  noise); the factors only evaluate.
- Published: the prediction plus the share alpha of the correction (optimum - prediction) that
  persists from one update to the next (core/estimation/persistence.py, keep_persistent_correction): the
  lag-one correlation of the corrections over their mean energy, 0 at the first update. The
  newest state is moved there, so the next update's window starts from what was published.
- LM starts a new state at its prediction plus the persisting share of the last update's
  correction (`_starting_state`): what persistence.py expects the next correction to repeat.
  The objective stays the prediction's (the prior's mean, the barrier's reference, the points'
  selection); LM takes fewer iterations, and where it stops within its tolerance can differ
  along directions the clouds hardly constrain (docs/design-notes.md, "Optimiser").
- The physics prior's scale makes mean(diag(scale K_rest)) = 1 / simulation_sigma^2 on the
  free dofs (factors.prior_scale); a ridge PRIOR_RIDGE / simulation_sigma^2 (1e-6 of the
  mean information) gives a free body's 6 rigid modes a tiny information. The prior
  carries a volume barrier (factors.VolumeBarrierFactor) that keeps every element above half
  its volume in the prediction, and LM cuts any step that would shrink an element below a
  quarter of its volume: no estimate contains a flat or inverted element.
- LM stops when the remaining decrease it can predict is below 0.5 cost units (the cost is
  chi^2 / 2 under the estimated weights: the remaining step is within one posterior standard
  deviation along it), never on a relative decrease: the window's cost grows with W and the
  clouds, and a relative test stopped the newest state short of small, statistically clear
  corrections (0.25, 0.7 standard deviations, against 0.5: docs/design-notes.md). Steps are
  inexact Newton steps: PCG to a relative residual of LINEAR_TOLERANCE (0.1, a usual forcing
  term of truncated Newton methods); the gain ratio judges each step on its true cost.
  Against 1e-3, an organ-scale update takes 0.6 of the time (PCG's iterations are its largest
  cost after the newest state's factorisation) with 4.4 LM iterations per update against 4.25
  and the same vertex RMSE to 0.2 %, and the accuracy suite's ratios move by at most 0.01, its
  LM iterations per update by at most 0.1.
- Published covariance (position_covariance (N, 3, 3), position_std = sqrt(trace / 3), 0 on
  fixed vertices): the covariance of the published mean, not of the optimum (core/estimation/covariance.py):
  the newest state's marginal posterior at its last linearisation (given the window's other
  states, tied to it only by the weak temporal factors), mixed with the prior's covariance by the
  share of the correction published, with the prior's real error scale learnt from each cloud's
  distances to the prediction (from the second cloud on where the noise is estimated from the
  clouds) and from the offsets two successive clouds share, published at its mean over the
  recent clouds plus one standard error of it (`_learn_prior_error_scale`).
- Dynamic settings (`reconfigure`: the sigmas, the robust kernel's scale, the gate) apply from
  the next update on: the factors it adds use them, the factors already in the window keep
  theirs (as they keep the weights estimated when they were added).
- Never NaN: a failed optimisation keeps the best finite state and says so in `message`.
"""

from __future__ import annotations

import copy
import threading
import time
from concurrent.futures import Future
from dataclasses import dataclass, field, fields, replace

import numpy as np
import scipy.sparse

import meshfg_ros.core.worker_threads as worker_threads
from meshfg_ros.core.estimation.covariance import (
    PRIOR_ERROR_MEMORY,
    PRIOR_ERROR_STANDARD_ERRORS,
    ForgettingMean,
    MarginalCovariance,
    TriangleOffsets,
    clipped_inverse,
    persistent_offset_scale,
    prior_error_scale,
    published_covariance,
    triangle_offsets,
)
from meshfg_ros.core.estimation.factor_graph import FactorGraph
from meshfg_ros.core.estimation.factors import (
    BARRIER_VOLUME_RATIO,
    PhysicsPriorFactor,
    PointToSurfaceFactor,
    TemporalFactor,
    VolumeBarrierFactor,
    prior_scale,
)
from meshfg_ros.core.physics.fem import STIFFNESS_KINDS, ElasticModel
from meshfg_ros.core.estimation.measurement_selection import (
    GATE_SIGMAS,
    MAX_BACK_FACING_SHARE,
    drop_points_on_tool,
    innovation_test,
    select_points,
    set_aside_far_input,
)
from meshfg_ros.core.inputs.input_checks import Scene, StampError, check_stamp, innovation_spread
from meshfg_ros.core.solvers.levenberg_marquardt import LevenbergMarquardtConfig, levenberg_marquardt
from meshfg_ros.core.solvers.linear_solvers import LINEAR_SOLVERS, LinearSolveError, NotPositiveDefiniteError, make_linear_solver
from meshfg_ros.core.geometry.mesh import InvalidMeshError, TetMesh, signed_volumes
from meshfg_ros.core.estimation.persistence import CorrectionPersistence
from meshfg_ros.core.estimation.noise import ROBUST_KERNELS, make_robust_kernel
from meshfg_ros.core.settings import check_settings, dynamic_fields, setting
from meshfg_ros.core.physics.tissue_and_tool import TissueAndTool
from meshfg_ros.core.estimation.weights import MIN_POINTS, PRIOR_NOISE_RATIO, MeasurementNoise, offsets_within_triangles

__all__ = [
    "FACTOR_CONFIGURATIONS",
    "STAGES",
    "LINEAR_SOLVERS",
    "ROBUST_KERNELS",
    "EstimatorConfig",
    "EstimatorConfigError",
    "EstimatorInputError",
    "EstimatorStampError",
    "EstimatorStepError",
    "PendingStep",
    "SlidingWindowEstimator",
    "StepResult",
]

FACTOR_CONFIGURATIONS = {
    "temporal": frozenset({"temporal"}),
    "measurement": frozenset({"measurement"}),
    "temporal+measurement": frozenset({"temporal", "measurement"}),
    "simulation+measurement": frozenset({"simulation", "measurement"}),
    "full": frozenset({"simulation", "measurement", "temporal"}),
    "simulation": frozenset({"simulation"}),
}
# LM stops when the cost could fall by less than this (chi^2 / 2 units, see the module doc).
ABSOLUTE_COST_TOLERANCE = 0.5
# Levenberg-Marquardt's settings; each update sets max_iterations and the time budget from the config.
LM_CONFIG = LevenbergMarquardtConfig(cost_tolerance=1e-9, absolute_cost_tolerance=ABSOLUTE_COST_TOLERANCE)
# PCG's relative residual in each LM step (inexact Newton, see the module doc).
LINEAR_TOLERANCE = 1e-1
# The physics prior's ridge, relative to its mean information: a free body's rigid modes get a tiny information.
PRIOR_RIDGE = 1e-6
# Draws for the prior's marginal covariance, made once per estimator (core/estimation/covariance.py):
# a 5 % relative spread of its variances, 65 MB of draws at organ scale (32k unknowns).
PRIOR_MARGINAL_SAMPLES = 256
# The robust kernel's scale when robust_scale is 0, in estimated sigmas: 2.3849 sigma gives the
# Cauchy kernel 95 % efficiency on Gaussian noise. (The data-driven gate and the tool gate's
# margin: measurement_selection.py.)
ROBUST_SCALE_SIGMAS = 2.3849
# Status text of an update whose cloud spreads more than MeasurementNoise.bounds times above or
# below the nominal measurement_sigma about the estimate (a value in the wrong units, say).
NOISE_OFF_NOMINAL = "measurement_sigma far from the clouds' spread: check it and its units"
# Old states are re-linearised once they moved by this many nominal measurement sigmas (RMS over
# vertices, FactorGraph.relinearize_threshold): a length, not a weight, for which measurement_sigma
# gives the scale of what matters; the quadratic model's error it allows, ~threshold^2 / edge
# length, is far below the measurement noise. The nominal sigma, not the estimate, so that the
# threshold does not move while the weights are learnt.
RELINEARIZATION_SIGMAS = 1.0
# An update whose estimated measurement sigma moved by more than REWEIGHT_CHANGE (relative) is
# solved again with it, at most MAX_REWEIGHT_ROUNDS times (the noise changed between clouds, or
# the first update started from the nominal sigma or from an estimate about its prediction that
# missed); the same rounds bound the first update's estimate before it optimises.
REWEIGHT_CHANGE = 0.25
MAX_REWEIGHT_ROUNDS = 4


class EstimatorConfigError(ValueError):
    """An estimator setting outside its valid range or an unknown name."""


class EstimatorInputError(ValueError):
    """update() input it cannot use: not an array of real numbers, a wrong shape, non-finite
    predicted positions or tool pose, or a bad stamp (EstimatorStampError)."""


class EstimatorStampError(EstimatorInputError):
    """A stamp that is not an integer number of nanoseconds in [0, 2**63), or not newer than the
    last update's (the callers' rule for repeated and backward stamps: core/inputs/input_checks.py)."""


class EstimatorStepError(RuntimeError):
    """An update that failed in the solver or its factors, or produced non-finite values; the
    message names the cause. The window is left as it was before the call."""


def _real_array(name: str, value) -> np.ndarray:
    """`value` as a float64 array, or EstimatorInputError when it is not an array of real numbers."""
    try:
        array = np.asarray(value)
    except (TypeError, ValueError, OverflowError) as error:  # ragged nesting, odd objects
        raise EstimatorInputError(f"{name} is not an array of numbers ({type(error).__name__})") from None
    if array.dtype.kind not in "iuf":
        raise EstimatorInputError(f"{name} must hold real numbers, got dtype {array.dtype}")
    return array.astype(np.float64, copy=False)


def _finite_result(result: StepResult) -> bool:
    values = (result.positions, result.position_std, result.position_covariance, result.initial_cost,
              result.final_cost)
    return all(np.isfinite(np.asarray(value, dtype=np.float64)).all() for value in values)


def _saved(obj) -> dict:
    """obj's attributes with its lists, dicts and sets copied: what an update appends to or replaces."""
    return {name: value.copy() if isinstance(value, (list, dict, set)) else value for name, value in vars(obj).items()}


def _restore(obj, saved: dict) -> None:
    vars(obj).clear()
    vars(obj).update(saved)


_LENGTH_RANGE = (1e-9, 10.0)  # metres: from a nanometre to a room-sized workspace


@dataclass(frozen=True)
class EstimatorConfig(TissueAndTool):
    """Estimator settings (SI units): the tissue model and the tool it shares with the simulator
    (TissueAndTool: the physics prior's stiffness; in sphere mode the points inside the tool
    sphere, plus a margin, are leaks, core/estimation/measurement_selection.py), and its own. See
    the module doc for the modelling choices. Every field is a parameter of the estimator node
    and the replay (core/settings.py); the dynamic ones may change while it runs
    (`SlidingWindowEstimator.reconfigure`)."""

    factors: str = setting("full", "Factor configuration of the estimator, by name.",
                           choices=tuple(FACTOR_CONFIGURATIONS))
    window_size: int = setting(5, "Number of states in the sliding window.", range=(1, 100))
    measurement_sigma: float = setting(
        1e-3, "Nominal standard deviation of a depth point along the surface normal, metres (the sensor's "
        "datasheet value; with estimate_weights the estimator starts from it and estimates the real spread "
        "from the residuals). A new value while running restarts that estimate from it.",
        range=_LENGTH_RANGE, dynamic=True)
    simulation_sigma: float = setting(
        1e-3, "Expected simulator error per vertex in metres; scales the FEM-stiffness information of the "
        "physics prior. Used with estimate_weights false; with estimate_weights the prior follows the "
        "estimated measurement sigma (a tenth of it, core/estimation/weights.py).", range=_LENGTH_RANGE, dynamic=True)
    temporal_sigma: float = setting(  # a weak random walk: up to ~1 cm per 1 Hz step (Table I: meshfg ablation)
        1e-2, "Standard deviation of a vertex's motion between two steps beyond the simulator's prediction, "
        "metres.", range=_LENGTH_RANGE, dynamic=True)
    stiffness_kind: str = setting("corotational", "FEM stiffness used as the prior's information matrix.",
                                  choices=STIFFNESS_KINDS)
    spd_projection: bool = setting(False, "Clamp negative eigenvalues of the element stiffness matrices.")
    robust_kernel: str | None = setting("cauchy", "Robust kernel on the point-to-surface residuals.",
                                        choices=ROBUST_KERNELS)  # None: as "none"
    robust_scale: float = setting(  # 0: ROBUST_SCALE_SIGMAS estimated measurement sigmas
        0.0, "Scale of the robust kernel in metres; 0: 2.4 times the (estimated) measurement sigma.",
        range=(0.0, 10.0), dynamic=True)
    gating_distance: float = setting(  # 0: GATE_SIGMAS robust innovation sigmas (see module doc)
        0.0, "Points farther than this from the predicted surface are rejected (metres); 0: five times the "
        "cloud's robust spread about the predicted surface (at least the measurement sigma).",
        range=(0.0, 10.0), dynamic=True)
    estimate_weights: bool = setting(
        True, "Estimate the measurement noise online from the residuals and weight the physics prior with a "
        "tenth of it (core/estimation/weights.py); false: use measurement_sigma and simulation_sigma as given.")
    keep_persistent_correction: bool = setting(
        True, "Publish the prediction plus only the share of the factor graph's correction that persists "
        "from one update to the next (core/estimation/persistence.py): noise fitted through the prior is left out; "
        "false: publish the optimum as it is.")
    max_iterations: int = setting(10, "Levenberg-Marquardt iterations per step (at most).", range=(1, 1000))
    linear_solver: str = setting("pcg", "Sparse solver of the normal equations.", choices=LINEAR_SOLVERS)
    # Five camera periods at 1 Hz: an update that needs longer is stopped, not left to fall behind.
    update_time_budget: float | None = setting(
        5.0, "Seconds (wall time) Levenberg-Marquardt may take per update: it then stops between iterations "
        "and returns its best state, 'time budget' in the status message.", range=(1e-3, 3600.0))

    def __post_init__(self):
        check_settings(self, EstimatorConfigError)


@dataclass
class StepResult:
    """Outcome of one update: the newest state's estimate and the optimisation's diagnostics."""

    step: int
    stamp_ns: int
    positions: np.ndarray          # (N, 3) newest state
    position_std: np.ndarray       # (N,) sqrt(trace(Sigma_ii) / 3), 0 on fixed vertices
    position_covariance: np.ndarray  # (N, 3, 3) Sigma_ii in m^2, zero on fixed vertices
    iterations: int
    initial_cost: float            # of the last LM run (after any re-weighting: costs at the final weights)
    final_cost: float              # of the last LM run
    converged: bool                # whether the last LM run passed an optimality test
    degraded: bool
    solve_time_ms: float
    num_points: int
    num_points_rejected: int
    window_size: int
    message: str = ""
    cost_history: list = field(default_factory=list)  # of the last LM run
    accepted_steps: int = 0        # over all LM runs of the update (iterations too)
    measurement_sigma: float = 0.0   # m, the measurement noise the update was weighted with (estimated)
    simulation_sigma: float = 0.0    # m, the simulation sigma the prior's weight corresponds to (estimated)
    linear_solve_ms: list = field(default_factory=list)  # wall time of each linear solve of the update's LM runs
    noise_off_nominal: bool = False  # the points' spread is beyond the noise estimate's bounds (NOISE_OFF_NOMINAL)
    stage_ms: dict = field(default_factory=dict)  # wall time of the update's stages (STAGES), ms


# The stages of an update, in order, as StepResult.stage_ms names them: checking the input,
# associating the points with the predicted surface and building the new state's factors;
# LM's linearisations, cost evaluations and step tests; its linear solves (the convergence tests'
# preconditioner applications included); the covariance (with the prior's error scale learnt for
# it, and in an estimator's first update the wait for the prior's blocks drawn at construction).
STAGES = ("association", "linearisation", "linear_solves", "covariance")


def _prior_blocks_at_rest(unit_information: scipy.sparse.csr_matrix, vertex_count: int,
                          free_vertices: np.ndarray) -> np.ndarray:
    """(N, 3, 3) the marginal covariance blocks of `unit_information` (over the free vertices'
    coordinates), zero on the fixed vertices."""
    covariance = np.zeros((vertex_count, 3, 3))
    covariance[free_vertices] = MarginalCovariance(PRIOR_MARGINAL_SAMPLES).blocks(unit_information)
    return covariance


@dataclass
class PendingStep:
    """A state added by `prepare` and not yet optimised (key = step number)."""

    key: int
    stamp_ns: int
    start: float                   # perf_counter() at prepare, for solve_time_ms
    num_points: int = 0
    num_points_rejected: int = 0   # non-finite or on the tool
    num_points_gated: int = 0      # farther from the predicted surface than the gate, or against a back face
    num_points_back_facing: int = 0
    back_facing_test_skipped: bool = False  # more than MAX_BACK_FACING_SHARE back-facing: not the sensor's viewpoint
    degraded: bool = False
    messages: list = field(default_factory=list)
    points: np.ndarray | None = None      # the cloud after the tool gate
    prediction: np.ndarray | None = None  # (N, 3) the prior's mean, fixed vertices reset
    prediction_volumes: np.ndarray | None = None  # (M,) signed element volumes of `prediction`
    viewpoint: np.ndarray | None = None   # (3,) the sensor's centre, for the back-face test
    # (vertices, Association of `points` on their surface): the innovation test's, which the
    # point selection reuses when the vertices are the prediction's.
    association: tuple | None = None
    # (measurement sigma, simulation sigma) at prepare: the prior's error scale is learnt from
    # `association` at these, with the covariance it scales (`_learn_prior_error_scale`)
    prior_error_sigmas: tuple | None = None
    prepare_ms: float = 0.0  # wall time of `prepare` (the "association" stage)
    # The share of the correction published (core/estimation/persistence.py): 1 when the optimum is published.
    published_share: float = 1.0
    # (3N, 3N) csr on the model's stiffness pattern [N/m]: an external simulator's stiffness used
    # instead of the model's K as the prior's information (core/physics/external_prior.py); None: the model's.
    prior_stiffness: object | None = None


class _PendingChanges:
    """Dynamic settings `reconfigure` changed since the last update began. A node's parameter
    callback adds to them while its solver thread may be updating, hence the lock."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._changes: dict = {}

    def add(self, changes: dict) -> None:
        with self._lock:
            self._changes.update(changes)

    def take(self) -> dict:
        with self._lock:
            changes, self._changes = self._changes, {}
        return changes


class _GivenStiffness:
    """An ElasticModel's stand-in for PhysicsPriorFactor whose K is a given matrix on the
    model's pattern (an external simulator's stiffness), whatever the state."""

    def __init__(self, model: ElasticModel, stiffness) -> None:
        self.vertex_count, self.diagonal_positions = model.vertex_count, model.diagonal_positions
        self._stiffness = scipy.sparse.csr_matrix(stiffness, dtype=np.float64)

    def stiffness(self, state=None, kind: str = "linear", spd_projection: bool = False):
        return self._stiffness.copy()


class SlidingWindowEstimator:
    """Sliding-window factor-graph estimator over states of `initial_mesh`."""

    def __init__(self, initial_mesh: TetMesh, config: EstimatorConfig | None = None):
        self.config = config or EstimatorConfig()
        self.mesh = initial_mesh
        self.initial_mesh = initial_mesh  # before any cut (remove_elements): what a restart starts from
        self.enabled = FACTOR_CONFIGURATIONS[self.config.factors]
        self.graph = FactorGraph(
            initial_mesh.vertex_count, initial_mesh.tetrahedra, initial_mesh.surface_triangles,
            initial_mesh.fixed_vertices, initial_mesh.vertices,
            RELINEARIZATION_SIGMAS * self.config.measurement_sigma,
        )
        self.model = None
        if "simulation" in self.enabled:
            cfg = self.config
            self.model = ElasticModel(initial_mesh.vertices, initial_mesh.tetrahedra, cfg.youngs_modulus, cfg.poisson_ratio)
            rest_stiffness = self.model.stiffness(None, kind=cfg.stiffness_kind, spd_projection=cfg.spd_projection)
            self.graph.locate_hessian_pattern(rest_stiffness)  # the prior's information has K's pattern
            # scale * K has mean diagonal 1 / sigma^2 with scale = unit_prior_scale / sigma^2
            self.unit_prior_scale = prior_scale(rest_stiffness, 1.0, self.graph.free_dofs)
            # kappa V_e per element: the prior's volume barrier in the prior's own units
            self.bulk_energy_scale = (self.model.lam + 2.0 * self.model.mu / 3.0) * self.model.volumes
            # The prior's covariance blocks at the rest shape for a unit simulation sigma
            # (core/estimation/covariance.py): scaled by simulation_sigma^2 at each update.
            free = self.graph.free_dofs
            unit_information = (self.unit_prior_scale * scipy.sparse.csr_matrix(rest_stiffness)[free][:, free]
                                + PRIOR_RIDGE * scipy.sparse.identity(free.size, format="csr"))
            # Drawn on the background thread (CHOLMOD without the GIL) while the rest is set up and
            # the first cloud and its prediction are awaited; an update needs it only for its
            # covariance (`unit_prior_covariance`).
            self._unit_prior_covariance: np.ndarray | Future = worker_threads.start_background(
                _prior_blocks_at_rest, unit_information, initial_mesh.vertex_count, self.graph.free_vertices)
        self.marginals = MarginalCovariance()
        # lambda^2 as published: the prediction's real error over the prior's model of it, learnt
        # from each update's innovation (core/estimation/covariance.py); 1 until the first.
        self.prior_error_scale = 1.0
        self._prior_error_memory = ForgettingMean(PRIOR_ERROR_MEMORY, initial=self.prior_error_scale)
        # The last cloud's offsets from its predicted surface, per triangle (covariance.py,
        # `persistent_offset_scale`); None before the first cloud and after a cut.
        self._last_offsets: TriangleOffsets | None = None
        self.noise = MeasurementNoise(self.config.measurement_sigma)
        self.persistence = CorrectionPersistence()
        # (N, 3) the persisting share of the last update's correction, which the next state
        # starts from on top of its prediction (`_starting_state`); None: the prediction alone.
        self.carried_correction: np.ndarray | None = None
        # The window's W block factors are made (ordering, symbolic analysis, memory first
        # touched) here, not by the first updates.
        self.solver = make_linear_solver(self.config.linear_solver, tolerance=LINEAR_TOLERANCE)
        self.solver.reserve(self.graph.block_pattern, self.config.window_size)
        self.anchor = initial_mesh.vertices.copy()
        self.step = 0
        self.last_estimate = initial_mesh.vertices.copy()
        self.scene = Scene.of(initial_mesh.vertices)  # what is far (core/inputs/input_checks.py)
        self.last_stamp_ns: int | None = None
        self.deadline: float | None = None  # perf_counter() at which the update's time budget ends
        self._pending_changes = _PendingChanges()

    @property
    def unit_prior_covariance(self) -> np.ndarray:
        """(N, 3, 3) the prior's covariance blocks at the rest shape for a unit simulation sigma,
        zero on fixed vertices, waiting for the draws started at construction. Raises what those
        draws raised (out of memory, a non-positive pivot): each update then fails with it, in
        its message."""
        if isinstance(self._unit_prior_covariance, Future):
            self._unit_prior_covariance = self._unit_prior_covariance.result()
        return self._unit_prior_covariance

    # ----------------------------------------------------------------------------- settings
    def reconfigure(self, **changes) -> None:
        """Change dynamic settings (EstimatorConfig fields marked dynamic: the sigmas, the robust
        kernel's scale, the gate); they apply from the next update on (see the module doc).

        Safe to call from another thread while an update runs. Raises EstimatorConfigError, and
        changes nothing, for a field that is unknown or not dynamic or a value the config refuses.
        """
        dynamic, known = dynamic_fields(EstimatorConfig), {item.name for item in fields(EstimatorConfig)}
        for name in changes:
            if name not in known:
                raise EstimatorConfigError(f"unknown setting {name}")
            if name not in dynamic:
                raise EstimatorConfigError(f"{name} cannot change while the estimator runs "
                                           f"(dynamic: {', '.join(sorted(dynamic))})")
        replace(self.config, **changes)  # validates the values
        self._pending_changes.add(changes)

    def restarted(self) -> SlidingWindowEstimator:
        """A new estimator from the initial mesh with this one's settings. It shares the queue of
        changes not yet applied, so a `reconfigure` that reaches this estimator while the restart
        is under way (from another thread) still applies to the new one."""
        fresh = SlidingWindowEstimator(self.initial_mesh, self.config)
        fresh._pending_changes = self._pending_changes
        return fresh

    def snapshot(self) -> SlidingWindowEstimator:
        """A copy of this estimator as it is now (its window and what it learnt), to run later
        updates again from (the scheduler's re-run of a stalled tool stream's clouds). It shares
        with this one the initial mesh, the queue of changes not yet applied and the factors the
        updates only refactor (CHOLMOD's, which cannot be copied): the linear solver's, which
        precondition PCG and are checked against each block they serve or refactored for it
        (linear_solvers.py), and the marginals', refactored for each covariance. The two never
        run updates at once: this one until the copy is `resume`d in its place, then the copy."""
        if "simulation" in self.enabled:
            self.unit_prior_covariance  # noqa: B018 - waited for here: a Future cannot be deep-copied
        shared = (self.initial_mesh, self._pending_changes, self.solver, self.marginals)
        return copy.deepcopy(self, memo={id(item): item for item in shared})

    def resume(self, replaced: SlidingWindowEstimator) -> None:
        """Go on from this snapshot in place of `replaced`, the estimator it was taken from, which
        has run updates since: the dynamic settings `replaced` took meanwhile (`reconfigure`)
        apply here too, and the graph's revision counter goes on from the larger of the two, so
        that none of this graph's linearisations passes for one of `replaced`'s in the factor
        cache of the solver they share."""
        self._apply_changes({name: getattr(replaced.config, name) for name in dynamic_fields(EstimatorConfig)
                             if getattr(replaced.config, name) != getattr(self.config, name)})
        self.graph.relinearizations = max(self.graph.relinearizations, replaced.graph.relinearizations)

    def remove_elements(self, removed_elements) -> bool:
        """Follow a cut: from the next update on, the window's states, the physics prior (the
        FEM stiffness of the remaining elements), the surface the points are projected on and
        the estimate use the mesh without the element slots `removed_elements`
        (TetMesh.without_elements: slots of the uncut mesh, cumulative; those removed already
        may be repeated). The vertices left without an element are held like fixed vertices at
        their last estimate (never estimated; zero std).

        The window restarts at the last estimate, which anchors the next state's temporal
        factor: the states and factors it held were made on the old elements and surface.
        What was learnt (measurement noise, correction persistence, the prior's error scale,
        stamps and step count) is kept. Returns whether the topology changed; raises
        EstimatorInputError, and changes nothing, for a slot out of range or a cut of every
        element."""
        try:
            mesh = self.mesh.without_elements(removed_elements)
        except InvalidMeshError as error:
            raise EstimatorInputError(f"removed_elements: {error}") from None
        if mesh is self.mesh:
            return False
        last = self.last_estimate
        held = mesh.vertices.copy()
        held[mesh.invalid_vertices] = last[mesh.invalid_vertices]
        fresh = SlidingWindowEstimator(mesh.with_vertices(held), self.config)
        kept = {name: getattr(self, name) for name in (
            "initial_mesh", "noise", "persistence", "prior_error_scale", "_prior_error_memory", "step",
            "last_stamp_ns", "scene", "_pending_changes")}
        vars(self).clear()
        vars(self).update(vars(fresh))
        vars(self).update(kept)
        self.last_estimate = last.copy()
        self.anchor = last.copy()
        return True

    def _apply_pending_changes(self) -> None:
        """Start using the settings `reconfigure` changed."""
        self._apply_changes(self._pending_changes.take())

    def _apply_changes(self, changes: dict) -> None:
        """Use the dynamic settings `changes` (field -> value): a new nominal measurement sigma
        restarts the noise estimate and the re-linearisation threshold from it (a new simulation
        sigma weights the priors of the states that follow, through `simulation_sigma`)."""
        if not changes:
            return
        old, self.config = self.config, replace(self.config, **changes)
        if self.config.measurement_sigma != old.measurement_sigma:
            self.noise = MeasurementNoise(self.config.measurement_sigma)
            self.graph.relinearize_threshold = RELINEARIZATION_SIGMAS * self.config.measurement_sigma

    # ----------------------------------------------------------------------------- input
    def _check_inputs(self, stamp_ns, points, predicted, tool_pose, viewpoint):
        """(stamp, finite points, predicted, tool pose, viewpoint, count of non-finite points
        dropped), or EstimatorInputError / EstimatorStampError; nothing is changed."""
        try:
            stamp_ns = check_stamp(stamp_ns)
        except StampError as error:
            raise EstimatorStampError(str(error)) from None
        if self.last_stamp_ns is not None and stamp_ns <= self.last_stamp_ns:
            raise EstimatorStampError(f"stamp {stamp_ns} ns is not newer than the last update's "
                                      f"{self.last_stamp_ns} ns")
        count = self.mesh.vertex_count
        if predicted is not None:
            predicted = _real_array("predicted", predicted)
            if predicted.shape != (count, 3):
                raise EstimatorInputError(f"predicted must have shape ({count}, 3), got {predicted.shape}")
            if not np.all(np.isfinite(predicted)):
                raise EstimatorInputError("predicted contains NaN or infinite positions")
        if tool_pose is not None:
            tool_pose = _real_array("tool_pose", tool_pose)
            if tool_pose.shape != (7,) or not np.all(np.isfinite(tool_pose)):
                raise EstimatorInputError(f"tool_pose must be 7 finite values [x y z qx qy qz qw], "
                                          f"got shape {tool_pose.shape}")
        if viewpoint is not None:
            viewpoint = _real_array("viewpoint", viewpoint)
            if viewpoint.shape != (3,) or not np.all(np.isfinite(viewpoint)):
                raise EstimatorInputError(f"viewpoint must be 3 finite coordinates, got shape {viewpoint.shape}")
        dropped = 0
        if points is not None:
            points = _real_array("points", points)
            if points.ndim != 2 or points.shape[1] != 3:
                raise EstimatorInputError(f"points must have shape (K, 3), got {points.shape}")
            finite = np.all(np.isfinite(points), axis=1)
            dropped = int(np.count_nonzero(~finite))
            points = points[finite]
        return stamp_ns, points, predicted, tool_pose, viewpoint, dropped

    # ----------------------------------------------------------------------------- update
    def update(self, stamp_ns: int, points=None, predicted=None, tool_pose=None, viewpoint=None,
               prior_stiffness=None) -> StepResult:
        """Add a state for `stamp_ns` with cloud `points` (K, 3) and simulator prediction
        `predicted` (N, 3) (either may be None), optimise the window, return the newest state.
        tool_pose (7,) (optional): where the tool is, to drop the cloud's points on it.
        viewpoint (3,) (optional): the sensor's centre, to drop the points against back faces
        of the predicted surface (core/estimation/measurement_selection.py).
        prior_stiffness (optional): (3N, 3N) csr on the model's stiffness pattern, positive
        definite on the free dofs, [N/m]: the prior's information instead of the model's K (an
        external simulator's, core/physics/external_prior.py), scaled like it; unused without `predicted`.

        Raises only EstimatorInputError (EstimatorStampError: stamps must be integer nanoseconds
        in [0, 2**63), each newer than the last update's) and EstimatorStepError; after either,
        the window, the step count and the last estimate are as they were before the call, so a
        bad input never poisons the next updates. Input that is well formed but implausible is
        not an error: far points are dropped, a far, inverted or contradicted prediction is set
        aside (the step runs degraded on the copy-forward), each said in the result's message.
        Settings changed by `reconfigure` apply from here on, also when the update fails."""
        self._apply_pending_changes()
        kept_objects = (self, self.graph, self.noise, self.persistence, self._prior_error_memory)
        saved = [_saved(obj) for obj in kept_objects]
        try:
            result = self.solve(self._prepare(stamp_ns, points, predicted, tool_pose, viewpoint, prior_stiffness))
            if not _finite_result(result):
                raise EstimatorStepError("the update produced non-finite values")
            return result
        except BaseException as error:
            # The solver's revision counter only grows: a block factor it made for a
            # linearisation of the failed update must never pass for a later one's.
            relinearizations = self.graph.relinearizations
            for obj, kept in zip(kept_objects, saved):
                _restore(obj, kept)
            self.graph.relinearizations = relinearizations
            if isinstance(error, (EstimatorInputError, EstimatorStepError)) or not isinstance(error, Exception):
                raise
            raise EstimatorStepError(f"update at {stamp_ns} ns failed: {type(error).__name__}: "
                                     f"{' '.join(str(error).split())[:300]}") from error

    def prepare(self, stamp_ns: int, points=None, predicted=None, tool_pose=None, viewpoint=None,
                prior_stiffness=None) -> PendingStep:
        """First half of `update`: validate the input, append the new state and its factors and
        slide the window, without optimising (benchmarks hand the same problem to other solvers).
        Input errors are raised before anything changes; `update` undoes a later failure."""
        self._apply_pending_changes()
        return self._prepare(stamp_ns, points, predicted, tool_pose, viewpoint, prior_stiffness)

    def _prepare(self, stamp_ns, points, predicted, tool_pose, viewpoint=None, prior_stiffness=None) -> PendingStep:
        """`prepare` with the settings as they are (`update` applied the pending changes before
        it saved the state a failure restores)."""
        start = time.perf_counter()
        cfg = self.config
        stamp_ns, points, predicted, tool_pose, viewpoint, dropped = self._check_inputs(
            stamp_ns, points, predicted, tool_pose, viewpoint)
        messages = [f"{dropped} non-finite point(s) dropped"] if dropped else []
        if "simulation" not in self.enabled:
            predicted = None  # a configuration without the physics prior starts from the copy-forward
        points, predicted, tool_pose, far = set_aside_far_input(self.scene, self.mesh, points, predicted, tool_pose,
                                                                messages)
        self.step += 1
        self.last_stamp_ns = stamp_ns
        self.deadline = None if cfg.update_time_budget is None else start + cfg.update_time_budget
        pending = PendingStep(self.step, stamp_ns, start, num_points_rejected=dropped + far, messages=messages,
                              viewpoint=viewpoint)
        points, on_tool = drop_points_on_tool(points, tool_pose, cfg.tool_mode, cfg.tool_radius, self.noise.sigma)
        if on_tool:
            pending.num_points_rejected += on_tool
            pending.messages.append(f"{on_tool} point(s) on the tool dropped")
        innovation = innovation_test(points, predicted, self.last_estimate, self.mesh.surface_triangles,
                                     cfg.measurement_sigma, self.scene)
        predicted = innovation.prediction
        if innovation.rejection is not None:
            pending.messages.append(innovation.rejection)
        if innovation.association is not None:
            pending.association = (predicted, innovation.association)
            # The prior's error scale is learnt from these distances against a noise estimate
            # made without them: one made from them would explain their spread away. Before any
            # cloud has estimated the noise (estimate_weights), there is none: the nominal sigma
            # is often off by tens of per cent (the suite's clouds spread 0.8-2.2x theirs), which
            # is many times the prior's share of the distances' variance; this cloud then gives
            # the offsets the next one's estimate compares with, and no estimate of its own.
            noise_known = self.noise.observed or not self.config.estimate_weights
            pending.prior_error_sigmas = (self.noise.sigma if noise_known else None, self.simulation_sigma)
            self._estimate_noise_before_first_update(points, predicted, innovation.association, viewpoint)
        prediction = predicted
        if prediction is None:
            prediction = self.last_estimate
            if "simulation" in self.enabled:
                pending.degraded = True
                pending.messages.append("no simulator prediction: copy-forward used as the prediction")
        graph = self.graph
        key = pending.key
        previous_key = graph.keys[-1] if graph.keys else None
        graph.add_state(key, prediction)
        pending.points, pending.prediction = points, graph.states[key].copy()
        if "simulation" in self.enabled:  # the volume barrier's reference, and the starting state's
            pending.prediction_volumes = signed_volumes(pending.prediction, self.model.tetrahedra)
        pending.prior_stiffness = prior_stiffness if predicted is not None else None
        for factor in self._state_factors(pending):
            graph.add_factor(factor)
        if "temporal" in self.enabled:
            if previous_key is None:
                graph.add_factor(TemporalFactor(key, cfg.temporal_sigma, anchor=self.anchor))
            else:
                graph.add_factor(TemporalFactor(key, cfg.temporal_sigma, previous_key=previous_key))
        self._slide()
        starting_state = self._starting_state(pending) if predicted is not None else None
        if starting_state is not None:
            graph.set_state(key, starting_state)
        graph.exact_keys = {key}
        for factor in graph.factors:
            if isinstance(factor, PhysicsPriorFactor):
                factor.invalidate_information()
        pending.prepare_ms = 1e3 * (time.perf_counter() - start)
        return pending

    def _estimate_noise_before_first_update(self, points, predicted, association, viewpoint) -> None:
        """With estimate_weights and no noise estimate yet (the first update, or the first after
        a new nominal sigma), move the measurement sigma to the spread of the points the
        measurement factor selects about the predicted surface, the gate following the sigma (at
        most MAX_REWEIGHT_ROUNDS times, until it moves by REWEIGHT_CHANGE or less). The first
        optimisation then weighs the cloud at its own noise, not at the nominal sigma, and
        `solve` rarely has to re-weight and solve the window again. Later updates keep the
        spread about the last optimum.

        Only where the prediction fits the cloud to within its noise: where the spread about
        the prediction exceeds, by more than REWEIGHT_CHANGE, the spread left once each
        triangle's mean offset is removed (weights.offsets_within_triangles: the prediction's
        error is smooth, the noise is not), the prediction is off by more than the noise, the
        first optimum keeps part of that misfit in its residuals, and neither spread tells the
        noise estimate it will give; the update then starts from the nominal sigma."""
        cfg = self.config
        if (not cfg.estimate_weights or "measurement" not in self.enabled or self.noise.observed
                or points is None or not len(points)):
            return
        normals = self.mesh.triangle_normals(predicted)
        for _ in range(MAX_REWEIGHT_ROUNDS):
            selected = select_points(points, self.mesh.surface_triangles, predicted, self.noise.sigma,
                                     cfg.gating_distance, viewpoint, association)
            triangle = selected.association.triangle
            signed = np.einsum("ij,ij->i", selected.points - selected.association.closest, normals[triangle])
            local = offsets_within_triangles(signed, triangle)
            if len(local) < MIN_POINTS or (innovation_spread(np.abs(signed)) >
                                           (1.0 + REWEIGHT_CHANGE) * innovation_spread(local)):
                return
            if self.noise.observe(local) <= REWEIGHT_CHANGE:
                return

    def _learn_prior_error_scale(self, predicted: np.ndarray, association, noise_sigma: float | None,
                                 simulation_sigma: float, points: np.ndarray) -> None:
        """lambda^2 from the cloud's distances to the predicted surface against the prior's
        variance along each point's normal (core/estimation/covariance.py), at the sigmas of the
        update's start, and from the offsets per triangle it shares with the last cloud's
        (`points`: the cloud `association` is of); kept when too few points tell, or when there
        is no noise estimate to hold the distances against (`noise_sigma` None: only the
        cloud's offsets are kept, for the next cloud's estimate)."""
        if "simulation" not in self.enabled:
            return
        found = association.triangle >= 0
        triangle = association.triangle[found]
        corners = self.mesh.surface_triangles[triangle]
        normals = self.mesh.triangle_normals(predicted)[triangle]
        at_points = np.einsum("pk,pkij->pij", association.barycentric[found], self.unit_prior_covariance[corners])
        variance = simulation_sigma**2 * np.einsum("pi,pij,pj->p", normals, at_points, normals)
        signed = np.einsum("ij,ij->i", points[found] - association.closest[found], normals)
        offsets = triangle_offsets(signed, triangle, variance, self.mesh.surface_triangles)
        persistent = persistent_offset_scale(self._last_offsets, offsets)
        self._last_offsets = offsets
        if noise_sigma is None:
            return
        scale = prior_error_scale(association.distance[found], variance, noise_sigma, GATE_SIGMAS, persistent)
        if scale is not None:
            memory = self._prior_error_memory
            self.prior_error_scale = memory.add(scale) + PRIOR_ERROR_STANDARD_ERRORS * memory.standard_error()

    def _state_factors(self, pending: PendingStep) -> list:
        """The physics prior and measurement factors of the pending state at the current weights: the
        measurement factor on the points the front end selects with them (select_points)."""
        cfg, graph, key = self.config, self.graph, pending.key
        factors = []
        if "simulation" in self.enabled:
            sigma = self.simulation_sigma
            scale = self.unit_prior_scale / sigma**2
            if pending.prior_stiffness is None:
                factors.append(PhysicsPriorFactor(key, pending.prediction, self.model, cfg.stiffness_kind,
                                                  cfg.spd_projection, scale, PRIOR_RIDGE / sigma**2))
            else:  # held for the whole update, as the model's K ("linear": never re-evaluated)
                given_scale = prior_scale(pending.prior_stiffness, 1.0, graph.free_dofs) / sigma**2
                factors.append(PhysicsPriorFactor(key, pending.prediction, _GivenStiffness(self.model,
                                                  pending.prior_stiffness), "linear", False, given_scale,
                                                  PRIOR_RIDGE / sigma**2))
            factors.append(VolumeBarrierFactor(key, self.model.tetrahedra,
                                               pending.prediction_volumes,
                                               scale * self.bulk_energy_scale,
                                               element_volumes=graph.element_volumes))
        pending.num_points, pending.num_points_gated = 0, 0
        points = pending.points
        if "measurement" in self.enabled and points is not None and len(points):
            sigma = self.noise.sigma
            known = pending.association
            association = known[1] if known is not None and np.array_equal(known[0], pending.prediction) else None
            selected = select_points(points, graph.surface_triangles, pending.prediction, sigma, cfg.gating_distance,
                                     pending.viewpoint, association)
            pending.num_points, pending.num_points_gated = len(selected.points), selected.num_gated
            pending.num_points_back_facing = selected.num_back_facing
            pending.back_facing_test_skipped = selected.back_facing_test_skipped
            if pending.num_points:
                robust = make_robust_kernel(cfg.robust_kernel, cfg.robust_scale or ROBUST_SCALE_SIGMAS * sigma)
                factors.append(PointToSurfaceFactor(key, selected.points, graph.surface_triangles, graph.vertex_count,
                                                    selected.noise, robust, (selected.vertices, selected.association)))
        return factors

    def solve(self, pending: PendingStep) -> StepResult:
        """Second half of `update`: optimise the window, return the newest state's estimate.

        With estimate_weights, the optimum's residual distances update the measurement sigma
        (weights.py) for the next update; when it moves by more than REWEIGHT_CHANGE, the newest
        state's factors are rebuilt with it and the window is solved again from where it is (at
        most MAX_REWEIGHT_ROUNDS times: where the noise changed between clouds, or where the
        first update's prediction was too far off for its noise estimate about the prediction,
        `_estimate_noise_before_first_update`)."""
        graph = self.graph
        messages = pending.messages
        optimise_start = time.perf_counter()
        result = self._optimise(messages)
        iterations, accepted, rounds = result["iterations"], result["accepted_steps"], 0
        solve_times = list(result["solve_times_ms"])
        decrement_ms = sum(result["decrement_times_ms"])
        while self.config.estimate_weights:
            distances = self._residual_distances(pending.key)
            if distances is None or self.noise.observe(distances) <= REWEIGHT_CHANGE or rounds == MAX_REWEIGHT_ROUNDS:
                break
            rounds += 1
            graph.replace_state_factors(pending.key, self._state_factors(pending))
            messages.append(f"re-weighted (measurement sigma {1e3 * self.noise.sigma:.3g} mm)")
            result = self._optimise(messages)
            iterations += result["iterations"]
            accepted += result["accepted_steps"]
            solve_times += result["solve_times_ms"]
            decrement_ms += sum(result["decrement_times_ms"])
        if pending.num_points_back_facing:
            messages.append(f"{pending.num_points_back_facing} point(s) against back faces dropped")
        if pending.back_facing_test_skipped:
            messages.append(f"back-face test skipped: over {MAX_BACK_FACING_SHARE:.0%} of the points lie against faces "
                            "turned away from the viewpoint, which cannot be the camera's")
        noise_off_nominal = self.config.estimate_weights and self.noise.spread_beyond_bounds
        if self.config.estimate_weights:
            messages.append(f"weights: measurement sigma {1e3 * self.noise.sigma:.3g} mm, "
                            f"simulation sigma {1e3 * self.simulation_sigma:.3g} mm")
        if noise_off_nominal:
            messages.append(f"{NOISE_OFF_NOMINAL} (the points spread {1e3 * self.noise.spread:.3g} mm about the "
                            f"estimate, measurement_sigma is {1e3 * self.noise.nominal_sigma:.3g} mm; the noise "
                            f"estimate is held within {self.noise.bounds:g}x of it)")
        if not accepted and not result["converged"]:
            # LM failed or stopped where it started: not at a share of a correction that no
            # cloud confirmed (_starting_state)
            graph.set_state(pending.key, pending.prediction)
        self._keep_persistent_correction(pending)
        positions = graph.states[pending.key].copy()
        self.last_estimate = positions
        covariance_start = time.perf_counter()
        covariance = self._position_covariance(pending, messages)
        std = np.sqrt(np.clip(np.einsum("vii->v", covariance) / 3.0, 0.0, None))
        optimisation_ms = 1e3 * (covariance_start - optimise_start)
        solving_ms = sum(solve_times) + decrement_ms
        stage_ms = {"association": pending.prepare_ms, "linearisation": optimisation_ms - solving_ms,
                    "linear_solves": float(solving_ms),
                    "covariance": 1e3 * (time.perf_counter() - covariance_start)}
        return StepResult(
            step=pending.key, stamp_ns=pending.stamp_ns, positions=positions, position_std=std,
            position_covariance=covariance,
            iterations=iterations, initial_cost=result["initial_cost"], final_cost=result["final_cost"],
            converged=result["converged"], degraded=pending.degraded,
            solve_time_ms=1e3 * (time.perf_counter() - pending.start), num_points=pending.num_points,
            num_points_rejected=pending.num_points_rejected + pending.num_points_gated, window_size=len(graph.keys),
            message="; ".join(messages), cost_history=result["cost_history"],
            accepted_steps=accepted, measurement_sigma=self.noise.sigma,
            simulation_sigma=self.simulation_sigma, linear_solve_ms=solve_times,
            noise_off_nominal=noise_off_nominal, stage_ms=stage_ms,
        )

    def _keep_persistent_correction(self, pending: PendingStep) -> None:
        """Move the newest state to its prediction plus the persisting share of its correction
        (core/estimation/persistence.py), for an update with a simulator prediction and a cloud."""
        if (not self.config.keep_persistent_correction or "simulation" not in self.enabled or pending.degraded
                or not pending.num_points):
            self.carried_correction = None
            return
        key = pending.key
        correction = self.graph.states[key] - pending.prediction
        share = self.persistence.observe(correction)
        pending.published_share = share
        self.carried_correction = share * correction
        self.graph.set_state(key, pending.prediction + self.carried_correction)
        pending.messages.append(f"correction kept {share:.2f} (the share persisting between updates)")

    def _starting_state(self, pending: PendingStep) -> np.ndarray | None:
        """Where LM starts a new state: its prediction plus the persisting share of the last
        correction, the part of it the next correction is expected to repeat (persistence.py:
        alpha c_t estimates what the simulation keeps getting wrong). The objective is the
        prediction's; the point where LM stops within its tolerance can differ (along directions
        the clouds hardly constrain, docs/design-notes.md), and it takes fewer iterations. None
        (start at the prediction) without such a share, or where the sum would shrink an
        element to BARRIER_VOLUME_RATIO of its predicted volume, where the volume barrier starts.
        An update whose LM accepted no step and did not converge is put back at its prediction
        (`solve`): no cloud confirmed the share it started from."""
        carried = self.carried_correction
        if carried is None or not carried.any():
            return None
        start = pending.prediction + carried
        if np.any(signed_volumes(start, self.model.tetrahedra) / pending.prediction_volumes <= BARRIER_VOLUME_RATIO):
            return None
        return start

    @property
    def simulation_sigma(self) -> float:
        """The simulation sigma [m] the physics prior is weighted with: PRIOR_NOISE_RATIO times the
        estimated measurement sigma with estimate_weights, else the configured one."""
        if self.config.estimate_weights:
            return PRIOR_NOISE_RATIO * self.noise.sigma
        return self.config.simulation_sigma

    def _residual_distances(self, key) -> np.ndarray | None:
        """Distances of the state's measured points to its surface (None without points)."""
        measurement = next((f for f in self.graph.state_factors(key) if isinstance(f, PointToSurfaceFactor)), None)
        if measurement is None:
            return None
        return measurement.associate(self.graph.states).distance

    def _slide(self) -> None:
        """Drop the oldest state beyond window_size; its estimate anchors the next one's temporal factor."""
        graph = self.graph
        while len(graph.keys) > self.config.window_size:
            dropped = graph.remove_state(graph.keys[0])
            self.anchor = dropped
            if "temporal" in self.enabled:
                graph.add_factor(TemporalFactor(graph.keys[0], self.config.temporal_sigma, anchor=dropped))

    def _optimise(self, messages) -> dict:
        graph = self.graph
        x0 = graph.get_x()
        remaining = None if self.deadline is None else max(self.deadline - time.perf_counter(), 1e-9)
        config = replace(LM_CONFIG, max_iterations=self.config.max_iterations, time_budget_s=remaining)
        try:
            lm = levenberg_marquardt(graph, x0, config, self.solver)
        except (LinearSolveError, NotPositiveDefiniteError, np.linalg.LinAlgError, FloatingPointError) as error:
            messages.append(f"optimisation failed ({error}); kept the initial guess")
            cost = float(graph.cost(x0))
            return dict(iterations=0, initial_cost=cost, final_cost=cost, converged=False, cost_history=[cost],
                        accepted_steps=0, solve_times_ms=[], decrement_times_ms=[])
        if not np.all(np.isfinite(lm.x)):
            messages.append("optimisation produced non-finite values; kept the initial guess")
            lm.x = x0
        graph.set_x(lm.x)
        messages.extend(lm.messages)
        messages.append(lm.summary())
        return dict(iterations=lm.iterations, initial_cost=lm.initial_cost, final_cost=lm.final_cost,
                    converged=lm.converged, cost_history=list(lm.cost_history), accepted_steps=lm.accepted_steps,
                    solve_times_ms=list(lm.solve_times_ms), decrement_times_ms=list(lm.decrement_times_ms))

    # ------------------------------------------------------------------------- covariance
    def _position_covariance(self, pending: PendingStep, messages) -> np.ndarray:
        """(N, 3, 3) covariance blocks of the published estimate's vertices, zero on fixed ones
        (core/estimation/covariance.py): the newest state's marginal posterior at its last linearisation
        (conditioned on the window's other states, which the weak temporal factors tie to it),
        mixed with the prior's covariance by the share of the correction published and scaled
        by the prior's learnt error."""
        graph = self.graph
        key, prior = pending.key, None
        if pending.prior_error_sigmas is not None:
            self._learn_prior_error_scale(*pending.association, *pending.prior_error_sigmas, pending.points)
        try:
            factor = self.solver.state_factor(key)
            posterior = self.marginals.blocks(graph.newest_information(), seed=key, factor=factor)
            # The next state borrows this factor, or the one the solver now makes of this
            # state's block (unless its block drifts): its draws start now, behind that factor
            # when there is one, to run while the next cloud and prediction are awaited.
            self.marginals.prepare(self.solver.refactor_newest_beside() or factor, seed=key + 1)
        except NotPositiveDefiniteError:
            posterior, clamped = clipped_inverse(graph.newest_vertex_information())
            messages.append("posterior information not positive definite: vertex-conditional covariance"
                            + (", some blocks clamped" if clamped else ""))
        if "simulation" in self.enabled:
            prior = self.simulation_sigma**2 * self.unit_prior_covariance[graph.free_vertices]
        blocks = published_covariance(posterior, prior, pending.published_share, self.prior_error_scale)
        if prior is not None:
            messages.append(f"prior error scale {np.sqrt(self.prior_error_scale):.3g}")
        covariance = np.zeros((self.mesh.vertex_count, 3, 3))
        covariance[graph.free_vertices] = blocks
        return np.where(np.isfinite(covariance), covariance, 0.0)
