"""One robot's solved local map as C-SAM's joining takes it (:class:`RobotMap`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from csam_ros.core.sam.factors import PosePrior
from csam_ros.core.sam.solver import Problem

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]


@dataclass
class RobotMap:
    """One robot's solved local map, as C-SAM uses it.

    ``problem`` holds the robot's factors with its poses and features as unknowns in its
    frame ``G_r`` (first pose at the origin, fixed by the gauge prior
    ``problem.factors[gauge_factor]``). ``pose_ids`` (N,) are the ids of the poses in stamp
    order, ``feature_ids`` (F,) those of the features with the robot's own ``feature_labels``.
    """

    name: str
    problem: Problem
    stamps: Array
    pose_ids: IntArray
    feature_labels: IntArray
    feature_ids: IntArray
    gauge_factor: int
    feature_covariances: Array | None = None
    # (2, 3): the local map's odometry calibration (s, k_d, k_s) and its sigmas, when estimated
    odometry_calibration: Array | None = None

    def __post_init__(self) -> None:
        if len(self.stamps) != len(self.pose_ids) or len(self.pose_ids) == 0:
            raise ValueError(
                f"robot {self.name!r}: {len(self.stamps)} stamps for {len(self.pose_ids)} poses"
            )
        if len(self.feature_labels) != len(self.feature_ids):
            raise ValueError(f"robot {self.name!r}: feature labels and ids differ in length")
        if self.feature_covariances is not None and np.shape(self.feature_covariances) != (
            len(self.feature_ids),
            2,
            2,
        ):
            raise ValueError(
                f"robot {self.name!r}: feature_covariances must have shape "
                f"({len(self.feature_ids)}, 2, 2), got {np.shape(self.feature_covariances)}"
            )
        gauge = self.problem.factors[self.gauge_factor]
        if not isinstance(gauge, PosePrior) or np.any(gauge.variables != self.pose_ids[0]):
            raise ValueError(
                f"robot {self.name!r}: factor {self.gauge_factor} is not the gauge prior on "
                "the first pose"
            )

    @property
    def poses(self) -> Array:
        return self.problem.values_of(self.pose_ids)

    @property
    def feature_positions(self) -> Array:
        if len(self.feature_ids) == 0:
            return np.zeros((0, 2))
        return self.problem.values_of(self.feature_ids)


def find_gauge_factor(problem: Problem, first_pose: int) -> int:
    """Index of the pose prior that fixes ``first_pose`` alone (the local gauge)."""
    for i, f in enumerate(problem.factors):
        if isinstance(f, PosePrior) and len(f) == 1 and int(f.variables[0, 0]) == first_pose:
            return i
    raise ValueError(f"no gauge prior on pose id {first_pose} in the local problem")
