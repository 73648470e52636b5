"""Matching stamps: the nearest of a sorted array of stamps to each query stamp."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from csam_ros.core.model import se2

IntArray = NDArray[np.int64]


def nearest_stamp(stamps: ArrayLike, query: ArrayLike) -> IntArray:
    """Index in ``stamps`` (sorted, not empty) of the stamp nearest each query stamp; of two
    at the same distance the earlier."""
    t, q = np.asarray(stamps), np.asarray(query)
    right = np.minimum(np.searchsorted(t, q), len(t) - 1)
    left = np.maximum(right - 1, 0)
    return np.where(np.abs(t[left] - q) <= np.abs(t[right] - q), left, right).astype(np.int64)


def matching_stamp(stamps: ArrayLike, query: ArrayLike, tolerance: float) -> IntArray:
    """Index in ``stamps`` (sorted) of the stamp nearest each query stamp when it is within
    ``tolerance`` of it, else -1."""
    t, q = np.asarray(stamps), np.asarray(query)
    if len(t) == 0:
        return np.full(q.shape, -1, dtype=np.int64)
    nearest = nearest_stamp(t, q)
    return np.where(np.abs(t[nearest] - q) <= tolerance, nearest, -1).astype(np.int64)


def regular_stamps(stamps: NDArray[np.float64], interval: float, t0: float) -> NDArray[np.float64]:
    """The grid ``t0 + k * interval`` over the span of sorted odometry ``stamps``, but only
    where consecutive samples are at most ``interval`` apart, so that a gap in the odometry
    adds no key pose (the grid points of each short interval ``(t_{i-1}, t_i]``)."""
    scaled = (stamps - t0) / interval
    dense = np.flatnonzero(np.diff(stamps) <= interval)
    k = np.concatenate([np.floor(scaled[dense]) + 1, np.floor(scaled[dense + 1])])
    k = np.unique(k[(k >= 0) & (k <= np.floor(scaled[-1]))])
    return t0 + interval * k


def corrected_poses(
    before: tuple[NDArray[np.float64], NDArray[np.float64]] | None,
    stamps: ArrayLike,
    poses: NDArray[np.float64],
    tolerance: float,
) -> NDArray[np.float64] | None:
    """``poses`` (N, 3) at ``stamps``, each moved by the correction ``C`` (``C (+) pose``)
    held at its stamp in ``before`` (stamps, corrections), else by that of the last held stamp
    before it (the first held one for those before all); None when no stamp is held."""
    if before is None:
        return None
    before_stamps, corrections = before
    held = matching_stamp(before_stamps, np.asarray(stamps, dtype=float), tolerance)
    matched = np.flatnonzero(held >= 0)
    if len(matched) == 0:
        return None
    nearest = np.searchsorted(matched, np.arange(len(held)), side="right") - 1
    return se2.compose(corrections[held[matched[np.maximum(nearest, 0)]]], poses)
