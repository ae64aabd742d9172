"""The estimator's settings while it runs: `reconfigure` changes the dynamic ones from the next
update on (as if configured so from the start), refuses the others, and the tool gate follows
tool_mode."""
from dataclasses import replace

import numpy as np
import pytest

from meshfg_ros.benchmarks.baselines import synthetic_sequence
import meshfg_ros.core.estimation.estimator as estimator_module
from meshfg_ros.core.estimation.measurement_selection import TOOL_MARGIN_SIGMAS
from meshfg_ros.core.estimation.estimator import (
    EstimatorConfig,
    EstimatorConfigError,
    EstimatorInputError,
    SlidingWindowEstimator,
)

BASE = EstimatorConfig(factors="full", window_size=2, measurement_sigma=5e-4)
# Every dynamic setting, each far from its default.
CHANGES = dict(measurement_sigma=2e-3, simulation_sigma=3e-4, temporal_sigma=4e-3, robust_scale=3e-3,
               gating_distance=0.02)


@pytest.fixture(scope="module")
def scene():
    return synthetic_sequence(target_vertices=60, points_per_step=300, steps=3, size=0.1, noise_sigma=5e-4,
                              prediction_error=3e-3, seed=2)


def updates(estimator, steps):
    return [estimator.update(step.stamp_ns, step.points, step.predicted) for step in steps]


@pytest.mark.parametrize("estimate_weights", [False, True])
def test_a_reconfigured_estimator_runs_as_one_configured_so_from_the_start(scene, estimate_weights):
    mesh, sequence = scene
    base = replace(BASE, estimate_weights=estimate_weights)
    reconfigured = SlidingWindowEstimator(mesh, base)
    reconfigured.reconfigure(**CHANGES)
    assert reconfigured.config == base  # pending until the next update
    configured = SlidingWindowEstimator(mesh, replace(base, **CHANGES))
    for ours, reference in zip(updates(reconfigured, sequence), updates(configured, sequence)):
        np.testing.assert_allclose(ours.positions, reference.positions, rtol=0.0, atol=1e-12)
        assert ours.measurement_sigma == pytest.approx(reference.measurement_sigma, rel=1e-12)
        assert ours.simulation_sigma == pytest.approx(reference.simulation_sigma, rel=1e-12)
    assert reconfigured.config == replace(base, **CHANGES)
    assert reconfigured.graph.relinearize_threshold == CHANGES["measurement_sigma"]


def test_changes_apply_from_the_next_update_and_survive_a_failed_one(scene):
    mesh, sequence = scene
    estimator = SlidingWindowEstimator(mesh, replace(BASE, estimate_weights=False))
    first = estimator.update(sequence[0].stamp_ns, sequence[0].points, sequence[0].predicted)
    estimator.reconfigure(measurement_sigma=1e-3)
    estimator.reconfigure(temporal_sigma=2e-2)  # adds to the first change
    with pytest.raises(EstimatorInputError):
        estimator.update(sequence[1].stamp_ns, np.zeros((4, 2)), sequence[1].predicted)
    assert (estimator.config.measurement_sigma, estimator.config.temporal_sigma) == (1e-3, 2e-2)
    second = estimator.update(sequence[1].stamp_ns, sequence[1].points, sequence[1].predicted)
    assert (first.measurement_sigma, second.measurement_sigma) == (5e-4, 1e-3)


def test_a_change_made_during_an_update_waits_for_the_next(scene, monkeypatch):
    """A node's parameter callback runs while its solver thread updates."""
    mesh, sequence = scene
    estimator = SlidingWindowEstimator(mesh, replace(BASE, estimate_weights=False))
    optimise = estimator._optimise

    def optimise_while_reconfigured(messages):
        estimator.reconfigure(measurement_sigma=1e-3)
        return optimise(messages)

    monkeypatch.setattr(estimator, "_optimise", optimise_while_reconfigured)
    during = estimator.update(sequence[0].stamp_ns, sequence[0].points, sequence[0].predicted)
    monkeypatch.setattr(estimator, "_optimise", optimise)
    after = estimator.update(sequence[1].stamp_ns, sequence[1].points, sequence[1].predicted)
    assert (during.measurement_sigma, after.measurement_sigma) == (5e-4, 1e-3)


@pytest.mark.parametrize("changes, message", [
    ({"window_size": 3}, r"window_size cannot change while the estimator runs \(dynamic: gating_distance, "),
    ({"youngs_modulus": 5e3}, "youngs_modulus cannot change while the estimator runs"),
    ({"measurement_sigma": -1.0}, r"measurement_sigma = -1.0 is outside \[1e-09, 10\]"),
    ({"measurement_sigma": 100.0}, r"measurement_sigma = 100.0 is outside \[1e-09, 10\]"),
    ({"gating_distance": float("nan")}, r"gating_distance must be finite, got nan"),
    ({"measurment_sigma": 1e-3}, "unknown setting measurment_sigma"),
])
def test_reconfigure_refuses_static_unknown_and_invalid_settings(scene, changes, message):
    mesh, sequence = scene
    estimator = SlidingWindowEstimator(mesh, replace(BASE, estimate_weights=False))
    with pytest.raises(EstimatorConfigError, match=message):
        estimator.reconfigure(temporal_sigma=2e-2, **changes)
    result = estimator.update(sequence[0].stamp_ns, sequence[0].points, sequence[0].predicted)
    assert estimator.config == replace(BASE, estimate_weights=False)  # nothing of the refused call applied
    assert result.measurement_sigma == 5e-4


@pytest.mark.parametrize("tool_mode, dropped", [("sphere", True), ("grasp", False)])
def test_points_on_the_tool_are_leaks_in_sphere_mode_only(scene, tool_mode, dropped):
    mesh, sequence = scene
    step = sequence[0]
    tool = np.array([*step.points[0], 0.0, 0.0, 0.0, 1.0])  # the sphere around a measured point
    config = replace(BASE, tool_mode=tool_mode, tool_radius=4e-3)
    reach = config.tool_radius + TOOL_MARGIN_SIGMAS * config.measurement_sigma  # the gate
    on_tool = int(np.count_nonzero(np.linalg.norm(step.points - tool[:3], axis=1) <= reach))
    with_tool = SlidingWindowEstimator(mesh, config).update(step.stamp_ns, step.points, step.predicted, tool)
    without = SlidingWindowEstimator(mesh, config).update(step.stamp_ns, step.points, step.predicted)
    assert on_tool >= 1
    assert ("point(s) on the tool dropped" in with_tool.message) is dropped
    assert with_tool.num_points_rejected - without.num_points_rejected == (on_tool if dropped else 0)


def test_the_tool_margin_is_at_most_one_radius_however_large_the_sigma(scene):
    """A nominal sigma far too large (here 3 sigma = 3.75 radii) must not drop the cloud around
    the tool: only points within two radii of its centre are leaks onto it."""
    mesh, sequence = scene
    step = sequence[0]
    tool = np.array([*step.points[0], 0.0, 0.0, 0.0, 1.0])
    config = replace(BASE, tool_radius=4e-3, measurement_sigma=5e-3, estimate_weights=False)
    distances = np.linalg.norm(step.points - tool[:3], axis=1)
    within_two_radii = int(np.count_nonzero(distances <= 2 * config.tool_radius))
    uncapped = config.tool_radius + TOOL_MARGIN_SIGMAS * config.measurement_sigma
    assert np.count_nonzero(distances <= uncapped) > within_two_radii  # the bound matters here
    with_tool = SlidingWindowEstimator(mesh, config).update(step.stamp_ns, step.points, step.predicted, tool)
    without = SlidingWindowEstimator(mesh, config).update(step.stamp_ns, step.points, step.predicted)
    assert with_tool.num_points_rejected - without.num_points_rejected == within_two_radii


@pytest.mark.parametrize("measurement_sigma, off_nominal", [(5e-4, False), (5e-2, True), (5e-6, True)])
def test_a_measurement_sigma_far_from_the_clouds_spread_is_reported(scene, measurement_sigma, off_nominal):
    """The scene's points spread 0.5 mm about the surface: a measurement_sigma 100x too large or
    too small (a value in the wrong units) is named in the status, and flagged for the node's
    diagnostics, at every update; the right one is not."""
    mesh, sequence = scene
    results = updates(SlidingWindowEstimator(mesh, replace(BASE, measurement_sigma=measurement_sigma)), sequence)
    assert [result.noise_off_nominal for result in results] == [off_nominal] * len(results)
    assert all((estimator_module.NOISE_OFF_NOMINAL in result.message) is off_nominal for result in results)
    assert all(np.all(np.isfinite(result.positions)) for result in results)


def test_a_restart_keeps_applied_settings_and_changes_still_pending(scene):
    """A change made while the estimator restarts (the node's parameter callback against its
    solver thread) reaches the restarted estimator, as do the changes applied before."""
    mesh, sequence = scene
    estimator = SlidingWindowEstimator(mesh, replace(BASE, estimate_weights=False))
    estimator.reconfigure(temporal_sigma=2e-2)
    updates(estimator, sequence[:1])
    estimator.reconfigure(measurement_sigma=1e-3)  # pending when the restart begins
    restarted = estimator.restarted()
    assert restarted.step == 0 and restarted.config.temporal_sigma == 2e-2
    estimator.reconfigure(robust_scale=3e-3)  # reaches the old object after the restart began
    updates(restarted, sequence[:1])
    assert (restarted.config.temporal_sigma, restarted.config.measurement_sigma, restarted.config.robust_scale) == (
        2e-2, 1e-3, 3e-3)
