"""Matching stamps: the nearest of a sorted array of stamps to each query stamp."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

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
