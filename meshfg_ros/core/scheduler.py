"""The step loop of meshfg_ros, ROS-free: which cloud is estimated when, with which prediction.

Two schedulers share the work, as the two nodes do:

- `PredictionScheduler` (the simulation node's side) keeps the simulator's timeline. The first
  tool pose of a timeline resets the simulator. Every cloud the estimator accepts asks for a
  prediction at the cloud's stamp t (`request`): the simulator moves the tool from its pose at the
  previous request (or the first pose) to the tool pose at t, interpolated from the buffered tool
  poses (core/inputs/tool_poses.py), starting from the estimate of the previous request. A request waits
  for that estimate (estimate_timeout) and for a tool pose at or after t (tool_pose_timeout); then
  it is answered with a prediction, or with a failure and its reason.
- `EstimationScheduler` (the estimator node's side) queues the clouds and pairs each with the
  answer for its stamp and the tool pose at its stamp. A cloud runs once its answer has come, an
  answer for a later cloud has come, or it has waited for its prediction: prediction_timeout, or
  longer where the simulator's recent predictions took longer (`prediction_wait_s`, so that a
  large mesh's slow predictions still arrive in time); without a prediction the step runs
  degraded. Until PREDICTION_TIMES_KEPT prediction times are measured, a cloud waits up to
  MAX_PREDICTION_WAIT_S for a simulator that is there (the caller says whether one is:
  `simulator_present`), unless a cloud already ran without its prediction: the first
  prediction includes the simulator's own set-up on the mesh, one or two measured times do not
  yet say how long the next takes (at organ scale on a loaded machine the second took 1.6x the
  first), and the first estimates without their physics would start the window without it.

After a stalled tool stream the simulator also answers the stamps it could not predict
(`Prediction.catch_up`), and the estimator runs those clouds again with them before the next
step, for the simulator to learn from (`EstimationScheduler.run`).

Newest first: when the pipeline is slower than the clouds, a request still waiting for the
previous estimate is superseded by the next cloud's (`PredictionScheduler.request`): the
simulator predicts the newest cloud from the newest estimate, and the estimator drops the
superseded cloud with a reason that names what one cloud costs (`clouds_skipped_behind`).
Estimates come less often but never without their physics, and the queue stays short.

A cut (`PredictionScheduler.remove_elements`, from the simulation node's blade or a request)
changes the simulator's mesh at once; each answer carries the element slots removed so far, and
the estimator follows them before it runs the step the answer belongs to.

Both apply the stamp rule of core/inputs/input_checks.py to their streams (a stale or invalid stamp is
dropped, a jump back restarts from the initial mesh) and return a `Rejection` (a counter name and
a one-line reason) for every input they set aside, so that the nodes count and log it.

Time: the schedulers never read a clock. Each call that may wait takes `now_s` (the caller's
monotonic clock; the nodes pass time.monotonic()), or `flush=True` (the end of a recording: every
wait is over). `OfflinePipeline` connects the two synchronously for the replay, the ablation, the
accuracy suite and the benchmarks: the nodes and the replay run this same code.
"""

from __future__ import annotations

import threading
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, replace

import numpy as np

from meshfg_ros.core.estimation.estimator import (
    EstimatorConfig,
    EstimatorInputError,
    EstimatorStepError,
    SlidingWindowEstimator,
    StepResult,
)
from meshfg_ros.core.inputs.input_checks import (
    DEFAULT_CLOCK_JUMP_THRESHOLD_S,
    INVALID,
    JUMP_BACK,
    NS_PER_S,
    STALE,
    check_initial_mesh,
    stamp_order,
)
from meshfg_ros.core.physics.external_prior import ExternalPriorError, ExternalStiffness, StiffnessProjection
from meshfg_ros.core.physics.learning_simulator import LearningSimulator
from meshfg_ros.core.geometry.mesh import TetMesh
from meshfg_ros.core.inputs.patient_mesh import PatientMeshError, check_against_clouds
from meshfg_ros.core.inputs.pose_history import InvalidPoseError, PoseHistory, as_pose
from meshfg_ros.core.physics.simulator import SimulatorConfig
from meshfg_ros.core.estimation.weights import MIN_POINTS
from meshfg_ros.core.inputs.tool_poses import DEFAULT_EXTRAPOLATION_HORIZON_S as TOOL_POSE_HORIZON_S
from meshfg_ros.core.inputs.tool_poses import PoseUnavailable, ToolPoseBuffer

# Bounds on what a scheduler holds while it waits: beyond them the oldest entry goes.
MAX_QUEUED_CLOUDS = 100
MAX_STORED_ANSWERS = 100
# A cloud's wait for its prediction follows the simulator's recent predictions: the longest of
# the last PREDICTION_TIMES_KEPT, with a margin for their jitter, within MAX_PREDICTION_WAIT_S (a
# simulator that stops answering costs each cloud at most that).
PREDICTION_TIMES_KEPT = 5
PREDICTION_WAIT_MARGIN = 1.5
MAX_PREDICTION_WAIT_S = 5.0
# A stalled stream's clouds run again (EstimationScheduler.run) only as far as their updates fit
# in this share of the clouds' period, so that the next clouds are not delayed into skips.
RERUN_SHARE_OF_PERIOD = 0.5


@dataclass(frozen=True)
class Rejection:
    """An input set aside: the diagnostics counter it counts in and why (one line)."""

    counter: str
    reason: str


# What EstimationScheduler.add_cloud says of a cloud it did not queue.
_CLOUD_NOT_QUEUED = frozenset({"clouds_rejected_stamp", "clouds_rejected_registration"})


def cloud_queued(rejections: list[Rejection]) -> bool:
    """Whether add_cloud queued the cloud it returned `rejections` for: then a prediction is to be
    requested for its stamp (the estimator node and the offline pipeline follow this one rule)."""
    return not any(rejection.counter in _CLOUD_NOT_QUEUED for rejection in rejections)


@dataclass(frozen=True)
class Prediction:
    """The simulator's answer for a cloud's stamp: positions (N, 3), or None with the failure."""

    stamp_ns: int
    positions: np.ndarray | None
    failure: str = ""
    tool_pose: np.ndarray | None = None  # (7,) the tool pose the simulator moved to
    # The simulator skipped this stamp for a newer cloud's while it waited for an estimate (the
    # pipeline is behind): the estimator drops the cloud instead of running it without physics.
    superseded: bool = False
    # An external simulator's stiffness at `positions` (world frame), the prior's information
    # for the step (core/physics/external_prior.py); None: the estimator's own model.
    stiffness: ExternalStiffness | None = None
    # slots of the uncut mesh's elements the simulator has removed (TetMesh.without_elements);
    # None: the simulator says nothing of its topology (the uncut mesh)
    removed_elements: np.ndarray | None = None
    # A stamp the simulator answered with a failure for want of a tool pose (a stalled stream),
    # predicted once poses came again (PredictionScheduler._catch_up): its cloud ran degraded,
    # and the estimator runs it again with this prediction (EstimationScheduler.run).
    catch_up: bool = False


@dataclass(frozen=True)
class SchedulingTimeouts:
    """Wall-time waits [s] of the live nodes (the offline pipeline never waits: it flushes)."""

    prediction_timeout: float = 0.5   # a cloud waits this long for its prediction
    estimate_timeout: float = 2.0     # a request waits this long for the previous estimate
    tool_pose_timeout: float = 0.2    # a request waits this long for a tool pose at or after its stamp


def _jump_ns(clock_jump_threshold_s: float) -> int:
    return int(clock_jump_threshold_s * NS_PER_S)


# --------------------------------------------------------------------------- simulation side
@dataclass
class _Request:
    stamp_ns: int
    arrival_s: float
    superseded: bool = False  # a newer request came while this one waited for the previous estimate


# After a stalled tool stream the simulator passes at most this many of the stamps it answered
# without a pose, one prediction each, before it predicts the next cloud (_catch_up): enough to
# follow the tool's path over a few seconds' gap, bounded in time at organ scale.
CATCH_UP_STEPS = 5


class PredictionScheduler:
    """The simulator's timeline over tool poses and prediction requests (module docstring)."""

    def __init__(self, mesh: TetMesh, model: SimulatorConfig, grasped_vertices: np.ndarray | None = None, *,
                 clock_jump_threshold: float = DEFAULT_CLOCK_JUMP_THRESHOLD_S,
                 tool_pose_extrapolation: float = TOOL_POSE_HORIZON_S,
                 timeouts: SchedulingTimeouts = SchedulingTimeouts(), newest_first: bool = True) -> None:
        """newest_first: supersede the requests still waiting for the previous estimate when a
        newer one comes (`request`); False: answer every request in order, however late."""
        self.mesh = mesh
        self.newest_first = newest_first
        self.scene = check_initial_mesh(mesh.vertices)
        self.simulator = LearningSimulator(mesh, model, grasped_vertices)
        self.timeouts = timeouts
        self._jump_ns = _jump_ns(clock_jump_threshold)
        self._poses = ToolPoseBuffer(extrapolation_horizon_s=tool_pose_extrapolation)
        self._requests: deque[_Request] = deque()
        self.restarted = False  # whether the last tool pose restarted the timeline
        self._restart_timeline()

    def remove_elements(self, removed_elements) -> bool:
        """Cut: predict on the mesh without the element slots `removed_elements` from now on
        (LearningSimulator.remove_elements: what it learnt is kept). Returns whether the topology
        changed; InvalidMeshError or NotPositiveDefiniteError, and nothing changed, for a cut the
        simulator cannot take."""
        if not self.simulator.remove_elements(removed_elements):
            return False
        self.mesh = self.simulator.rest_mesh
        self._caught_up = {}  # predictions on the uncut mesh teach the cut one nothing
        return True

    def _restart_timeline(self) -> None:
        """Forget poses, requests and estimates: the next tool pose starts a new timeline (and
        resets the simulator, which forgets what it learnt)."""
        self._poses.clear()
        self._requests.clear()
        self._start_ns: int | None = None       # stamp of the timeline's first tool pose
        self._previous_ns: int | None = None    # stamp of the last request answered (or the start)
        self._tool_ns: int | None = None        # stamp the simulator's tool pose belongs to
        self._tool_pose: np.ndarray | None = None  # and that pose
        # The newest stamps answered without a tool pose (a stalled stream), which the tool passes
        # on its way to the next pose (_catch_up).
        self._unposed: deque[int] = deque(maxlen=CATCH_UP_STEPS)
        self._caught_up: dict[int, np.ndarray] = {}  # catch-up predictions not learnt from yet, by stamp
        self._previous_done_s = 0.0
        self._state = self.mesh.vertices.copy()
        self._state_ns: int | None = None       # stamp of the estimate self._state is
        self._skipped_ns: int | None = None     # newest stamp the estimator will not answer
        self._predicted: Prediction | None = None  # the last prediction, for its estimate's correction

    @property
    def state(self) -> np.ndarray:
        """The state (N, 3) the next prediction starts from: the newest estimate, or the initial mesh."""
        return self._state

    @property
    def state_stamp_ns(self) -> int | None:
        """Stamp of the estimate the next prediction starts from (None: the initial mesh)."""
        return self._state_ns

    @property
    def tool_pose_unavailable(self) -> dict[str, int]:
        """How often no tool pose could be given for a request, by PoseUnavailable.reason."""
        return dict(self._poses.unavailable)

    def add_tool_pose(self, stamp_ns: int, pose: np.ndarray) -> Rejection | None:
        """Take a tool pose (7,) (world frame); a Rejection when it is set aside. A stamp that
        jumps back restarts the timeline (`restarted` is then True until the next call)."""
        self.restarted = False
        try:
            pose = as_pose(pose)
        except InvalidPoseError as error:
            return Rejection("tool_poses_rejected_malformed", f"tool pose at {stamp_ns} ns: {error}")
        order = stamp_order(self._poses.newest_ns, stamp_ns, self._jump_ns)
        if order in (STALE, INVALID):
            reason = "is negative" if order == INVALID else f"is not newer than {self._poses.newest_ns} ns"
            return Rejection("tool_poses_rejected_stamp", f"tool pose stamp {stamp_ns} ns {reason}: dropped")
        if self.scene.far(pose[None, :3])[0]:
            return Rejection("tool_poses_rejected_far",
                             f"tool pose at {stamp_ns} ns is {self.scene.describe(pose[None, :3])}: dropped")
        if order == JUMP_BACK:
            self._restart_timeline()
            self.restarted = True
        self._poses.insert(stamp_ns, pose)
        if self._start_ns is None:
            self._start_ns = self._previous_ns = self._tool_ns = stamp_ns
            self._tool_pose = pose
            self.simulator.reset(pose)
        return None

    def request(self, stamp_ns: int, now_s: float = 0.0) -> None:
        """Ask for a prediction at a cloud's stamp (answered by `poll`, in stamp order). Newest
        first: the requests still waiting for the previous estimate when a newer one comes are
        superseded by it (answered at once with `superseded`, the simulator not moved), so that a
        pipeline slower than the clouds predicts the newest cloud from the newest estimate instead
        of falling further behind; one that keeps up (the offline pipeline always does) never
        supersedes."""
        if self.newest_first and self._requests and not self._previous_settled():
            for waiting in self._requests:
                waiting.superseded = True
        self._requests.append(_Request(stamp_ns, now_s))
        while len(self._requests) > MAX_QUEUED_CLOUDS:
            self._requests.popleft()

    def add_estimate(self, stamp_ns: int, positions: np.ndarray | None, degraded: bool = False,
                     position_std: np.ndarray | None = None) -> Rejection | None:
        """The estimate at a requested stamp; None: the estimator gives none for it (its update
        failed), so the next request need not wait and starts from the newest state. `degraded`:
        the update ran without this stamp's prediction (it came late, or was rejected), so the
        estimate is the next start but its difference from the prediction teaches the body load
        and the Poisson ratio nothing; a degraded estimate at a stamp answered without a tool pose
        (a stalled stream) is not even that: the physics of the tool's motion is missing from it
        (the hidden tissue stays where it was), so the simulator stays at the state it had and the
        tool passes that stamp on its way to the next one (_catch_up). `position_std` (N,): the
        estimate's posterior std, which weighs their fit (core/physics/model_fit.py); without it they learn
        nothing from this estimate."""
        if self._start_ns is None or not self._start_ns <= stamp_ns <= self._previous_ns:
            return None  # not a stamp this timeline predicted (a looped recording, or no pose yet)
        if positions is None:
            self._skipped_ns = max(stamp_ns, self._skipped_ns or 0)
            return None
        positions = np.asarray(positions, dtype=np.float64)
        if not self._usable_estimate(positions):
            return _unusable_estimate(stamp_ns, "estimate")
        if degraded and stamp_ns > self._tool_ns:  # the simulator never reached it: no pose for it
            self._skipped_ns = max(stamp_ns, self._skipped_ns or 0)  # settled, but no start state
            return None
        if self._state_ns is None or stamp_ns > self._state_ns:
            self._state, self._state_ns = positions, stamp_ns
            if not degraded and self._predicted is not None and self._predicted.stamp_ns == stamp_ns:
                self.simulator.learn(self._predicted.positions, positions, position_std)
        return None

    def poll(self, now_s: float = 0.0, flush: bool = False) -> list[Prediction]:
        """Answer the requests that are ready, oldest first (module docstring)."""
        answers = []
        while self._requests:
            request = self._requests[0]
            answered = self._answer(request, now_s, flush) if self._start_ns is not None else (
                self._answer_without_poses(request, now_s, flush))
            if answered is None:
                break
            self._requests.popleft()
            answers.extend(answered)
        return answers

    def _answer_without_poses(self, request: _Request, now_s: float, flush: bool) -> tuple[Prediction] | None:
        """A request of a timeline no tool pose has started: after tool_pose_timeout it fails with
        the reason (no tool pose received yet), so that its cloud runs at once, degraded, and the
        estimator and the user learn why."""
        if not (flush or now_s - request.arrival_s >= self.timeouts.tool_pose_timeout):
            return None
        try:
            self._poses.pose_at(request.stamp_ns)
        except PoseUnavailable as error:
            return (Prediction(request.stamp_ns, None, str(error)),)
        raise AssertionError("a tool pose buffer without a timeline holds no pose")

    def _answer(self, request: _Request, now_s: float, flush: bool) -> tuple[Prediction, ...] | None:
        """The answers a ready request gets, None while it waits: its own, after a stalled stream
        preceded by the catch-up's (_catch_up)."""
        stamp = request.stamp_ns
        if request.superseded:
            return (Prediction(stamp, None, "superseded: a newer cloud came while this one waited for the previous "
                                            "estimate (the pipeline is behind the clouds)", superseded=True),)
        if stamp <= self._previous_ns:
            if stamp == self._start_ns:
                return (Prediction(stamp, None, "the first tool pose only starts the simulation"),)
            return (Prediction(stamp, None, f"the cloud is not newer than the simulator's tool pose "
                                            f"({self._previous_ns} ns)"),)
        waited_s = now_s - max(request.arrival_s, self._previous_done_s)
        if not (self._previous_settled() or flush or waited_s >= self.timeouts.estimate_timeout):
            return None
        covered = self._poses.newest_ns is not None and self._poses.newest_ns >= stamp
        if not (covered or flush or waited_s >= self.timeouts.tool_pose_timeout):
            return None
        try:
            pose = self._poses.pose_at(stamp)
        except PoseUnavailable as error:
            self._unposed.append(stamp)
            return (self._finish(Prediction(stamp, None, str(error)), now_s),)
        try:
            caught_up = self._catch_up(stamp, pose)
            dt = (stamp - self._tool_ns) / NS_PER_S  # the tool moves from where the simulator left it
            self._tool_ns, self._tool_pose = stamp, pose
            predicted = self.simulator.predict(self._state, pose, dt)
        except (ValueError, RuntimeError) as error:
            self._restart_simulator(pose)
            return (self._finish(Prediction(stamp, None, str(error), pose), now_s),)
        if not np.isfinite(predicted).all():
            self._restart_simulator(pose)
            return (self._finish(Prediction(stamp, None, "the predicted positions are not finite", pose), now_s),)
        self._predicted = Prediction(stamp, predicted, "", pose)
        return (*caught_up, self._finish(self._predicted, now_s))

    def _catch_up(self, stamp: int, pose: np.ndarray) -> list[Prediction]:
        """After a stalled tool stream: the simulator passes the stamps it answered without a tool
        pose (the newest CATCH_UP_STEPS), one prediction each, with the tool interpolated between
        where it left it and `pose` at `stamp` (the path in between is unknown), from the state it
        had before the stall. In one jump the tool's contact would drag the tissue over the whole
        gap at once, and from a degraded estimate the hidden tissue would start where the stall
        left it (docs/design-notes.md, "A stalled tool stream"). Returns these predictions
        (`catch_up`), answered before the stamp's own, so that the estimator runs the stalled
        clouds again with them and the simulator learns from those estimates
        (learn_from_catch_up). ValueError / RuntimeError: a step the simulator cannot take, as a
        prediction's."""
        gap = [skipped for skipped in self._unposed if self._tool_ns < skipped < stamp]
        self._unposed.clear()
        if not gap:
            return []
        path = PoseHistory(duration_ns=stamp - self._tool_ns + 1, max_samples=2)
        path.insert(self._tool_ns, self._tool_pose)
        path.insert(stamp, pose)
        self._caught_up = {}
        answers = []
        for skipped, skipped_pose in zip(gap, path.interpolate(gap)):
            self._state = self.simulator.predict(self._state, skipped_pose, (skipped - self._tool_ns) / NS_PER_S)
            self._tool_ns, self._tool_pose = skipped, skipped_pose
            self._caught_up[skipped] = self._state
            answers.append(Prediction(skipped, self._state, "", skipped_pose, catch_up=True,
                                      removed_elements=self.simulator.rest_mesh.removed_elements))
        return answers

    def learn_from_catch_up(self, stamp_ns: int, positions: np.ndarray, position_std: np.ndarray | None,
                            degraded: bool = False) -> bool | Rejection:
        """The estimate of a stalled stream's cloud run again with its catch-up prediction
        (EstimationScheduler.run): the simulator learns from its correction of that prediction,
        as from any estimate's (add_estimate), what the stall's degraded estimates could not
        teach. Its state stays the newest estimate's. Returns True when it learnt; False for a
        stamp it did not catch up (or learnt from already) and for a degraded estimate (the
        estimator set the prediction aside), which teach nothing; a Rejection for an estimate
        it cannot use."""
        predicted = self._caught_up.get(stamp_ns)
        if predicted is None or degraded:
            return False
        positions = np.asarray(positions, dtype=np.float64)
        if not self._usable_estimate(positions):
            return _unusable_estimate(stamp_ns, "catch-up estimate")
        del self._caught_up[stamp_ns]
        self.simulator.learn(predicted, positions, position_std)
        return True

    def _usable_estimate(self, positions: np.ndarray) -> bool:
        """Whether an estimate's positions (float64) can be a start state or be learnt from: one
        finite position per vertex, none far outside the scene."""
        return (positions.shape == self._state.shape and bool(np.isfinite(positions).all())
                and not self.scene.far(positions).any())

    def _restart_simulator(self, pose: np.ndarray) -> None:
        """After a failed prediction: the tool restarts at `pose` and the simulator forgets what it
        learnt, which may be what failed (LearningSimulator.reset), and its catch-up."""
        self._tool_pose = pose
        self._caught_up = {}
        self.simulator.reset(pose)

    def _previous_settled(self) -> bool:
        """Whether the state to predict from is known: the previous request's estimate has come,
        the estimator said it gives none, or the previous stamp is the timeline's start."""
        previous = self._previous_ns
        return (previous == self._start_ns or (self._state_ns is not None and self._state_ns >= previous)
                or (self._skipped_ns is not None and self._skipped_ns >= previous))

    def _finish(self, answer: Prediction, now_s: float) -> Prediction:
        self._previous_ns = answer.stamp_ns
        self._previous_done_s = now_s
        return replace(answer, removed_elements=self.simulator.rest_mesh.removed_elements)


def _unusable_estimate(stamp_ns: int, what: str) -> Rejection:
    return Rejection("estimates_ignored", f"{what} at {stamp_ns} ns has a wrong vertex count, non-finite positions "
                     "or positions far outside the scene: ignored")


# --------------------------------------------------------------------------- estimator side
@dataclass(frozen=True, eq=False)
class CloudStep:
    """A cloud ready to run: its world-frame points, its prediction (or None) and tool pose."""

    stamp_ns: int
    points: np.ndarray
    arrival_s: float
    predicted: np.ndarray | None
    tool_pose: np.ndarray | None
    restart: bool = False  # the estimator restarts from the initial mesh before this step
    viewpoint: np.ndarray | None = None  # the sensor's centre (world frame), when known
    stiffness: ExternalStiffness | None = None  # the prediction's stiffness (Prediction.stiffness)
    removed_elements: np.ndarray | None = None  # the answer's (Prediction.removed_elements)
    # The simulator answered this stamp with a failure and no tool pose covers it, where tool
    # poses came before: a stalled tool stream (EstimationScheduler.run holds such a step to run
    # it again).
    stalled: bool = False


@dataclass(frozen=True)
class StepOutcome:
    """What running a CloudStep gave: a finite result, or None with the error's text."""

    step: CloudStep
    result: StepResult | None
    error: str = ""
    counter: str = ""  # "failed_steps" or "nonfinite_estimates" when result is None
    # What was set aside or changed on the way: an external stiffness refused or repaired.
    notes: tuple[Rejection, ...] = ()
    # A stalled stream's clouds run again before this step with their late predictions
    # (EstimationScheduler.run), oldest first: for the simulator to learn from, not to publish.
    reruns: tuple[StepOutcome, ...] = ()


@dataclass
class _HeldSteps:
    """Clouds that ran degraded while the tool stream stalled, and those that ran without a
    prediction right after it, kept with the estimator as it was before the first of them until
    the simulator's late predictions for them come. Of a stall longer than CATCH_UP_STEPS clouds
    the newest are kept, as the simulator catches up the newest stamps: the older ones' estimates
    drop out of the window when the snapshot is restored."""

    snapshot: SlidingWindowEstimator
    steps: deque[CloudStep] = field(default_factory=lambda: deque(maxlen=CATCH_UP_STEPS))
    predictions: dict[int, Prediction] = field(default_factory=dict)


class EstimationScheduler:
    """The estimator's queue of clouds, paired with predictions and tool poses (module docstring).

    Thread-safe use (the estimator node): the add_* methods and `next_step` under the caller's
    lock, `run` outside it (it touches the estimator, and the held clouds of a stalled stream
    under a lock of their own).
    """

    def __init__(self, mesh: TetMesh, config: EstimatorConfig, *,
                 clock_jump_threshold: float = DEFAULT_CLOCK_JUMP_THRESHOLD_S,
                 tool_pose_extrapolation: float = TOOL_POSE_HORIZON_S,
                 timeouts: SchedulingTimeouts = SchedulingTimeouts(),
                 scale_origin: np.ndarray | None = None,
                 simulator_present: Callable[[], bool] | None = None) -> None:
        """scale_origin: where mesh_scale scales a mesh read from a file (mesh_pose's position),
        for the registration check's units hint; None for a mesh given in the world frame.
        simulator_present: whether a simulator is there to answer (the estimator node: a
        publisher on predicted_mesh), asked while the clouds wait for the first answers (module
        docstring); None: never assumed."""
        self.mesh = mesh
        self.timeouts = timeouts
        self._simulator_present = simulator_present
        self._scale_origin = scale_origin
        self.estimator = SlidingWindowEstimator(mesh, config)
        self.scene = check_initial_mesh(mesh.vertices)
        self._jump_ns = _jump_ns(clock_jump_threshold)
        self._poses = ToolPoseBuffer(extrapolation_horizon_s=tool_pose_extrapolation)
        self._clouds: deque[CloudStep] = deque()  # prediction and tool pose filled in by next_step
        self._answers: dict[int, Prediction] = {}
        self._newest_cloud_ns: int | None = None
        self._newest_answer_ns: int | None = None
        self._last_step_ns: int | None = None
        self._solver_free_s = 0.0
        self._prediction_times_s: deque[float] = deque(maxlen=PREDICTION_TIMES_KEPT)
        # (stamp, when its prediction could start, how long it waited) of the last cloud run
        # without its answer, so that a late prediction's time is measured too and the next
        # clouds wait for theirs, and its warning says how long that cloud waited
        self._ran_without_answer: tuple[int, float, float] | None = None
        self._update_s = 0.0  # wall time of the last step
        # and of the recent steps that had a prediction (what a stall's clouds cost to run again)
        self._predicted_update_times_s: deque[float] = deque(maxlen=PREDICTION_TIMES_KEPT)
        self._cloud_period_s: float | None = None  # between the last two clouds' stamps
        self._registered = False  # whether a cloud has confirmed the mesh's size and place
        # (the estimator's model, the projection of external stiffness onto its K's pattern)
        self._stiffness_projection: tuple | None = None
        self._held: _HeldSteps | None = None  # a stalled stream's clouds, to run again (run)
        self._held_lock = threading.Lock()  # `run` holds and releases them, add_prediction fills them

    def reconfigure(self, changes: dict) -> None:
        """Apply changed dynamic settings (field name -> value) from the next update on, also after
        a restart (SlidingWindowEstimator.restarted); EstimatorConfigError, and nothing changed,
        for a value the estimator refuses."""
        self.estimator.reconfigure(**changes)

    @property
    def queued(self) -> int:
        """Clouds waiting to run."""
        return len(self._clouds)

    def add_cloud(self, stamp_ns: int, points: np.ndarray, now_s: float = 0.0,
                  viewpoint: np.ndarray | None = None) -> list[Rejection]:
        """Queue a cloud (K, 3) in the world frame, taken from `viewpoint` (3,: the sensor's
        centre in the world frame; None when unknown). Returns what was set aside: this cloud (a stale
        or invalid stamp), the oldest queued one (backlog), or the restart a jump back causes
        (counter clock_jumps_back). `cloud_queued` says whether this cloud was queued."""
        order = stamp_order(self._newest_cloud_ns, stamp_ns, self._jump_ns)
        if order in (STALE, INVALID):
            reason = "is negative" if order == INVALID else f"is not newer than {self._newest_cloud_ns} ns"
            return [Rejection("clouds_rejected_stamp", f"cloud stamp {stamp_ns} ns {reason}: dropped")]
        if not self._registered:
            rejection = self._registration(stamp_ns, points)
            if rejection is not None:
                return [rejection]
        notes = []
        restart = order == JUMP_BACK
        if restart:
            back_s = (self._newest_cloud_ns - stamp_ns) / NS_PER_S
            notes.append(Rejection("clock_jumps_back",
                                   f"cloud stamp jumped back by {back_s:.3f} s: restarting from the initial mesh"))
        if self._newest_cloud_ns is not None and not restart:
            self._cloud_period_s = (stamp_ns - self._newest_cloud_ns) / NS_PER_S
        self._newest_cloud_ns = stamp_ns
        self._clouds.append(CloudStep(stamp_ns, points, now_s, None, None, restart, viewpoint))
        if len(self._clouds) > MAX_QUEUED_CLOUDS:
            dropped = self._clouds.popleft()
            notes.append(Rejection("clouds_dropped_backlog", f"cloud at {dropped.stamp_ns} ns dropped: "
                                   f"{MAX_QUEUED_CLOUDS} clouds wait for the solver"))
        return notes

    def _registration(self, stamp_ns: int, points: np.ndarray) -> Rejection | None:
        """Until a cloud of MIN_POINTS points or more has agreed with the mesh in size and place
        (core/inputs/patient_mesh.py), each cloud is compared with it; one that disagrees is rejected
        with the reason (a mesh in millimetres, a missing registration)."""
        near = points[~self.scene.far(points)]  # far points are the estimator's to drop and count
        if len(near) < MIN_POINTS:
            return None
        try:
            check_against_clouds(self.mesh, [near], self._scale_origin)
        except PatientMeshError as error:
            return Rejection("clouds_rejected_registration", f"cloud at {stamp_ns} ns rejected: {error}")
        self._registered = True
        return None

    def add_tool_pose(self, stamp_ns: int, pose: np.ndarray) -> None:
        """Buffer a tool pose (world frame) for the tool gate; a jump back empties the buffer."""
        try:
            pose = as_pose(pose)
        except InvalidPoseError:
            return  # the simulation side counts it
        order = stamp_order(self._poses.newest_ns, stamp_ns, self._jump_ns)
        if order in (STALE, INVALID):
            return
        if order == JUMP_BACK:
            self._poses.clear()
        self._poses.insert(stamp_ns, pose)

    @property
    def prediction_wait_s(self) -> float:
        """How long a cloud waits for its prediction: prediction_timeout, or PREDICTION_WAIT_MARGIN
        times the longest of the recent predictions' times when longer (at most MAX_PREDICTION_WAIT_S);
        MAX_PREDICTION_WAIT_S while a simulator is there whose times are not yet known and no cloud
        ran without its prediction (module docstring)."""
        if (len(self._prediction_times_s) < PREDICTION_TIMES_KEPT and self._ran_without_answer is None
                and self._simulator_present is not None and self._simulator_present()):
            return max(self.timeouts.prediction_timeout, MAX_PREDICTION_WAIT_S)
        measured = PREDICTION_WAIT_MARGIN * max(self._prediction_times_s, default=0.0)
        return max(self.timeouts.prediction_timeout, min(measured, MAX_PREDICTION_WAIT_S))

    def _cost_per_cloud(self) -> str:
        """What one cloud costs against the clouds' period, for the reasons of a pipeline behind."""
        parts = [f"the prediction takes {1e3 * max(self._prediction_times_s):.0f} ms" if self._prediction_times_s
                 else "no prediction has come yet",
                 f"the update {1e3 * self._update_s:.0f} ms" if self._update_s else "no update has ended yet"]
        if self._cloud_period_s is not None:
            parts.append(f"clouds come every {1e3 * self._cloud_period_s:.0f} ms")
        return "per cloud " + "; ".join(parts)

    def add_prediction(self, answer: Prediction, now_s: float | None = None) -> Rejection | None:
        """Take the simulator's answer for a stamp (a prediction or a failure), arrived at `now_s`
        (the caller's monotonic clock; None offline, where nothing waits)."""
        stamp = answer.stamp_ns
        newest = self._newest_answer_ns
        if answer.superseded:
            skipped = [cloud for cloud in self._clouds if cloud.stamp_ns == stamp]
            if not skipped:
                return None
            self._clouds.remove(skipped[0])
            return Rejection("clouds_skipped_behind", f"cloud at {stamp} ns skipped: the pipeline is behind the "
                             f"clouds and the simulator predicts the newest one ({self._cost_per_cloud()}). Send "
                             "smaller clouds (a voxel filter), use a coarser mesh or a lower max_iterations")
        if answer.positions is not None and now_s is not None:
            queued = next((cloud for cloud in self._clouds if cloud.stamp_ns == stamp), None)
            if queued is not None:
                self._prediction_times_s.append(now_s - max(queued.arrival_s, self._solver_free_s))
            elif self._ran_without_answer is not None and self._ran_without_answer[0] == stamp:
                self._prediction_times_s.append(now_s - self._ran_without_answer[1])
        if self._take_catch_up(answer):
            return None
        if newest is not None and newest - stamp > self._jump_ns:
            self._answers.clear()  # the simulator restarted its timeline (a looped recording)
        elif self._last_step_ns is not None and 0 <= self._last_step_ns - stamp <= self._jump_ns:
            ran = self._ran_without_answer
            waited = f"it waited {ran[2]:.2f} s; " if ran is not None and ran[0] == stamp else ""
            return Rejection("predictions_rejected", f"prediction at {stamp} ns came after its cloud ran without it "
                             f"({waited}{self._cost_per_cloud()}): the step ran degraded")
        if answer.positions is not None and answer.positions.shape != self.mesh.vertices.shape:
            self._newest_answer_ns = stamp
            self._answers[stamp] = Prediction(stamp, None, "wrong vertex count")
            return Rejection("predictions_rejected", f"prediction at {stamp} ns has {answer.positions.shape[0]} "
                             f"vertices, the mesh {self.mesh.vertex_count}: ignored")
        self._newest_answer_ns = stamp
        self._answers[stamp] = answer
        while len(self._answers) > MAX_STORED_ANSWERS:
            del self._answers[min(self._answers)]
        return None

    def _take_catch_up(self, answer: Prediction) -> bool:
        """Whether `answer` is a late prediction for a held cloud (_HeldSteps): the simulator's
        catch-up of a stalled stamp, or the answer of a cloud that ran without it after the
        stall; kept for `run`."""
        with self._held_lock:
            held = self._held
            if (held is None or answer.positions is None or answer.positions.shape != self.mesh.vertices.shape
                    or not any(step.stamp_ns == answer.stamp_ns for step in held.steps)):
                return False
            held.predictions[answer.stamp_ns] = answer
            return True

    def next_step(self, now_s: float = 0.0, flush: bool = False) -> CloudStep | None:
        """The oldest cloud if it is ready to run (module docstring), else None."""
        if not self._clouds:
            return None
        queued = self._clouds[0]
        stamp = queued.stamp_ns
        waited = flush or now_s - max(queued.arrival_s, self._solver_free_s) >= self.prediction_wait_s
        answer = self._answers.get(stamp)
        later_answer = any(stamp < other <= self._newest_cloud_ns for other in self._answers)
        if answer is None and not (later_answer or waited):
            return None
        pose_pending = self._poses.newest_ns is not None and self._poses.newest_ns < stamp
        if pose_pending and not (waited or (answer is not None and answer.tool_pose is not None)):
            return None
        self._clouds.popleft()
        for old in [other for other in self._answers if other <= stamp]:
            del self._answers[old]
        if answer is None:
            start_s = max(queued.arrival_s, self._solver_free_s)
            self._ran_without_answer = (stamp, start_s, max(now_s - start_s, 0.0))
        self._last_step_ns = stamp
        tool_pose = answer.tool_pose if answer is not None and answer.tool_pose is not None else self._tool_pose(stamp)
        predicted = answer.positions if answer is not None else None
        removed = answer.removed_elements if answer is not None else None
        stiffness = answer.stiffness if answer is not None else None
        return replace(queued, predicted=predicted, tool_pose=tool_pose, removed_elements=removed, stiffness=stiffness,
                       stalled=(answer is not None and predicted is None and tool_pose is None
                                and self._poses.newest_ns is not None))

    def _tool_pose(self, stamp_ns: int) -> np.ndarray | None:
        try:
            return self._poses.pose_at(stamp_ns)
        except PoseUnavailable:
            return None

    def run(self, step: CloudStep, now: Callable[[], float] | None = None) -> StepOutcome:
        """Run one step on the estimator. A failed update leaves the window as it was; a
        non-finite result (never returned) restarts the estimator from the initial mesh.

        A stalled tool stream: the clouds that run degraded for want of a tool pose, and those
        that run without a prediction after them, are held (the newest CATCH_UP_STEPS) with a
        snapshot of the estimator from before the first of them. When the simulator's late
        predictions for them have come (its catch-up, PredictionScheduler._catch_up), the next
        step with a prediction first runs them again from that snapshot, in order: the window
        then holds estimates made with the tool's physics instead of the degraded ones, and the
        simulator learns the load and the Poisson ratio from them
        (PredictionScheduler.learn_from_catch_up) as if the stream had not stalled
        (`StepOutcome.reruns`; older than the estimates already out, they are not published).
        Only the newest that fit in half the clouds' period run again, none where an update
        takes more than half the period (`_affordable_reruns`). Where none of them could be
        estimated again, the estimator keeps the window it had."""
        start_s = now() if now is not None else 0.0
        if step.restart:
            self.estimator = self.estimator.restarted()
            with self._held_lock:
                self._held = None
        reruns = self._run_held(step)
        outcome = replace(self._update(step), reruns=reruns)
        self._solver_free_s = now() if now is not None else 0.0
        self._update_s = self._solver_free_s - start_s
        if now is not None and step.predicted is not None:
            self._predicted_update_times_s.append(self._update_s / (1 + len(reruns)))
        return outcome

    def _run_held(self, step: CloudStep) -> tuple[StepOutcome, ...]:
        """Hold a stalled `step` (snapshot first); after the stall, run the held clouds that have
        their predictions again from the snapshot and let go of the rest."""
        if (step.stalled or (self._held is not None and step.predicted is None)) and self._affordable_reruns():
            snapshot = self.estimator.snapshot() if self._held is None else None
            with self._held_lock:
                if snapshot is not None:
                    self._held = _HeldSteps(snapshot)
                self._held.steps.append(step)
            return ()
        with self._held_lock:
            held, self._held = self._held, None
        if held is None:
            return ()
        again = [(cloud, held.predictions[cloud.stamp_ns]) for cloud in held.steps if cloud.stamp_ns in held.predictions]
        again = again[max(len(again) - self._affordable_reruns(), 0):]
        if not again:
            return ()
        live, self.estimator = self.estimator, held.snapshot
        self.estimator.resume(live)
        outcomes = tuple(self._update(replace(cloud, predicted=answer.positions, tool_pose=answer.tool_pose,
                                              removed_elements=answer.removed_elements, stiffness=answer.stiffness,
                                              stalled=False))
                         for cloud, answer in again)
        if all(outcome.result is None for outcome in outcomes):
            self.estimator = live  # nothing ran again: the stall's degraded states are better than none
        return outcomes

    def _affordable_reruns(self) -> int:
        """How many held clouds run again before a step: as many updates as fit in
        RERUN_SHARE_OF_PERIOD of the clouds' period, at the longest of the recent updates with a
        prediction (all where nothing is timed: offline). None at organ scale, where one update
        takes more than half the period: there a re-run delayed the next clouds until they were
        skipped or ran degraded, which cost more accuracy than its learning gave
        (docs/design-notes.md, "A stalled tool stream")."""
        if not self._predicted_update_times_s or self._cloud_period_s is None:
            return CATCH_UP_STEPS
        return int(RERUN_SHARE_OF_PERIOD * self._cloud_period_s / max(self._predicted_update_times_s))

    def _update(self, step: CloudStep) -> StepOutcome:
        notes: tuple[Rejection, ...] = ()
        try:
            if step.removed_elements is not None:
                self.estimator.remove_elements(step.removed_elements)
            prior_stiffness, notes = self._prior_stiffness(step)
            result = self.estimator.update(step.stamp_ns, step.points, step.predicted, step.tool_pose, step.viewpoint,
                                           prior_stiffness)
        except (EstimatorInputError, EstimatorStepError) as error:
            outcome = StepOutcome(step, None, str(error), "failed_steps", notes)
        else:
            if _finite(result):
                outcome = StepOutcome(step, result, notes=notes)
            else:
                self.estimator = self.estimator.restarted()
                outcome = StepOutcome(step, None, "the estimate is not finite: the estimator restarts from the "
                                      "initial mesh", "nonfinite_estimates", notes)
        return outcome

    def _prior_stiffness(self, step: CloudStep) -> tuple:
        """(the prior's information made of the step's external stiffness or None, notes): a
        stiffness refused leaves the step on the estimator's own (core/physics/external_prior.py)."""
        model = self.estimator.model
        if step.stiffness is None or step.predicted is None or model is None:
            return None, ()
        if self._stiffness_projection is None or self._stiffness_projection[0] is not model:
            self._stiffness_projection = (model, StiffnessProjection(model.stiffness(None, kind="linear"),
                                                                     self.estimator.graph.free_dofs))
        try:
            information = self._stiffness_projection[1].information(step.stiffness)
        except ExternalPriorError as error:
            return None, (Rejection(error.counter, f"stiffness at {step.stamp_ns} ns: {error}"),)
        notes = (Rejection("sim_bridge_stiffness_repaired", f"stiffness at {step.stamp_ns} ns: {information.note}"),
                 ) if information.note else ()
        return information.matrix, notes


def _finite(result: StepResult) -> bool:
    values = [result.positions, result.position_std, result.initial_cost, result.final_cost, result.solve_time_ms]
    return all(np.isfinite(np.asarray(value, dtype=np.float64)).all() for value in values)


# --------------------------------------------------------------------------- offline
@dataclass(frozen=True)
class PipelineStep:
    """One estimate of the offline pipeline, with its inputs, the simulation-alone baseline,
    the body load the simulator learnt from it (None with estimate_body_load off) and the mesh
    the estimate is on (its topology after any cut)."""

    stamp_ns: int
    points: np.ndarray
    predicted: np.ndarray | None
    simulation_only: np.ndarray | None
    result: StepResult
    body_acceleration: np.ndarray | None = None
    mesh: TetMesh | None = None


class OfflinePipeline:
    """Both schedulers connected synchronously, plus the open-loop simulation ("simulation
    alone": the same simulator and tool poses, fed its own predictions instead of estimates).

    Feed tool poses and world-frame clouds in arrival order (`tool_pose`, `cloud`); each call
    returns the steps it completed; `finish` flushes the waits at the end of the input.
    """

    def __init__(self, mesh: TetMesh, model: SimulatorConfig, config: EstimatorConfig,
                 grasped_vertices: np.ndarray | None = None, *,
                 clock_jump_threshold: float = DEFAULT_CLOCK_JUMP_THRESHOLD_S,
                 tool_pose_extrapolation: float = TOOL_POSE_HORIZON_S,
                 alter_prediction: Callable[[int, np.ndarray], np.ndarray] | None = None) -> None:
        shared = dict(clock_jump_threshold=clock_jump_threshold, tool_pose_extrapolation=tool_pose_extrapolation)
        self.simulation = PredictionScheduler(mesh, model, grasped_vertices, **shared)
        # The simulation alone learns nothing: it never sees an estimate.
        self.open_loop = PredictionScheduler(
            mesh, replace(model, estimate_body_load=False, estimate_poisson_ratio=False), grasped_vertices, **shared)
        self.estimation = EstimationScheduler(mesh, config, **shared)
        self._alter_prediction = alter_prediction
        self._open_loop_states: dict[int, np.ndarray] = {}
        self._simulation_only = mesh.vertices

    def tool_pose(self, stamp_ns: int, pose: np.ndarray) -> list[PipelineStep]:
        """Take a tool pose (world frame)."""
        if self.simulation.add_tool_pose(stamp_ns, pose) is None and self.simulation.restarted:
            self._simulation_only = self.simulation.mesh.vertices
        self.open_loop.add_tool_pose(stamp_ns, pose)
        self.estimation.add_tool_pose(stamp_ns, pose)
        return self._pump(False)

    def cloud(self, stamp_ns: int, points: np.ndarray, viewpoint: np.ndarray | None = None) -> list[PipelineStep]:
        """Take a cloud (K, 3) in the world frame, taken from `viewpoint` (None: unknown)."""
        if cloud_queued(self.estimation.add_cloud(stamp_ns, points, viewpoint=viewpoint)):
            self.simulation.request(stamp_ns)
            self.open_loop.request(stamp_ns)
        return self._pump(False)

    def cut(self, removed_elements) -> list[PipelineStep]:
        """Remove element slots (a cut) from both simulators; the estimator follows with the
        next prediction (PredictionScheduler.remove_elements)."""
        self.simulation.remove_elements(removed_elements)
        self.open_loop.remove_elements(removed_elements)
        return self._pump(False)

    def finish(self) -> list[PipelineStep]:
        """Run what still waits (the input has ended)."""
        return self._pump(True)

    def _pump(self, flush: bool) -> list[PipelineStep]:
        steps = []
        while True:
            for answer in self.open_loop.poll(flush=flush):
                if answer.catch_up:  # the simulation alone keeps no estimate of a stalled stamp
                    continue
                if answer.positions is not None:  # a failed open-loop step leaves the baseline where it was
                    self._simulation_only = answer.positions
                self.open_loop.add_estimate(answer.stamp_ns, answer.positions)
                self._open_loop_states[answer.stamp_ns] = self._simulation_only
            answers = self.simulation.poll(flush=flush)
            for answer in answers:
                if answer.positions is not None and self._alter_prediction is not None:
                    answer = replace(answer, positions=self._alter_prediction(answer.stamp_ns, answer.positions))
                self.estimation.add_prediction(answer)
            step = self.estimation.next_step(flush=flush)
            if step is None and not answers:
                return steps
            while step is not None:
                outcome = self.estimation.run(step)
                for again in outcome.reruns:
                    if again.result is not None:
                        self.simulation.learn_from_catch_up(again.step.stamp_ns, again.result.positions,
                                                            _as_sent(again.result.position_std), again.result.degraded)
                result = outcome.result
                self.simulation.add_estimate(step.stamp_ns, None if result is None else result.positions,
                                             degraded=result is not None and result.degraded,
                                             position_std=None if result is None else _as_sent(result.position_std))
                if outcome.result is not None:
                    steps.append(PipelineStep(step.stamp_ns, step.points, step.predicted,
                                              self._open_loop_states.pop(step.stamp_ns, None), outcome.result,
                                              self.simulation.simulator.body_acceleration,
                                              self.estimation.estimator.mesh))
                for old in [s for s in self._open_loop_states if s < step.stamp_ns]:
                    del self._open_loop_states[old]
                step = self.estimation.next_step(flush=flush)


def _as_sent(position_std: np.ndarray) -> np.ndarray:
    """The std as the TetraMesh message carries it (float32) to the live simulation node, so
    that a replay's simulator learns exactly what the live one learns."""
    return position_std.astype(np.float32).astype(np.float64)


def run_offline(pipeline: OfflinePipeline, events: Iterator[tuple]) -> Iterator[PipelineStep]:
    """Drive `pipeline` with ("pose" | "cloud" | "cut", stamp_ns, array) events in arrival order (a
    cut's array: the element slots removed); a cloud's event may carry its viewpoint (3,) or None
    as a fourth item."""
    for kind, stamp_ns, data, *viewpoint in events:
        if kind == "pose":
            yield from pipeline.tool_pose(stamp_ns, data)
        elif kind == "cut":
            yield from pipeline.cut(data)
        else:
            yield from pipeline.cloud(stamp_ns, data, *viewpoint)
    yield from pipeline.finish()


__all__ = [
    "CloudStep",
    "EstimationScheduler",
    "OfflinePipeline",
    "PipelineStep",
    "Prediction",
    "PredictionScheduler",
    "Rejection",
    "SchedulingTimeouts",
    "StepOutcome",
    "cloud_queued",
    "run_offline",
]
