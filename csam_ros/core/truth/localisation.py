"""One robot's poses smoothed against the known landmarks (the smoothing engine), with the
covariances of its poses and of consecutive pairs: the E-step of the noise estimation
(:mod:`csam_ros.core.truth.calibration`) and the range-scale estimates
(:mod:`csam_ros.core.truth.range_scale`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from csam_ros.core.model import se2
from csam_ros.core.model.log import GroundTruth, OdometryLog, RobotLog
from csam_ros.core.model.motion import dead_reckoning, odometry_between
from csam_ros.core.model.sensor import polar_to_cartesian
from csam_ros.core.sam.covariance import factorize_at_estimate
from csam_ros.core.sam.factors import (
    POINT,
    POSE,
    Cauchy,
    PointObservation,
    PointPrior,
    RelativePose,
)
from csam_ros.core.sam.solver import Problem, SolverOptions
from csam_ros.core.truth.noise_model import NoiseModel
from csam_ros.core.truth.snapshots import Snapshots

FloatArray = NDArray[np.float64]


@dataclass
class Localisation:
    """One robot's smoothed poses at its feature stamps, landmarks held at their truth."""

    robot: str
    stamps: FloatArray  # (N,) key stamps
    poses: FloatArray  # (N, 3) world frame
    pose_covariances: FloatArray  # (N, 3, 3)
    pair_covariances: FloatArray  # (N-1, 6, 6) joint of consecutive poses
    odometry_z: FloatArray  # (N-1, 3) composed odometry between keys
    odometry_unit: FloatArray  # (N-1, 3, 3, 3) covariance per unit density of v, v_lat, omega
    observation_key: NDArray[np.int64]  # (K,) observation -> key
    ranges: FloatArray  # (K,)
    range_residuals: FloatArray  # (K,) measured - predicted
    bearing_residuals: FloatArray  # (K,)
    range_variance: FloatArray  # (K,) of the prediction, from the pose covariance
    bearing_variance: FloatArray  # (K,)
    iterations: int
    seconds: float


def _unit_density_odometry(
    odometry: OdometryLog, keys: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Composed odometry between keys and its covariance for a unit density of each input."""
    durations = np.diff(odometry.stamps)
    per_sample = np.concatenate([[durations[0]], durations])
    unit = []
    relative = np.zeros((keys.size - 1, 3))
    for k in range(3):
        sigmas = np.zeros((odometry.stamps.size, 3))
        sigmas[:, k] = 1.0 / np.sqrt(per_sample)
        factors = odometry_between(odometry.stamps, odometry.inputs, sigmas, keys)
        relative = factors.relative_poses
        unit.append(factors.covariances)
    return relative, np.stack(unit, axis=1)


def localise(
    robot: RobotLog,
    truth: GroundTruth,
    noise: NoiseModel,
    snapshots: Snapshots,
    robust: bool = True,
) -> Localisation:
    """Smooth one robot's poses at its feature stamps given the true landmarks.

    Odometry factors between consecutive feature stamps (covariance from the densities of
    ``noise``), Cartesian landmark observations with a Cauchy kernel, landmarks tied to their
    truth by a 1 mm prior. Started from the snapshot poses, dead reckoning in between.
    """
    began = time.perf_counter()
    features = robot.features
    odometry = robot.odometry
    inside = (features.stamps >= odometry.stamps[0]) & (features.stamps <= odometry.stamps[-1])
    keys, key_of = np.unique(features.stamps[inside], return_inverse=True)
    relative, unit = _unit_density_odometry(odometry, keys)
    odometry_cov = np.einsum("k,nkij->nij", noise.densities() ** 2, unit)

    # start: snapshot poses, dead reckoning from the nearest snapshot elsewhere
    reckoned = dead_reckoning(relative)
    snap_key = np.searchsorted(keys, snapshots.stamps)
    snap_key = np.clip(snap_key, 0, keys.size - 1)
    exact = keys[snap_key] == snapshots.stamps
    anchor_keys, anchor_poses = snap_key[exact], snapshots.poses[exact]
    nearest = np.clip(np.searchsorted(anchor_keys, np.arange(keys.size)), 0, anchor_keys.size - 1)
    previous = np.clip(nearest - 1, 0, anchor_keys.size - 1)
    closer = np.abs(anchor_keys[previous] - np.arange(keys.size)) < np.abs(
        anchor_keys[nearest] - np.arange(keys.size)
    )
    anchor = np.where(closer, previous, nearest)
    initial = se2.compose(
        anchor_poses[anchor],
        se2.between(reckoned[anchor_keys[anchor]], reckoned),
    )

    problem = Problem()
    pose_ids = problem.add_variables(POSE, [("x", k) for k in range(keys.size)], initial)
    subjects = np.array(truth.feature_ids)
    point_ids = problem.add_variables(
        POINT, [("l", int(s)) for s in subjects], truth.feature_positions
    )
    problem.add_factor(PointPrior(point_ids, truth.feature_positions, covariance=np.eye(2) * 1e-6))
    problem.add_factor(RelativePose(pose_ids[:-1], pose_ids[1:], relative, covariance=odometry_cov))
    labels = truth.label_to_feature[robot.name]
    where = {int(s): k for k, s in enumerate(subjects)}
    obs_subject_row = np.array(
        [where[labels[int(lab)]] for lab in features.labels[inside]], dtype=np.int64
    )
    ranges = features.ranges[inside]
    bearings = features.bearings[inside]
    sigma_r = noise.sigma_range + noise.sigma_range_per_m * ranges
    z, z_cov = polar_to_cartesian(ranges, bearings, sigma_r, noise.sigma_bearing)
    problem.add_factor(
        PointObservation(
            pose_ids[key_of],
            point_ids[obs_subject_row],
            z,
            covariance=z_cov,
            robust=Cauchy() if robust else None,
        )
    )
    report = problem.solve(SolverOptions(max_iterations=50))
    poses = problem.values_of(pose_ids)

    # Covariances of the poses and of consecutive pairs. The landmarks are held to 1 mm, so
    # the pose block of the information matrix (conditional on the landmarks) is block
    # tridiagonal: its selected inverse comes from one forward and one backward recursion.
    system = factorize_at_estimate(problem)
    n_pose = 3 * keys.size
    information = system.full_matrix()[:n_pose, :n_pose]
    pose_cov, pair_cov = chain_covariances(information, keys.size)
    landmarks = truth.feature_positions[obs_subject_row]
    pose_of = poses[key_of]
    d = landmarks - pose_of[:, :2]
    predicted_r = np.linalg.norm(d, axis=1)
    predicted_b = np.arctan2(d[:, 1], d[:, 0]) - pose_of[:, 2]
    j_r = np.stack([-d[:, 0] / predicted_r, -d[:, 1] / predicted_r, np.zeros_like(predicted_r)], 1)
    j_b = np.stack(
        [d[:, 1] / predicted_r**2, -d[:, 0] / predicted_r**2, -np.ones_like(predicted_r)], 1
    )
    c = pose_cov[key_of]
    return Localisation(
        robot=robot.name,
        stamps=keys,
        poses=poses,
        pose_covariances=pose_cov,
        pair_covariances=pair_cov,
        odometry_z=relative,
        odometry_unit=unit,
        observation_key=key_of,
        ranges=ranges,
        range_residuals=ranges - predicted_r,
        bearing_residuals=se2.wrap_angle(bearings - predicted_b),
        range_variance=np.einsum("ki,kij,kj->k", j_r, c, j_r),
        bearing_variance=np.einsum("ki,kij,kj->k", j_b, c, j_b),
        iterations=report.iterations,
        seconds=time.perf_counter() - began,
    )


def chain_covariances(information: sp.spmatrix, n: int) -> tuple[FloatArray, FloatArray]:
    """Diagonal and first off-diagonal blocks of the inverse of a block-tridiagonal matrix.

    ``information`` is ``(3n, 3n)`` symmetric with 3x3 blocks, nonzero only on the block
    diagonal and the first block off-diagonals. Returns the covariances ``(n, 3, 3)`` and the
    joint covariances of consecutive blocks ``(n-1, 6, 6)``.
    """
    block = np.arange(3)
    rows = 3 * np.arange(n)[:, None, None] + block[None, :, None]
    cols = 3 * np.arange(n)[:, None, None] + block[None, None, :]
    rows, cols = np.broadcast_arrays(rows, cols)
    diagonal = np.asarray(information[rows.reshape(-1), cols.reshape(-1)]).reshape(n, 3, 3)
    upper = np.asarray(information[rows[:-1].reshape(-1), (cols[:-1] + 3).reshape(-1)]).reshape(
        n - 1, 3, 3
    )
    schur = np.empty_like(diagonal)
    schur[0] = diagonal[0]
    for k in range(1, n):
        schur[k] = diagonal[k] - upper[k - 1].T @ np.linalg.solve(schur[k - 1], upper[k - 1])
    schur_inverse = np.linalg.inv(schur)
    cov = np.empty_like(diagonal)
    cross = np.empty_like(upper)
    cov[-1] = schur_inverse[-1]
    for k in range(n - 2, -1, -1):
        gain = schur_inverse[k] @ upper[k]  # S_k^-1 B_k
        cross[k] = -gain @ cov[k + 1]
        cov[k] = schur_inverse[k] - cross[k] @ gain.T
    pair = np.zeros((n - 1, 6, 6))
    pair[:, :3, :3] = cov[:-1]
    pair[:, 3:, 3:] = cov[1:]
    pair[:, :3, 3:] = cross
    pair[:, 3:, :3] = cross.transpose(0, 2, 1)
    return 0.5 * (cov + cov.transpose(0, 2, 1)), pair
