"""A robot's local map checked against its own measurements before it is joined (the counts
in :mod:`~csam_ros.core.smoothing.fold_check`).

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

import numpy as np
from numpy.typing import NDArray

from csam_ros.core.joining.result import LocalMapCheck
from csam_ros.core.smoothing.fold_check import ConsistencyOptions, factor_outliers
from csam_ros.core.smoothing.robot_map import RobotMap

IntArray = NDArray[np.int64]

# fewer observations of a feature than this say too little about its share beyond the gate
MIN_FEATURE_OBSERVATIONS = 5


def check_local_map(m: RobotMap, options: ConsistencyOptions) -> LocalMapCheck:
    """Check ``m``'s own factors at its solution (module docs)."""
    counts = factor_outliers(m.problem, options.gate_probability)
    reasons = counts.reasons(options)
    inconsistent: list[int] = []
    if len(counts.observed):
        ids, seen = np.unique(counts.observed, return_counts=True)
        outliers = np.zeros(len(ids), dtype=np.int64)
        bad_ids, bad_counts = np.unique(counts.observed_outliers, return_counts=True)
        outliers[np.searchsorted(ids, bad_ids)] = bad_counts
        split = (seen >= MIN_FEATURE_OBSERVATIONS) & (
            outliers > options.max_feature_outliers * seen
        )
        label_of = dict(zip(m.feature_ids.tolist(), m.feature_labels.tolist(), strict=True))
        inconsistent = sorted(label_of[int(i)] for i in ids[split] if int(i) in label_of)
    return LocalMapCheck(
        trajectory_factors=counts.trajectory_factors,
        trajectory_outliers=counts.trajectory_outliers,
        observation_factors=counts.observation_factors,
        observation_outliers=counts.observation_outliers,
        inconsistent_features=inconsistent,
        reason="inconsistent local map: " + "; ".join(reasons) if reasons else "",
    )
