"""Landmarks whose true positions are exchanged in a data set's ground truth, found from the
measurements (MR.CLAM Dataset 1: subjects 11 and 17), and the exchange that repairs it."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from csam_ros.core.model.log import GroundTruth, MultiRobotLog
from csam_ros.core.truth.noise_model import NoiseModel
from csam_ros.core.truth.snapshots import landmark_consistency, snapshot_localisation


@dataclass(frozen=True)
class LandmarkSwap:
    """Two landmark subjects whose true positions are exchanged in a ground truth, with the
    share of each one's snapshot residuals beyond the gross gate before and after."""

    subjects: tuple[int, int]
    gross_before: tuple[float, float]
    gross_after: tuple[float, float]

    def line(self) -> str:
        (a, b), before, after = self.subjects, self.gross_before, self.gross_after
        return (
            f"true positions of landmark subjects {a} and {b} exchanged (detected: "
            f"{before[0]:.0%} and {before[1]:.0%} of their measurements miss by metres, "
            f"{after[0]:.0%} and {after[1]:.0%} after)"
        )


def detect_landmark_swaps(
    log: MultiRobotLog,
    noise: NoiseModel,
    misfit: float = 0.5,
    fit: float = 0.1,
    min_measurements: int = 5,
) -> list[LandmarkSwap]:
    """Pairs of landmark subjects whose true positions are exchanged in ``log.truth``.

    A subject misfits when more than ``misfit`` of its snapshot residuals are gross
    (:func:`landmark_consistency`: its measurements miss its true position by metres while
    the other landmarks fit); two misfits are a swap when, their positions exchanged, both
    fit (at most ``fit`` gross). Needs no robot ground truth. MR.CLAM Dataset 1: subjects 11
    and 17 at 97 % and 98 %, every other subject at most 3 %; Datasets 2 and 4: none above
    2 %."""
    if log.truth is None:
        raise ValueError("detecting swapped landmarks needs the landmark ground truth")

    def gross(truth: GroundTruth) -> dict[int, float]:
        trial = replace(log, truth=truth)
        snapshots = {n: snapshot_localisation(r, truth, noise) for n, r in log.robots.items()}
        return {
            subject: entry["gross_fraction"]
            for subject, entry in landmark_consistency(trial, snapshots).items()
            if entry["n"] >= min_measurements
        }

    before = gross(log.truth)
    misfits = sorted(s for s, share in before.items() if share > misfit)
    swaps: list[LandmarkSwap] = []
    for i, a in enumerate(misfits):
        for b in misfits[i + 1 :]:
            if any({a, b} & set(s.subjects) for s in swaps):
                continue
            after = gross(exchange_landmarks(log.truth, a, b))
            if after.get(a, 1.0) <= fit and after.get(b, 1.0) <= fit:
                swaps.append(LandmarkSwap((a, b), (before[a], before[b]), (after[a], after[b])))
    return swaps


def exchange_landmarks(truth: GroundTruth, a: int, b: int) -> GroundTruth:
    """``truth`` with the positions of landmark subjects ``a`` and ``b`` exchanged."""
    rows = [int(np.flatnonzero(truth.feature_ids == s)[0]) for s in (a, b)]
    positions = truth.feature_positions.copy()
    positions[rows] = positions[rows[::-1]]
    return replace(truth, feature_positions=positions)
