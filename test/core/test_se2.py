"""Finite-difference checks of the SE(2) compounding Jacobians, random and degenerate poses."""

import numpy as np
import pytest

from csam_ros.core import se2


def numeric_jacobian(fun, x, eps=1e-6):
    """Central differences of ``fun`` at ``x`` (one pose), angle differences wrapped."""
    f0 = fun(x)
    jac = np.zeros((len(f0), len(x)))
    for j in range(len(x)):
        dx = np.zeros(len(x))
        dx[j] = eps
        diff = fun(x + dx) - fun(x - dx)
        if len(f0) == 3:
            diff[2] = se2.wrap_angle(diff[2])
        jac[:, j] = diff / (2 * eps)
    return jac


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
    for a, b, ja, jb in zip(a_all, b_all, j1, j2, strict=True):
        np.testing.assert_allclose(
            ja, numeric_jacobian(lambda x, b=b: se2.compose(x, b), a), atol=1e-7
        )
        np.testing.assert_allclose(
            jb, numeric_jacobian(lambda x, a=a: se2.compose(a, x), b), atol=1e-7
        )


def test_inverse_jacobian_matches_finite_differences():
    rng = np.random.default_rng(2)
    poses = sample_poses(rng, 8)
    jac = se2.inverse_jacobian(poses)
    for a, j in zip(poses, jac, strict=True):
        np.testing.assert_allclose(j, numeric_jacobian(se2.inverse, a), atol=1e-7)


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
