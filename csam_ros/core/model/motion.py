"""Motion model: constant turn with lateral slip (paper eq. 4-10, docs/METHOD.md section 2).

Input ``u = (v, v_lat, omega)`` held constant over ``T``::

    U(u, T) = ( v/w sin(wT) - v_lat/w (1 - cos(wT)),
                v/w (1 - cos(wT)) + v_lat/w sin(wT),
                wT )

written as ``U = (T a v - T b v_lat, T b v + T a v_lat, wT)`` with ``theta = wT``,
``a = sin(theta)/theta`` and ``b = (1 - cos(theta))/theta``. Both are evaluated without any
division by a small ``omega``: ``a`` through ``np.sinc`` and ``b = (theta/2) sinc(theta/2)^2``;
their derivatives use the exact quotient for ``|theta| >= 1e-2`` and a Taylor series (error
below ``1e-20``) below. (A threshold of 1e-4 as in the paper would lose about four digits in
the derivative ``(theta cos theta - sin theta)/theta^2`` by cancellation.) ``omega = 0`` is
exact.

Noise ``w ~ N(0, diag(s_v^2, s_vlat^2, s_w^2))`` gives the step covariance ``G Q G^T`` with
``G = dU/du``, in the frame of the pose at the start of the step.

Odometry sampled faster than key poses are wanted (MR.CLAM: about 67 Hz) is composed with
``(+)`` between key poses, and the covariance propagated with the Jacobians of ``(+)``
(:func:`odometry_between`). A sample interval that contains a key stamp is split there;
constant input makes the split exact for the mean. The input noise of a split sample is
treated as white over the sample: a piece of duration ``dt`` of a sample of duration ``T``
gets input covariance ``Q T / dt``, so the pieces compose to the unsplit step's covariance
(exactly for the heading, to first order for the translation) wherever the split falls.

Residual convention of the resulting factors: ``between(x_a, x_b) - z`` in the frame of
``x_a`` (see :class:`csam_ros.core.sam.factors.RelativePose`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from csam_ros.core.model import se2
from csam_ros.core.model.log import covariances_from_correlations

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]

SERIES_THRESHOLD = 1e-2


def _coefficients(theta: Array) -> tuple[Array, Array, Array, Array]:
    """``a, b`` and their derivatives ``da/dtheta, db/dtheta`` (no division by small theta)."""
    a = np.sinc(theta / np.pi)
    half = np.sinc(theta / (2.0 * np.pi))
    b = 0.5 * theta * half * half
    small = np.abs(theta) < SERIES_THRESHOLD
    t = np.where(small, 1.0, theta)  # safe divisor where the exact form is used
    t2 = theta * theta
    da_exact = (theta * np.cos(theta) - np.sin(theta)) / (t * t)
    db_exact = (theta * np.sin(theta) - 2.0 * np.sin(0.5 * theta) ** 2) / (t * t)
    da_series = theta * (-1.0 / 3.0 + t2 * (1.0 / 30.0 - t2 * (1.0 / 840.0 - t2 / 45360.0)))
    db_series = 0.5 + t2 * (-1.0 / 8.0 + t2 * (1.0 / 144.0 - t2 * (1.0 / 5760.0)))
    return a, b, np.where(small, da_series, da_exact), np.where(small, db_series, db_exact)


def increment(inputs: ArrayLike, dt: ArrayLike) -> Array:
    """``U(u, T)`` for inputs ``(K, 3)`` and durations ``(K,)``: relative poses ``(K, 3)``."""
    return increment_and_jacobian(inputs, dt)[0]


def increment_one(v: float, v_lat: float, omega: float, T: float) -> tuple[float, float, float]:
    """``U(u, T)`` of one input in scalar arithmetic, as :func:`increment` (to rounding): what
    dead reckoning sample by sample calls, some fifty times faster than a row of
    :func:`increment`. Neither ``a = sin(theta)/theta`` nor ``b = 2 sin(theta/2)^2/theta``
    cancels for a small ``theta``."""
    theta = omega * T
    if theta == 0.0:
        a, b = 1.0, 0.0
    else:
        a, b = math.sin(theta) / theta, 2.0 * math.sin(0.5 * theta) ** 2 / theta
    return T * (a * v - b * v_lat), T * (b * v + a * v_lat), theta


def increment_and_jacobian(inputs: ArrayLike, dt: ArrayLike) -> tuple[Array, Array]:
    """``U(u, T)`` ``(K, 3)`` and ``G = dU/du`` ``(K, 3, 3)``."""
    u = np.asarray(inputs, dtype=float)
    T = np.asarray(dt, dtype=float)
    v, vl, w = u[..., 0], u[..., 1], u[..., 2]
    theta = w * T
    a, b, da, db = _coefficients(theta)
    U = np.stack([T * (a * v - b * vl), T * (b * v + a * vl), theta], axis=-1)
    G = np.zeros(U.shape + (3,))
    G[..., 0, 0] = T * a
    G[..., 0, 1] = -T * b
    G[..., 1, 0] = T * b
    G[..., 1, 1] = T * a
    # d/domega = T * d/dtheta
    G[..., 0, 2] = T * T * (da * v - db * vl)
    G[..., 1, 2] = T * T * (db * v + da * vl)
    G[..., 2, 2] = T
    return U, G


def step_covariance(inputs: ArrayLike, dt: ArrayLike, sigmas: ArrayLike) -> tuple[Array, Array]:
    """``U`` and its covariance ``G Q G^T`` with ``Q = diag(sigmas^2)``."""
    U, G = increment_and_jacobian(inputs, dt)
    q = np.asarray(sigmas, dtype=float) ** 2
    return U, np.einsum("kij,kj,klj->kil", G, q, G)


def compose_segments(
    increments: ArrayLike, covariances: ArrayLike, segment_starts: ArrayLike
) -> tuple[Array, Array]:
    """Compose consecutive increments with ``(+)`` within segments, propagating covariance.

    ``segment_starts`` (sorted, first 0) are the indices where segments begin. Returns the
    composed relative pose ``(M, 3)`` and covariance ``(M, 3, 3)`` of each segment, from the
    first increment's start frame. Vectorised by cumulative sums over all increments.
    """
    cov = np.asarray(covariances, dtype=float)
    starts = np.asarray(segment_starts, dtype=np.int64)
    total, J = segment_jacobians(increments, starts)
    return total, _propagated(J, cov, starts)


def _propagated(J: Array, cov: Array, starts: Array) -> Array:
    """Each segment's covariance ``sum J_k cov_k J_k^T`` over its pieces, symmetrised."""
    contrib = np.matmul(np.matmul(J, cov), J.transpose(0, 2, 1))
    summed = np.add.reduceat(contrib.reshape(len(J), 9), starts, axis=0).reshape(-1, 3, 3)
    return 0.5 * (summed + summed.transpose(0, 2, 1))


@dataclass
class OdometryFactors:
    """Relative motion between consecutive key stamps, ready for ``RelativePose``."""

    key_stamps: Array  # (M,)
    relative_poses: Array  # (M-1, 3) pose of key m+1 in the frame of key m
    covariances: Array  # (M-1, 3, 3) in the frame of key m


def check_odometry(stamps: ArrayLike, inputs: ArrayLike, sigmas: ArrayLike) -> None:
    """Raise ``ValueError`` naming the first bad odometry sample."""
    t = np.asarray(stamps, dtype=float)
    u = np.asarray(inputs, dtype=float)
    q = np.asarray(sigmas, dtype=float)
    if t.ndim != 1 or u.shape != (len(t), 3) or q.shape != (len(t), 3):
        raise ValueError(
            f"odometry: stamps (N,), inputs (N, 3), sigmas (N, 3) expected, got {t.shape}, "
            f"{u.shape}, {q.shape}"
        )
    if (
        np.isfinite(t).all()
        and np.isfinite(u).all()
        and np.isfinite(q).all()
        and (q >= 0).all()
        and (t[1:] > t[:-1]).all()
    ):
        return  # valid: a few array operations (called once per odometry message online)
    for name, arr in (("stamp", t), ("input", u), ("sigma", q)):
        bad = np.flatnonzero(~np.isfinite(arr.reshape(len(t), -1)).all(axis=1))
        if bad.size:
            raise ValueError(f"odometry sample {bad[0]}: {name} is not finite")
    bad = np.flatnonzero(np.diff(t) <= 0)
    if bad.size:
        raise ValueError(
            f"odometry sample {bad[0] + 1}: stamps must increase strictly "
            f"({t[bad[0]]} then {t[bad[0] + 1]})"
        )
    bad = np.flatnonzero((q < 0).any(axis=1))
    if bad.size:
        raise ValueError(f"odometry sample {bad[0]}: negative sigma {q[bad[0]].tolist()}")


def odometry_between(
    stamps: ArrayLike,
    inputs: ArrayLike,
    sigmas: ArrayLike,
    key_stamps: ArrayLike,
    check: bool = True,
    correlations: ArrayLike | None = None,
) -> OdometryFactors:
    """Compose odometry samples into relative poses between consecutive ``key_stamps``.

    Sample ``i`` holds the input over ``(stamps[i-1], stamps[i]]`` (the first sample only
    marks the start). ``key_stamps`` must be strictly increasing and within
    ``[stamps[0], stamps[-1]]``; sample intervals are split at key stamps that fall inside.
    ``correlations`` ``(N, 3)``, if given, correlate each sample's input noise
    (:func:`csam_ros.core.model.log.covariances_from_correlations`; none: independent).
    """
    t = np.asarray(stamps, dtype=float)
    u = np.asarray(inputs, dtype=float)
    q = np.asarray(sigmas, dtype=float)
    keys = np.asarray(key_stamps, dtype=float)
    if check:
        check_odometry(t, u, q)
    _check_keys(t, keys)
    if len(keys) == 1:
        return OdometryFactors(keys, np.zeros((0, 3)), np.zeros((0, 3, 3)))
    U, G, cov, sample, starts = _pieces(t, u, q, keys, correlations)
    rel, rel_cov = compose_segments(U, cov, starts)
    return OdometryFactors(keys, rel, rel_cov)


def _check_keys(t: Array, keys: Array) -> None:
    """ValueError unless ``keys`` increase strictly within the odometry span ``t``."""
    if keys.ndim != 1 or len(keys) == 0:
        raise ValueError("key_stamps must be a non-empty one-dimensional array")
    bad = np.flatnonzero(np.diff(keys) <= 0)
    if bad.size:
        raise ValueError(f"key stamp {bad[0] + 1} ({keys[bad[0] + 1]}) does not increase")
    outside = np.flatnonzero((keys < t[0]) | (keys > t[-1]))
    if outside.size:
        raise ValueError(
            f"key stamp {keys[outside[0]]} lies outside the odometry span [{t[0]}, {t[-1]}]"
        )


def _pieces(
    t: Array, u: Array, q: Array, keys: Array, correlations: ArrayLike | None
) -> tuple[Array, Array, Array, IntArray, IntArray]:
    """The odometry between ``keys`` cut into pieces at sample and key stamps: each piece's
    increment ``U``, its Jacobian ``G = dU/du``, its covariance, the sample it comes from,
    and where each key interval's pieces start."""
    lo = np.searchsorted(t, keys[0], side="right")  # first sample ending after keys[0]
    hi = np.searchsorted(t, keys[-1], side="left")  # last sample needed
    inner = t[lo:hi]
    bounds = np.union1d(inner, keys)
    piece_end = bounds[1:]
    piece_start = bounds[:-1]
    sample = np.searchsorted(t, piece_end, side="left")
    dt = piece_end - piece_start
    duration = t[sample] - t[sample - 1]
    U, G = increment_and_jacobian(u[sample], dt)
    if correlations is None:
        var = q[sample] ** 2 * (duration / dt)[:, None]
        cov = np.einsum("kij,kj,klj->kil", G, var, G)
    else:
        sigma = q[sample] * np.sqrt(duration / dt)[:, None]
        rho = np.asarray(correlations, dtype=float).reshape(-1, 3)[sample]
        cov = G @ covariances_from_correlations(sigma, rho) @ G.transpose(0, 2, 1)
    segment = np.searchsorted(keys, piece_end, side="left") - 1
    starts = np.flatnonzero(np.diff(np.concatenate([[-1], segment])))
    return U, G, cov, sample, starts


def dead_reckoning(relative_poses: ArrayLike, start: ArrayLike = (0.0, 0.0, 0.0)) -> Array:
    """Poses ``(M, 3)`` obtained by composing relative poses ``(M-1, 3)`` from ``start``."""
    rel = np.asarray(relative_poses, dtype=float)
    first = np.asarray(start, dtype=float)[None]
    if len(rel) == 0:
        return first.copy()
    inc = np.concatenate([first, rel])
    heading_after = np.cumsum(inc[:, 2])
    heading_before = heading_after - inc[:, 2]
    c, s = np.cos(heading_before), np.sin(heading_before)
    px = np.cumsum(c * inc[:, 0] - s * inc[:, 1])
    py = np.cumsum(s * inc[:, 0] + c * inc[:, 1])
    return np.stack([px, py, se2.wrap_angle(heading_after)], axis=1)


def odometry_poses(
    stamps: ArrayLike, inputs: ArrayLike, start: ArrayLike = (0.0, 0.0, 0.0)
) -> Array:
    """Dead-reckoned poses ``(N, 3)`` at the odometry sample stamps from ``start``.

    Sample ``i`` holds its input over ``(stamps[i-1], stamps[i]]`` (the first only marks the
    start); the exact increments ``U(u, T)`` (eq. 4-10) are composed with ``(+)``.
    """
    t = np.asarray(stamps, dtype=float)
    u = np.asarray(inputs, dtype=float)
    return dead_reckoning(increment(u[1:], np.diff(t)), start)


def odometry_poses_at(
    stamps: ArrayLike, inputs: ArrayLike, poses: ArrayLike, query: ArrayLike
) -> Array:
    """Dead-reckoned poses ``(Q, 3)`` at ``query`` stamps inside ``[stamps[0], stamps[-1]]``:
    the pose of :func:`odometry_poses` at the last sample stamp before, moved on by the exact
    increment of the input active then."""
    t = np.asarray(stamps, dtype=float)
    u = np.asarray(inputs, dtype=float)
    p = np.asarray(poses, dtype=float)
    q = np.asarray(query, dtype=float)
    index = np.clip(np.searchsorted(t, q, side="right"), 1, len(t) - 1)
    before = index - 1
    return se2.compose(p[before], increment(u[index], q - t[before]))


# ---------------------------------------------------------------------------------------------
# odometry calibration (docs/METHOD.md, "Calibrating the odometry")


def calibrated_inputs(
    inputs: ArrayLike, calibration: ArrayLike, driving_speed: float
) -> tuple[Array, Array]:
    """True inputs ``(s v, s v_lat, k omega)`` ``(N, 3)`` of logged ``inputs`` under the
    calibration ``c = (s, k_d, k_s)``, with ``k = k_d`` where ``|v| > driving_speed`` else
    ``k_s``, and their derivatives ``du/dc`` ``(N, 3, 3)`` (linear in ``c``)."""
    u = np.asarray(inputs, dtype=float)
    s, k_driving, k_spot = np.asarray(calibration, dtype=float)
    driving = np.abs(u[:, 0]) > driving_speed
    scaled = np.stack(
        [s * u[:, 0], s * u[:, 1], np.where(driving, k_driving, k_spot) * u[:, 2]], axis=1
    )
    du_dc = np.zeros((len(u), 3, 3))
    du_dc[:, 0, 0] = u[:, 0]
    du_dc[:, 1, 0] = u[:, 1]
    du_dc[:, 2, 1] = np.where(driving, u[:, 2], 0.0)
    du_dc[:, 2, 2] = np.where(driving, 0.0, u[:, 2])
    return scaled, du_dc


def segment_jacobians(increments: ArrayLike, segment_starts: ArrayLike) -> tuple[Array, Array]:
    """The composed relative pose ``(M, 3)`` of each segment (as :func:`compose_segments`) and
    the Jacobian ``(K, 3, 3)`` of its segment's composition with respect to each increment."""
    inc = np.asarray(increments, dtype=float)
    starts = np.asarray(segment_starts, dtype=np.int64)
    count = len(inc)
    seg_len = np.diff(np.append(starts, count))
    heading_after = np.cumsum(inc[:, 2])
    heading_before = heading_after - inc[:, 2]
    theta = heading_before - np.repeat(heading_before[starts], seg_len)
    c, s = np.cos(theta), np.sin(theta)
    wx = c * inc[:, 0] - s * inc[:, 1]
    wy = s * inc[:, 0] + c * inc[:, 1]
    px, py = np.cumsum(wx), np.cumsum(wy)
    px -= np.repeat(px[starts] - wx[starts], seg_len)
    py -= np.repeat(py[starts] - wy[starts], seg_len)
    ends = np.append(starts[1:], count) - 1
    total = np.stack([px[ends], py[ends], heading_after[ends] - heading_before[starts]], axis=1)
    tx = np.repeat(total[:, 0], seg_len) - px
    ty = np.repeat(total[:, 1], seg_len) - py
    J = np.zeros((count, 3, 3))
    J[:, 0, 0], J[:, 0, 1], J[:, 0, 2] = c, -s, -ty
    J[:, 1, 0], J[:, 1, 1], J[:, 1, 2] = s, c, tx
    J[:, 2, 2] = 1.0
    return total, J


@dataclass
class CalibratedOdometryFactors(OdometryFactors):
    """:class:`OdometryFactors` composed at a calibration ``c0`` with ``dz/dc`` at ``c0``."""

    calibration: Array  # (3,) c0
    calibration_jacobians: Array  # (M-1, 3, 3) dz/dc


def calibrated_odometry_between(
    stamps: ArrayLike,
    inputs: ArrayLike,
    sigmas: ArrayLike,
    key_stamps: ArrayLike,
    calibration: ArrayLike,
    driving_speed: float,
    correlations: ArrayLike | None = None,
) -> CalibratedOdometryFactors:
    """:func:`odometry_between` of the inputs corrected by ``calibration`` ``(s, k_d, k_s)``
    (:func:`calibrated_inputs`; the input noise unchanged), with the Jacobian of each composed
    relative pose with respect to the calibration, by the chain rule through the pieces and
    the composition. ``key_stamps`` as for :func:`odometry_between` (checked there)."""
    t = np.asarray(stamps, dtype=float)
    keys = np.asarray(key_stamps, dtype=float)
    c0 = np.asarray(calibration, dtype=float).reshape(3)
    u, du_dc = calibrated_inputs(inputs, c0, driving_speed)
    _check_keys(t, keys)
    if len(keys) == 1:
        empty = np.zeros((0, 3, 3))
        return CalibratedOdometryFactors(keys, np.zeros((0, 3)), empty, c0, empty)
    q = np.asarray(sigmas, dtype=float)
    U, G, cov, sample, starts = _pieces(t, u, q, keys, correlations)
    rel, J = segment_jacobians(U, starts)
    per_piece = J @ G @ du_dc[sample]
    dz_dc = np.add.reduceat(per_piece.reshape(len(U), 9), starts, axis=0).reshape(-1, 3, 3)
    return CalibratedOdometryFactors(keys, rel, _propagated(J, cov, starts), c0, dz_dc)


def inputs_from_increments(increments: ArrayLike, dt: ArrayLike) -> Array:
    """The constant inputs ``u`` ``(K, 3)`` whose increments ``U(u, T)`` over durations ``dt``
    ``(K,)`` are ``increments`` ``(K, 3)``: the inverse of :func:`increment` for turns
    ``|dtheta| < 2 pi`` (a heading difference wrapped to (-pi, pi] always is).

    ``omega = dtheta / T``, and ``(v, v_lat)`` solve the chord's 2x2 system
    ``T [[a, -b], [b, a]] (v, v_lat) = (dx, dy)``, whose determinant
    ``T^2 (a^2 + b^2) = T^2 sinc(theta/2)^2`` vanishes only at full turns."""
    inc = np.asarray(increments, dtype=float)
    T = np.asarray(dt, dtype=float)
    theta = inc[..., 2]
    a, b, _, _ = _coefficients(theta)
    scale = T * (a * a + b * b)
    dx, dy = inc[..., 0], inc[..., 1]
    return np.stack([(a * dx + b * dy) / scale, (a * dy - b * dx) / scale, theta / T], axis=-1)


def inputs_from_poses(stamps: ArrayLike, poses: ArrayLike) -> Array:
    """The constant inputs ``(N-1, 3)`` between consecutive poses ``(N, 3)`` at ``stamps``
    ``(N,)`` (integrated odometry, as drivers publish it): sample ``i`` holds the input over
    ``(stamps[i-1], stamps[i]]``, as :func:`odometry_poses` takes it, so the two are inverse."""
    p = np.asarray(poses, dtype=float)
    return inputs_from_increments(se2.between(p[:-1], p[1:]), np.diff(np.asarray(stamps, float)))


def default_input_sigmas(
    inputs: ArrayLike, dt: ArrayLike, per_m: float, per_rad: float, floor: float
) -> Array:
    """Sigmas ``(K, 3)`` of odometry inputs ``(K, 3)`` over durations ``dt`` ``(K,)`` that
    came without any: the variance of the position grows by ``per_m**2`` per metre travelled
    and that of the heading by ``per_rad**2`` per radian turned, each by at least
    ``floor**2`` per second (at rest).

    A random walk in distance and turn, so that the covariance of a factor composed from
    many samples does not depend on how often the odometry was sampled; as input sigmas
    over the sample's ``T`` (the step's variance is ``sigma_u^2 T^2``)."""
    u = np.asarray(inputs, dtype=float).reshape(-1, 3)
    T = np.asarray(dt, dtype=float).reshape(-1)
    distance = np.hypot(u[:, 0], u[:, 1]) * T
    turn = np.abs(u[:, 2]) * T
    translation = np.sqrt(np.maximum(per_m * per_m * distance, floor * floor * T)) / T
    heading = np.sqrt(np.maximum(per_rad * per_rad * turn, floor * floor * T)) / T
    return np.stack([translation, translation, heading], axis=1)
