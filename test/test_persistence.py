"""The share of a correction that persists between updates (core/estimation/persistence.py)."""

import numpy as np
import pytest

from meshfg_ros.benchmarks.baselines import synthetic_sequence
from meshfg_ros.core.estimation.estimator import EstimatorConfig, EstimatorStepError, SlidingWindowEstimator
from meshfg_ros.core.estimation.persistence import HORIZON, CorrectionPersistence

SIZE = 600  # values per correction (200 vertices)


def shares(corrections) -> list:
    persistence = CorrectionPersistence()
    return [persistence.observe(correction) for correction in corrections]


def test_the_first_correction_has_nothing_to_persist_with():
    assert shares([np.ones(SIZE)]) == [0.0]


def test_noise_that_is_new_at_every_update_is_not_kept():
    rng = np.random.default_rng(0)
    # E[share] = 0 with a spread of about 1 / sqrt(HORIZON * 600) = 0.009 after the last update.
    assert shares(rng.normal(size=(40, SIZE)))[-1] < 0.05


def test_a_systematic_error_under_noise_keeps_its_share_of_the_energy():
    """c_t = s + n_t with |s|^2 = E|n|^2: half of a correction's energy persists."""
    rng = np.random.default_rng(1)
    systematic = rng.normal(size=SIZE)
    corrections = systematic + rng.normal(size=(40, SIZE))
    assert shares(corrections)[-1] == pytest.approx(0.5, abs=0.05)
    assert shares(np.tile(systematic, (3, 1)))[1:] == pytest.approx([1.0, 1.0])


def test_after_a_change_of_regime_the_share_follows_within_the_horizon():
    """A long stretch of noise, then a systematic error as large as the noise appears: the share
    passes 0.3 (of the 0.5 it tends to) within HORIZON updates, not after as many as the stretch."""
    rng = np.random.default_rng(4)
    noise = rng.normal(size=(300, SIZE))
    systematic = rng.normal(size=SIZE)
    after = shares([*noise, *(systematic + rng.normal(size=(HORIZON, SIZE)))])[300:]
    assert after[HORIZON - 1] > 0.3 and after[HORIZON - 1] > after[2]


def test_corrections_that_undo_each_other_are_not_kept():
    correction = np.random.default_rng(2).normal(size=SIZE)
    assert shares([correction, -correction, correction]) == [0.0, 0.0, 0.0]


def test_a_correction_of_another_size_or_not_finite_is_refused():
    persistence = CorrectionPersistence()
    persistence.observe(np.zeros((200, 3)))
    with pytest.raises(ValueError, match="600"):
        persistence.observe(np.zeros((100, 3)))
    with pytest.raises(ValueError, match="non-finite"):
        persistence.observe(np.full((200, 3), np.nan))


def test_a_failed_update_leaves_the_persistence_as_it_was(monkeypatch):
    mesh, sequence = synthetic_sequence(target_vertices=60, points_per_step=400, steps=3, size=0.1,
                                        noise_sigma=5e-4, prediction_error=2e-3, seed=3)
    estimator = SlidingWindowEstimator(mesh, EstimatorConfig(window_size=2))
    for step in sequence[:2]:
        estimator.update(step.stamp_ns, step.points, step.predicted)
    before = dict(vars(estimator.persistence))

    def fail(*_):
        raise RuntimeError("posterior std failed")

    monkeypatch.setattr(SlidingWindowEstimator, "_position_covariance", fail)
    with pytest.raises(EstimatorStepError, match="posterior std failed"):
        estimator.update(sequence[2].stamp_ns, sequence[2].points, sequence[2].predicted)
    after = vars(estimator.persistence)
    assert after["products"] == before["products"] and after["energies"] == before["energies"]
    np.testing.assert_array_equal(after["previous"], before["previous"])
