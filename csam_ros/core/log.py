"""Plain data classes for what robots measure: the input of every smoother.

The simulator, the MR.CLAM and slam2d importers, the bag reader of offline replay and the
nodes all speak these types, so a bag runs through the core offline exactly as through the
nodes.

Conventions (SI units, radians, body frame x forward, y left):

- Odometry: sample ``i`` at stamp ``t_i`` holds the mean input ``u_i = (v, v_lat, omega)``
  over ``(t_{i-1}, t_i]``; the first sample of a robot only marks its start time, its
  input is unused. ``sigma`` is ``(s_v, s_vlat, s_omega)`` of that input.
- Features: range ``r`` and bearing ``beta`` from the robot centre to a point feature,
  with the observing robot's own feature label (labels mean nothing across robots).
- Rendezvous: range and bearing from the observing robot to the ``observed`` robot.
"""

from __future__ import annotations

from dataclasses import dataclass, field

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


def empty_rendezvous() -> RendezvousLog:
    """A rendezvous log with no observations."""
    z = np.zeros(0)
    return RendezvousLog(z, [], z, z, z, z)
