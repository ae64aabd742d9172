"""Inputs held until a node has its mesh (nodes/held_inputs.py) and what the nodes say about them."""
import pytest

from meshfg_ros.nodes.diagnostics import EstimatorCounters, SimulatorCounters, waiting_for_mesh_message
from meshfg_ros.nodes.held_inputs import HeldUntilMesh


def test_held_inputs_go_to_their_handlers_in_arrival_order_and_an_overflow_drops_the_oldest_of_its_kind():
    held = HeldUntilMesh({"pose": 2, "request": 5})
    handed = []

    def pose(item):
        handed.append(("pose", item))

    def request(item):
        handed.append(("request", item))

    assert held.hold("pose", pose, 1) is None
    assert held.hold("request", request, 10) is None
    assert held.hold("pose", pose, 2) is None
    assert held.hold("pose", pose, 3) == "pose dropped: 2 of them wait for the initial mesh"
    assert held.hold("request", request, 11) is None
    held.release()
    # Arrival order across kinds: an estimate must follow the request it answers.
    assert handed == [("request", 10), ("pose", 2), ("pose", 3), ("request", 11)]
    handed.clear()
    held.release()
    assert handed == []
    assert held.hold("pose", pose, 4) is None and held.hold("pose", pose, 5) is None  # counts start again


def test_every_kind_needs_room_for_one():
    with pytest.raises(ValueError, match="capacity"):
        HeldUntilMesh({"cloud": 0})


def test_the_waiting_message_counts_what_is_held_and_dropped():
    assert waiting_for_mesh_message(EstimatorCounters()) == "waiting for initial_mesh"
    assert waiting_for_mesh_message(EstimatorCounters(inputs_held_before_mesh=4)) == (
        "waiting for initial_mesh; 4 inputs held until it comes")
    assert waiting_for_mesh_message(SimulatorCounters(inputs_held_before_mesh=7, inputs_dropped_before_mesh=2)) == (
        "waiting for initial_mesh; 7 inputs held until it comes, 2 dropped")
    assert waiting_for_mesh_message(EstimatorCounters(inputs_held_before_mesh=1, initial_meshes_rejected=2),
                                    "initial_mesh in frame 'map', expected 'world': rejected") == (
        "waiting for initial_mesh; 1 inputs held until it comes; 2 initial_mesh rejected, the last: initial_mesh in "
        "frame 'map', expected 'world': rejected")
