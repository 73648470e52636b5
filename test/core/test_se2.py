"""Finite-difference checks of the SE(2) compounding Jacobians, random and degenerate poses."""

import numpy as np
import pytest
from jacobians import numeric_jacobian

from csam_ros.core import se2


def sample_poses(rng, count):
    poses = rng.uniform(-5, 5, (count, 3))
    poses[:, 2] = rng.uniform(-np.pi, np.pi, count)
    degenerate = np.array(
        [[0.0, 0.0, 0.0], [0.0, 0.0, np.pi], [1e-12, -1e-12, -np.pi + 1e-9], [3.0, 0.0, np.pi / 2]]
    )
    return np.concatenate([poses, degenerate])


@pytest.mark.parametrize("seed", [0, 1])
def test_compose_jacobians_match_finite_differences(seed):
    rng = np.random.default_rng(seed)
    a_all = sample_poses(rng, 6)
    b_all = sample_poses(rng, 6)[::-1]
    j1, j2 = se2.compose_jacobians(a_all, b_all)
    numeric_a = numeric_jacobian(lambda x: se2.compose(x, b_all), a_all, angles=[2])
    numeric_b = numeric_jacobian(lambda x: se2.compose(a_all, x), b_all, angles=[2])
    np.testing.assert_allclose(j1, numeric_a, atol=1e-7)
    np.testing.assert_allclose(j2, numeric_b, atol=1e-7)


def test_inverse_jacobian_matches_finite_differences():
    rng = np.random.default_rng(2)
    poses = sample_poses(rng, 8)
    jac = se2.inverse_jacobian(poses)
    np.testing.assert_allclose(jac, numeric_jacobian(se2.inverse, poses, angles=[2]), atol=1e-7)


def test_compose_inverse_between_are_consistent():
    rng = np.random.default_rng(3)
    a = sample_poses(rng, 10)
    b = sample_poses(rng, 10)[::-1]
    np.testing.assert_allclose(se2.compose(a, se2.between(a, b)) - b, 0, atol=1e-12)
    ident = se2.compose(a, se2.inverse(a))
    np.testing.assert_allclose(ident, 0, atol=1e-12)
    p = rng.normal(size=(len(a), 2))
    np.testing.assert_allclose(se2.inverse_transform_point(a, se2.transform_point(a, p)), p)


def test_wrap_angle_range():
    a = np.array([-np.pi, np.pi, 3 * np.pi, -3 * np.pi, 0.0, 7.0, -7.0])
    w = se2.wrap_angle(a)
    assert np.all(w > -np.pi) and np.all(w <= np.pi)
    np.testing.assert_allclose(np.cos(w), np.cos(a), atol=1e-12)
    np.testing.assert_allclose(np.sin(w), np.sin(a), atol=1e-12)
