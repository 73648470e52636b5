"""Chi-square quantiles: the gates on squared whitened errors and the size of confidence
ellipses."""

from __future__ import annotations

from scipy.special import gammaincinv

# the tables' rounded quantiles with 2 degrees of freedom
CHI2_2DOF_95 = 5.991  # a 2D Gaussian's 95 % ellipse
CHI2_2DOF_99 = 9.21  # the association gate on the Mahalanobis distance


def chi2_quantile(probability: float, dof: int) -> float:
    """The chi-square quantile of ``probability`` (in (0, 1)) with ``dof`` degrees of freedom
    (scipy.stats.chi2.ppf without importing scipy.stats, 0.6 s)."""
    if not 0.0 < probability < 1.0:
        raise ValueError(f"probability must be in (0, 1), got {probability}")
    return float(2.0 * gammaincinv(0.5 * dof, probability))
