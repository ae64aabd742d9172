"""core/estimation/chi_squared.py gives scipy.stats.chi2's quantile and density."""
import numpy as np
import pytest
from scipy.stats import chi2

from meshfg_ros.core.estimation import chi_squared


@pytest.mark.parametrize("dof", [1, 2, 3, 7.5])
def test_quantile_and_density_match_scipy_stats(dof):
    probability = np.linspace(0.001, 0.999, 999)
    np.testing.assert_allclose(chi_squared.quantile(probability, dof), chi2.ppf(probability, dof), rtol=1e-13)
    x = np.linspace(0.01, 40.0, 1000)
    np.testing.assert_allclose(chi_squared.density(x, dof), chi2.pdf(x, dof), rtol=1e-13)


def test_quantile_is_the_inverse_of_the_distribution_function():
    x = chi_squared.quantile(np.array([0.05, 0.5, 0.95]), 3)
    np.testing.assert_allclose(chi2.cdf(x, 3), [0.05, 0.5, 0.95], rtol=1e-12)
    assert chi_squared.quantile(0.95, 3) == pytest.approx(7.8147, abs=1e-4)
