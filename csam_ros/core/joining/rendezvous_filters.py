"""Robust pre-filters of real measurements before C-SAM (for the UTIAS MR.CLAM data set).

Simulation is clean; real robots are not. Two filters act on the robots' rendezvous logs
and return new logs plus what they dropped (nothing is dropped silently; feature
measurements and odometry are untouched: outlying feature measurements are the local
smoother's robust kernel's job). Both are settings of C-SAM (:class:`csam_ros.core.joining.config.
CsamConfig`), so the nodes and an offline replay apply them alike.

- :func:`thin_rendezvous`: robots that meet many times (MR.CLAM: 700-2,000 rendezvous
  measurements per robot) would each bring a pose, and Algorithm 1 enters every local map
  through the dense marginal information of all its rendezvous poses, whose size grows
  quadratically. Keep at most one measurement per ordered robot pair per ``min_interval``
  seconds and at most ``max_per_pair`` per ordered pair, spread over time
  (:class:`RendezvousThinning`, a streaming rule the smoothers apply as data arrive).
- :func:`consistent_rendezvous`: a wrong rendezvous measurement (a misread robot barcode, a
  reflection) joins maps wrongly. Every measurement between robots ``p`` and ``q`` (either
  direction) gives a correspondence between a point in ``G_p`` and one in ``G_q`` (the
  measured robot's position from the measurement and from its own trajectory); the base node
  is the rigid motion between them. A RANSAC over pairs of correspondences keeps the
  measurements consistent with the motion most of them agree on, within a tolerance of
  ``gate`` measurement sigmas plus ``drift`` metres for the local maps' own errors.
"""

from __future__ import annotations

import bisect
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray

from csam_ros.core.model import se2
from csam_ros.core.model.log import MultiRobotLog, RendezvousLog
from csam_ros.core.model.motion import odometry_between

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]


@dataclass
class FilterReport:
    """Rendezvous measurements kept and dropped, per observing robot and reason."""

    kept: dict[str, int] = field(default_factory=dict)
    dropped: dict[str, dict[str, int]] = field(default_factory=dict)
    pairs: dict[str, dict] = field(default_factory=dict)  # "p|q" -> details (consistency)

    def add(self, robot: str, reason: str, n: int) -> None:
        if n > 0:
            entry = self.dropped.setdefault(robot, {})
            entry[reason] = entry.get(reason, 0) + int(n)

    def total(self, reason: str) -> int:
        return sum(d.get(reason, 0) for d in self.dropped.values())

    def to_dict(self) -> dict:
        return {"kept": dict(self.kept), "dropped": dict(self.dropped), "pairs": dict(self.pairs)}

    @classmethod
    def from_dict(cls, node: object, where: str = "report") -> FilterReport:
        """The inverse of :meth:`to_dict`; a malformed ``node`` is a ValueError naming it."""
        if not isinstance(node, Mapping) or sorted(node) != ["dropped", "kept", "pairs"]:
            raise ValueError(f"{where}: expected an object of 'kept', 'dropped' and 'pairs'")

        def counts(value: object, at: str) -> dict[str, int]:
            if not isinstance(value, Mapping) or not all(
                isinstance(n, int) and not isinstance(n, bool) for n in value.values()
            ):
                raise ValueError(f"{at}: expected an object of counts, got {value!r:.80}")
            return dict(value)

        pairs = node["pairs"]
        if not isinstance(pairs, Mapping) or not all(
            isinstance(p, Mapping) for p in pairs.values()
        ):
            raise ValueError(f"{where}.pairs: expected an object of objects, got {pairs!r:.80}")
        dropped = node["dropped"]
        if not isinstance(dropped, Mapping):
            raise ValueError(f"{where}.dropped: expected an object, got {dropped!r:.80}")
        return cls(
            kept=counts(node["kept"], f"{where}.kept"),
            dropped={r: counts(d, f"{where}.dropped.{r}") for r, d in dropped.items()},
            pairs={k: dict(p) for k, p in pairs.items()},
        )


def select_rendezvous(log: RendezvousLog, keep: BoolArray) -> RendezvousLog:
    """The measurements of ``log`` where ``keep`` is true."""
    keep = np.asarray(keep, dtype=bool)
    if keep.shape != log.stamps.shape:
        raise ValueError(f"keep mask has shape {keep.shape}, log has {log.stamps.shape}")
    return RendezvousLog(
        log.stamps[keep],
        [o for o, k in zip(log.observed, keep, strict=True) if k],
        log.ranges[keep],
        log.bearings[keep],
        log.sigma_range[keep],
        log.sigma_bearing[keep],
    )


class RendezvousThinning:
    """Streaming thinning of rendezvous measurements, per ordered robot pair.

    A measurement of ``observed`` by ``observer`` is kept when it comes at least the pair's
    interval (initially ``min_interval`` s) after the pair's last kept one. When a pair holds
    more than ``max_per_pair``, every other kept measurement is dropped (the newest stays) and
    the interval becomes the smallest gap left, so that the kept set stays spread over the
    whole run. Decisions depend only on the pair's measurements in arrival order: the
    observer's and the observed robot's smoothers, and the offline :func:`thin_rendezvous`,
    all reach the same kept set.
    """

    def __init__(self, min_interval: float = 0.0, max_per_pair: int | None = None) -> None:
        if not min_interval >= 0 or (max_per_pair is not None and max_per_pair < 1):
            raise ValueError(
                f"rendezvous thinning: min_interval={min_interval} must be >= 0 and "
                f"max_per_pair={max_per_pair} >= 1 (or None)"
            )
        self.min_interval = float(min_interval)
        self.max_per_pair = max_per_pair
        self._kept: dict[tuple[str, str], list[float]] = {}
        self._interval: dict[tuple[str, str], float] = {}

    def offer(self, observer: str, observed: str, stamp: float) -> bool:
        """Whether the measurement is kept now (it may be decimated by a later one)."""
        pair = (observer, observed)
        kept = self._kept.setdefault(pair, [])
        if kept and stamp - kept[-1] < self._interval.get(pair, self.min_interval):
            return False
        kept.append(float(stamp))
        if self.max_per_pair is not None and len(kept) > self.max_per_pair:
            kept[:] = kept[len(kept) % 2 == 0 :: 2]  # keeps the newest
            gaps = np.diff(kept)
            self._interval[pair] = float(gaps.min()) if gaps.size else self.min_interval
        return True

    def is_kept(self, observer: str, observed: str, stamp: float) -> bool:
        kept = self._kept.get((observer, observed), [])  # in stamp order (offer keeps it so)
        i = bisect.bisect_left(kept, float(stamp))
        return i < len(kept) and kept[i] == float(stamp)

    def kept_stamps(self, observer: str, observed: str) -> list[float]:
        return list(self._kept.get((observer, observed), ()))

    def state(self) -> tuple[dict[tuple[str, str], list[float]], dict[tuple[str, str], float]]:
        """The kept stamps and current interval of each pair (copies), for :meth:`restore`."""
        return {pair: list(s) for pair, s in self._kept.items()}, dict(self._interval)

    def restore(
        self,
        kept: Mapping[tuple[str, str], Sequence[float]],
        interval: Mapping[tuple[str, str], float],
    ) -> None:
        """Continue from :meth:`state` of an earlier thinning with the same settings."""
        self._kept = {pair: list(s) for pair, s in kept.items()}
        self._interval = dict(interval)


def thin_rendezvous(
    logs: Mapping[str, RendezvousLog], min_interval: float = 0.0, max_per_pair: int | None = None
) -> tuple[dict[str, RendezvousLog], FilterReport]:
    """Each robot's measurements thinned by :class:`RendezvousThinning` in stamp order."""
    thinning = RendezvousThinning(min_interval, max_per_pair)
    report = FilterReport()
    out: dict[str, RendezvousLog] = {}
    for name, rv in logs.items():
        order = np.argsort(rv.stamps, kind="stable")
        offered = np.zeros(rv.stamps.size, dtype=bool)
        for i in order:
            offered[i] = thinning.offer(name, rv.observed[i], rv.stamps[i])
        keep = np.array(
            [thinning.is_kept(name, o, t) for o, t in zip(rv.observed, rv.stamps, strict=True)],
            dtype=bool,
        )
        keep &= offered  # a second measurement of one pair at one stamp stays dropped
        report.add(name, "thinned_interval", int((~offered).sum()))
        report.add(name, "thinned_cap", int((offered & ~keep).sum()))
        out[name] = select_rendezvous(rv, keep)
        report.kept[name] = int(keep.sum())
    return out, report


def _interpolate(stamps: FloatArray, poses: FloatArray, at: FloatArray) -> FloatArray:
    """Poses at ``at`` by linear interpolation (heading unwrapped); clamped to the ends."""
    heading = np.unwrap(poses[:, 2])
    return np.stack(
        [
            np.interp(at, stamps, poses[:, 0]),
            np.interp(at, stamps, poses[:, 1]),
            se2.wrap_angle(np.interp(at, stamps, heading)),
        ],
        -1,
    )


def _two_point_motions(
    a: FloatArray, b: FloatArray, first: NDArray[np.int64], second: NDArray[np.int64]
) -> FloatArray:
    """Rigid motions ``(x, y, phi)`` with ``a = motion (+) b`` fixed by two correspondences."""
    da, db = a[second] - a[first], b[second] - b[first]
    heading = np.arctan2(da[:, 1], da[:, 0]) - np.arctan2(db[:, 1], db[:, 0])
    c, s = np.cos(heading), np.sin(heading)
    tx = a[first, 0] - (c * b[first, 0] - s * b[first, 1])
    ty = a[first, 1] - (s * b[first, 0] + c * b[first, 1])
    return np.stack([tx, ty, heading], -1)


def _fit_motion(a: FloatArray, b: FloatArray) -> FloatArray:
    """Least-squares rigid motion ``a ~ motion (+) b`` (Kabsch, no scale)."""
    ma, mb = a.mean(axis=0), b.mean(axis=0)
    u, _, vt = np.linalg.svd((b - mb).T @ (a - ma))
    d = np.sign(np.linalg.det(vt.T @ u.T)) or 1.0
    rotation = vt.T @ np.diag([1.0, d]) @ u.T
    t = ma - rotation @ mb
    return np.array([t[0], t[1], np.arctan2(rotation[1, 0], rotation[0, 0])])


def consistent_rendezvous(
    logs: Mapping[str, RendezvousLog],
    trajectories: Mapping[str, tuple[FloatArray, FloatArray]],
    gate: float = 3.0,
    drift: float = 0.3,
    min_spread: float = 0.5,
    min_support: int = 4,
    max_hypotheses: int = 1000,
    seed: int = 0,
) -> tuple[dict[str, RendezvousLog], FilterReport]:
    """Drop rendezvous measurements inconsistent with the base node most others agree on.

    ``trajectories`` maps each robot to ``(stamps, poses)`` of its local map (frame ``G_r``).
    A measurement is consistent when its correspondence misses the best rigid motion by less
    than ``gate * sqrt(s_r^2 + r^2 s_b^2) + drift``. Pairs with fewer than ``min_support``
    consistent measurements (or too little spread to fix a motion) are left untouched and
    reported as unverified.
    """
    rng = np.random.default_rng(seed)
    names = list(logs)
    keep = {n: np.ones(logs[n].stamps.size, dtype=bool) for n in names}
    report = FilterReport()
    for i, p in enumerate(names):
        for q in names[i + 1 :]:
            points_p, points_q, tolerance, owner, row = [], [], [], [], []
            for observer, target in ((p, q), (q, p)):
                rv = logs[observer]
                rows = np.flatnonzero(np.array(rv.observed, dtype=object) == target)
                if rows.size == 0 or observer not in trajectories or target not in trajectories:
                    continue
                t = rv.stamps[rows]
                body = np.stack(
                    [
                        rv.ranges[rows] * np.cos(rv.bearings[rows]),
                        rv.ranges[rows] * np.sin(rv.bearings[rows]),
                    ],
                    -1,
                )
                observer_pose = _interpolate(*trajectories[observer], t)
                measured = se2.transform_point(observer_pose, body)  # target in G_observer
                target_xy = _interpolate(*trajectories[target], t)[:, :2]  # target in G_target
                if observer == p:
                    points_p.append(measured)
                    points_q.append(target_xy)
                else:
                    points_p.append(target_xy)
                    points_q.append(measured)
                sigma = np.sqrt(
                    rv.sigma_range[rows] ** 2 + (rv.ranges[rows] * rv.sigma_bearing[rows]) ** 2
                )
                tolerance.append(gate * sigma + drift)
                owner += [observer] * rows.size
                row.append(rows)
            if not points_p:
                continue
            a = np.concatenate(points_p)
            b = np.concatenate(points_q)
            tol = np.concatenate(tolerance)
            rows_all = np.concatenate(row)
            key = f"{p}|{q}"
            first, second = np.triu_indices(a.shape[0], 1)
            spread = np.linalg.norm(b[second] - b[first], axis=1) >= min_spread
            first, second = first[spread], second[spread]
            if first.size > max_hypotheses:
                pick = rng.choice(first.size, max_hypotheses, replace=False)
                first, second = first[pick], second[pick]
            if first.size == 0:
                report.pairs[key] = {
                    "n": int(a.shape[0]),
                    "verified": False,
                    "reason": "measurements do not spread",
                }
                continue
            motions = _two_point_motions(a, b, first, second)
            predicted = se2.transform_point(motions[:, None, :], b[None, :, :])
            miss = np.linalg.norm(predicted - a[None], axis=-1)
            support = (miss < tol[None]).sum(axis=1)
            best = int(np.argmax(support))
            inliers = miss[best] < tol
            if inliers.sum() >= 3:  # refine on the inliers, then decide once more
                motion = _fit_motion(a[inliers], b[inliers])
                inliers = np.linalg.norm(se2.transform_point(motion, b) - a, axis=1) < tol
            else:
                motion = motions[best]
            verified = bool(inliers.sum() >= min_support)
            report.pairs[key] = {
                "n": int(a.shape[0]),
                "inliers": int(inliers.sum()),
                "verified": verified,
                "base_node": [float(v) for v in motion],
            }
            if not verified:
                report.pairs[key]["reason"] = f"fewer than {min_support} consistent measurements"
                continue
            owners = np.array(owner, dtype=object)
            for observer in (p, q):
                mine = owners == observer
                bad_rows = rows_all[mine & ~inliers]
                keep[observer][bad_rows] = False
                report.add(observer, "inconsistent", bad_rows.size)
    out = {}
    for name in names:
        out[name] = select_rendezvous(logs[name], keep[name])
        report.kept[name] = int(keep[name].sum())
    return out, report


@dataclass
class OdometryScale:
    """Multiplicative corrections of one robot's odometry: true = scale * reported."""

    forward: float = 1.0
    turn: float = 1.0
    intervals: int = 0


def odometry_scales(
    log: MultiRobotLog,
    trajectories: Mapping[str, tuple[FloatArray, FloatArray]],
    min_forward: float = 0.005,
    min_turn: float = 0.005,
) -> dict[str, OdometryScale]:
    """Scale factors of the forward and turn odometry that best explain smoothed trajectories.

    Between consecutive trajectory stamps the odometry is composed (first order: forward
    distance and turn angle) and regressed through the origin on the trajectory's own relative
    motion. A smoothed map pulls its poses towards the odometry, so one estimate is biased
    towards 1: re-estimate on the map rebuilt from corrected odometry until it settles
    (:func:`scale_odometry` composes corrections).
    """
    out = {}
    for name, robot in log.robots.items():
        if name not in trajectories:
            continue
        stamps, poses = trajectories[name]
        odometry = robot.odometry
        inside = (stamps >= odometry.stamps[0]) & (stamps <= odometry.stamps[-1])
        stamps, poses = stamps[inside], poses[inside]
        composed = odometry_between(
            odometry.stamps, odometry.inputs, odometry.sigmas, stamps
        ).relative_poses
        relative = se2.between(poses[:-1], poses[1:])
        forward = np.abs(composed[:, 0]) > min_forward
        turn = np.abs(composed[:, 2]) > min_turn
        scale = OdometryScale(intervals=int(len(composed)))
        if forward.any():
            scale.forward = float(
                np.sum(relative[forward, 0] * composed[forward, 0])
                / np.sum(composed[forward, 0] ** 2)
            )
        if turn.any():
            scale.turn = float(
                np.sum(relative[turn, 2] * composed[turn, 2]) / np.sum(composed[turn, 2] ** 2)
            )
        out[name] = scale
    return out


def scale_odometry(log: MultiRobotLog, scales: Mapping[str, OdometryScale]) -> MultiRobotLog:
    """A log whose odometry inputs ``v`` and ``omega`` are multiplied by the robots' scales."""
    robots = {}
    for name, robot in log.robots.items():
        scale = scales.get(name)
        if scale is None:
            robots[name] = robot
            continue
        if not (scale.forward > 0 and scale.turn > 0):
            raise ValueError(f"{name}: odometry scales must be positive, got {scale}")
        inputs = robot.odometry.inputs * np.array([scale.forward, 1.0, scale.turn])
        robots[name] = replace(robot, odometry=replace(robot.odometry, inputs=inputs))
    return MultiRobotLog(robots, log.truth)
