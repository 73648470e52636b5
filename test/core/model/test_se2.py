"""SE(2) compounding: Jacobians against finite differences on random and degenerate poses;
group identities, angle wrapping and point transforms as properties (hypothesis)."""

import numpy as np
import pytest
from hypothesis import example, given
from hypothesis import strategies as st
from jacobians import numeric_jacobian
from strategies import assert_poses_close, points, poses

from csam_ros.core.model import se2


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


# -- properties ------------------------------------------------------------------------------


@given(poses(), poses())
def test_between_undoes_compose(a, b):
    assert_poses_close(se2.compose(a, se2.between(a, b)), b)
    assert_poses_close(se2.between(a, se2.compose(a, b)), b)
    assert_poses_close(se2.between(a, b), se2.inverse(se2.between(b, a)))


@given(poses())
def test_inverse_is_an_inverse(a):
    zero = np.zeros(3)
    assert_poses_close(se2.compose(a, se2.inverse(a)), zero)
    assert_poses_close(se2.compose(se2.inverse(a), a), zero)
    assert_poses_close(se2.inverse(se2.inverse(a)), a)
    assert_poses_close(se2.compose(a, zero), a)
    assert_poses_close(se2.compose(zero, a), a)


@given(poses(), poses(), poses())
def test_compose_is_associative(a, b, c):
    left = se2.compose(se2.compose(a, b), c)
    right = se2.compose(a, se2.compose(b, c))
    assert_poses_close(left, right, atol=1e-8)


@given(poses(), poses())
@example(np.array([0.0, 0.0, np.pi / 2]), np.array([0.0, 0.0, np.pi / 2]))
def test_one_compose_in_scalars_is_the_vectorised_compose(a, b):
    one = np.array(se2.compose_one(tuple(a.tolist()), tuple(b.tolist())))
    assert -np.pi < one[2] <= np.pi
    assert_poses_close(one, se2.compose(a, b), atol=1e-12)


@given(poses(), poses())
def test_composed_headings_are_wrapped(a, b):
    for pose in (se2.compose(a, b), se2.inverse(a), se2.between(a, b)):
        assert -np.pi < pose[2] <= np.pi


@given(st.floats(-1e4, 1e4, allow_nan=False))
@example(np.pi)
@example(-np.pi)
@example(-3 * np.pi)
def test_wrap_angle_range_and_idempotence(angle):
    w = se2.wrap_angle(angle)
    assert -np.pi < w <= np.pi
    assert se2.wrap_angle(w) == w
    np.testing.assert_allclose([np.cos(w), np.sin(w)], [np.cos(angle), np.sin(angle)], atol=1e-9)


@given(poses(), points(), points())
def test_transform_point_is_a_rigid_motion(a, p, q):
    moved = se2.transform_point(a, p)
    np.testing.assert_allclose(moved, se2.compose(a, [p[0], p[1], 0.0])[:2], atol=1e-12)
    np.testing.assert_allclose(se2.inverse_transform_point(a, moved), p, atol=1e-9)
    np.testing.assert_allclose(
        se2.transform_point(se2.inverse(a), p), se2.inverse_transform_point(a, p), atol=1e-9
    )
    distance = np.linalg.norm(moved - se2.transform_point(a, q))
    np.testing.assert_allclose(distance, np.linalg.norm(p - q), atol=1e-9)


@given(poses(), poses())
@example(np.array([1.0, 2.0, np.pi / 2]), np.array([0.5, -1.0, np.pi / 2]))  # heading at pi
def test_compose_jacobians_are_derivatives(a, b):
    j1, j2 = se2.compose_jacobians(a, b)
    np.testing.assert_allclose(
        j1, numeric_jacobian(lambda x: se2.compose(x, b), a, angles=[2]), atol=1e-7
    )
    np.testing.assert_allclose(
        j2, numeric_jacobian(lambda x: se2.compose(a, x), b, angles=[2]), atol=1e-7
    )


@given(poses())
def test_inverse_jacobian_is_the_derivative(a):
    expected = numeric_jacobian(se2.inverse, a, angles=[2])
    np.testing.assert_allclose(se2.inverse_jacobian(a), expected, atol=1e-7)
