"""The live pipeline on a recording, as separate processes, and its latency.

`run_live_pipeline(bag, workdir)` starts simulation_node, estimator_node and a downstream
recorder (this module's `record` command) as separate processes in namespace /meshfg over
real DDS, waits until they are connected, plays the recording's inputs with bag_player, and
returns what the recorder received: every estimate, its status, and the latency from a
cloud's arrival to its estimate's arrival (both seen by the recorder, one clock).
`measure_live_latency(bag)` summarises that latency (median, p95) for `meshfg bench`.
The nodes get the parameters the offline replay would use on the recording
(meshfg_ros.replay.replay_parameters), so both estimate the same trajectory.

    python -m meshfg_ros.benchmarks.latency record OUT.npz --clouds N [--timeout S] --ros-args ...
"""

from __future__ import annotations

import argparse
import ctypes
import gc
import os
import random
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import rclpy
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rclpy.utilities import remove_ros_args
from sensor_msgs.msg import PointCloud2

from meshfg_msgs.msg import EstimatorStatus, TetraMesh
from meshfg_ros.parameters import parameters_yaml
from meshfg_ros.io.messages import stamp_ns_from_msg
from meshfg_ros.replay import load_inputs, replay_parameters
from meshfg_ros.io.tf_messages import TF_STATIC_TOPIC, TF_TOPIC
from meshfg_ros.topics import INITIAL_MESH_TOPIC, POINTS_TOPIC, TOOL_POSE_TOPIC

if TYPE_CHECKING:
    from meshfg_ros.evaluation.evaluate import EvaluationInputs

NAMESPACE = "/meshfg"
READY_FILE = "recorder.ready"
# Wall-clock timeouts of the pipeline run, far above any step's time even on a loaded 2-core
# machine: a timeout would run a step degraded, and the run would no longer match the replay.
# (tool_pose_timeout stays: a recording's last cloud may have no tool pose after it, and the
# offline replay extrapolates then at once, as the live node does after that wait.)
# Reliable points: with the sensor-data profile, a saturated machine lost clouds in the
# transport (2 to 4 of 15 clouds at 4x playback, in full-suite runs). Every cloud in order
# (newest_first off): a recording played faster than the pipeline runs must not skip clouds.
LIVE_OVERRIDES = {"prediction_timeout": 10.0, "estimate_timeout": 10.0, "transform_timeout": 10.0,
                  "points_reliable": True, "newest_first": False}
PLAYED_TOPIC_READERS = 2
_SHUTDOWN_TIMEOUT_S = 20.0
_POLL_S = 0.05


class LivePipelineError(RuntimeError):
    """A pipeline process failed or the recorder did not receive every estimate (one line)."""


@dataclass(frozen=True)
class LiveRun:
    """What the downstream recorder received, one row per estimate in arrival order."""

    stamps_ns: np.ndarray  # (S,) int64
    steps: np.ndarray  # (S,) int64
    positions: np.ndarray  # (S, N, 3) float64
    position_std: np.ndarray  # (S, N) float64
    latency_ms: np.ndarray  # (S,) cloud arrival -> estimate arrival at the recorder
    degraded: np.ndarray  # (S,) bool, from the status of the same stamp
    solve_time_ms: np.ndarray  # (S,) from the status of the same stamp
    clouds_after_start: int  # clouds that arrived after the first estimate (the nodes' start-up is over)
    after_start: np.ndarray  # (S,) bool: the estimate's cloud is one of those
    expected_steps: int  # clouds in the recording
    exit_codes: dict[str, int]
    logs: dict[str, str]  # stderr of each process
    parameters: dict[str, Any]

    @property
    def final_estimate(self) -> np.ndarray:
        """(N, 3) positions of the last estimate received."""
        return self.positions[-1]


def ros_environment(base: Mapping[str, str] | None = None) -> dict[str, str]:
    """Environment for DDS on loopback only; a random domain unless ROS_DOMAIN_ID is set."""
    env = dict(os.environ if base is None else base)
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    env.setdefault("ROS_DOMAIN_ID", str(random.randint(1, 100)))
    env.setdefault("PYTHONUNBUFFERED", "1")
    return env


def executable(name: str) -> str:
    """Path of a console script of this environment (next to the running Python)."""
    path = Path(sys.executable).parent / name
    if not path.exists():
        raise LivePipelineError(f"console script {name} not found next to {sys.executable}")
    return str(path)


def run_live_pipeline(
    bag: str | Path,
    workdir: str | Path,
    rate: float = 1.0,
    overrides: Mapping[str, Any] | None = None,
    timeout_s: float = 180.0,
    env: Mapping[str, str] | None = None,
    use_sim_time: bool = True,
    single_process: bool = False,
) -> LiveRun:
    """Run simulation_node, estimator_node, the recorder and bag_player on `bag` (see module doc).

    overrides: parameters over the replay's (LIVE_OVERRIDES first); use_sim_time: the nodes run
    on the player's /clock; single_process: meshfg_stack instead of the two node processes.
    Raises LivePipelineError if a process fails or an estimate is missing after timeout_s.
    """
    bag, workdir = Path(bag).resolve(), Path(workdir).resolve()
    workdir.mkdir(parents=True, exist_ok=True)
    inputs = load_inputs(bag)
    params = replay_parameters(inputs, {**LIVE_OVERRIDES, **(overrides or {})})
    params_file = workdir / "parameters.yaml"
    params_file.write_text(parameters_yaml(params))
    expected = len(inputs.clouds)
    env = ros_environment(env)
    ros_args = ["--ros-args", "-r", f"__ns:={NAMESPACE}"]
    out = workdir / "estimates.npz"
    node_args = [*ros_args, "--params-file", str(params_file), "-p", f"use_sim_time:={str(use_sim_time).lower()}"]
    nodes = ["meshfg_stack"] if single_process else ["simulation_node", "estimator_node"]
    commands = {
        **{name: [executable(name), *node_args] for name in nodes},
        "recorder": [sys.executable, "-m", "meshfg_ros.benchmarks.latency", "record", str(out), "--clouds", str(expected),
                     "--timeout", str(timeout_s), *ros_args],
    }
    processes: dict[str, subprocess.Popen] = {}
    logs = {name: workdir / f"{name}.log" for name in [*commands, "bag_player"]}
    _return_freed_memory()
    try:
        for name, command in commands.items():
            processes[name] = _start(command, logs[name], workdir, env)
        _wait_until_ready(workdir / READY_FILE, processes, timeout_s)
        statics = {static for _, static, _ in inputs.transforms}  # the recording's transform topics
        played = [TOOL_POSE_TOPIC, POINTS_TOPIC]
        if True in statics:
            played.append(TF_STATIC_TOPIC)
        if False in statics:
            played.append(TF_TOPIC)
        if not params["mesh_file"]:
            played.insert(0, INITIAL_MESH_TOPIC)
        # Each played topic has two readers (both nodes; points: the estimator and the recorder):
        # the player waits for both, or a node that joins late misses the first messages.
        player_command = [executable("bag_player"), str(bag), "--rate", str(rate), "--topics", *played,
                          "--ros-args", "-p", f"subscribers:={PLAYED_TOPIC_READERS}"]
        processes["bag_player"] = _start(player_command, logs["bag_player"], workdir, env)
        exit_codes = _wait_for_recorder(processes, timeout_s)
        for name in nodes:
            processes[name].send_signal(signal.SIGINT)
            exit_codes[name] = processes[name].wait(timeout=_SHUTDOWN_TIMEOUT_S)
    except subprocess.TimeoutExpired as error:
        raise LivePipelineError(f"{error.cmd[0]} did not stop; logs in {workdir}") from None
    finally:
        for process in processes.values():
            if process.poll() is None:
                process.kill()
                process.wait()
    texts = {name: path.read_text() for name, path in logs.items() if path.exists()}
    if any(exit_codes.values()) or not out.exists():
        failed = ", ".join(f"{name} exited {code}" for name, code in exit_codes.items() if code)
        raise LivePipelineError(f"live pipeline failed ({failed or 'no estimates written'}); logs in {workdir}")
    received = np.load(out)
    return LiveRun(
        stamps_ns=received["stamps_ns"], steps=received["steps"], positions=received["positions"],
        position_std=received["position_std"], latency_ms=received["latency_ms"], degraded=received["degraded"],
        solve_time_ms=received["solve_time_ms"], clouds_after_start=int(received["clouds_after_start"]),
        after_start=received["after_start"],
        expected_steps=expected, exit_codes=exit_codes, logs=texts,
        parameters=params,
    )


@dataclass(frozen=True)
class ReplayErrors:
    """What a live run on a recording with ground truth is judged against: the recording's truth
    and clouds with its offline replay's estimates (`evaluation.evaluate.EvaluationInputs`),
    which the live nodes should match (the replay is what they compute without timing). The live
    estimates are evaluated as `meshfg eval` evaluates a replay, over the clouds the live run
    estimated, and so is the replay over the same clouds."""

    inputs: EvaluationInputs

    @classmethod
    def of(cls, bag: str | Path) -> ReplayErrors:
        """Replay `bag` offline (meshfg_ros.replay, as `meshfg replay` writes it) and read it
        beside the recording's truth."""
        from meshfg_ros.evaluation.evaluate import load_inputs as load_evaluation_inputs
        from meshfg_ros.replay import write_replay

        with tempfile.TemporaryDirectory(prefix="meshfg-reference-") as workdir:
            replay = Path(workdir) / "replay"
            write_replay(bag, replay)
            return cls(load_evaluation_inputs(replay, bag))

    def judge(self, run: LiveRun) -> dict:
        """Over the stamps the live run estimated and the replay too: the mean vertex RMSE (m,
        free vertices) live, of the replay and of the simulation alone, and the live run's over
        the replay's; and `calibration`, the live and the replay's position_std's mean NEES and
        95 % coverage per CALIBRATION_REPORTED_SETS, pooled over those stamps from the
        CALIBRATION_POOLED_FROM_STEP-th on (each None where undefined)."""
        from meshfg_ros.evaluation.evaluate import evaluate

        known = set(self.inputs.stamps)
        estimated = [(stamp, positions, std) for stamp, positions, std in
                     zip(run.stamps_ns.tolist(), run.positions, run.position_std) if stamp in known]
        if not estimated:
            return {}
        stamps = tuple(stamp for stamp, _, _ in estimated)
        replay = evaluate(replace(self.inputs, stamps=stamps))
        # The live estimates in the replay's place (on its topology after a cut: the live nodes
        # follow the same cuts); no predictions, so no correction figures.
        live = evaluate(replace(
            self.inputs, stamps=stamps, estimates={"factor_graph": {stamp: positions for stamp, positions, _ in estimated}},
            position_std={stamp: std for stamp, _, std in estimated}, predictions={},
            estimate_meshes={"factor_graph": self.inputs.estimate_meshes.get("factor_graph", {})}))
        rmse = {name: evaluation["vertex_rmse"][method]["all"]["mean"] for name, evaluation, method in (
            ("live", live, "factor_graph"), ("replay", replay, "factor_graph"), ("simulation", replay, "simulation"))}
        return {"vertex_rmse_live_m": rmse["live"], "vertex_rmse_replay_m": rmse["replay"],
                "vertex_rmse_simulation_m": rmse["simulation"], "live_over_replay": rmse["live"] / rmse["replay"],
                "calibration": {name: _pooled_calibration(evaluation) for name, evaluation in (("live", live),
                                                                                              ("replay", replay))}}


# The vertex sets whose pooled calibration ReplayErrors.judge reports, as `meshfg accuracy` does.
CALIBRATION_REPORTED_SETS = ("all", "unobserved_external")


def _pooled_calibration(evaluation: dict) -> dict:
    """{set: {"mean_nees", "coverage_95"}} pooled over the steps (None where the evaluation has no
    calibration or the set no vertex)."""
    sets = evaluation.get("calibration", {}).get("sets", {})
    pooled = {name: (sets.get(name) or {}).get("pooled") or {} for name in CALIBRATION_REPORTED_SETS}
    return {name: {figure: summary.get(figure) for figure in ("mean_nees", "coverage_95")}
            for name, summary in pooled.items()}


def measure_live_latency(
    bag: str | Path,
    rate: float = 1.0,
    overrides: Mapping[str, Any] | None = None,
    timeout_s: float = 180.0,
    single_process: bool = False,
    reference: ReplayErrors | None = None,
) -> dict:
    """Latency of the live pipeline on `bag` (cloud arrival -> estimate arrival downstream, ms).

    Returns steps, expected_steps, latency_ms_median / _p95 / _max, solve_time_ms_median,
    overhead_ms_median (latency minus the estimator's own solve time: prediction, transport,
    pairing, and waiting behind earlier steps when a solve outlasts the cloud period),
    degraded_steps, degraded_after_first (the estimates after the first), rate and single_process;
    and the same after the start-up (the first estimate's update factors its block, which the later
    ones borrow, and a cloud that comes while the nodes set up on the mesh waits for them):
    first_latency_ms, clouds_after_start and estimated_after_start (clouds that arrived after
    the first estimate, and how many of them were estimated), and latency_ms_max_after_start and
    degraded_after_start over those same clouds (a cloud that arrived while the first was still
    being estimated waited for the start-up too). With a `reference` (the recording's ground
    truth and its offline replay) also the accuracy and calibration of the live estimates beside
    the replay's (ReplayErrors.judge).
    """
    with tempfile.TemporaryDirectory(prefix="meshfg-live-") as workdir:
        run = run_live_pipeline(bag, workdir, rate, overrides, timeout_s, single_process=single_process)
    accuracy = reference.judge(run) if reference is not None else {}
    return {**accuracy, **live_figures(run), "rate": float(rate), "single_process": single_process}


def live_figures(run: LiveRun) -> dict[str, float]:
    """measure_live_latency's figures of `run`, its accuracy, rate and process layout aside."""
    after_start = run.after_start
    return {
        "steps": int(run.stamps_ns.size),
        "expected_steps": run.expected_steps,
        "latency_ms_median": float(np.median(run.latency_ms)),
        "latency_ms_p95": float(np.percentile(run.latency_ms, 95)),
        "latency_ms_max": float(np.max(run.latency_ms)),
        "solve_time_ms_median": float(np.median(run.solve_time_ms)),
        "overhead_ms_median": float(np.median(run.latency_ms - run.solve_time_ms)),
        "degraded_steps": int(np.count_nonzero(run.degraded)),
        "degraded_after_first": int(np.count_nonzero(run.degraded[1:])),
        "first_latency_ms": float(run.latency_ms[0]),
        "clouds_after_start": run.clouds_after_start,
        "estimated_after_start": int(np.count_nonzero(after_start)),
        "latency_ms_max_after_start": float(np.max(run.latency_ms[after_start])) if after_start.any() else float("nan"),
        "degraded_after_start": int(np.count_nonzero(run.degraded[after_start])),
    }


def _return_freed_memory() -> None:
    """Give the memory this process has freed back to the system before the nodes start
    (glibc's malloc_trim; nothing where the C library has none). A robot's computer does not
    hold a replay's freed heap beside the nodes, and on the project's VMs the nodes' set-up on
    an organ-scale mesh took longer beside one: after the bench's offline reference replay of
    organ-slab (about 1 GB kept by the process), the estimator node's set-up took 2.4-3.2 s
    against 1.7-2.3 s with that memory returned, and the first estimate came 2.2-2.5 s after its
    cloud in 3 of 4 runs against 0.8-1.0 s in 3 of 3 (docs/design-notes.md)."""
    gc.collect()
    try:
        trim = ctypes.CDLL(None).malloc_trim
    except (OSError, AttributeError):
        return
    trim(0)


def _start(command: list[str], log: Path, workdir: Path, env: Mapping[str, str]) -> subprocess.Popen:
    with open(log, "w") as stream:
        # cwd = workdir: `python -m` must not see a source checkout's meshfg_msgs/ folder.
        return subprocess.Popen(command, stdout=stream, stderr=subprocess.STDOUT, cwd=workdir, env=env)


def _wait_until_ready(ready_file: Path, processes: Mapping[str, subprocess.Popen], timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while not ready_file.exists():
        exited = {name: process.poll() for name, process in processes.items() if process.poll() is not None}
        if exited:
            raise LivePipelineError(f"pipeline process exited before the start: {exited}")
        if time.monotonic() > deadline:
            raise LivePipelineError(f"the pipeline did not connect within {timeout_s} s")
        time.sleep(_POLL_S)


def _wait_for_recorder(processes: Mapping[str, subprocess.Popen], timeout_s: float) -> dict[str, int]:
    """Exit codes of the recorder and the player once both are done; any other exit is an error."""
    deadline = time.monotonic() + timeout_s + 30.0  # the recorder times out by itself first
    while processes["recorder"].poll() is None or processes["bag_player"].poll() is None:
        failed = {name: process.poll() for name, process in processes.items() if process.poll()}
        if failed:
            return failed
        if time.monotonic() > deadline:
            raise LivePipelineError(f"the recorder did not finish within {timeout_s} s")
        time.sleep(_POLL_S)
    return {"recorder": processes["recorder"].returncode, "bag_player": processes["bag_player"].returncode}


# ---------------------------------------------------------------------------- the recorder
def record(out: Path, clouds: int, timeout_s: float, args: list[str]) -> int:
    """Recorder process: wait for the pipeline's graph, then record the estimates of `clouds`
    clouds to `out`, until the newest cloud's estimate came (a pipeline behind the clouds skips
    some: core/scheduler.py, newest first)."""
    rclpy.init(args=args)
    node = Node("live_recorder")
    cloud_arrivals: dict[int, float] = {}
    estimates: list[tuple[int, int, float, np.ndarray, np.ndarray]] = []
    statuses: dict[int, tuple[bool, float]] = {}

    def on_cloud(msg):
        cloud_arrivals.setdefault(stamp_ns_from_msg(msg.header.stamp), time.monotonic())

    def on_estimate(msg):
        estimates.append((stamp_ns_from_msg(msg.header.stamp), msg.step, time.monotonic(),
                          np.array(msg.positions, dtype=np.float64).reshape(-1, 3),
                          np.array(msg.position_std, dtype=np.float64)))

    def on_status(msg):
        statuses[stamp_ns_from_msg(msg.header.stamp)] = (msg.degraded, msg.solve_time_ms)

    # Depth > the number of steps: a slow recorder loses nothing.
    keep_all = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE,
                          durability=DurabilityPolicy.TRANSIENT_LOCAL)
    # Reliable (the player publishes reliably): a cloud lost here would leave a step without latency.
    node.create_subscription(PointCloud2, "points", on_cloud, QoSProfile(depth=1000))
    node.create_subscription(TetraMesh, "estimated_mesh", on_estimate, keep_all)
    node.create_subscription(EstimatorStatus, "status", on_status, QoSProfile(depth=1000))
    try:
        deadline = time.monotonic() + timeout_s
        while not _connected(node):
            if time.monotonic() > deadline:
                print(f"live_recorder: the pipeline did not connect within {timeout_s} s", file=sys.stderr)
                return 4
            rclpy.spin_once(node, timeout_sec=_POLL_S)
        (out.parent / READY_FILE).touch()
        def newest_estimated() -> bool:
            if len(cloud_arrivals) < clouds:
                return False
            newest = max(cloud_arrivals)
            return newest in statuses and any(estimate[0] == newest for estimate in estimates)

        while not newest_estimated() and time.monotonic() < deadline:
            rclpy.spin_once(node, timeout_sec=_POLL_S)
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    if not estimates:
        print(f"live_recorder: no estimate received within {timeout_s} s", file=sys.stderr)
        return 2
    stamps = np.array([e[0] for e in estimates], dtype=np.int64)
    latency = np.array([(e[2] - cloud_arrivals.get(e[0], np.nan)) * 1e3 for e in estimates])
    after_start = np.array([cloud_arrivals.get(e[0], -np.inf) > estimates[0][2] for e in estimates])
    np.savez(out, stamps_ns=stamps, steps=np.array([e[1] for e in estimates], dtype=np.int64),
             positions=np.stack([e[3] for e in estimates]), position_std=np.stack([e[4] for e in estimates]),
             clouds_after_start=sum(arrival > estimates[0][2] for arrival in cloud_arrivals.values()),
             after_start=after_start,
             latency_ms=latency, degraded=np.array([statuses.get(s, (True, np.nan))[0] for s in stamps]),
             solve_time_ms=np.array([statuses.get(s, (True, np.nan))[1] for s in stamps]))
    if not newest_estimated():
        print(f"live_recorder: {len(estimates)} estimates of {clouds} clouds, not the newest cloud's, within "
              f"{timeout_s} s", file=sys.stderr)
        return 3
    return 0


def _connected(node) -> bool:
    """Whether the simulator and the estimator are up and connected to each other and to us."""
    return (node.count_publishers("predicted_mesh") >= 1 and node.count_subscribers("predicted_mesh") >= 1
            and node.count_publishers("estimated_mesh") >= 1 and node.count_subscribers("estimated_mesh") >= 2
            and node.count_subscribers("tool_pose") >= 2 and node.count_subscribers("points") >= 2
            and node.count_subscribers("initial_mesh") >= 2 and node.count_publishers("status") >= 1)


def main(argv: list[str] | None = None) -> int:
    """`python -m meshfg_ros.benchmarks.latency record OUT.npz --clouds N [--timeout S] --ros-args ...`."""
    argv = sys.argv if argv is None else argv
    parser = argparse.ArgumentParser(prog="python -m meshfg_ros.benchmarks.latency")
    commands = parser.add_subparsers(dest="command", required=True)
    recorder = commands.add_parser("record", help="record the estimates of a running pipeline")
    recorder.add_argument("out", type=Path)
    recorder.add_argument("--clouds", type=int, required=True, help="clouds whose estimates to wait for")
    recorder.add_argument("--timeout", type=float, default=180.0)
    options = parser.parse_args(remove_ros_args(argv)[1:])
    return record(options.out, options.clouds, options.timeout, argv)


if __name__ == "__main__":
    sys.exit(main())
