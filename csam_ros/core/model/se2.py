"""SE(2) compounding after Smith, Self & Cheeseman, vectorised over leading axes.

A pose is ``(x, y, phi)``; arrays of poses have shape ``(..., 3)``. Every function
broadcasts over the leading axes, so one call handles all factors of one kind; ``compose_one``
is :func:`compose` for one pair in scalar arithmetic (dead reckoning sample by sample).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

Array = NDArray[np.float64]


def wrap_angle(angle: ArrayLike) -> Array:
    """Wrap angles to (-pi, pi]."""
    a = np.asarray(angle, dtype=float)
    wrapped = np.mod(a + np.pi, 2.0 * np.pi) - np.pi
    return np.where(wrapped == -np.pi, np.pi, wrapped)


def rotation(phi: ArrayLike) -> Array:
    """Rotation matrices ``R(phi)`` of shape ``(..., 2, 2)``."""
    phi = np.asarray(phi, dtype=float)
    c, s = np.cos(phi), np.sin(phi)
    return np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)


def compose(a: ArrayLike, b: ArrayLike) -> Array:
    """``a (+) b``: pose ``b`` given in frame ``a``, expressed in ``a``'s parent frame."""
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    x = a[..., 0] + c * b[..., 0] - s * b[..., 1]
    y = a[..., 1] + s * b[..., 0] + c * b[..., 1]
    return np.stack([x, y, wrap_angle(a[..., 2] + b[..., 2])], -1)


def compose_one(
    a: tuple[float, float, float], b: tuple[float, float, float]
) -> tuple[float, float, float]:
    """:func:`compose` of one pair of poses in scalar arithmetic (to rounding)."""
    c, s = math.cos(a[2]), math.sin(a[2])
    heading = math.remainder(a[2] + b[2], 2.0 * math.pi)
    return (
        a[0] + c * b[0] - s * b[1],
        a[1] + s * b[0] + c * b[1],
        math.pi if heading == -math.pi else heading,
    )


def inverse(a: ArrayLike) -> Array:
    """``(-)a``: the parent frame expressed in frame ``a``."""
    a = np.asarray(a, dtype=float)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    x = -c * a[..., 0] - s * a[..., 1]
    y = s * a[..., 0] - c * a[..., 1]
    return np.stack([x, y, wrap_angle(-a[..., 2])], -1)


def between(a: ArrayLike, b: ArrayLike) -> Array:
    """``(-)a (+) b``: pose ``b`` expressed in frame ``a``."""
    return compose(inverse(a), b)


def transform_point(a: ArrayLike, p: ArrayLike) -> Array:
    """``a (+) p`` for a point ``p`` (shape ``(..., 2)``) given in frame ``a``."""
    a = np.asarray(a, dtype=float)
    p = np.asarray(p, dtype=float)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    return np.stack(
        [a[..., 0] + c * p[..., 0] - s * p[..., 1], a[..., 1] + s * p[..., 0] + c * p[..., 1]], -1
    )


def inverse_transform_point(a: ArrayLike, p: ArrayLike) -> Array:
    """``(-)a (+) p``: a point given in ``a``'s parent frame, expressed in frame ``a``."""
    a = np.asarray(a, dtype=float)
    p = np.asarray(p, dtype=float)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    dx = p[..., 0] - a[..., 0]
    dy = p[..., 1] - a[..., 1]
    return np.stack([c * dx + s * dy, -s * dx + c * dy], -1)


def compose_jacobians(a: ArrayLike, b: ArrayLike) -> tuple[Array, Array]:
    """Jacobians ``J1 = d(a (+) b)/da`` and ``J2 = d(a (+) b)/db``, each ``(..., 3, 3)``."""
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    shape = np.broadcast_shapes(a.shape, b.shape)[:-1]
    j1 = np.zeros(shape + (3, 3))
    j1[..., 0, 0] = 1.0
    j1[..., 1, 1] = 1.0
    j1[..., 2, 2] = 1.0
    j1[..., 0, 2] = -s * b[..., 0] - c * b[..., 1]
    j1[..., 1, 2] = c * b[..., 0] - s * b[..., 1]
    j2 = np.zeros(shape + (3, 3))
    j2[..., 0, 0] = c
    j2[..., 0, 1] = -s
    j2[..., 1, 0] = s
    j2[..., 1, 1] = c
    j2[..., 2, 2] = 1.0
    return j1, j2


def inverse_jacobian(a: ArrayLike) -> Array:
    """Jacobian ``d((-)a)/da``, shape ``(..., 3, 3)``."""
    a = np.asarray(a, dtype=float)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    x, y = a[..., 0], a[..., 1]
    j = np.zeros(a.shape[:-1] + (3, 3))
    j[..., 0, 0] = -c
    j[..., 0, 1] = -s
    j[..., 0, 2] = s * x - c * y
    j[..., 1, 0] = s
    j[..., 1, 1] = -c
    j[..., 1, 2] = c * x + s * y
    j[..., 2, 2] = -1.0
    return j
