"""Range-bearing sensor model in Cartesian form (paper eq. 11-17, docs/METHOD.md section 3).

A feature measured at range ``r`` and bearing ``beta`` from the robot centre becomes the
Cartesian observation ``z = (r cos beta, r sin beta)`` with covariance
``Sigma_z = R(beta) diag(s_r^2, r^2 s_beta^2) R(beta)^T`` (the transpose is right; the
paper's eq. 14 drops it). The prediction is ``h(x, l) = R(phi)^T (l - t)``.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

Array = NDArray[np.float64]

# The covariance ``diag(s_r^2, r^2 s_beta^2)`` is singular at r = 0; the tangential sigma is
# kept at least this fraction of the range sigma so that Sigma_z stays positive definite.
MIN_TANGENTIAL_RATIO = 1e-6


def polar_to_cartesian(
    ranges: ArrayLike,
    bearings: ArrayLike,
    sigma_range: ArrayLike,
    sigma_bearing: ArrayLike,
) -> tuple[Array, Array]:
    """Cartesian observations ``(K, 2)`` and their covariances ``(K, 2, 2)``.

    Raises ``ValueError`` naming the first offending observation for non-finite input, a
    negative range or a non-positive sigma.
    """
    r, b, sr, sb = np.broadcast_arrays(
        *(
            np.atleast_1d(np.asarray(a, dtype=float))
            for a in (ranges, bearings, sigma_range, sigma_bearing)
        )
    )
    for name, arr in (("range", r), ("bearing", b), ("sigma_range", sr), ("sigma_bearing", sb)):
        bad = np.flatnonzero(~np.isfinite(arr))
        if bad.size:
            raise ValueError(f"observation {bad[0]}: {name} is not finite ({arr[bad[0]]})")
    bad = np.flatnonzero(r < 0)
    if bad.size:
        raise ValueError(f"observation {bad[0]}: negative range {r[bad[0]]}")
    for name, arr in (("sigma_range", sr), ("sigma_bearing", sb)):
        bad = np.flatnonzero(arr <= 0)
        if bad.size:
            raise ValueError(f"observation {bad[0]}: {name} must be positive, got {arr[bad[0]]}")
    c, s = np.cos(b), np.sin(b)
    z = np.stack([r * c, r * s], axis=-1)
    radial = sr**2
    tangential = np.maximum(r * sb, MIN_TANGENTIAL_RATIO * sr) ** 2
    cov = np.empty(r.shape + (2, 2))
    cov[..., 0, 0] = c * c * radial + s * s * tangential
    cov[..., 1, 1] = s * s * radial + c * c * tangential
    cov[..., 0, 1] = cov[..., 1, 0] = c * s * (radial - tangential)
    return z, cov


def predict(poses: ArrayLike, points: ArrayLike) -> Array:
    """``h(x, l) = R(phi)^T (l - t)``: points in the body frames of the poses, ``(K, 2)``."""
    x = np.asarray(poses, dtype=float)
    p = np.asarray(points, dtype=float)
    c, s = np.cos(x[..., 2]), np.sin(x[..., 2])
    dx = p[..., 0] - x[..., 0]
    dy = p[..., 1] - x[..., 1]
    return np.stack([c * dx + s * dy, -s * dx + c * dy], axis=-1)


def predict_jacobians(poses: ArrayLike, points: ArrayLike) -> tuple[Array, Array, Array]:
    """``h`` with ``dh/dx`` ``(K, 2, 3)`` and ``dh/dl`` ``(K, 2, 2)``.

    ``dh/dt = -R^T``, ``dh/dphi = (h_y, -h_x)``, ``dh/dl = R^T``.
    """
    x = np.asarray(poses, dtype=float)
    h = predict(x, points)
    c, s = np.cos(x[..., 2]), np.sin(x[..., 2])
    shape = h.shape[:-1]
    d_pose = np.zeros(shape + (2, 3))
    d_point = np.zeros(shape + (2, 2))
    d_pose[..., 0, 0], d_pose[..., 0, 1], d_pose[..., 0, 2] = -c, -s, h[..., 1]
    d_pose[..., 1, 0], d_pose[..., 1, 1], d_pose[..., 1, 2] = s, -c, -h[..., 0]
    d_point[..., 0, 0], d_point[..., 0, 1] = c, s
    d_point[..., 1, 0], d_point[..., 1, 1] = -s, c
    return h, d_pose, d_point


def cartesian_to_polar(points_in_body: ArrayLike) -> tuple[Array, Array]:
    """Range and bearing of body-frame points (for simulation and gating)."""
    p = np.asarray(points_in_body, dtype=float)
    return np.hypot(p[..., 0], p[..., 1]), np.arctan2(p[..., 1], p[..., 0])
