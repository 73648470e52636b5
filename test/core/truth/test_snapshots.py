"""Snapshot localisation and the noise estimates from snapshots, on synthetic cases with known
answers."""

from __future__ import annotations

import numpy as np
from noise_models import noise_model

from csam_ros.core.model import se2
from csam_ros.core.model.log import FeatureLog, GroundTruth, OdometryLog, RobotLog, empty_rendezvous
from csam_ros.core.truth.noise_model import DENSITY_FLOOR
from csam_ros.core.truth.snapshots import _fit_densities, snapshot_localisation


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
    noise = noise_model((0.01, 0.0, 0.002), (1.0, 1.0, 1.0))
    snapshots = snapshot_localisation(robot, truth, noise)
    np.testing.assert_allclose(snapshots.stamps, [0.0, 1.0, 2.0])
    np.testing.assert_allclose(snapshots.poses[:, :2], poses[:, :2], atol=0.03)
    np.testing.assert_allclose(snapshots.poses[:, 2], poses[:, 2], atol=0.01)
    outlier = (snapshots.snapshot == 1) & (snapshots.labels == 13)
    assert abs(snapshots.range_residuals[outlier][0] - 2.5) < 0.1


def test_a_density_the_data_drive_to_zero_stays_at_the_floor() -> None:
    """Pose-pair errors with no lateral noise at all (MR.CLAM Dataset 4's q_vlat came out
    6e-10, and the odometry factors of short intervals were singular): the fitted density
    stays at DENSITY_FLOOR, the others are found."""
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
