"""A local map's state as arrays (:class:`LocalMapState`, what checkpoints and state files
hold) and the report of one update."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from csam_ros.core.sam.solver import SolveReport

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]


@dataclass
class UpdateReport:
    """What one :meth:`LocalMap.update` did."""

    new_poses: int
    inserted_poses: int  # of which inserted in the past (splitting an odometry factor)
    new_landmarks: int
    new_observations: int
    solve: SolveReport | None
    seconds: float


@dataclass
class LocalMapState:
    """Everything a :class:`LocalMap` holds: its data (odometry, feature observations as
    Cartesian points with square-root information, requested stamps) and its solved state
    (key poses, odometry factors, landmarks), so that :meth:`LocalMap.from_state` gives back
    the same map, estimate included, with no solve."""

    odometry_stamps: Array  # (N,)
    odometry_inputs: Array  # (N, 3)
    odometry_sigmas: Array  # (N, 3)
    odometry_correlations: Array  # (N, 3) of the input noise (log.CORRELATION_PAIRS)
    feature_stamps: Array  # (K,) the first ``integrated_features`` integrated, in stamp order
    feature_labels: IntArray  # (K,)
    feature_points: Array  # (K, 2)
    feature_sqrt_information: Array  # (K, 2, 2)
    requested: Array  # (R,) requested pose stamps
    keys: Array  # (P,) key pose stamps
    key_values: Array  # (P, 3)
    relative: Array  # (P - 1, 3) odometry between keys
    relative_sqrt_information: Array  # (P - 1, 3, 3)
    landmark_labels: IntArray  # (L,)
    landmark_values: Array  # (L, 2)
    integrated_features: int
    dropped_features: int
    last_solved_odometry: float  # -inf: never solved
    solved: bool  # whether the map has a solved problem (poses to publish)
    # (3,) estimated odometry calibration (s, k_d, k_s); (0,): none (calibration off)
    odometry_calibration: Array = field(default_factory=lambda: np.zeros(0))


def check_state(name: str, s: LocalMapState) -> None:
    """ValueError naming the field when the arrays of ``s`` do not fit together."""
    p, k, n_lm = len(s.keys), len(s.feature_stamps), len(s.landmark_labels)
    shapes = {
        "odometry_inputs": (s.odometry_inputs, (len(s.odometry_stamps), 3)),
        "odometry_sigmas": (s.odometry_sigmas, (len(s.odometry_stamps), 3)),
        "odometry_correlations": (s.odometry_correlations, (len(s.odometry_stamps), 3)),
        "feature_labels": (s.feature_labels, (k,)),
        "feature_points": (s.feature_points, (k, 2)),
        "feature_sqrt_information": (s.feature_sqrt_information, (k, 2, 2)),
        "key_values": (s.key_values, (p, 3)),
        "relative": (s.relative, (max(p - 1, 0), 3)),
        "relative_sqrt_information": (s.relative_sqrt_information, (max(p - 1, 0), 3, 3)),
        "landmark_values": (s.landmark_values, (n_lm, 2)),
    }
    for field_name, (value, shape) in shapes.items():
        if np.shape(value) != shape:
            raise ValueError(f"{name}: {field_name} has shape {np.shape(value)}, not {shape}")
    if not 0 <= s.integrated_features <= k:
        raise ValueError(f"{name}: {s.integrated_features} integrated of {k} features")
    if s.solved and p == 0:
        raise ValueError(f"{name}: a solved map without key poses")
