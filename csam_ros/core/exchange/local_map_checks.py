"""Checks at the merger's boundary: local maps and rendezvous rows from the smoothers, before
any number of theirs is trusted. A refused map or row is counted under a reason of
:mod:`csam_ros.core.exchange.validation`, as bad sensor input is."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from csam_ros.core.exchange.validation import (
    NO_POSE_AT_STAMP,
    NOT_FINITE,
    SELF_OBSERVATION,
    UNKNOWN_ROBOT,
    DropCounter,
    range_bearing_mask,
)
from csam_ros.core.model.stamps import nearest_stamp
from csam_ros.core.sam.factors import ROBUST_KERNELS, singular_sqrt_information

# Largest magnitude accepted in a local map: coordinates in metres (or radians) and
# square-root information (1 / sigma; the gauge prior's is 1e6). Beyond them a map is
# nonsense, and squares of such numbers would swamp the joint solve.
MAX_COORDINATE = 1e9
MAX_SQRT_INFORMATION = 1e12


@dataclass(frozen=True)
class LocalMapArrays:
    """A local map's numbers as its message carries them, before any is trusted: N poses,
    F features, M odometry and K observation factors (square-root information row-major)."""

    stamps: NDArray[np.float64]  # (N,) s
    poses: NDArray[np.float64]  # (N, 3)
    pose_covariances: NDArray[np.float64]  # (0,) or (9 N,)
    feature_labels: NDArray[np.int64]  # (F,)
    feature_xy: NDArray[np.float64]  # (F, 2)
    feature_cov: NDArray[np.float64]  # (F, 3) xx, xy, yy
    prior_sqrt_information: NDArray[np.float64]  # (9,)
    odometry_ends: NDArray[np.int64]  # (M, 2) pose indices
    odometry_delta: NDArray[np.float64]  # (M, 3)
    odometry_sqrt_information: NDArray[np.float64]  # (M, 9)
    observation_pose: NDArray[np.int64]  # (K,)
    observation_label: NDArray[np.int64]  # (K,)
    observation_xy: NDArray[np.float64]  # (K, 2)
    observation_sqrt_information: NDArray[np.float64]  # (K, 4)
    robust_kernel: str
    robust_parameter: float
    cost: float
    # (0,) not estimated, or (6,): s, k_d, k_s and their sigmas (docs/METHOD.md 4.4.1)
    odometry_calibration: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))


def _number_fault(name: str, values: NDArray[np.float64], bound: float) -> str | None:
    flat = values.reshape(-1)
    bad = np.flatnonzero(~np.isfinite(flat) | (np.abs(flat) > bound))
    if len(bad) == 0:
        return None
    return (
        f"{name}: value {flat[bad[0]]!r} at {int(bad[0])} is not a finite number within {bound:g}"
    )


def _sqrt_information_fault(name: str, rows: NDArray[np.float64], size: int) -> str | None:
    """Each row must be a finite, bounded ``size`` x ``size`` matrix that the factors take
    as non-singular."""
    fault = _number_fault(name, rows, MAX_SQRT_INFORMATION)
    if fault is not None or len(rows) == 0:
        return fault
    singular = singular_sqrt_information(rows.reshape(-1, size, size))
    if len(singular):
        return f"{name} {int(singular[0])} has a singular square-root information"
    return None


def _index_fault(name: str, index: NDArray[np.int64], n: int) -> str | None:
    bad = np.flatnonzero((index < 0) | (index >= n))
    if len(bad) == 0:
        return None
    return f"{name} {int(bad[0])} names pose {int(index.reshape(-1)[bad[0]])} of {n}"


def _unreached_pose(n: int, ends: NDArray[np.int64]) -> int | None:
    """The first pose that odometry does not connect to pose 0, or None."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import breadth_first_order

    graph = coo_matrix((np.ones(len(ends)), (ends[:, 0], ends[:, 1])), shape=(n, n)).tocsr()
    reached = np.zeros(n, dtype=bool)
    reached[breadth_first_order(graph, 0, directed=False, return_predecessors=False)] = True
    missing = np.flatnonzero(~reached)
    return int(missing[0]) if len(missing) else None


def local_map_fault(m: LocalMapArrays) -> str | None:
    """What makes a local map unusable for C-SAM, in words (the first fault found), or None.

    Besides finite, bounded numbers and indices in range, the map must be solvable on its
    own: non-singular square-root information, every pose tied to the first by odometry and
    every feature observed, so that a map refused here is one the joint solve would choke on.
    """
    n = len(m.poses)
    if n == 0:
        return "no poses"
    if len(m.stamps) != n:
        return f"{n} poses with {len(m.stamps)} stamps"
    steps = np.diff(m.stamps)
    if np.any(~(steps > 0)):
        i = int(np.flatnonzero(~(steps > 0))[0]) + 1
        return f"pose stamps do not increase at pose {i} ({m.stamps[i - 1]!r}, {m.stamps[i]!r})"
    if len(m.pose_covariances) not in (0, 9 * n):
        return f"{len(m.pose_covariances)} pose covariance values for {n} poses"
    for name, values, bound in (
        ("pose stamps", m.stamps, np.inf),
        ("poses", m.poses, MAX_COORDINATE),
        ("pose covariances", m.pose_covariances, np.inf),
        ("features", m.feature_xy, MAX_COORDINATE),
        ("feature covariances", m.feature_cov, np.inf),
        ("odometry deltas", m.odometry_delta, MAX_COORDINATE),
        ("observations", m.observation_xy, MAX_COORDINATE),
    ):
        fault = _number_fault(name, values, bound)
        if fault is not None:
            return fault
    labels, counts = np.unique(m.feature_labels, return_counts=True)
    if np.any(counts > 1):
        return f"feature label {int(labels[counts > 1][0])} appears more than once"
    for fault in (
        _sqrt_information_fault("gauge prior", m.prior_sqrt_information.reshape(1, 9), 3),
        _sqrt_information_fault("odometry factor", m.odometry_sqrt_information, 3),
        _sqrt_information_fault("observation factor", m.observation_sqrt_information, 2),
        _index_fault("odometry factor", m.odometry_ends, n),
        _index_fault("observation factor", m.observation_pose, n),
    ):
        if fault is not None:
            return fault
    loops = np.flatnonzero(m.odometry_ends[:, 0] == m.odometry_ends[:, 1])
    if len(loops):
        i = int(loops[0])
        return f"odometry factor {i} joins pose {int(m.odometry_ends[i, 0])} to itself"
    unknown = np.flatnonzero(~np.isin(m.observation_label, m.feature_labels))
    if len(unknown):
        i = int(unknown[0])
        return f"observation factor {i} of unknown feature {int(m.observation_label[i])}"
    unseen = np.flatnonzero(~np.isin(m.feature_labels, m.observation_label))
    if len(unseen):
        return f"feature {int(m.feature_labels[unseen[0]])} has no observation"
    unreached = _unreached_pose(n, m.odometry_ends)
    if unreached is not None:
        return f"pose {unreached} is not tied to the first pose by odometry"
    if m.robust_kernel not in ("", *ROBUST_KERNELS):
        return f"unknown robust kernel {m.robust_kernel!r}"
    if m.robust_kernel and not (0 < m.robust_parameter <= MAX_COORDINATE):
        return f"robust kernel parameter {m.robust_parameter!r} is not a positive number"
    if not (np.isfinite(m.cost) and m.cost >= 0):
        return f"cost {m.cost!r} is not a finite non-negative number"
    return _calibration_fault(np.asarray(m.odometry_calibration, dtype=float))


def _calibration_fault(calibration: NDArray[np.float64]) -> str | None:
    if calibration.shape not in ((0,), (6,)):
        return f"odometry calibration of shape {calibration.shape}, not (0,) or (6,)"
    # the scales of a map that has seen little can be anything; their sigmas are positive
    if len(calibration) and not (
        np.all(np.abs(calibration) <= MAX_COORDINATE) and np.all(calibration[3:] > 0)
    ):
        return f"odometry calibration {calibration.tolist()}: not finite or a sigma not positive"
    return None


def rendezvous_row_mask(
    robot: str,
    robots: list[str],
    stamps: ArrayLike,
    observed: list[str],
    ranges: ArrayLike,
    bearings: ArrayLike,
    sigma_range: ArrayLike,
    sigma_bearing: ArrayLike,
    pose_stamps: ArrayLike | None,
    tolerance: float,
    drops: DropCounter,
) -> NDArray[np.bool_]:
    """Which rendezvous measurements by ``robot`` the merger may use; counts the others once,
    by their first fault: bad numbers, a robot observing itself or one not in ``robots``, or a
    stamp within the span of ``robot``'s local map (``pose_stamps``, when known) at which it
    holds no pose. A stamp after the map's last pose is kept: the map has not caught up yet."""
    t = np.asarray(stamps, dtype=float)
    keep = range_bearing_mask(
        ranges, bearings, sigma_range, sigma_bearing, 2 * np.pi, drops
    ) & np.isfinite(t)
    drops.add(NOT_FINITE, int((~np.isfinite(t) & keep).sum()))
    names = np.asarray(observed, dtype=object).reshape(-1)
    for reason, bad in (
        (SELF_OBSERVATION, names == robot),
        (UNKNOWN_ROBOT, ~np.isin(names, np.asarray(robots, dtype=object))),
    ):
        fault = keep & bad
        drops.add(reason, int(fault.sum()))
        keep &= ~fault
    if pose_stamps is not None and len(pose_stamps) and keep.any():
        ps = np.asarray(pose_stamps, dtype=float)
        gap = np.abs(ps[nearest_stamp(ps, t)] - t)
        fault = keep & (t <= ps[-1] + tolerance) & (gap > tolerance)
        drops.add(NO_POSE_AT_STAMP, int(fault.sum()))
        keep &= ~fault
    return keep
