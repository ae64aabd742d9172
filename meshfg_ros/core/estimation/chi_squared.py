"""The chi-squared distribution's quantile and density, as scipy.stats.chi2 computes them.

Through scipy.special, the functions scipy.stats.chi2 itself calls, with the same results to
the bit: importing scipy.stats takes about half a second, which every node, command and test
process would pay at start-up for these two functions.
"""
from __future__ import annotations

import numpy as np
from scipy.special import gammaincinv, gammaln, xlogy

__all__ = ["density", "quantile"]


def quantile(probability, dof: float):
    """x with P(chi^2_dof <= x) = probability (scipy.stats.chi2.ppf)."""
    return 2.0 * gammaincinv(dof / 2.0, probability)


def density(x, dof: float):
    """The probability density of chi^2_dof at x (scipy.stats.chi2.pdf), for x > 0."""
    return np.exp(xlogy(dof / 2.0 - 1.0, x) - x / 2.0 - gammaln(dof / 2.0) - np.log(2.0) * dof / 2.0)
