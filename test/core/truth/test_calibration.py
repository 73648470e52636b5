"""Range scales of the noise estimation on a synthetic case with a known answer."""

from __future__ import annotations

import numpy as np

from csam_ros.core.truth.calibration import range_scale
from csam_ros.core.truth.localisation import Localisation


def test_range_scale_recovers_a_camera_scale_despite_outliers() -> None:
    rng = np.random.default_rng(3)
    n = 4000
    predicted = rng.uniform(0.5, 6.0, size=n)
    measured = 0.985 * predicted * (1 + rng.normal(scale=0.03, size=n))
    measured[:100] *= 0.5  # 2.5% gross short outliers, ignored by the gate
    key = np.arange(n)
    zeros = np.zeros(n)
    loc = Localisation(
        robot="robot1",
        stamps=np.linspace(0.0, 100.0, n),
        poses=np.zeros((n, 3)),
        pose_covariances=np.zeros((n, 3, 3)),
        pair_covariances=np.zeros((n - 1, 6, 6)),
        odometry_z=np.zeros((n - 1, 3)),
        odometry_unit=np.zeros((n - 1, 3, 3, 3)),
        observation_key=key,
        ranges=measured,
        range_residuals=measured - predicted,
        bearing_residuals=zeros,
        range_variance=zeros,
        bearing_variance=zeros,
        iterations=0,
        seconds=0.0,
    )
    whole, first, second = range_scale(loc)
    assert abs(whole - 0.985) < 0.003
    assert abs(first - 0.985) < 0.004 and abs(second - 0.985) < 0.004
