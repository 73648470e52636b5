"""The covariance of Algorithm 1's state (rendezvous poses and base nodes) from the block
factor of its information matrix at the estimate (docs/METHOD.md sections 4.5 and 5).

:class:`FactoredStateCovariance` never forms the whole inverse to answer for blocks: the base
nodes' joint covariance is the inverse of the factor's last block alone (the base nodes are
eliminated last: :mod:`~csam_ros.core.sam.block_cholesky`); other entries come from solves
with the factor, one per wanted column; the blocks on the factor's pattern all at once from
its block selected inverse (:meth:`FactoredStateCovariance.selected_inverse`, which Algorithm 2
starts from, with the information matrix kept: docs/METHOD.md section 6.1). The whole matrix
(:meth:`FactoredStateCovariance.dense`) is formed only on request. :class:`DenseStateCovariance`
wraps a dense matrix (the dense oracle's)."""

from __future__ import annotations

from typing import Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from csam_ros.core.sam.block_cholesky import BlockFactor

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]


class StateCovariance(Protocol):
    """The covariance of a state of ``dim`` scalars, by blocks or whole."""

    @property
    def dim(self) -> int: ...

    def block(self, rows: ArrayLike, cols: ArrayLike) -> Array:
        """Covariance entries (len(rows), len(cols)) at scalar positions of the state."""
        ...

    def dense(self) -> Array:
        """The whole covariance (dim, dim)."""
        ...


class DenseStateCovariance:
    """A covariance held as a dense matrix."""

    def __init__(self, matrix: Array) -> None:
        self.matrix = np.asarray(matrix, dtype=float)

    @property
    def dim(self) -> int:
        return len(self.matrix)

    def block(self, rows: ArrayLike, cols: ArrayLike) -> Array:
        return self.matrix[np.ix_(np.asarray(rows, np.int64), np.asarray(cols, np.int64))]

    def dense(self) -> Array:
        return self.matrix


class FactoredStateCovariance:
    """The inverse of the matrix factored by a :class:`BlockFactor` whose last block holds the
    base nodes (module docstring)."""

    def __init__(self, factor: BlockFactor, information: Array | None = None) -> None:
        self.factor = factor
        self.information = information  # the factored matrix's CSC values, when kept
        self._last = factor.pattern.scalars[-1]
        self._last_inverse: Array | None = None
        self._selected: dict[tuple[int, int], Array] | None = None

    def selected_inverse(self) -> dict[tuple[int, int], Array]:
        """:meth:`BlockFactor.selected_inverse`, computed once."""
        if self._selected is None:
            self._selected = self.factor.selected_inverse()
        return self._selected

    @property
    def dim(self) -> int:
        return self.factor.pattern.n

    def block(self, rows: ArrayLike, cols: ArrayLike) -> Array:
        """Entries within the last block from its inverse; others by solves with the factor
        (one per column)."""
        rows = np.asarray(rows, dtype=np.int64)
        cols = np.asarray(cols, dtype=np.int64)
        n = self.dim
        where = np.full(n, -1, dtype=np.int64)
        where[self._last] = np.arange(len(self._last))
        if np.all(where[rows] >= 0) and np.all(where[cols] >= 0):
            if self._last_inverse is None:
                self._last_inverse = self.factor.last_block_inverse()
            return self._last_inverse[np.ix_(where[rows], where[cols])]
        unit = np.zeros((n, len(cols)))
        unit[cols, np.arange(len(cols))] = 1.0
        return self.factor.solve(unit)[rows]

    def dense(self) -> Array:
        return self.factor.dense_inverse()
