"""Pieces of the noise estimation on synthetic cases with known answers."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import scipy.sparse as sp

from csam_ros.core.model import se2
from csam_ros.core.model.log import FeatureLog, GroundTruth, OdometryLog, RobotLog, empty_rendezvous
from csam_ros.core.truth.calibration import (
    NEUTRAL_START,
    Localisation,
    NoiseModel,
    chain_covariances,
    detect_landmark_swaps,
    exchange_landmarks,
    range_scale,
    robust_sigma,
    snapshot_localisation,
)


def test_chain_covariances_match_the_dense_inverse() -> None:
    rng = np.random.default_rng(1)
    n = 9
    information = np.zeros((3 * n, 3 * n))
    for k in range(n):
        a = rng.normal(size=(3, 3))
        information[3 * k : 3 * k + 3, 3 * k : 3 * k + 3] += a @ a.T + np.eye(3)
    for k in range(n - 1):
        j = rng.normal(size=(3, 6))
        information[3 * k : 3 * k + 6, 3 * k : 3 * k + 6] += j.T @ j
    dense = np.linalg.inv(information)
    cov, pair = chain_covariances(sp.csr_matrix(information), n)
    for k in range(n):
        np.testing.assert_allclose(cov[k], dense[3 * k : 3 * k + 3, 3 * k : 3 * k + 3], atol=1e-12)
    for k in range(n - 1):
        np.testing.assert_allclose(pair[k], dense[3 * k : 3 * k + 6, 3 * k : 3 * k + 6], atol=1e-12)


def test_robust_sigma_of_a_normal_sample() -> None:
    values = np.random.default_rng(0).normal(scale=0.3, size=20000)
    values[:500] = 50.0  # 2.5% gross outliers barely move it
    assert abs(robust_sigma(values) - 0.3) < 0.02


def test_snapshot_localisation_recovers_poses_despite_an_outlier() -> None:
    rng = np.random.default_rng(2)
    landmarks = np.array([[4.0, 0.0], [4.0, 2.0], [5.0, -1.5], [6.0, 1.0], [3.0, -2.0]])
    truth = GroundTruth(np.arange(5), landmarks, {"robot1": {10 + k: k for k in range(5)}})
    poses = np.array([[0.0, 0.0, 0.1], [0.5, 0.2, -0.2], [1.0, -0.3, 0.05]])
    stamps, labels, ranges, bearings = [], [], [], []
    for t, pose in enumerate(poses):
        local = se2.inverse_transform_point(pose, landmarks)
        r = np.linalg.norm(local, axis=1) + rng.normal(scale=0.01, size=5)
        b = np.arctan2(local[:, 1], local[:, 0]) + rng.normal(scale=0.002, size=5)
        if t == 1:
            r[3] += 2.5  # a gross outlier in the middle frame
        stamps += [float(t)] * 5
        labels += list(range(10, 15))
        ranges += r.tolist()
        bearings += b.tolist()
    k = len(stamps)
    features = FeatureLog(
        np.array(stamps),
        np.array(labels),
        np.array(ranges),
        np.array(bearings),
        np.full(k, 0.01),
        np.full(k, 0.002),
    )
    odometry = OdometryLog(np.array([0.0, 3.0]), np.zeros((2, 3)), np.ones((2, 3)))
    robot = RobotLog("robot1", odometry, features, empty_rendezvous())
    noise = NoiseModel(
        sigma_range=0.01,
        sigma_range_per_m=0.0,
        sigma_bearing=0.002,
        q_v=1.0,
        q_vlat=1.0,
        q_omega=1.0,
    )
    snapshots = snapshot_localisation(robot, truth, noise)
    np.testing.assert_allclose(snapshots.stamps, [0.0, 1.0, 2.0])
    np.testing.assert_allclose(snapshots.poses[:, :2], poses[:, :2], atol=0.03)
    np.testing.assert_allclose(snapshots.poses[:, 2], poses[:, 2], atol=0.01)
    outlier = (snapshots.snapshot == 1) & (snapshots.labels == 13)
    assert abs(snapshots.range_residuals[outlier][0] - 2.5) < 0.1


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


def test_noise_model_from_a_mapping_and_its_checks() -> None:
    start = NEUTRAL_START  # q = (0.02, 0.01, 0.04)
    changed = NoiseModel.from_dict({"q_v": 0.5, "sigma_bearing": "0.03"}, start)
    assert (changed.q_v, changed.sigma_bearing, changed.q_omega) == (0.5, 0.03, 0.04)
    assert changed.densities().tolist() == [0.5, 0.01, 0.04]
    with pytest.raises(ValueError, match="unknown noise keys"):
        NoiseModel.from_dict({"q_x": 1.0}, start)
    with pytest.raises(TypeError):
        NoiseModel.from_dict({"q_v": 1.0})  # no defaults: every value is required
    with pytest.raises(ValueError, match="sigma_range_per_m must be finite and >= 0"):
        NoiseModel.from_dict({"sigma_range_per_m": -0.1}, start)
    with pytest.raises(ValueError, match="q_omega must be finite and > 0"):
        NoiseModel.from_dict({"q_omega": float("nan")}, start)


def test_a_density_the_data_drive_to_zero_stays_at_the_floor() -> None:
    """Pose-pair errors with no lateral noise at all (MR.CLAM Dataset 4's q_vlat came out
    6e-10, and the odometry factors of short intervals were singular): the fitted density
    stays at DENSITY_FLOOR, the others are found."""
    from csam_ros.core.truth.calibration import DENSITY_FLOOR, _fit_densities

    rng = np.random.default_rng(4)
    n = 2000
    gaps = rng.uniform(1.0, 20.0, n)
    a_terms = np.zeros((n, 3, 3, 3))
    for k in range(3):
        a_terms[:, k, k, k] = gaps
    c = np.tile(np.eye(3) * 1e-6, (n, 1, 1))
    truth = np.array([0.02, 0.0, 0.04])
    e = rng.normal(size=(n, 3)) * np.sqrt(truth**2 * gaps[:, None] + 1e-6)
    q, _ = _fit_densities(e, a_terms, c)
    assert q[1] == DENSITY_FLOOR
    np.testing.assert_allclose(q[[0, 2]], truth[[0, 2]], rtol=0.1)


def test_swapped_landmarks_in_the_truth_are_found_from_the_measurements() -> None:
    from csam_ros.datasets.scenario import load_scenario
    from csam_ros.datasets.simulation import simulate

    log = simulate(load_scenario("map_joining"), 1)
    assert log.truth is not None
    noise = NoiseModel(
        sigma_range=0.01,
        sigma_range_per_m=0.0,
        sigma_bearing=0.012,
        q_v=0.1,
        q_vlat=0.1,
        q_omega=0.1,
    )
    assert detect_landmark_swaps(log, noise) == []  # the simulator's truth is right
    # the most observed feature of each area, metres apart
    observed = np.concatenate(
        [
            [log.truth.label_to_feature[name][int(k)] for k in robot.features.labels]
            for name, robot in log.robots.items()
        ]
    )
    subjects, counts = np.unique(observed, return_counts=True)
    x = log.truth.feature_positions[np.searchsorted(log.truth.feature_ids, subjects), 0]
    a = int(subjects[x < 0][np.argmax(counts[x < 0])])
    b = int(subjects[x > 0][np.argmax(counts[x > 0])])
    swapped = replace(log, truth=exchange_landmarks(log.truth, a, b))
    (swap,) = detect_landmark_swaps(swapped, noise)
    assert swap.subjects == (min(a, b), max(a, b))
    assert min(swap.gross_before) > 0.5 and max(swap.gross_after) <= 0.1
    assert f"subjects {min(a, b)} and {max(a, b)} exchanged" in swap.line()
