"""Sensor model: Cartesian observation covariance, prediction Jacobians, input checks; the
same as properties (hypothesis)."""

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from jacobians import numeric_block_jacobians
from strategies import angles, batches, points, poses

from csam_ros.core.model import se2, sensor


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


# -- properties ------------------------------------------------------------------------------


@given(batches(poses(), 3), batches(points(), 3))
def test_prediction_and_jacobians_properties(x, landmarks):
    h, d_pose, d_point = sensor.predict_jacobians(x, landmarks)
    np.testing.assert_allclose(h, se2.inverse_transform_point(x, landmarks), atol=1e-12)
    np.testing.assert_allclose(h, sensor.predict(x, landmarks), atol=0)
    num_x, num_l = numeric_block_jacobians(lambda b: sensor.predict(*b), [x, landmarks])
    np.testing.assert_allclose(d_pose, num_x, atol=1e-7)
    np.testing.assert_allclose(d_point, num_l, atol=1e-7)


ranges = st.floats(0.01, 50.0)
sigmas = st.floats(1e-4, 1.0)


@given(ranges, angles(), sigmas, sigmas)
def test_polar_to_cartesian_properties(r, b, sr, sb):
    z, cov = sensor.polar_to_cartesian([r], [b], [sr], [sb])
    back_r, back_b = sensor.cartesian_to_polar(z)
    np.testing.assert_allclose(back_r, [r], rtol=1e-12)
    np.testing.assert_allclose(se2.wrap_angle(back_b - b), 0.0, atol=1e-12)
    # first-order propagation of diag(sr^2, sb^2) through (r cos b, r sin b)
    jac = np.array([[np.cos(b), -r * np.sin(b)], [np.sin(b), r * np.cos(b)]])
    expected = jac @ np.diag([sr**2, sb**2]) @ jac.T
    np.testing.assert_allclose(cov[0], expected, rtol=1e-9, atol=1e-15 * np.abs(expected).max())
    np.testing.assert_array_equal(cov[0], cov[0].T)
    assert np.linalg.eigvalsh(cov[0]).min() > 0
