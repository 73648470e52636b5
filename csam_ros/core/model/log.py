"""Plain data classes for what robots measure: the input of every smoother.

The simulator, the MR.CLAM and slam2d importers, the bag reader of offline replay and the
nodes all speak these types, so a bag runs through the core offline exactly as through the
nodes.

Conventions (SI units, radians, body frame x forward, y left):

- Odometry: sample ``i`` at stamp ``t_i`` holds the mean input ``u_i = (v, v_lat, omega)``
  over ``(t_{i-1}, t_i]``; the first sample of a robot only marks its start time, its
  input is unused. ``sigma`` is ``(s_v, s_vlat, s_omega)`` of that input and, when given,
  ``correlations`` the correlation coefficients of its pairs ``(v, v_lat)``, ``(v, omega)``,
  ``(v_lat, omega)`` (none: independent).
- Features: range ``r`` and bearing ``beta`` from the robot centre to a point feature,
  with the observing robot's own feature label (labels mean nothing across robots).
- Feature points: a point feature's position ``(x, y)`` in the body frame with its full 2x2
  covariance (Cartesian observations, e.g. of a 2D SLAM file), labelled as features are.
- Rendezvous: range and bearing from the observing robot to the ``observed`` robot.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


@dataclass
class OdometryLog:
    """Odometry inputs of one robot, sorted by stamp."""

    stamps: FloatArray  # (N,) seconds
    inputs: FloatArray  # (N, 3) v [m/s], v_lat [m/s], omega [rad/s]
    sigmas: FloatArray  # (N, 3) s_v, s_vlat, s_omega
    correlations: FloatArray | None = None  # (N, 3) rho(v, v_lat), rho(v, w), rho(v_lat, w)

    def covariances(self) -> FloatArray:
        """Input covariances ``(N, 3, 3)`` from the sigmas and correlations."""
        return covariances_from_correlations(self.sigmas, self.correlations)


@dataclass
class FeatureLog:
    """Range-bearing observations of point features by one robot, sorted by stamp."""

    stamps: FloatArray  # (K,)
    labels: IntArray  # (K,) the robot's own feature label
    ranges: FloatArray  # (K,) m
    bearings: FloatArray  # (K,) rad
    sigma_range: FloatArray  # (K,) m
    sigma_bearing: FloatArray  # (K,) rad


@dataclass
class FeaturePointLog:
    """Cartesian observations of point features by one robot, sorted by stamp."""

    stamps: FloatArray  # (K,)
    labels: IntArray  # (K,) the robot's own feature label
    points: FloatArray  # (K, 2) m, in the body frame (x forward, y left)
    covariances: FloatArray  # (K, 2, 2) m^2


@dataclass
class RendezvousLog:
    """Range-bearing observations of other robots by one robot, sorted by stamp."""

    stamps: FloatArray  # (K,)
    observed: list[str]  # (K,) name of the observed robot
    ranges: FloatArray
    bearings: FloatArray
    sigma_range: FloatArray
    sigma_bearing: FloatArray


@dataclass
class RobotLog:
    """Everything one robot measured."""

    name: str
    odometry: OdometryLog
    features: FeatureLog
    rendezvous: RendezvousLog
    points: FeaturePointLog = field(default_factory=lambda: empty_points())


@dataclass
class GroundTruth:
    """What only scoring may look at: true features, label meaning, true trajectories."""

    feature_ids: IntArray  # (F,)
    feature_positions: FloatArray  # (F, 2) in the world frame
    label_to_feature: dict[str, dict[int, int]]  # robot -> its label -> feature id
    trajectory_stamps: dict[str, FloatArray] = field(default_factory=dict)
    trajectories: dict[str, FloatArray] = field(default_factory=dict)  # robot -> (N, 3) world


@dataclass
class MultiRobotLog:
    """A whole run: the robots' logs in a fixed order and, when known, the ground truth."""

    robots: dict[str, RobotLog]
    truth: GroundTruth | None = None


def empty_features() -> FeatureLog:
    """A feature log with no observations."""
    z = np.zeros(0)
    return FeatureLog(z, np.zeros(0, dtype=np.int64), z, z, z, z)


def empty_points() -> FeaturePointLog:
    """A feature point log with no observations."""
    return FeaturePointLog(
        np.zeros(0), np.zeros(0, dtype=np.int64), np.zeros((0, 2)), np.zeros((0, 2, 2))
    )


# pairs of input components each correlation coefficient of an odometry sample belongs to
CORRELATION_PAIRS = ((0, 1), (0, 2), (1, 2))


def covariances_from_correlations(
    sigmas: FloatArray, correlations: FloatArray | None = None
) -> FloatArray:
    """Covariances ``(N, 3, 3)`` of odometry inputs with ``sigmas`` ``(N, 3)`` and, if given,
    the ``correlations`` ``(N, 3)`` of :data:`CORRELATION_PAIRS`."""
    s = np.asarray(sigmas, dtype=float).reshape(-1, 3)
    rho = np.zeros((len(s), 3, 3))
    rho[:, [0, 1, 2], [0, 1, 2]] = 1.0
    if correlations is not None:
        c = np.asarray(correlations, dtype=float).reshape(-1, 3)
        for k, (i, j) in enumerate(CORRELATION_PAIRS):
            rho[:, i, j] = rho[:, j, i] = c[:, k]
    return s[:, :, None] * rho * s[:, None, :]


def correlations_from_covariances(covariances: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Sigmas ``(N, 3)`` and correlations ``(N, 3)`` of input covariances ``(N, 3, 3)``, the
    inverse of :func:`covariances_from_correlations` (a zero sigma: non-finite correlations)."""
    cov = np.asarray(covariances, dtype=float).reshape(-1, 3, 3)
    with np.errstate(invalid="ignore", divide="ignore"):
        s = np.sqrt(np.diagonal(cov, axis1=1, axis2=2))
        rho = np.stack([cov[:, i, j] / (s[:, i] * s[:, j]) for i, j in CORRELATION_PAIRS], 1)
    return s, rho


def correlations_valid(correlations: FloatArray) -> NDArray[np.bool_]:
    """Which rows of correlations ``(N, 3)`` give a positive definite input covariance (for
    any positive sigmas): finite, and every leading minor of the correlation matrix positive."""
    c = np.asarray(correlations, dtype=float).reshape(-1, 3)
    with np.errstate(invalid="ignore", over="ignore"):
        first, det = correlation_minors(c[:, 0], c[:, 1], c[:, 2])
        return np.isfinite(c).all(axis=1) & (first > 0) & (det > 0)


def correlation_minors(a: Any, b: Any, d: Any) -> tuple[Any, Any]:
    """The second and third leading minors of the correlation matrix with correlations
    ``a, b, d`` (CORRELATION_PAIRS order), floats or arrays alike."""
    return 1.0 - a * a, 1.0 + 2.0 * a * b * d - a * a - b * b - d * d


def empty_rendezvous() -> RendezvousLog:
    """A rendezvous log with no observations."""
    z = np.zeros(0)
    return RendezvousLog(z, [], z, z, z, z)
