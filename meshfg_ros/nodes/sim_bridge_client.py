"""The estimator node's client of the XPBD tissue simulator's sim_bridge service (parameter
prediction_source: sim_bridge): each accepted cloud's prediction is the simulator's state when
the cloud is accepted, handed to the estimator on the same path as the simulation node's.

The simulator runs on its own on wall time and its service returns its current state; it does
not predict at a stamp. For each cloud the client sends a `sim_bridge/srv/FactorGraphState`
request (compute_stiffness_matrix per the parameter sim_bridge_stiffness, update_last_mesh
false), and turns the answer into a core.scheduler.Prediction for the cloud's stamp: the
message's arrays (`answer_from_msg`) are checked against the estimator's mesh and moved from the
simulator's frame (its header's frame_id, `sim/world` when empty) into world_frame through /tf
(core/external_prior.bridge_state); the stiffness is made the prior's information in the solver
thread (core/scheduler.py). Elements the simulator removed (its ElementsList's invalid_indices:
a cut) go with the prediction as removed element slots, which the estimator follows from that
step on (SlidingWindowEstimator.remove_elements). The client reads the removals from each
answer's own mesh and never asks for update_last_mesh: with removals only, the current
invalid_indices say the whole topology; a refined or coarsened mesh (other slot counts) is
refused. Whatever goes wrong is a failed Prediction (the step runs degraded
on the previous estimate at once) and a Rejection with its counter, saying what to fix:
the service not there (sim_bridge_unavailable), MAX_IN_FLIGHT calls unanswered
(sim_bridge_busy), a call unanswered for the longest wait of a cloud (sim_bridge_late: the call
is dropped), wrong sizes, indices or non-finite values (sim_bridge_rejected_malformed), another
or a refined mesh (sim_bridge_rejected_mesh), a frame /tf cannot place (sim_bridge_rejected_frame).
A slow answer goes to the scheduler like any: its cloud waits prediction_timeout, or longer
after slow answers (EstimationScheduler.prediction_wait_s), and an answer after its cloud ran
is the scheduler's predictions_rejected.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import numpy as np
from rclpy.node import Node
from sim_bridge.srv import FactorGraphState

from meshfg_ros.core.physics.external_prior import BridgeAnswer, ExternalPriorError, bridge_state
from meshfg_ros.core.inputs.frames import FrameLookupError, TransformBuffer
from meshfg_ros.core.geometry.mesh import TetMesh
from meshfg_ros.core.scheduler import MAX_PREDICTION_WAIT_S, Prediction, Rejection

__all__ = ["MAX_IN_FLIGHT", "SIM_FRAME", "SimBridgeClient", "answer_from_msg"]

SIM_FRAME = "sim/world"  # the simulator's frame when its answer names none
# Calls waiting for their answer at most: beyond, a cloud is not asked for (the simulator lags).
MAX_IN_FLIGHT = 4


def answer_from_msg(msg: Any, with_stiffness: bool) -> BridgeAnswer:
    """The arrays of a sim_bridge/msg/FactorGraphState (numpy views of its sequences)."""
    mesh = msg.sim_mesh
    stiffness = None
    if with_stiffness:
        matrix = msg.sim_stiffness_mat
        stiffness = (np.asarray(matrix.row_indices, dtype=np.int64), np.asarray(matrix.col_indices, dtype=np.int64),
                     np.asarray(matrix.values, dtype=np.float32), (int(matrix.rows), int(matrix.cols)))
    return BridgeAnswer(
        positions=np.asarray(mesh.vertices.data, dtype=np.float64),
        valid_vertex_count=int(mesh.vertices.size),
        invalid_vertices=np.asarray(mesh.vertices.invalid_indices, dtype=np.int64),
        elements=np.asarray(mesh.elements.data, dtype=np.int64),
        invalid_elements=np.asarray(mesh.elements.invalid_indices, dtype=np.int64),
        stiffness=stiffness)


class SimBridgeClient:
    """Asks the sim_bridge service for each cloud's prediction (module docstring); hands each
    answer to `on_answer(prediction or None, notes)` in the executor thread (None: a call given up
    on, whose cloud the scheduler has run without a prediction)."""

    def __init__(self, node: Node, service: str, with_stiffness: bool, world_frame: str, transforms: TransformBuffer,
                 timeout_s: float, on_answer: Callable[[Prediction | None, list[Rejection]], None]) -> None:
        self._client = node.create_client(FactorGraphState, service)
        self._service, self._with_stiffness, self._world = service, with_stiffness, world_frame
        # A call is given up on when no cloud waits for it any longer (the scheduler's longest wait).
        self._timeout_s = max(timeout_s, MAX_PREDICTION_WAIT_S)
        self._transforms, self._on_answer = transforms, on_answer
        self._mesh: TetMesh | None = None
        self._in_flight: dict[int, tuple[Any, float]] = {}  # cloud stamp -> (future, sent at, monotonic s)

    def set_mesh(self, mesh: TetMesh) -> None:
        """The estimator's mesh (the simulator's vertex order) the answers are checked against."""
        self._mesh = mesh

    def request(self, stamp_ns: int) -> None:
        """Ask for the prediction of the cloud at `stamp_ns` (accepted now)."""
        self._drop_late()
        if not self._client.service_is_ready():
            return self._fail(stamp_ns, "sim_bridge_unavailable", f"no sim_bridge service {self._service}: start the "
                              "simulator's sim_bridge node, or set sim_bridge_service to its service")
        if len(self._in_flight) >= MAX_IN_FLIGHT:
            return self._fail(stamp_ns, "sim_bridge_busy", f"{MAX_IN_FLIGHT} calls to {self._service} wait for their "
                              "answer: the simulator lags the clouds; lower the cloud rate")
        request = FactorGraphState.Request(compute_stiffness_matrix=self._with_stiffness, update_last_mesh=False)
        future = self._client.call_async(request)
        self._in_flight[stamp_ns] = (future, time.monotonic())
        future.add_done_callback(lambda done: self._answered(stamp_ns, done))

    def _drop_late(self) -> None:
        """Calls unanswered for longer than the timeout: their clouds ran degraded; forgotten."""
        now = time.monotonic()
        for stamp_ns, (future, sent_s) in list(self._in_flight.items()):
            if now - sent_s > self._timeout_s:
                del self._in_flight[stamp_ns]
                self._client.remove_pending_request(future)
                self._on_answer(None, [self._late(stamp_ns, now - sent_s)])

    def _late(self, stamp_ns: int, waited_s: float) -> Rejection:
        return Rejection("sim_bridge_late", f"{self._service} has not answered for the cloud at {stamp_ns} ns in "
                         f"{waited_s:.2f} s: that step ran without it; check that the simulator runs and its load")

    def _answered(self, stamp_ns: int, future) -> None:
        if self._in_flight.pop(stamp_ns, None) is None or future.cancelled():
            return  # already given up on
        try:
            response = future.result()
            frame = response.fg_state.sim_mesh.header.frame_id or SIM_FRAME
            to_world = (np.eye(4) if frame.strip("/") == self._world.strip("/")
                        else self._transforms.lookup(self._world, frame, stamp_ns))
            positions, stiffness, removed = bridge_state(answer_from_msg(response.fg_state, self._with_stiffness),
                                                         self._mesh, to_world)
        except ExternalPriorError as error:
            return self._fail(stamp_ns, error.counter, f"sim_bridge answer for the cloud at {stamp_ns} ns: {error}")
        except FrameLookupError as error:
            return self._fail(stamp_ns, "sim_bridge_rejected_frame", (
                f"cannot place the simulator's frame in {self._world}: {error}; publish its transform on /tf_static"))
        except Exception as error:  # noqa: BLE001 - no answer, however odd, may stop the node
            return self._fail(stamp_ns, "sim_bridge_rejected_malformed", f"sim_bridge answer unusable: {error!r}")
        self._on_answer(Prediction(stamp_ns, positions, stiffness=stiffness, removed_elements=removed), [])

    def _fail(self, stamp_ns: int, counter: str, reason: str) -> None:
        self._on_answer(Prediction(stamp_ns, None, reason), [Rejection(counter, reason)])
