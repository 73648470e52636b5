"""A local map's odometry calibration ``c = (s, k_d, k_s)`` (docs/METHOD.md, odometry
calibration): distance scale, turn-rate scale while driving and on the spot, estimated with the
poses and features.

The odometry between two key poses is composed at a linearisation point ``c0`` with its
Jacobian ``J = dz/dc`` (:func:`csam_ros.core.model.motion.calibrated_odometry_between`), and
enters the solve as ``z(c) ~ z(c0) + J (c - c0)``, as preintegrated IMU factors take a bias
correction; when the estimate moves more than ``calibration_relinearise`` from ``c0`` the
intervals are composed anew at it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from csam_ros.core.model import motion
from csam_ros.core.sam.covariance import factorize_at_estimate, marginal_covariance
from csam_ros.core.sam.factors import CALIBRATION, CalibratedRelativePose, LinearPrior
from csam_ros.core.sam.solver import Problem
from csam_ros.core.smoothing.local_map_config import LocalMapOptions

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]

CALIBRATION_KEY = ("c", 0)
CALIBRATION_ROUNDS = 5  # converged solves: recompositions at most


@dataclass
class OdometryCalibration:
    """A local map's estimate of its odometry calibration ``(s, k_d, k_s)``
    (:func:`csam_ros.core.model.motion.calibrated_inputs`) and its marginal sigmas."""

    scale: Array  # (3,)
    sigma: Array  # (3,)


class OdometryCalibrator:
    """The calibration unknowns of one local map: the estimate, the point its odometry factors
    were composed at (``linearised_at``) and their Jacobians ``dz/dc`` there, one per odometry
    factor in the map's order (the map keeps them in step with its factors)."""

    def __init__(self, options: LocalMapOptions) -> None:
        self.options = options
        self.estimate = np.ones(3)
        self.linearised_at = np.ones(3)
        self.jacobians = np.zeros((0, 3, 3))
        self._problem: Problem | None = None  # the last solve's, with the unknowns
        self._sigma: Array | None = None

    def compose(
        self, stamps: Array, inputs: Array, sigmas: Array, keys: Array, correlations: Array | None
    ) -> motion.CalibratedOdometryFactors:
        """The odometry between consecutive ``keys`` at ``linearised_at``, with ``dz/dc``."""
        return motion.calibrated_odometry_between(
            stamps,
            inputs,
            sigmas,
            keys,
            self.linearised_at,
            self.options.driving_speed,
            correlations=correlations,
        )

    def at_estimate(self, relative: Array) -> Array:
        """The odometry factors' relative poses at the estimate, to first order from where they
        were composed: what the map's published problem carries."""
        if len(relative) == 0:
            return relative
        return relative + np.einsum("kij,j->ki", self.jacobians, self.estimate - self.linearised_at)

    def add_factors(
        self, problem: Problem, poses: IntArray, relative: Array, sqrt_information: Array
    ) -> None:
        """The calibration unknowns, their prior at 1 and the odometry factors in them."""
        cal = problem.add_variable(CALIBRATION, CALIBRATION_KEY, self.estimate)
        prior = np.diag(1.0 / np.asarray(self.options.calibration_sigmas, dtype=float))
        problem.add_factor(
            LinearPrior([cal], [CALIBRATION], np.ones(3), prior, name="calibration prior")
        )
        problem.add_factor(
            CalibratedRelativePose(
                poses[:-1],
                poses[1:],
                np.full(len(poses) - 1, cal),
                relative,
                self.jacobians,
                self.linearised_at,
                sqrt_information,
                name="odometry",
            )
        )

    def take(self, problem: Problem) -> bool:
        """Take the solved estimate of ``problem``; whether it moved more than
        ``calibration_relinearise`` from where the odometry was composed."""
        self.estimate = problem.value(CALIBRATION_KEY).copy()
        self._problem, self._sigma = problem, None
        moved = np.abs(self.estimate - self.linearised_at).max()
        return bool(moved > self.options.calibration_relinearise)

    def restore(self, estimate: Array, where: str) -> None:
        """Start from a saved estimate (``(3,)``, or ``(0,)``: none saved)."""
        estimate = np.asarray(estimate, dtype=float).reshape(-1)
        if len(estimate) not in (0, 3) or not np.all(np.isfinite(estimate)):
            raise ValueError(f"{where}: odometry_calibration {estimate.tolist()}")
        self.estimate = estimate.copy() if len(estimate) else np.ones(3)

    def result(self) -> OdometryCalibration:
        """The estimate and its marginal sigmas (NaN until a solve since a restore)."""
        if self._sigma is None:
            if self._problem is None:
                self._sigma = np.full(3, np.nan)
            else:
                system = factorize_at_estimate(self._problem)
                cov = marginal_covariance(self._problem, [CALIBRATION_KEY], system)
                self._sigma = np.sqrt(np.diag(cov))
        return OdometryCalibration(self.estimate.copy(), self._sigma.copy())
