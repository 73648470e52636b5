"""A single-robot 2D landmark SLAM file as a measurement log (``csam import slam2d``).

A file read by :func:`csam_ros.datasets.slam2d.read_slam2d` holds relative poses and Cartesian
landmark observations with covariances; a :class:`~csam_ros.core.log.MultiRobotLog` holds what
a robot measures: odometry inputs ``u = (v, v_lat, omega)`` with independent sigmas and
range-bearing observations with independent sigmas. The conversion:

- Poses. The pose ids (of every record, vertices included) sorted ascending must form one
  chain: exactly one odometry edge ``(p_k, p_{k+1})`` between each pair of consecutive ids
  and no other edge. A loop closure (an edge between non-consecutive poses), a backward or
  repeated edge, or a missing link raises :class:`Slam2dFormatError` naming the line or the
  pose ids. Pose ``p_k`` gets the stamp ``k * sample_time``; the first odometry sample (stamp
  0) only marks the start (its input is zero, its sigmas those of the first step).
- Odometry. The relative pose ``z = (dx, dy, dtheta)`` of edge ``k`` becomes the input ``u``
  of sample ``k + 1`` with ``U(u, T) = z`` exactly (:func:`csam_ros.core.motion.increment`,
  ``T = sample_time``): ``omega = dtheta / T`` and ``(v, v_lat)`` from the 2x2 system
  ``T [[a, -b], [b, a]] (v, v_lat) = (dx, dy)`` with ``a = sin(theta)/theta``,
  ``b = (1 - cos(theta))/theta`` evaluated as in ``motion`` (no division by a small theta).
  ``dtheta`` is first wrapped to (-pi, pi] (the factor's angle error is wrapped, so nothing
  changes), which keeps ``a^2 + b^2 >= 4/pi^2``: the system is always well conditioned.
- Odometry covariance. ``Lambda`` of ``z`` maps to the input covariance
  ``Q = G^-1 Lambda G^-T`` (``G = dU/du`` at ``u``), so ``G Q G^T = Lambda`` exactly. The
  log carries only ``sigma = sqrt(diag(Q))``: *the correlations of Q are dropped* (the local
  map then uses ``G diag(sigma^2) G^T``, not ``Lambda``).
- Landmarks. An observation ``d = (dx, dy)`` in the pose frame becomes the range ``|d|`` and
  bearing ``atan2(dy, dx)``, stamped at its pose, labelled with the landmark id. Its
  covariance maps with the polar Jacobian ``J = d(r, beta)/d(dx, dy)`` to ``J C J^T``; the log
  carries ``sqrt(diag(J C J^T))``: *the range-bearing correlation is dropped* (none for an
  isotropic ``C``). An observation closer than ``min_range`` has no bearing and is dropped
  and counted (:class:`Slam2dImport`, and a logged warning).
- Dropped from the file: vertex values (initial estimates only) and landmark vertices never
  observed. There is no ground truth (``truth = None``).

So a file whose covariances are exactly of the form ``G diag(q^2) G^T`` and
``R(beta) diag(s_r^2, r^2 s_beta^2) R(beta)^T`` gives a local map equal to the file's own
optimum (to 1e-7 in the tests); otherwise the two differ by the effect of the dropped
correlations. Measured on simulated 40-pose runs (``test/core/test_slam2d_log.py``, 20 seeds):
a covariance diagonal in the pose frame for odometry moves the landmarks by at most 0.3 of
their largest sigma (median 0.07); an anisotropic Cartesian observation covariance whose axes
are not radial (``diag(0.03^2, 0.01^2)`` in the robot frame) by up to 1.6 sigma (median 0.8),
since the range-bearing model can only express covariances with radial and tangential axes.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from csam_ros.core import se2
from csam_ros.core.log import FeatureLog, MultiRobotLog, OdometryLog, RobotLog, empty_rendezvous
from csam_ros.core.motion import increment_and_jacobian
from csam_ros.datasets.slam2d import Slam2dData, Slam2dFormatError, read_slam2d

Array = NDArray[np.float64]

MIN_RANGE = 1e-9  # m: an observation this close to the robot centre has no bearing

_ODOMETRY_RECORDS = ("ODOMETRY", "EDGE_SE2")
_OBSERVATION_RECORDS = ("LANDMARK", "EDGE_SE2_XY")

_log = logging.getLogger(__name__)


@dataclass
class Slam2dImport:
    """A converted file: the log and what the conversion left out."""

    log: MultiRobotLog
    poses: int  # odometry samples = poses of the chain
    observations: int  # range-bearing observations kept
    dropped_too_close: int  # observations closer than min_range (no bearing)

    def __str__(self) -> str:
        text = f"{self.poses} poses, {self.observations} landmark observations"
        if self.dropped_too_close:
            text += f", {self.dropped_too_close} dropped (closer than the minimum range)"
        return text


def inputs_from_relative_poses(relative_poses: ArrayLike, dt: float) -> Array:
    """Inputs ``u (K, 3)`` of the motion model with ``increment(u, dt) == z`` (angle wrapped)."""
    z = np.asarray(relative_poses, dtype=float).reshape(-1, 3)
    omega = se2.wrap_angle(z[:, 2]) / dt
    # G's translation block (T a, T b) does not depend on (v, v_lat): evaluate it at zero speed
    _, g = increment_and_jacobian(
        np.stack([0 * omega, 0 * omega, omega], axis=1), np.full_like(omega, dt)
    )
    ta, tb = g[:, 0, 0], g[:, 1, 0]
    norm = ta * ta + tb * tb
    v = (ta * z[:, 0] + tb * z[:, 1]) / norm
    v_lat = (ta * z[:, 1] - tb * z[:, 0]) / norm
    return np.stack([v, v_lat, omega], axis=1)


def input_covariances(inputs: ArrayLike, dt: float, covariances: ArrayLike) -> Array:
    """``Q = G^-1 Lambda G^-T`` ``(K, 3, 3)``: the input covariance giving ``Lambda`` exactly."""
    u = np.asarray(inputs, dtype=float).reshape(-1, 3)
    lam = np.asarray(covariances, dtype=float).reshape(-1, 3, 3)
    _, g = increment_and_jacobian(u, np.full(len(u), dt))
    left = np.linalg.solve(g, lam)  # G^-1 Lambda
    q = np.linalg.solve(g, left.transpose(0, 2, 1))  # G^-1 Lambda G^-T (Lambda symmetric)
    return 0.5 * (q + q.transpose(0, 2, 1))


def polar_observations(
    points: ArrayLike, covariances: ArrayLike
) -> tuple[Array, Array, Array, Array]:
    """Range, bearing and their sigmas ``sqrt(diag(J C J^T))`` of Cartesian observations.

    The range-bearing correlation is dropped. Callers remove points at the origin first.
    """
    d = np.asarray(points, dtype=float).reshape(-1, 2)
    cov = np.asarray(covariances, dtype=float).reshape(-1, 2, 2)
    r = np.hypot(d[:, 0], d[:, 1])
    beta = np.arctan2(d[:, 1], d[:, 0])
    c, s = np.cos(beta), np.sin(beta)
    cxx, cxy, cyy = cov[:, 0, 0], cov[:, 0, 1], cov[:, 1, 1]
    var_radial = c * c * cxx + 2.0 * c * s * cxy + s * s * cyy
    var_tangential = s * s * cxx - 2.0 * c * s * cxy + c * c * cyy
    return r, beta, np.sqrt(var_radial), np.sqrt(var_tangential) / r


def _odometry_line(path: Path, edge: int, records: tuple[str, ...] = _ODOMETRY_RECORDS) -> str:
    """``path:line`` of the ``edge``-th odometry record (0-based) of the file (or of the
    ``records`` given)."""
    count = -1
    with path.open(errors="replace") as handle:
        for number, raw in enumerate(handle, start=1):
            tokens = raw.split("#", 1)[0].split()
            if tokens and tokens[0] in records:
                count += 1
                if count == edge:
                    return f"{path}:{number}"
    return str(path)


def _chain(data: Slam2dData, path: Path) -> tuple[Array, Array, Array]:
    """Relative poses and covariances of the chain, in the order of the sorted pose ids, and
    the index of each one's record among the file's odometry records."""
    pose_ids = data.pose_ids
    if len(pose_ids) == 0:
        raise Slam2dFormatError(f"{path}: no poses")
    if len(pose_ids) == 1:
        raise Slam2dFormatError(
            f"{path}: no odometry record ({' or '.join(_ODOMETRY_RECORDS)}): a robot's log "
            f"needs at least two poses joined by odometry, the file has only pose {pose_ids[0]}"
        )
    position = {int(p): k for k, p in enumerate(pose_ids)}
    first = np.array([position[int(a)] for a in data.odometry_first], dtype=np.int64)
    second = np.array([position[int(b)] for b in data.odometry_second], dtype=np.int64)
    link = np.full(len(pose_ids) - 1, -1, dtype=np.int64)  # edge of each consecutive pair
    for e, (a, b) in enumerate(zip(first, second, strict=True)):
        ids = f"{pose_ids[a]} -> {pose_ids[b]}"
        if b != a + 1:
            if a == b + 1:
                reason = "runs backwards (the chain goes from lower to higher pose ids)"
            else:
                reason = (
                    "is not between consecutive poses (a loop closure?); only a single odometry "
                    "chain can be imported"
                )
            raise Slam2dFormatError(f"{_odometry_line(path, e)}: odometry {ids} {reason}")
        if link[a] >= 0:
            raise Slam2dFormatError(
                f"{_odometry_line(path, e)}: second odometry edge {ids} (the first is at "
                f"{_odometry_line(path, int(link[a]))})"
            )
        link[a] = e
    missing = np.flatnonzero(link < 0)
    if missing.size:
        k = int(missing[0])
        raise Slam2dFormatError(
            f"{path}: no odometry from pose {pose_ids[k]} to pose {pose_ids[k + 1]}: the poses "
            "do not form one chain"
        )
    return data.odometry[link], data.odometry_covariance[link], link


def _check_usable(
    values: Array, sigmas: Array, path: Path, rows: Array, records: tuple[str, ...]
) -> None:
    """Raise naming the first record whose converted values are not finite or whose sigmas
    are not positive (a number beyond floating point range, e.g. ``dx = 1e308``); ``rows``
    gives each one's index among the file's ``records``."""
    bad = ~np.isfinite(values).all(axis=1) | ~(sigmas > 0).all(axis=1)
    if bad.any():
        k = int(np.flatnonzero(bad)[0])
        raise Slam2dFormatError(
            f"{_odometry_line(path, int(rows[k]), records)}: the record converts to a "
            "non-finite value or a zero sigma in the robot's log (a number beyond floating "
            "point range)"
        )


def convert_slam2d(
    data: Slam2dData,
    robot: str = "robot1",
    sample_time: float = 1.0,
    min_range: float = MIN_RANGE,
) -> Slam2dImport:
    """The log of a file's contents (see the module docstring for the approximations)."""
    path = Path(data.source)
    if not (np.isfinite(sample_time) and sample_time > 0):
        raise ValueError(f"sample_time must be a positive number of seconds, got {sample_time}")
    relative, covariance, link = _chain(data, path)
    count = len(relative) + 1
    stamps = np.arange(count) * float(sample_time)
    inputs = inputs_from_relative_poses(relative, sample_time)
    q = input_covariances(inputs, sample_time, covariance)
    sigmas = np.sqrt(np.diagonal(q, axis1=1, axis2=2))
    _check_usable(np.concatenate([inputs, sigmas], axis=1), sigmas, path, link, _ODOMETRY_RECORDS)
    first_sigma = sigmas[:1] if len(sigmas) else np.ones((1, 3))
    odometry = OdometryLog(
        stamps, np.concatenate([np.zeros((1, 3)), inputs]), np.concatenate([first_sigma, sigmas])
    )

    position = {int(p): k for k, p in enumerate(data.pose_ids)}
    pose_index = np.array([position[int(p)] for p in data.observation_pose], dtype=np.int64)
    keep = np.hypot(data.observations[:, 0], data.observations[:, 1]) >= min_range
    dropped = int((~keep).sum())
    if dropped:
        _log.warning(
            "%s: %d landmark observation(s) closer than %g m to the robot dropped (no bearing)",
            path,
            dropped,
            min_range,
        )
    order = np.flatnonzero(keep)[np.argsort(pose_index[keep], kind="stable")]
    r, beta, sigma_r, sigma_b = polar_observations(
        data.observations[order], data.observation_covariance[order]
    )
    polar = np.stack([r, beta, sigma_r, sigma_b], axis=1)
    _check_usable(polar, polar[:, 2:], path, order, _OBSERVATION_RECORDS)
    features = FeatureLog(
        stamps[pose_index[order]],
        data.observation_landmark[order].astype(np.int64),
        r,
        beta,
        sigma_r,
        sigma_b,
    )
    log = MultiRobotLog({robot: RobotLog(robot, odometry, features, empty_rendezvous())})
    return Slam2dImport(log, count, len(order), dropped)


def read_slam2d_log(
    path: str | Path, robot: str = "robot1", sample_time: float = 1.0
) -> MultiRobotLog:
    """Read a text or g2o 2D SLAM file as the log of one robot ``robot``.

    Raises :class:`Slam2dFormatError` for a missing file, a malformed line, or poses that do
    not form a single odometry chain. Dropped observations are logged as a warning.
    """
    path = Path(path)
    if not path.is_file():
        raise Slam2dFormatError(f"{path}: no such file")
    return convert_slam2d(read_slam2d(path), robot, sample_time).log
