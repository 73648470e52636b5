"""Jacobians of every factor kind against central finite differences; input checks; residuals,
Jacobians, whitening and robust kernels as properties (hypothesis)."""

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from jacobians import numeric_block_jacobians, numeric_jacobian
from strategies import batches, covariances, points, poses

from csam_ros.core.model import se2
from csam_ros.core.sam.factors import (
    POINT,
    POSE,
    ROBUST_KERNELS,
    CalibratedRelativePose,
    Cauchy,
    Huber,
    LinearPrior,
    PointObservation,
    PointPrior,
    PosePrior,
    RelativePose,
    RelativePosition,
    robust_kernel,
    robust_kernel_name,
    sqrt_information_from_covariance,
)


def random_poses(rng, count):
    x = rng.uniform(-4, 4, (count, 3))
    x[:, 2] = rng.uniform(-np.pi, np.pi, count)
    return x


def check_jacobians(factor, blocks, angles=(), atol=1e-6):
    """Compare the analytic Jacobian blocks of all factors with central differences
    (``angles``: the error components that are angles)."""
    errors, jac = factor.evaluate(blocks)
    assert errors.shape == (len(factor), jac[0].shape[1])
    stacked_errors, stacked = factor.evaluate_stacked(blocks)
    np.testing.assert_array_equal(stacked_errors, errors)
    np.testing.assert_array_equal(stacked, np.concatenate(jac, axis=2))
    numeric = numeric_block_jacobians(lambda b: factor.evaluate(b, False)[0], blocks, angles=angles)
    for j, block in enumerate(blocks):
        assert jac[j].shape == (len(factor), errors.shape[1], block.shape[1])
        np.testing.assert_allclose(jac[j], numeric[j], atol=atol, rtol=1e-6)


def unit_w(count, dim):
    return np.broadcast_to(np.eye(dim), (count, dim, dim))


def test_pose_prior_jacobian_and_wrapped_error():
    rng = np.random.default_rng(0)
    x = random_poses(rng, 10)
    prior = random_poses(rng, 10)
    f = PosePrior(np.arange(10), prior, unit_w(10, 3))
    check_jacobians(f, [x], angles=[2])
    e, _ = f.evaluate([x], False)
    assert np.all(np.abs(e[:, 2]) <= np.pi)


def test_point_prior_jacobian():
    rng = np.random.default_rng(1)
    f = PointPrior(np.arange(5), rng.normal(size=(5, 2)), unit_w(5, 2))
    check_jacobians(f, [rng.normal(size=(5, 2))])


def test_relative_pose_jacobians_and_error():
    rng = np.random.default_rng(2)
    a, b = random_poses(rng, 12), random_poses(rng, 12)
    a[0] = [0, 0, 0]
    b[0] = [0, 0, 0]  # coincident poses
    z = se2.between(a, b)
    f = RelativePose(np.arange(12), np.arange(12, 24), z, unit_w(12, 3))
    check_jacobians(f, [a, b], angles=[2])
    np.testing.assert_allclose(f.evaluate([a, b], False)[0], 0, atol=1e-12)


def test_calibrated_relative_pose_jacobians_and_error():
    rng = np.random.default_rng(12)
    a, b = random_poses(rng, 9), random_poses(rng, 9)
    cal = 1.0 + 0.2 * rng.normal(size=(9, 3))
    lin = np.array([1.1, 0.7, 0.95])
    dz_dc = rng.normal(size=(9, 3, 3))
    z = se2.between(a, b) - np.einsum("kij,kj->ki", dz_dc, cal - lin)
    f = CalibratedRelativePose(
        np.arange(9), np.arange(9, 18), np.full(9, 18), z, dz_dc, lin, unit_w(9, 3)
    )
    check_jacobians(f, [a, b, cal], angles=[2])
    np.testing.assert_allclose(f.evaluate([a, b, cal], False)[0], 0, atol=1e-12)
    np.testing.assert_array_equal(f.evaluate([a, b, cal])[1][2], -dz_dc)


@pytest.mark.parametrize("distance", [3.0, 1e-3, 0.0])
def test_point_observation_jacobians_including_range_near_zero(distance):
    rng = np.random.default_rng(3)
    x = random_poses(rng, 8)
    direction = rng.normal(size=(8, 2))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    points = x[:, :2] + distance * direction
    z = se2.inverse_transform_point(x, points)
    f = PointObservation(np.arange(8), np.arange(8, 16), z, unit_w(8, 2))
    check_jacobians(f, [x, points])
    np.testing.assert_allclose(f.evaluate([x, points], False)[0], 0, atol=1e-12)


def cartesian_observations(rng, count):
    """Poses, points, noisy Cartesian measurements and full (correlated, anisotropic) 2x2
    covariances of ``count`` observations."""
    x = random_poses(rng, count)
    landmarks = x[:, :2] + rng.uniform(-6, 6, (count, 2))
    b = rng.normal(size=(count, 2, 2))
    cov = 0.05 * b @ b.transpose(0, 2, 1) + 1e-3 * np.eye(2)
    z = se2.inverse_transform_point(x, landmarks) + rng.normal(0, 0.2, (count, 2))
    return x, landmarks, z, cov


def test_cartesian_observation_with_full_covariance_against_finite_differences():
    """The whitened residual ``W (R^T (l - t) - z)`` and its Jacobian, ``W^T W = C^-1``."""
    x, landmarks, z, cov = cartesian_observations(np.random.default_rng(11), 12)
    f = PointObservation(np.arange(12), np.arange(12, 24), z, covariance=cov)
    r, jac, cost = f.whitened([x, landmarks])
    e = se2.inverse_transform_point(x, landmarks) - z
    np.testing.assert_allclose(cost, 0.5 * np.einsum("ki,kij,kj->k", e, np.linalg.inv(cov), e))
    numeric = numeric_block_jacobians(lambda b: f.whitened(b, False)[0], [x, landmarks])
    np.testing.assert_allclose(jac, np.concatenate(numeric, axis=2), atol=1e-6, rtol=1e-6)
    check_jacobians(f, [x, landmarks])


def test_cartesian_observation_equals_gtsam_transform_to():
    """The same factor in GTSAM (``Pose2.transformTo`` with its own Jacobians, the covariance
    as a Gaussian noise model): whitened errors, costs and whitened Jacobians agree, GTSAM's
    pose Jacobian being against its tangent space (``d(global) = blkdiag(R, 1) d(tangent)``)."""
    gtsam = pytest.importorskip("gtsam")
    x, landmarks, z, cov = cartesian_observations(np.random.default_rng(12), 10)
    f = PointObservation(np.arange(10), np.arange(10, 20), z, covariance=cov)
    r, jac, cost = f.whitened([x, landmarks])

    def error(zk):
        def fn(this, values, H):
            pose = values.atPose2(this.keys()[0])
            point = np.asarray(values.atPoint2(this.keys()[1]), dtype=float)
            jp, jl = np.zeros((2, 3), order="F"), np.zeros((2, 2), order="F")
            e = pose.transformTo(point, jp, jl) - zk
            if H is not None:
                H[0], H[1] = jp, jl
            return e

        return fn

    for k in range(10):
        values = gtsam.Values()
        values.insert(0, gtsam.Pose2(*x[k]))
        values.insert(1, landmarks[k])
        noise = gtsam.noiseModel.Gaussian.Covariance(cov[k])
        factor = gtsam.CustomFactor(noise, [0, 1], error(z[k]))
        assert factor.error(values) == pytest.approx(cost[k], rel=1e-10)
        linear = factor.linearize(values)
        a, b = linear.jacobian()
        tangent = np.eye(3)
        tangent[:2, :2] = se2.rotation(x[k, 2])
        ours = np.concatenate([jac[k][:, :3] @ tangent, jac[k][:, 3:]], axis=1)
        # whitening is unique up to an orthogonal factor: compare the normal equations
        np.testing.assert_allclose(ours.T @ ours, a.T @ a, rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(ours.T @ r[k], -a.T @ b, rtol=1e-9, atol=1e-9)


def test_relative_position_jacobians():
    rng = np.random.default_rng(4)
    a, b = random_poses(rng, 9), random_poses(rng, 9)
    b[0, :2] = a[0, :2]
    z = se2.between(a, b)[:, :2]
    f = RelativePosition(np.arange(9), np.arange(9, 18), z, unit_w(9, 2))
    check_jacobians(f, [a, b])
    _, jac = f.evaluate([a, b])
    np.testing.assert_allclose(jac[1][:, :, 2], 0)


def test_linear_prior_whitened_jacobian_and_wrap():
    rng = np.random.default_rng(5)
    pose = random_poses(rng, 1)
    point = rng.normal(size=(1, 2))
    mean = np.concatenate([pose[0], point[0]])
    mean[2] = se2.wrap_angle(mean[2] + 2 * np.pi - 0.1)
    R = np.triu(rng.normal(size=(5, 5))) + 3 * np.eye(5)
    f = LinearPrior([0, 1], [POSE, POINT], mean, R)
    r, jac, cost = f.whitened([pose, point])
    delta = np.concatenate([pose[0], point[0]]) - mean
    delta[2] = se2.wrap_angle(delta[2])
    np.testing.assert_allclose(r[0], R @ delta)
    np.testing.assert_allclose(jac[0], R)
    np.testing.assert_allclose(cost, 0.5 * delta @ R.T @ R @ delta)


def test_whitening_uses_sqrt_information_of_covariance():
    rng = np.random.default_rng(6)
    m = rng.normal(size=(4, 3, 3))
    cov = m @ m.transpose(0, 2, 1) + 0.1 * np.eye(3)
    w = sqrt_information_from_covariance(cov)
    np.testing.assert_allclose(w.transpose(0, 2, 1) @ w, np.linalg.inv(cov), rtol=1e-9, atol=1e-9)
    a, b = random_poses(rng, 4), random_poses(rng, 4)
    f = RelativePose(np.arange(4), np.arange(4, 8), np.zeros((4, 3)), covariance=cov)
    e, _ = f.evaluate([a, b], False)
    _, _, cost = f.whitened([a, b], False)
    expected = 0.5 * np.einsum("ki,kij,kj->k", e, np.linalg.inv(cov), e)
    np.testing.assert_allclose(cost, expected, rtol=1e-9)


@pytest.mark.parametrize("kernel", [Huber(1.0), Cauchy(1.0)])
def test_robust_kernel_reweights_rows(kernel):
    x = np.array([[0.1, 0, 0], [5.0, 0, 0]])
    f = PosePrior([0, 1], np.zeros((2, 3)), unit_w(2, 3), robust=kernel)
    r, jac, cost = f.whitened([x])
    s = np.array([0.01, 25.0])
    weight = kernel.weight(s)
    np.testing.assert_allclose(r[:, 0], np.sqrt(weight) * x[:, 0])
    np.testing.assert_allclose(jac[:, 0, 0], np.sqrt(weight))
    np.testing.assert_allclose(cost, 0.5 * kernel.rho(s))
    assert weight[0] == pytest.approx(1.0, abs=0.02) and weight[1] < 0.5
    # rho' is the weight: check by central differences
    numeric = numeric_jacobian(lambda v: kernel.rho(v[:, 0]), s[:, None])[:, 0]
    np.testing.assert_allclose(numeric, weight, rtol=1e-5)


def test_non_positive_definite_covariance_names_factor():
    cov = np.stack([np.eye(3), np.diag([1.0, 1.0, -1.0])])
    with pytest.raises(ValueError, match="Odometry.*factor 1.*positive definite"):
        RelativePose([0, 1], [1, 2], np.zeros((2, 3)), covariance=cov, name="Odometry")
    with pytest.raises(ValueError, match="factor 0 is not symmetric"):
        PointPrior([0], [[0, 0]], covariance=[[[1.0, 0.5], [0.0, 1.0]]])


def test_non_finite_measurement_is_rejected():
    z = np.zeros((3, 2))
    z[2, 1] = np.nan
    with pytest.raises(ValueError, match="PointObservation measurement: entry 2"):
        PointObservation([0, 0, 0], [1, 2, 3], z, covariance=np.eye(2))
    with pytest.raises(ValueError, match="shape"):
        PointObservation([0, 0], [1, 2], np.zeros((3, 2)), covariance=np.eye(2))
    with pytest.raises(ValueError, match="exactly one"):
        PointPrior([0], [[0, 0]])


def test_singular_sqrt_information_is_rejected():
    w = np.array([[[1.0, 2.0], [0.5, 1.0]]])
    with pytest.raises(ValueError, match="sqrt_information of factor 0 is singular"):
        PointPrior([0], [[0.0, 0.0]], w)


# -- properties ------------------------------------------------------------------------------

K = 3  # factors per drawn example
pose_batches = batches(poses(), K)
point_batches = batches(points(), K)


def ids(offset=0):
    return np.arange(K) + offset


def assert_zero_errors(factor, blocks):
    e, _ = factor.evaluate(blocks, False)
    np.testing.assert_allclose(e, 0.0, atol=1e-9)


@given(pose_batches, pose_batches)
def test_pose_prior_properties(x, prior):
    assert_zero_errors(PosePrior(ids(), x, unit_w(K, 3)), [x])
    f = PosePrior(ids(), prior, unit_w(K, 3))
    check_jacobians(f, [x], angles=[2])
    assert np.all(np.abs(f.evaluate([x], False)[0][:, 2]) <= np.pi)


@given(point_batches, point_batches)
def test_point_prior_properties(x, prior):
    assert_zero_errors(PointPrior(ids(), x, unit_w(K, 2)), [x])
    check_jacobians(PointPrior(ids(), prior, unit_w(K, 2)), [x])


@given(pose_batches, pose_batches, pose_batches)
def test_relative_pose_properties(a, b, z):
    exact = RelativePose(ids(), ids(K), se2.between(a, b), unit_w(K, 3))
    assert_zero_errors(exact, [a, b])
    check_jacobians(RelativePose(ids(), ids(K), z, unit_w(K, 3)), [a, b], angles=[2])


@given(pose_batches, point_batches, point_batches)
def test_point_observation_properties(x, landmarks, z):
    exact = PointObservation(ids(), ids(K), se2.inverse_transform_point(x, landmarks), unit_w(K, 2))
    assert_zero_errors(exact, [x, landmarks])
    check_jacobians(PointObservation(ids(), ids(K), z, unit_w(K, 2)), [x, landmarks])


@given(pose_batches, pose_batches, point_batches)
def test_relative_position_properties(a, b, z):
    exact = RelativePosition(ids(), ids(K), se2.between(a, b)[:, :2], unit_w(K, 2))
    assert_zero_errors(exact, [a, b])
    check_jacobians(RelativePosition(ids(), ids(K), z, unit_w(K, 2)), [a, b])


@given(poses(), points(), st.integers(-3, 3), covariances(5))
def test_linear_prior_is_zero_at_its_mean_modulo_full_turns(pose, point, turns, covariance):
    mean = np.concatenate([pose, point])
    mean[2] += 2 * np.pi * turns
    rmat = np.linalg.cholesky(np.linalg.inv(covariance)).T
    f = LinearPrior([0, 1], [POSE, POINT], mean, rmat)
    r, jac, cost = f.whitened([pose[None], point[None]])
    np.testing.assert_allclose(r, 0.0, atol=1e-8)
    np.testing.assert_allclose(jac[0], rmat)
    assert cost[0] == pytest.approx(0.0, abs=1e-12)


@given(pose_batches, pose_batches, pose_batches, batches(covariances(3), K))
def test_whitened_cost_is_the_mahalanobis_norm(a, b, z, covariance):
    f = RelativePose(ids(), ids(K), z, covariance=covariance)
    e, _ = f.evaluate([a, b], False)
    r, jac, cost = f.whitened([a, b])
    expected = 0.5 * np.einsum("ki,kij,kj->k", e, np.linalg.inv(covariance), e)
    np.testing.assert_allclose(cost, expected, rtol=1e-8, atol=1e-12)
    np.testing.assert_allclose(cost, 0.5 * np.einsum("ki,ki->k", r, r), rtol=1e-12)
    _, raw = f.evaluate([a, b])
    np.testing.assert_allclose(jac, f.sqrt_information @ np.concatenate(raw, axis=2), atol=1e-12)


kernels = st.one_of(
    st.floats(0.1, 10.0).map(Huber),
    st.floats(0.1, 10.0).map(Cauchy),
)
squared_norms = st.floats(0.0, 1e6, allow_nan=False)


@given(kernels, squared_norms, squared_norms)
def test_robust_kernel_cost_and_weight_bounds(kernel, s, t):
    s, t = sorted((s, t))
    pair = np.array([s, t])
    rho, weight = kernel.rho(pair), kernel.weight(pair)
    assert kernel.rho(np.array([0.0]))[0] == 0.0 and kernel.weight(np.array([0.0]))[0] == 1.0
    assert np.all(rho <= pair * (1 + 1e-12))  # never costs more than least squares
    assert np.all((weight > 0) & (weight <= 1))
    assert rho[0] <= rho[1] * (1 + 1e-12)  # cost non-decreasing
    assert weight[0] >= weight[1] * (1 - 1e-12)  # weight non-increasing


@given(kernels, st.floats(1e-3, 1e3))
def test_robust_kernel_weight_is_the_cost_derivative(kernel, s):
    numeric = numeric_jacobian(lambda v: kernel.rho(v[:, 0]), np.array([[s]]))[0, 0]
    np.testing.assert_allclose(kernel.weight(np.array([s]))[0], numeric, rtol=1e-5, atol=1e-9)


@given(kernels, pose_batches, pose_batches)
def test_robust_kernel_scales_rows_by_the_square_root_of_the_weight(kernel, x, prior):
    plain = PosePrior(ids(), prior, unit_w(K, 3))
    robust = PosePrior(ids(), prior, unit_w(K, 3), robust=kernel)
    r0, j0, c0 = plain.whitened([x])
    r, j, c = robust.whitened([x])
    s = 2 * c0
    scale = np.sqrt(kernel.weight(s))
    np.testing.assert_allclose(r, r0 * scale[:, None], atol=1e-12)
    np.testing.assert_allclose(j, j0 * scale[:, None, None], atol=1e-12)
    np.testing.assert_allclose(c, 0.5 * kernel.rho(s), rtol=1e-12)
    assert np.all(c <= c0 * (1 + 1e-12))


def test_robust_kernels_by_name_and_back() -> None:
    for name, kind in ROBUST_KERNELS.items():
        kernel = robust_kernel(name, 1.5)
        assert type(kernel) is kind and robust_kernel_name(kernel) == (name, 1.5)
        assert robust_kernel(name) == kind()  # parameter 0: the kernel's default
    assert robust_kernel("") is None and robust_kernel_name(None) == ("", 0.0)

    class Unnamed(Huber):
        pass

    assert robust_kernel_name(Unnamed()) is None
