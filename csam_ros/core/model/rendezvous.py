"""Rendezvous measurement model through base nodes (paper eq. 22-24, docs/METHOD.md section 5).

A rendezvous measurement is the position of the observed robot in the observer's body frame.
With every robot's local frame ``G_r`` placed in the reference frame by its base node ``B_r``
(the identity for the reference robot), the prediction is

    c = translation of ( (-)(B_o (+) x_o) (+) B_t (+) x_t )

for observer pose ``x_o`` in ``G_o`` and observed pose ``x_t`` in ``G_t``. Between two robots
``p`` (reference) and ``q`` with ``b_pq = B_q`` this is the paper's eq. 22 when ``p`` observes
``q``, ``translation((-)x_p (+) b_pq (+) x_q)``, and its mirror ``translation((-)x_q (+) (-)b_pq
(+) x_p)`` when ``q`` observes ``p``: one function covers both directions and measurements
between two non-reference robots (docs/METHOD.md section 7).

The same model with points instead of poses gives the feature association residual of
Algorithm 2: ``r = B_a (+) l_a - B_c (+) l_c`` (see :func:`point_difference`).

Every function is vectorised over a leading axis of ``K`` measurements.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, fields

import numpy as np
from numpy.typing import ArrayLike, NDArray

from csam_ros.core.model import se2
from csam_ros.core.model.log import RendezvousLog
from csam_ros.core.model.sensor import polar_to_cartesian
from csam_ros.core.model.stamps import nearest_stamp

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]


@dataclass
class RendezvousPrediction:
    """Predicted relative positions and their Jacobians, all vectorised over ``K``.

    ``position`` (K, 2) is the observed robot's position in the observer's body frame;
    ``d_observer_pose`` (K, 2, 3), ``d_observer_base`` (K, 2, 3), ``d_observed_position``
    (K, 2, 2) and ``d_observed_base`` (K, 2, 3) are its derivatives (the paper's ``C^p``,
    ``C^q`` and ``B^pq`` blocks of eq. 24 before whitening).
    """

    position: Array
    d_observer_pose: Array
    d_observer_base: Array
    d_observed_position: Array
    d_observed_base: Array


def _point_in_parent(base: Array, point: Array) -> tuple[Array, Array, Array]:
    """``base (+) point`` with its Jacobians with respect to ``base`` (K,2,3) and ``point``."""
    c, s = np.cos(base[:, 2]), np.sin(base[:, 2])
    rot = se2.rotation(base[:, 2])
    out = se2.transform_point(base, point)
    d_base = np.zeros((len(base), 2, 3))
    d_base[:, 0, 0] = 1.0
    d_base[:, 1, 1] = 1.0
    d_base[:, 0, 2] = -s * point[:, 0] - c * point[:, 1]
    d_base[:, 1, 2] = c * point[:, 0] - s * point[:, 1]
    return out, d_base, rot


def predict(
    observer_pose: ArrayLike,
    observer_base: ArrayLike,
    observed_position: ArrayLike,
    observed_base: ArrayLike,
) -> RendezvousPrediction:
    """Position of the observed robot in the observer's body frame, with Jacobians (eq. 22).

    ``observer_pose`` (K, 3) is in the observer's frame ``G_o``, ``observed_position`` (K, 2)
    (the first two components of the observed pose; the prediction does not depend on its
    heading) in ``G_t``; ``observer_base`` and ``observed_base`` (K, 3) place those frames in
    the reference frame (pass zeros for the reference robot).
    """
    x_o = np.atleast_2d(np.asarray(observer_pose, dtype=float))
    b_o = np.atleast_2d(np.asarray(observer_base, dtype=float))
    t = np.atleast_2d(np.asarray(observed_position, dtype=float))[:, :2]
    b_t = np.atleast_2d(np.asarray(observed_base, dtype=float))
    k = max(len(x_o), len(b_o), len(t), len(b_t))
    x_o, b_o, b_t = (np.broadcast_to(a, (k, 3)) for a in (x_o, b_o, b_t))
    t = np.broadcast_to(t, (k, 2))

    observer_global = se2.compose(b_o, x_o)
    observed_global, d_target_base, d_target_point = _point_in_parent(b_t, t)
    position = se2.inverse_transform_point(observer_global, observed_global)

    rot_t = np.swapaxes(se2.rotation(observer_global[:, 2]), -1, -2)  # R(phi)^T
    d_global = np.zeros((k, 2, 3))  # d position / d observer_global
    d_global[:, :, :2] = -rot_t
    d_global[:, 0, 2] = position[:, 1]
    d_global[:, 1, 2] = -position[:, 0]
    j_base, j_pose = se2.compose_jacobians(b_o, x_o)
    return RendezvousPrediction(
        position=position,
        d_observer_pose=d_global @ j_pose,
        d_observer_base=d_global @ j_base,
        d_observed_position=rot_t @ d_target_point,
        d_observed_base=rot_t @ d_target_base,
    )


def predict_pair(
    pose_p: ArrayLike, base_node: ArrayLike, pose_q: ArrayLike, p_observes_q: ArrayLike
) -> tuple[Array, Array, Array, Array]:
    """The paper's two-robot connector ``c_m(x_p, b_pq, x_q)`` in either direction.

    ``p_observes_q`` (K,) selects ``translation((-)x_p (+) b_pq (+) x_q)`` (True) or
    ``translation((-)x_q (+) (-)b_pq (+) x_p)`` (False, ``q`` observes ``p``). Returns the
    prediction (K, 2) and its Jacobians with respect to ``x_p``, ``b_pq`` and ``x_q``, each
    (K, 2, 3).
    """
    x_p = np.atleast_2d(np.asarray(pose_p, dtype=float))
    x_q = np.atleast_2d(np.asarray(pose_q, dtype=float))
    b = np.atleast_2d(np.asarray(base_node, dtype=float))
    k = max(len(x_p), len(x_q), len(b))
    x_p, x_q, b = (np.broadcast_to(a, (k, 3)) for a in (x_p, x_q, b))
    forward = np.broadcast_to(np.asarray(p_observes_q, dtype=bool), (k,))
    zero = np.zeros((k, 3))
    fwd = predict(x_p, zero, x_q[:, :2], b)
    bwd = predict(x_q, b, x_p[:, :2], zero)
    sel = forward[:, None]
    position = np.where(sel, fwd.position, bwd.position)
    sel3 = forward[:, None, None]
    d_p = np.zeros((k, 2, 3))
    d_q = np.zeros((k, 2, 3))
    d_p[:] = np.where(sel3, fwd.d_observer_pose, 0.0)
    d_p[:, :, :2] += np.where(sel3, 0.0, bwd.d_observed_position)
    d_q[:] = np.where(sel3, 0.0, bwd.d_observer_pose)
    d_q[:, :, :2] += np.where(sel3, fwd.d_observed_position, 0.0)
    d_b = np.where(sel3, fwd.d_observed_base, bwd.d_observer_base)
    return position, d_p, d_b, d_q


def point_difference(
    point_a: ArrayLike, base_a: ArrayLike, point_c: ArrayLike, base_c: ArrayLike
) -> tuple[Array, Array, Array, Array, Array]:
    """Association residual ``r = B_a (+) l_a - B_c (+) l_c`` (Algorithm 2) with Jacobians.

    Returns ``r`` (K, 2) and its Jacobians with respect to ``l_a`` (K,2,2), ``B_a`` (K,2,3),
    ``l_c`` (K,2,2) and ``B_c`` (K,2,3). For two robots with ``p`` the reference this is the
    paper's ``l_i^p - b_pq (+) l_j^q``.
    """
    la = np.atleast_2d(np.asarray(point_a, dtype=float))
    lc = np.atleast_2d(np.asarray(point_c, dtype=float))
    ba = np.atleast_2d(np.asarray(base_a, dtype=float))
    bc = np.atleast_2d(np.asarray(base_c, dtype=float))
    k = max(len(la), len(lc), len(ba), len(bc))
    la, lc = (np.broadcast_to(a, (k, 2)) for a in (la, lc))
    ba, bc = (np.broadcast_to(a, (k, 3)) for a in (ba, bc))
    ga, d_ba, d_la = _point_in_parent(ba, la)
    gc, d_bc, d_lc = _point_in_parent(bc, lc)
    return ga - gc, d_la, d_ba, -d_lc, -d_bc


@dataclass
class RendezvousSet:
    """All rendezvous measurements among a set of robots, one row per measurement.

    Robot fields index :attr:`robots`; pose fields index that robot's pose stamps (the poses
    of its local map). ``position`` and ``covariance`` are the Cartesian observation of the
    observed robot in the observer's body frame (docs/METHOD.md section 3).
    """

    robots: list[str]
    observer: IntArray
    observed: IntArray
    stamps: Array
    observer_pose: IntArray
    observed_pose: IntArray
    position: Array  # (K, 2)
    covariance: Array  # (K, 2, 2)
    bearing: Array  # (K,) measured bearing, for the mutual-observation heading

    def __len__(self) -> int:
        return len(self.stamps)

    def subset(self, mask: NDArray[np.bool_]) -> RendezvousSet:
        """The measurements selected by a boolean mask."""
        rows = {f.name: getattr(self, f.name)[mask] for f in fields(self) if f.name != "robots"}
        return RendezvousSet(robots=self.robots, **rows)

    def between(self, a: int, c: int) -> NDArray[np.bool_]:
        """Mask of the measurements between robots ``a`` and ``c`` in either direction."""
        return ((self.observer == a) & (self.observed == c)) | (
            (self.observer == c) & (self.observed == a)
        )


def required_stamps(logs: Mapping[str, RendezvousLog]) -> dict[str, Array]:
    """Stamps at which each robot's local map must hold a pose: the rendezvous measurements
    it made and the ones other robots made of it (sorted, unique)."""
    out: dict[str, list[Array]] = {name: [] for name in logs}
    for name, log in logs.items():
        out[name].append(np.asarray(log.stamps, dtype=float))
        for other in set(log.observed):
            if other in out:
                mask = np.array([o == other for o in log.observed], dtype=bool)
                out[other].append(np.asarray(log.stamps, dtype=float)[mask])
    return {
        name: np.unique(np.concatenate(parts)) if parts else np.zeros(0)
        for name, parts in out.items()
    }


def _pose_index(
    stamps: Array, query: Array, tolerance: float, robot: str, strict: bool = True
) -> IntArray:
    """Index of the pose at each query stamp (-1 where none when not ``strict``); raises
    naming the robot and the stamp when ``strict``."""
    if len(query) == 0:
        return np.zeros(0, dtype=np.int64)
    if len(stamps) == 0:
        if not strict:
            return np.full(len(query), -1, dtype=np.int64)
        raise ValueError(f"robot {robot!r} has no poses but rendezvous stamps need some")
    nearest = nearest_stamp(stamps, query)
    missing = np.abs(stamps[nearest] - query) > tolerance
    if missing.any() and strict:
        first = int(np.flatnonzero(missing)[0])
        raise ValueError(
            f"robot {robot!r} has no pose at rendezvous stamp {query[first]:.9f} s "
            f"(nearest {stamps[nearest[first]]:.9f} s): its local map must hold a pose at "
            "every rendezvous stamp that involves it"
        )
    return np.where(missing, -1, nearest).astype(np.int64)


def collect(
    logs: Mapping[str, RendezvousLog],
    pose_stamps: Mapping[str, ArrayLike],
    tolerance: float = 1e-6,
    skip_missing_poses: bool = False,
) -> tuple[RendezvousSet, list[str]]:
    """Gather the rendezvous measurements among the robots of ``pose_stamps``.

    ``logs`` holds each robot's rendezvous log; ``pose_stamps`` the stamps of each robot's
    local-map poses, in the robots' order (which :attr:`RendezvousSet.robots` keeps).
    Measurements of or by a robot without a map, and of a robot by itself, are left out and
    described in the returned notes. A measurement at a stamp where a map holds no pose is
    an error naming robot and stamp, or, with ``skip_missing_poses`` (a map that has not yet
    caught up, online), left out and counted in the notes.
    """
    robots = list(pose_stamps)
    index = {name: i for i, name in enumerate(robots)}
    stamps_of = {n: np.asarray(s, dtype=float) for n, s in pose_stamps.items()}
    notes: list[str] = []
    parts: list[tuple[Array, ...]] = []
    for name, log in logs.items():
        k = len(log.stamps)
        if k == 0:
            continue
        if name not in index:
            notes.append(f"{k} rendezvous measurement(s) by {name!r} ignored: no map of {name!r}")
            continue
        observed = np.array([index.get(o, -1) for o in log.observed], dtype=np.int64)
        if len(observed) != k:
            raise ValueError(f"rendezvous log of {name!r}: {len(observed)} names for {k} stamps")
        self_seen = observed == index[name]
        if self_seen.any():
            notes.append(f"{int(self_seen.sum())} rendezvous measurement(s) of {name!r} by itself")
        unknown = observed < 0
        for other in sorted({log.observed[i] for i in np.flatnonzero(unknown)}):
            count = sum(1 for o in log.observed if o == other)
            notes.append(
                f"{count} rendezvous measurement(s) of {other!r} by {name!r} ignored: "
                f"no map of {other!r}"
            )
        keep = ~(self_seen | unknown)
        if not keep.any():
            continue
        stamps = np.asarray(log.stamps, dtype=float)[keep]
        z, cov = polar_to_cartesian(
            np.asarray(log.ranges)[keep],
            np.asarray(log.bearings)[keep],
            np.asarray(log.sigma_range)[keep],
            np.asarray(log.sigma_bearing)[keep],
        )
        obs = observed[keep]
        strict = not skip_missing_poses
        observed_pose = np.empty(len(obs), dtype=np.int64)
        for c in np.unique(obs):
            sel = obs == c
            observed_pose[sel] = _pose_index(
                stamps_of[robots[c]], stamps[sel], tolerance, robots[c], strict
            )
        observer_pose = _pose_index(stamps_of[name], stamps, tolerance, name, strict)
        found = (observer_pose >= 0) & (observed_pose >= 0)
        if not found.all():
            notes.append(
                f"{int((~found).sum())} rendezvous measurement(s) by {name!r} left out: "
                "no pose at their stamp yet"
            )
        parts.append(
            (
                np.full(int(found.sum()), index[name], dtype=np.int64),
                obs[found],
                stamps[found],
                observer_pose[found],
                observed_pose[found],
                z[found],
                cov[found],
                np.asarray(log.bearings, dtype=float)[keep][found],
            )
        )
    if not parts:
        empty = np.zeros(0, dtype=np.int64)
        return (
            RendezvousSet(
                robots,
                empty,
                empty,
                np.zeros(0),
                empty,
                empty,
                np.zeros((0, 2)),
                np.zeros((0, 2, 2)),
                np.zeros(0),
            ),
            notes,
        )
    cols = [np.concatenate(c) for c in zip(*parts, strict=True)]
    order = np.lexsort((cols[1], cols[0], cols[2]))
    cols = [c[order] for c in cols]
    return RendezvousSet(robots, *cols), notes
