"""A robot's local map checked against its own measurements before it is joined.

A local map can fold: after a long stretch without observations, or from a wrong loop (two
features taken for one), the smoother settles where the trajectory bends against its
odometry, or where one feature's observations split into two groups that cannot both fit.
C-SAM would join such a map as it is, and associate its misplaced features with the right
features of other robots.

The check evaluates the map's own factors at its solution, each factor's squared whitened
error ``s = ||W e||^2`` (no robust kernel) against the chi2 gate of its dimension
(docs/METHOD.md section 6.5):

- the trajectory: the share of the factors between poses (odometry and gap bridges) beyond
  the gate. Healthy maps have next to none (MR.CLAM Dataset 1: at most 2 of 4,426-6,555 per
  robot);
  a folded trajectory many (a simulated wrong loop of five features: 64 of 64). Above
  ``max_trajectory_outliers`` the robot stays pending;
- the observations: the share beyond the gate of all of them (MR.CLAM: 4-8 %, its
  outlier tails; above ``max_observation_outliers`` the robot stays pending) and of each
  feature's own (MR.CLAM: at most 16 %; a feature of a wrong loop: 59-100 %). A feature
  above ``max_feature_outliers`` (with at least ``MIN_FEATURE_OBSERVATIONS``) is not
  associated with other robots' features: the robot joins through its other parts.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from csam_ros.core.joining.result import LocalMapCheck
from csam_ros.core.model.chi_square import chi2_quantile
from csam_ros.core.sam.factors import POINT, POSE
from csam_ros.core.smoothing.robot_map import RobotMap

IntArray = NDArray[np.int64]

# fewer observations of a feature than this say too little about its share beyond the gate
MIN_FEATURE_OBSERVATIONS = 5


@dataclass(frozen=True)
class ConsistencyOptions:
    """Where a local map stops being trusted (fractions of factors beyond the gate)."""

    gate_probability: float = 0.999
    max_trajectory_outliers: float = 0.02
    max_observation_outliers: float = 0.3
    max_feature_outliers: float = 0.3


def _share(part: int, whole: int) -> float:
    return part / whole if whole else 0.0


def check_local_map(m: RobotMap, options: ConsistencyOptions) -> LocalMapCheck:
    """Check ``m``'s own factors at its solution (module docs)."""
    problem = m.problem
    trajectory = [0, 0]
    observation = [0, 0]
    outlier_ids: list[IntArray] = []
    observed_ids: list[IntArray] = []
    for factor, squared in zip(problem.factors, problem.squared_errors(), strict=True):
        if len(factor) == 0:
            continue
        outlier = squared > chi2_quantile(options.gate_probability, factor.residual_dim)
        if all(kind is POSE for kind in factor.kinds) and len(factor.kinds) == 2:
            trajectory[0] += len(factor)
            trajectory[1] += int(outlier.sum())
        elif POINT in factor.kinds:
            points = factor.variables[:, factor.kinds.index(POINT)]
            observation[0] += len(factor)
            observation[1] += int(outlier.sum())
            observed_ids.append(points)
            outlier_ids.append(points[outlier])
    reasons = []
    if _share(trajectory[1], trajectory[0]) > options.max_trajectory_outliers:
        reasons.append(
            f"{trajectory[1]} of {trajectory[0]} factors between poses beyond the "
            f"{options.gate_probability:.1%} gate"
        )
    if _share(observation[1], observation[0]) > options.max_observation_outliers:
        reasons.append(
            f"{observation[1]} of {observation[0]} observations beyond the "
            f"{options.gate_probability:.1%} gate"
        )
    inconsistent: list[int] = []
    if observed_ids:
        ids, counts = np.unique(np.concatenate(observed_ids), return_counts=True)
        outliers = np.zeros(len(ids), dtype=np.int64)
        bad_ids, bad_counts = np.unique(np.concatenate(outlier_ids), return_counts=True)
        outliers[np.searchsorted(ids, bad_ids)] = bad_counts
        split = (counts >= MIN_FEATURE_OBSERVATIONS) & (
            outliers > options.max_feature_outliers * counts
        )
        label_of = dict(zip(m.feature_ids.tolist(), m.feature_labels.tolist(), strict=True))
        inconsistent = sorted(label_of[int(i)] for i in ids[split] if int(i) in label_of)
    return LocalMapCheck(
        trajectory_factors=trajectory[0],
        trajectory_outliers=trajectory[1],
        observation_factors=observation[0],
        observation_outliers=observation[1],
        inconsistent_features=inconsistent,
        reason="inconsistent local map: " + "; ".join(reasons) if reasons else "",
    )
