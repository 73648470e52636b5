"""Chi-square quantiles against the tables and scipy."""

from __future__ import annotations

import math

import pytest

from csam_ros.core.model.chi_square import CHI2_2DOF_95, CHI2_2DOF_99, chi2_quantile


def test_chi2_quantile_matches_the_table_values_and_scipy() -> None:
    assert chi2_quantile(0.95, 2) == pytest.approx(CHI2_2DOF_95, abs=5e-4)
    assert chi2_quantile(0.99, 2) == pytest.approx(CHI2_2DOF_99, abs=5e-4)
    assert chi2_quantile(0.9, 2) == pytest.approx(-2.0 * math.log1p(-0.9))
    scipy_stats = pytest.importorskip("scipy.stats")
    assert chi2_quantile(0.999, 3) == pytest.approx(scipy_stats.chi2.ppf(0.999, 3))
    with pytest.raises(ValueError, match="probability"):
        chi2_quantile(1.0, 2)
