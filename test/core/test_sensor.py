"""Sensor model: Cartesian observation covariance, prediction Jacobians, input checks."""

import numpy as np
import pytest
from jacobians import numeric_block_jacobians

from csam_ros.core import se2, sensor


def test_cartesian_covariance_is_rotated_polar_covariance():
    r, b, sr, sb = 2.0, 0.7, 0.01, 0.012
    z, cov = sensor.polar_to_cartesian([r], [b], [sr], [sb])
    np.testing.assert_allclose(z[0], [r * np.cos(b), r * np.sin(b)])
    rot = se2.rotation(b)
    np.testing.assert_allclose(cov[0], rot @ np.diag([sr**2, (r * sb) ** 2]) @ rot.T)
    # first-order propagation of the polar noise through (r cos b, r sin b)
    jac = np.array([[np.cos(b), -r * np.sin(b)], [np.sin(b), r * np.cos(b)]])
    np.testing.assert_allclose(cov[0], jac @ np.diag([sr**2, sb**2]) @ jac.T)


def test_zero_range_keeps_covariance_positive_definite():
    _, cov = sensor.polar_to_cartesian([0.0], [0.3], [0.01], [0.01])
    assert np.linalg.eigvalsh(cov[0]).min() > 0


@pytest.mark.parametrize("distance", [2.0, 1e-4, 0.0])
def test_prediction_jacobians_match_finite_differences(distance):
    rng = np.random.default_rng(0)
    x = rng.uniform(-3, 3, (5, 3))
    d = rng.normal(size=(5, 2))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    lm = x[:, :2] + distance * d
    h, jx, jl = sensor.predict_jacobians(x, lm)
    np.testing.assert_allclose(h, se2.inverse_transform_point(x, lm), atol=1e-15)
    num_x, num_l = numeric_block_jacobians(lambda b: sensor.predict(*b), [x, lm])
    np.testing.assert_allclose(jx, num_x, atol=1e-8)
    np.testing.assert_allclose(jl, num_l, atol=1e-8)


def test_polar_round_trip():
    r, b = sensor.cartesian_to_polar(np.array([[3.0, 4.0], [-1.0, 0.0]]))
    np.testing.assert_allclose(r, [5.0, 1.0])
    np.testing.assert_allclose(b, [np.arctan2(4, 3), np.pi])


def test_bad_observations_are_named():
    with pytest.raises(ValueError, match="observation 1: negative range"):
        sensor.polar_to_cartesian([1.0, -1.0], [0, 0], [0.1, 0.1], [0.1, 0.1])
    with pytest.raises(ValueError, match="observation 0: bearing is not finite"):
        sensor.polar_to_cartesian([1.0], [np.nan], [0.1], [0.1])
    with pytest.raises(ValueError, match="observation 0: sigma_bearing must be positive"):
        sensor.polar_to_cartesian([1.0], [0.0], [0.1], [0.0])
