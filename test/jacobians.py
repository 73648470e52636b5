"""Central finite differences for the Jacobian checks of the tests.

test/conftest.py puts this folder on ``sys.path``, so a test imports it as ``jacobians``.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from csam_ros.core.model import se2

Array = NDArray[np.float64]
EPS = 1e-6


def numeric_jacobian(
    fun: Callable[[Array], ArrayLike],
    x: ArrayLike,
    eps: float = EPS,
    angles: Sequence[int] = (),
) -> Array:
    """Central differences of ``fun`` at ``x`` along the last axis of ``x``.

    ``x`` has shape ``(..., n)`` and ``fun(x)`` shape ``(..., m)`` with the same leading axes
    (or ``(...)``: one scalar per item); the result has shape ``(..., m, n)`` (``(..., n)``).
    The output components listed in ``angles`` are differenced modulo 2 pi, so that an angle
    that crosses pi between ``x - eps`` and ``x + eps`` does not jump by 2 pi.
    """
    x = np.asarray(x, dtype=float)
    wrap = list(angles)
    columns = []
    for j in range(x.shape[-1]):
        dx = np.zeros_like(x)
        dx[..., j] = eps
        diff = np.asarray(fun(x + dx), dtype=float) - np.asarray(fun(x - dx), dtype=float)
        if wrap:
            diff[..., wrap] = se2.wrap_angle(diff[..., wrap])
        columns.append(diff / (2.0 * eps))
    return np.stack(columns, axis=-1)


def numeric_block_jacobians(
    fun: Callable[[list[Array]], ArrayLike],
    blocks: Sequence[ArrayLike],
    eps: float = EPS,
    angles: Sequence[int] = (),
) -> list[Array]:
    """:func:`numeric_jacobian` of ``fun(blocks)`` with respect to each block in turn, the
    other blocks held at their values."""
    values = [np.asarray(b, dtype=float) for b in blocks]

    def varying(j: int) -> Callable[[Array], ArrayLike]:
        def partial(v: Array) -> ArrayLike:
            return fun([v if i == j else b for i, b in enumerate(values)])

        return partial

    return [numeric_jacobian(varying(j), b, eps, angles) for j, b in enumerate(values)]


def numeric_hessian(system: Any, x: ArrayLike, eps: float = 1e-5) -> Array:
    """Central differences of the gradient ``A^T r`` of normal equations ``system``
    (:class:`~csam_ros.core.sam.normal_equations.NormalEquations`) at ``x``: the cost's
    Hessian, columns by scalar."""

    def gradient(values: Array) -> Array:
        system.linearize(values)
        return system.gradient.copy()

    return numeric_jacobian(gradient, x, eps)
