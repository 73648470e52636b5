"""A local map against its own measurements: the shares of its factors beyond the chi2 gate
(docs/METHOD.md section 6.5), which the smoother uses to recover a fold
(:mod:`~csam_ros.core.smoothing.fold_recovery`) and the merger to keep a folded map out
(:mod:`~csam_ros.core.joining.consistency`).

Each factor's squared whitened error ``s = ||W e||^2`` (no robust kernel) at the solution is
compared with the gate of its dimension. Factors between two poses (odometry, gap bridges)
count for the trajectory, factors on a point feature for the observations.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from csam_ros.core.model.chi_square import chi2_quantile
from csam_ros.core.sam.factors import POINT, POSE
from csam_ros.core.sam.solver import Problem

IntArray = NDArray[np.int64]


@dataclass(frozen=True)
class ConsistencyOptions:
    """Where a local map stops being trusted (fractions of factors beyond the gate)."""

    gate_probability: float = 0.999
    max_trajectory_outliers: float = 0.02
    max_observation_outliers: float = 0.3
    max_feature_outliers: float = 0.3


@dataclass(frozen=True)
class FactorOutliers:
    """How many of a map's factors lie beyond the gate, and which features they observe."""

    trajectory_factors: int
    trajectory_outliers: int
    observation_factors: int
    observation_outliers: int
    observed: IntArray  # the feature variable of each observation factor
    observed_outliers: IntArray  # ... of each one beyond the gate

    def reasons(self, options: ConsistencyOptions) -> list[str]:
        """Why the map is not to be trusted, in words (empty: it is)."""
        reasons = []
        gate = f"{options.gate_probability:.1%} gate"
        if _share(self.trajectory_outliers, self.trajectory_factors) > (
            options.max_trajectory_outliers
        ):
            reasons.append(
                f"{self.trajectory_outliers} of {self.trajectory_factors} factors between "
                f"poses beyond the {gate}"
            )
        if _share(self.observation_outliers, self.observation_factors) > (
            options.max_observation_outliers
        ):
            reasons.append(
                f"{self.observation_outliers} of {self.observation_factors} observations beyond "
                f"the {gate}"
            )
        return reasons


def _share(part: int, whole: int) -> float:
    return part / whole if whole else 0.0


def factor_outliers(problem: Problem, gate_probability: float) -> FactorOutliers:
    """Count ``problem``'s factors beyond the gate at its current values (module docs)."""
    trajectory = [0, 0]
    observation = [0, 0]
    observed: list[IntArray] = [np.zeros(0, dtype=np.int64)]
    outliers: list[IntArray] = [np.zeros(0, dtype=np.int64)]
    for factor, squared in zip(problem.factors, problem.squared_errors(), strict=True):
        if len(factor) == 0:
            continue
        beyond = squared > chi2_quantile(gate_probability, factor.residual_dim)
        if all(kind is POSE for kind in factor.kinds) and len(factor.kinds) == 2:
            trajectory[0] += len(factor)
            trajectory[1] += int(beyond.sum())
        elif POINT in factor.kinds:
            points = factor.variables[:, factor.kinds.index(POINT)]
            observation[0] += len(factor)
            observation[1] += int(beyond.sum())
            observed.append(points)
            outliers.append(points[beyond])
    return FactorOutliers(
        trajectory[0],
        trajectory[1],
        observation[0],
        observation[1],
        np.concatenate(observed),
        np.concatenate(outliers),
    )
