"""Checks on measurements at the system boundary: bad input is dropped and counted, never fatal.

Nodes (and offline replay, which must give the same result) run every incoming message through
these checks before it reaches a smoother or the merger. A dropped item is counted under a
reason that shows in ``/csam/status``; accepted data is never touched by a later bad message.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

# Reasons, as they appear in /csam/status and summary.json.
NOT_FINITE = "not_finite"
NON_POSITIVE_RANGE = "non_positive_range"
NON_POSITIVE_SIGMA = "non_positive_sigma"
OUTSIDE_FIELD_OF_VIEW = "outside_field_of_view"
UNKNOWN_ROBOT = "unknown_robot"
SELF_OBSERVATION = "self_observation"
STAMP_BACKWARDS = "stamp_backwards"
DUPLICATE = "duplicate"
EMPTY = "empty"
CALLBACK_ERROR = "callback_error"  # a node callback failed unexpectedly on this message
# The merger's boundary: local maps and rendezvous poses from the smoothers.
MALFORMED_LOCAL_MAP = "malformed_local_map"
MALFORMED_RENDEZVOUS_POSES = "malformed_rendezvous_poses"
ROBOT_MISMATCH = "robot_mismatch"  # a message naming another robot than the one of its topic
NO_POSE_AT_STAMP = "no_pose_at_stamp"  # a rendezvous row inside the map's span but at no pose
FAILED_SOLVE = "failed_solve"  # a merger solve that raised or gave non-finite numbers

# A noisy bearing may fall a little outside the field of view: allow this many sigmas.
BEARING_MARGIN_SIGMAS = 5.0


@dataclass
class DropCounter:
    """Counts of dropped items by reason."""

    counts: Counter[str] = field(default_factory=Counter)

    def add(self, reason: str, n: int = 1) -> None:
        if n > 0:
            self.counts[reason] += n

    @property
    def total(self) -> int:
        return sum(self.counts.values())

    def as_dict(self) -> dict[str, int]:
        return dict(sorted(self.counts.items()))


@dataclass
class StampGuard:
    """Rejects a message whose stamp goes backwards or repeats on one stream (topic).

    Only accepted messages move the guard, so a rejected message (say, a garbage stamp far in
    the future with invalid content) cannot block the stream.
    """

    last_stamp: float = -np.inf

    def reason(self, stamp: float) -> str | None:
        """The drop reason for a message at ``stamp``, or None if its stamp is acceptable."""
        if not np.isfinite(stamp):
            return NOT_FINITE
        if stamp < self.last_stamp:
            return STAMP_BACKWARDS
        if stamp == self.last_stamp:
            return DUPLICATE
        return None

    def accept(self, stamp: float) -> None:
        self.last_stamp = stamp


def range_bearing_mask(
    ranges: ArrayLike,
    bearings: ArrayLike,
    sigma_range: ArrayLike,
    sigma_bearing: ArrayLike,
    field_of_view: float,
    drops: DropCounter,
) -> NDArray[np.bool_]:
    """Which range-bearing observations are valid; counts the others by their first fault.

    ``field_of_view`` is the sensor's full opening angle in radians (2 pi: no limit).
    """
    r = np.asarray(ranges, dtype=float)
    b = np.asarray(bearings, dtype=float)
    sr = np.asarray(sigma_range, dtype=float)
    sb = np.asarray(sigma_bearing, dtype=float)
    keep = np.ones(r.shape, dtype=bool)
    for reason, bad in (
        (NOT_FINITE, ~(np.isfinite(r) & np.isfinite(b) & np.isfinite(sr) & np.isfinite(sb))),
        (NON_POSITIVE_RANGE, r <= 0),
        (NON_POSITIVE_SIGMA, (sr <= 0) | (sb <= 0)),
        (OUTSIDE_FIELD_OF_VIEW, np.abs(b) > 0.5 * field_of_view + BEARING_MARGIN_SIGMAS * sb),
    ):
        fault = keep & bad
        drops.add(reason, int(fault.sum()))
        keep &= ~fault
    return keep


def odometry_ok(inputs: ArrayLike, sigmas: ArrayLike, drops: DropCounter) -> bool:
    """Whether one odometry sample (input and its sigmas) is usable; counts it if not."""
    u = np.asarray(inputs, dtype=float)
    s = np.asarray(sigmas, dtype=float)
    if not (np.all(np.isfinite(u)) and np.all(np.isfinite(s))):
        drops.add(NOT_FINITE)
        return False
    if np.any(s <= 0):
        drops.add(NON_POSITIVE_SIGMA)
        return False
    return True


class MeasurementFilter:
    """Validates every robot's measurement streams as they arrive, counting drops per robot.

    ``robots`` lists the known robot names (None: any name is accepted as a robot, but a
    rendezvous must still name another robot). Each (robot, stream) pair has its own
    :class:`StampGuard`. Within a message, single bad observations are dropped and the rest kept;
    a message that arrives with no observation is dropped as ``empty``.
    """

    def __init__(self, robots: list[str] | None = None, field_of_view: float = 2 * np.pi) -> None:
        self.robots = None if robots is None else list(robots)
        self.field_of_view = float(field_of_view)
        self.drops: dict[str, DropCounter] = {}
        self._guards: dict[tuple[str, str], StampGuard] = {}

    def counter(self, robot: str) -> DropCounter:
        """The drop counter of ``robot`` (unknown robots are counted under their own name)."""
        return self.drops.setdefault(robot, DropCounter())

    def _stamp_fault(self, robot: str, stream: str, stamp: float) -> str | None:
        if self.robots is not None and robot not in self.robots:
            return UNKNOWN_ROBOT
        return self._guards.setdefault((robot, stream), StampGuard()).reason(stamp)

    def _accept(self, robot: str, stream: str, stamp: float) -> None:
        self._guards[(robot, stream)].accept(stamp)

    def odometry(self, robot: str, stamp: float, inputs: ArrayLike, sigmas: ArrayLike) -> bool:
        """Whether an odometry sample is accepted."""
        fault = self._stamp_fault(robot, "odometry", stamp)
        if fault is not None:
            self.counter(robot).add(fault)
            return False
        if not odometry_ok(inputs, sigmas, self.counter(robot)):
            return False
        self._accept(robot, "odometry", stamp)
        return True

    def features(
        self,
        robot: str,
        stamp: float,
        ranges: ArrayLike,
        bearings: ArrayLike,
        sigma_range: ArrayLike,
        sigma_bearing: ArrayLike,
    ) -> NDArray[np.bool_] | None:
        """Mask of the accepted observations of one feature scan, or None if it is dropped."""
        return self._observations(
            robot, "features", stamp, ranges, bearings, sigma_range, sigma_bearing, None
        )

    def rendezvous(
        self,
        robot: str,
        stamp: float,
        observed: list[str],
        ranges: ArrayLike,
        bearings: ArrayLike,
        sigma_range: ArrayLike,
        sigma_bearing: ArrayLike,
    ) -> NDArray[np.bool_] | None:
        """Mask of the accepted observations of other robots, or None if the message is dropped."""
        return self._observations(
            robot, "rendezvous", stamp, ranges, bearings, sigma_range, sigma_bearing, observed
        )

    def _observations(
        self,
        robot: str,
        stream: str,
        stamp: float,
        ranges: ArrayLike,
        bearings: ArrayLike,
        sigma_range: ArrayLike,
        sigma_bearing: ArrayLike,
        observed: list[str] | None,
    ) -> NDArray[np.bool_] | None:
        drops = self.counter(robot)
        r = np.asarray(ranges, dtype=float)
        if r.size == 0:
            if self.robots is None or robot in self.robots:
                drops.add(EMPTY)
            else:
                drops.add(UNKNOWN_ROBOT)
            return None
        fault = self._stamp_fault(robot, stream, stamp)
        if fault is not None:
            drops.add(fault)
            return None
        keep = range_bearing_mask(
            r, bearings, sigma_range, sigma_bearing, self.field_of_view, drops
        )
        if observed is not None:
            names = np.asarray(observed, dtype=object)
            own = keep & (names == robot)
            drops.add(SELF_OBSERVATION, int(own.sum()))
            keep &= ~own
            if self.robots is not None:
                unknown = keep & ~np.isin(names, self.robots)
                drops.add(UNKNOWN_ROBOT, int(unknown.sum()))
                keep &= ~unknown
        if not keep.any():  # every observation was counted under its own fault
            return None
        self._accept(robot, stream, stamp)
        return keep


# -- local maps and rendezvous poses at the merger --------------------------------------------

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


def _number_fault(name: str, values: NDArray[np.float64], bound: float) -> str | None:
    flat = values.reshape(-1)
    bad = np.flatnonzero(~np.isfinite(flat) | (np.abs(flat) > bound))
    if len(bad) == 0:
        return None
    return (
        f"{name}: value {flat[bad[0]]!r} at {int(bad[0])} is not a finite number within {bound:g}"
    )


def _sqrt_information_fault(name: str, rows: NDArray[np.float64], size: int) -> str | None:
    """Each row must be a finite, bounded, non-singular ``size`` x ``size`` matrix."""
    fault = _number_fault(name, rows, MAX_SQRT_INFORMATION)
    if fault is not None or len(rows) == 0:
        return fault
    sv = np.linalg.svd(rows.reshape(-1, size, size), compute_uv=False)
    singular = np.flatnonzero(sv[:, -1] <= 1e-12 * np.maximum(sv[:, 0], 1e-300))
    if len(singular):
        return f"{name} {int(singular[0])} is singular (singular values {sv[singular[0]]})"
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
    if m.robust_kernel not in ("", "huber", "cauchy"):
        return f"unknown robust kernel {m.robust_kernel!r}"
    if m.robust_kernel and not (0 < m.robust_parameter <= MAX_COORDINATE):
        return f"robust kernel parameter {m.robust_parameter!r} is not a positive number"
    if not (np.isfinite(m.cost) and m.cost >= 0):
        return f"cost {m.cost!r} is not a finite non-negative number"
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
        near = np.clip(np.searchsorted(ps, t), 1, max(len(ps) - 1, 1))
        gap = np.minimum(np.abs(ps[near - 1] - t), np.abs(ps[np.minimum(near, len(ps) - 1)] - t))
        fault = keep & (t <= ps[-1] + tolerance) & (gap > tolerance)
        drops.add(NO_POSE_AT_STAMP, int(fault.sum()))
        keep &= ~fault
    return keep
