"""Inputs held until a node has its mesh (nodes/held_inputs.py) and what the nodes say about them."""
import pytest

from meshfg_ros.nodes.diagnostics import EstimatorCounters, SimulatorCounters, waiting_for_mesh_message
from meshfg_ros.nodes.held_inputs import HeldUntilMesh


def test_held_inputs_come_back_oldest_first_and_an_overflow_drops_the_oldest():
    held = HeldUntilMesh("tool pose", capacity=3)
    assert [held.hold(k) for k in range(3)] == [None, None, None]
    assert held.hold(3) == "tool pose dropped: 3 of them wait for the initial mesh"
    assert len(held) == 3
    released = []
    assert held.release(released.append) == 3
    assert released == [1, 2, 3]
    assert len(held) == 0 and held.release(released.append) == 0


def test_a_holder_needs_room_for_one():
    with pytest.raises(ValueError, match="capacity"):
        HeldUntilMesh("cloud", 0)


def test_the_waiting_message_counts_what_is_held_and_dropped():
    assert waiting_for_mesh_message(EstimatorCounters()) == "waiting for initial_mesh"
    assert waiting_for_mesh_message(EstimatorCounters(inputs_held_before_mesh=4)) == (
        "waiting for initial_mesh; 4 inputs held until it comes")
    assert waiting_for_mesh_message(SimulatorCounters(inputs_held_before_mesh=7, inputs_dropped_before_mesh=2)) == (
        "waiting for initial_mesh; 7 inputs held until it comes, 2 dropped")
