"""A single-robot 2D landmark SLAM file as a measurement log (``csam import slam2d``).

A file read by :func:`csam_ros.datasets.slam2d.read_slam2d` holds relative poses and Cartesian
landmark observations with covariances; a :class:`~csam_ros.core.model.log.MultiRobotLog` holds what
a robot measures: odometry inputs ``u = (v, v_lat, omega)`` with their covariance and
Cartesian feature observations with theirs. The conversion:

- Poses. The pose ids (of every record, vertices included) sorted ascending must form one
  chain: exactly one odometry edge ``(p_k, p_{k+1})`` between each pair of consecutive ids
  and no other edge. A loop closure (an edge between non-consecutive poses), a backward or
  repeated edge, or a missing link raises :class:`Slam2dFormatError` naming the line or the
  pose ids. Pose ``p_k`` gets the stamp ``k * sample_time``; the first odometry sample (stamp
  0) only marks the start (its input is zero, its sigmas those of the first step).
- Odometry. The relative pose ``z = (dx, dy, dtheta)`` of edge ``k`` becomes the input ``u``
  of sample ``k + 1`` with ``U(u, T) = z`` exactly (:func:`csam_ros.core.model.motion.increment`,
  ``T = sample_time``): ``omega = dtheta / T`` and ``(v, v_lat)`` from the 2x2 system
  ``T [[a, -b], [b, a]] (v, v_lat) = (dx, dy)`` with ``a = sin(theta)/theta``,
  ``b = (1 - cos(theta))/theta`` evaluated as in ``motion`` (no division by a small theta).
  ``dtheta`` is first wrapped to (-pi, pi] (the factor's angle error is wrapped, so nothing
  changes), which keeps ``a^2 + b^2 >= 4/pi^2``: the system is always well conditioned.
- Odometry covariance. ``Lambda`` of ``z`` maps to the input covariance
  ``Q = G^-1 Lambda G^-T`` (``G = dU/du`` at ``u``), so ``G Q G^T = Lambda`` exactly. The log
  carries ``Q`` whole: its sigmas ``sqrt(diag(Q))`` and the correlations of its pairs
  (:class:`~csam_ros.core.model.log.OdometryLog`; in a bag, the twist covariance's off-diagonal
  entries).
- Landmarks. An observation ``d = (dx, dy)`` in the pose frame stays a Cartesian observation
  (:class:`~csam_ros.core.model.log.FeaturePointLog`) with its full 2x2 covariance, stamped at its
  pose and labelled with the landmark id; in a bag it travels on ``/<robot>/feature_points``.
- Dropped from the file: vertex values (initial estimates only) and landmark vertices never
  observed. There is no ground truth (``truth = None``).

So a file's local map has the file's own objective: the same odometry factors (up to
rounding in ``G Q G^T``) and the same observation factors (``PointObservation``), and the map
is the file's optimum from the local map's start (to 1e-7 in the tests, for correlated
covariances of both kinds).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from csam_ros.core.model import se2
from csam_ros.core.model.log import (
    FeaturePointLog,
    MultiRobotLog,
    OdometryLog,
    RobotLog,
    correlations_from_covariances,
    correlations_valid,
    empty_features,
    empty_rendezvous,
)
from csam_ros.core.model.motion import increment_and_jacobian
from csam_ros.datasets.slam2d import Slam2dData, Slam2dFormatError, read_slam2d

Array = NDArray[np.float64]

_ODOMETRY_RECORDS = ("ODOMETRY", "EDGE_SE2")
_OBSERVATION_RECORDS = ("LANDMARK", "EDGE_SE2_XY")


@dataclass
class Slam2dImport:
    """A converted file: the log and its size."""

    log: MultiRobotLog
    poses: int  # odometry samples = poses of the chain
    observations: int  # Cartesian landmark observations

    def __str__(self) -> str:
        return f"{self.poses} poses, {self.observations} landmark observations"


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
    values: Array,
    sigmas: Array,
    correlations: Array,
    path: Path,
    rows: Array,
    records: tuple[str, ...],
) -> None:
    """Raise naming the first record whose converted values are not finite, whose sigmas are
    not positive or whose correlations give no positive definite covariance (a number beyond
    floating point range, e.g. ``dx = 1e308``, or a covariance singular in rounding); ``rows``
    gives each one's index among the file's ``records``."""
    bad = ~np.isfinite(values).all(axis=1) | ~(sigmas > 0).all(axis=1)
    bad |= ~correlations_valid(correlations)
    if bad.any():
        k = int(np.flatnonzero(bad)[0])
        raise Slam2dFormatError(
            f"{_odometry_line(path, int(rows[k]), records)}: the record converts to a "
            "non-finite value, a zero sigma or a singular covariance in the robot's log (a "
            "number beyond floating point range)"
        )


def convert_slam2d(
    data: Slam2dData, robot: str = "robot1", sample_time: float = 1.0
) -> Slam2dImport:
    """The log of a file's contents (see the module docstring)."""
    path = Path(data.source)
    if not (np.isfinite(sample_time) and sample_time > 0):
        raise ValueError(f"sample_time must be a positive number of seconds, got {sample_time}")
    relative, covariance, link = _chain(data, path)
    count = len(relative) + 1
    stamps = np.arange(count) * float(sample_time)
    inputs = inputs_from_relative_poses(relative, sample_time)
    sigmas, correlations = correlations_from_covariances(
        input_covariances(inputs, sample_time, covariance)
    )
    values = np.concatenate([inputs, sigmas, correlations], axis=1)
    _check_usable(values, sigmas, correlations, path, link, _ODOMETRY_RECORDS)
    first = np.ones((1, 3)) if count == 1 else sigmas[:1]
    odometry = OdometryLog(
        stamps,
        np.concatenate([np.zeros((1, 3)), inputs]),
        np.concatenate([first, sigmas]),
        np.concatenate([np.zeros((1, 3)), correlations]),
    )
    position = {int(p): k for k, p in enumerate(data.pose_ids)}
    pose_index = np.array([position[int(p)] for p in data.observation_pose], dtype=np.int64)
    order = np.argsort(pose_index, kind="stable")
    points = FeaturePointLog(
        stamps[pose_index[order]],
        data.observation_landmark[order].astype(np.int64),
        data.observations[order],
        data.observation_covariance[order],
    )
    robot_log = RobotLog(robot, odometry, empty_features(), empty_rendezvous(), points)
    return Slam2dImport(MultiRobotLog({robot: robot_log}), count, len(order))


def read_slam2d_log(
    path: str | Path, robot: str = "robot1", sample_time: float = 1.0
) -> MultiRobotLog:
    """Read a text or g2o 2D SLAM file as the log of one robot ``robot``.

    Raises :class:`Slam2dFormatError` for a missing file, a malformed line, or poses that do
    not form a single odometry chain.
    """
    path = Path(path)
    if not path.is_file():
        raise Slam2dFormatError(f"{path}: no such file")
    return convert_slam2d(read_slam2d(path), robot, sample_time).log
