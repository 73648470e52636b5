"""Hypothesis strategies and comparisons shared by the property-based tests.

test/conftest.py puts this folder on ``sys.path`` (import as ``strategies``) and loads the
fixed hypothesis profile the properties run under.
"""

from __future__ import annotations

import numpy as np
from hypothesis import strategies as st
from numpy.typing import ArrayLike, NDArray

from csam_ros.core.model import se2

Array = NDArray[np.float64]


def coordinates(bound: float = 10.0) -> st.SearchStrategy[float]:
    """A finite coordinate in ``[-bound, bound]``."""
    return st.floats(-bound, bound, allow_nan=False, allow_infinity=False)


def angles() -> st.SearchStrategy[float]:
    """A heading in ``[-pi, pi]``, both ends included (-pi and pi are the same heading)."""
    return st.floats(-np.pi, np.pi, allow_nan=False, allow_infinity=False)


def poses(bound: float = 10.0) -> st.SearchStrategy[Array]:
    """One pose ``(x, y, phi)``."""
    return st.tuples(coordinates(bound), coordinates(bound), angles()).map(np.array)


def points(bound: float = 10.0) -> st.SearchStrategy[Array]:
    """One point ``(x, y)``."""
    return st.tuples(coordinates(bound), coordinates(bound)).map(np.array)


def covariances(dim: int) -> st.SearchStrategy[Array]:
    """A symmetric positive definite ``(dim, dim)`` matrix, condition number below about 1e3."""
    entries = st.lists(coordinates(1.0), min_size=dim * dim, max_size=dim * dim)
    return entries.map(lambda m: _spd(np.reshape(m, (dim, dim))))


def _spd(m: Array) -> Array:
    return m @ m.T + 0.01 * np.eye(len(m))


def batches(item: st.SearchStrategy[Array], size: int) -> st.SearchStrategy[Array]:
    """``size`` items stacked into one array ``(size, ...)``."""
    return st.lists(item, min_size=size, max_size=size).map(np.array)


def assert_poses_close(actual: ArrayLike, expected: ArrayLike, atol: float = 1e-9) -> None:
    """Poses equal up to ``atol``, headings compared modulo 2 pi."""
    a = np.asarray(actual, dtype=float)
    b = np.asarray(expected, dtype=float)
    np.testing.assert_allclose(a[..., :2], b[..., :2], atol=atol)
    np.testing.assert_allclose(se2.wrap_angle(a[..., 2] - b[..., 2]), 0.0, atol=atol)
