"""Local map updates: after its first map, a smoother sends what changed, not the whole map.

A local map only grows. Poses and features are added; factors are added, and a pose inserted
in the past splits the odometry factor of its interval into two. So against the map its
receivers hold, a smoother sends (:func:`map_changes`):

- the poses and features that are new or moved beyond a tolerance (:class:`UpdateTolerance`):
  a loose one for most poses, which the merger uses only as linearisation points and initial
  values (it re-solves them), a tight one for the features and the rendezvous poses, whose
  estimates it takes as the means of its alignment and association;
- the odometry factors that are new or replaced, keyed by the stamp of their first pose;
- the observation factors after the ones held.

Poses are keyed by stamp (integer ns), so indices that shift when a pose is inserted never
travel. The sender applies each update to its own copy of the held map
(:class:`UpdateSender`), so sender and receivers hold the same map whatever the tolerance.
Anything other than growth (the gauge prior or the kernel changed, a held pose, feature or
factor gone or altered) makes the update complete: the whole map, as after a resync.

Updates of one sender chain: each names the ``sequence`` of the update it applies to
(``base_sequence``; 0 for a complete one), within a ``session`` drawn when the sender starts.
A receiver applies an update only on top of that one (:func:`apply_update`); an update already
applied changes nothing, and one whose base it does not hold raises :class:`MissingBaseError`,
after which it asks the sender for a complete update. The sender's answer names its session
and the sequence of the complete update it sent (:func:`resync_answer`), so that a receiver
can tell a restart of the sender (a new session) from another publisher's map.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from csam_ros.core.exchange.local_map_checks import LocalMapArrays
from csam_ros.core.model import se2

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]


@dataclass(frozen=True)
class UpdateTolerance:
    """How far an estimate may move before it is sent again: a receiver's copy of every pose
    is within ``position`` and ``heading`` of the sender's, of every key pose (rendezvous) and
    feature within ``key`` (m and rad); exact after an ``exact`` update."""

    position: float = 0.02  # m
    heading: float = 0.02  # rad
    key: float = 1e-3  # m and rad

    @classmethod
    def exact(cls) -> UpdateTolerance:
        return cls(0.0, 0.0, 0.0)


@dataclass(frozen=True, eq=False)
class KeyedMap:
    """A local map (or the changes to one) keyed by stamps instead of pose indices: N poses,
    F features, M odometry factors (sorted by their first pose), K observation factors."""

    pose_stamps: IntArray  # (N,) ns, increasing
    poses: Array  # (N, 3)
    feature_labels: IntArray  # (F,)
    feature_xy: Array  # (F, 2)
    prior_sqrt_information: Array  # (9,) the gauge prior on the first pose
    odometry_stamps: IntArray  # (M, 2) ns of the two poses
    odometry_delta: Array  # (M, 3)
    odometry_sqrt_information: Array  # (M, 9) row-major
    observation_stamps: IntArray  # (K,) ns of the observing pose
    observation_label: IntArray  # (K,)
    observation_xy: Array  # (K, 2)
    observation_sqrt_information: Array  # (K, 4) row-major
    robust_kernel: str
    robust_parameter: float
    cost: float
    odometry_calibration: Array  # (0,) or (6,): as in LocalMapArrays

    @classmethod
    def of(cls, m: LocalMapArrays) -> KeyedMap:
        """``m`` keyed by its pose stamps (seconds rounded to ns, as stamps travel)."""
        stamps = np.round(np.asarray(m.stamps, dtype=float) * 1e9).astype(np.int64)
        odometry = stamps[m.odometry_ends].reshape(-1, 2)
        order = np.argsort(odometry[:, 0], kind="stable")
        return cls(
            pose_stamps=stamps,
            poses=np.asarray(m.poses, dtype=float).reshape(-1, 3),
            feature_labels=np.asarray(m.feature_labels, dtype=np.int64),
            feature_xy=np.asarray(m.feature_xy, dtype=float).reshape(-1, 2),
            prior_sqrt_information=np.asarray(m.prior_sqrt_information, dtype=float),
            odometry_stamps=odometry[order],
            odometry_delta=m.odometry_delta.reshape(-1, 3)[order],
            odometry_sqrt_information=m.odometry_sqrt_information.reshape(-1, 9)[order],
            observation_stamps=stamps[m.observation_pose],
            observation_label=np.asarray(m.observation_label, dtype=np.int64),
            observation_xy=m.observation_xy.reshape(-1, 2),
            observation_sqrt_information=m.observation_sqrt_information.reshape(-1, 4),
            robust_kernel=m.robust_kernel,
            robust_parameter=float(m.robust_parameter),
            cost=float(m.cost),
            odometry_calibration=np.asarray(m.odometry_calibration, dtype=float).reshape(-1),
        )

    def arrays(self) -> LocalMapArrays:
        """The map with pose indices (covariances left out); ValueError naming a factor whose
        stamp is not a pose's."""
        return LocalMapArrays(
            stamps=self.pose_stamps / 1e9,
            poses=self.poses,
            pose_covariances=np.zeros(0),
            feature_labels=self.feature_labels,
            feature_xy=self.feature_xy,
            feature_cov=np.zeros((len(self.feature_labels), 3)),
            prior_sqrt_information=self.prior_sqrt_information,
            odometry_ends=self._pose_index(self.odometry_stamps, "odometry factor"),
            odometry_delta=self.odometry_delta,
            odometry_sqrt_information=self.odometry_sqrt_information,
            observation_pose=self._pose_index(self.observation_stamps, "observation factor"),
            observation_label=self.observation_label,
            observation_xy=self.observation_xy,
            observation_sqrt_information=self.observation_sqrt_information,
            robust_kernel=self.robust_kernel,
            robust_parameter=self.robust_parameter,
            cost=self.cost,
            odometry_calibration=self.odometry_calibration,
        )

    def _pose_index(self, stamps: IntArray, what: str) -> IntArray:
        index = np.searchsorted(self.pose_stamps, stamps)
        found = index < len(self.pose_stamps)
        found[found] = self.pose_stamps[index[found]] == stamps[found]
        if not found.all():
            bad = np.flatnonzero(~found.reshape(-1))[0]
            raise ValueError(f"{what} at stamp {int(stamps.reshape(-1)[bad])} ns has no pose")
        return index.astype(np.int64)

    @property
    def num_observations(self) -> int:
        return len(self.observation_label)


@dataclass(frozen=True)
class MapUpdate:
    """One update of a sender's local map: ``changes`` to apply on top of update
    ``base_sequence`` of the same ``session``, or the complete map when ``base_sequence`` is 0
    (``observations_before`` is the number of observation factors the base holds)."""

    session: int
    sequence: int
    base_sequence: int
    observations_before: int
    changes: KeyedMap

    @property
    def complete(self) -> bool:
        return self.base_sequence == 0


@dataclass(frozen=True)
class HeldMap:
    """A local map as a receiver holds it: the result of update ``sequence`` of ``session``."""

    session: int
    sequence: int
    map: KeyedMap


RESYNC_ANSWER = "session {session} sequence {sequence}"


def resync_answer(session: int, sequence: int) -> str:
    """A sender's answer to a resync request: its session, and the sequence of the complete
    update it sent (0: it has sent nothing yet)."""
    return RESYNC_ANSWER.format(session=session, sequence=sequence)


def read_resync_answer(text: str) -> tuple[int, int] | None:
    """The (session, sequence) of :func:`resync_answer`'s text; None when it is not one."""
    words = text.split()
    if len(words) != 4 or words[0] != "session" or words[2] != "sequence":
        return None
    try:
        session, sequence = int(words[1]), int(words[3])
    except ValueError:
        return None
    if not (0 <= session < 2**32 and 0 <= sequence < 2**32):
        return None
    return session, sequence


class MissingBaseError(ValueError):
    """An update on top of one the receiver does not hold: it needs a complete update."""


def _within(
    a: Array, b: Array, position: float | Array, heading: float | Array = 0.0
) -> NDArray[np.bool_]:
    """Row by row: are poses (or points, two columns) ``a`` within the bounds of ``b``?"""
    near = np.all(np.abs(a[:, :2] - b[:, :2]) <= np.reshape(position, (-1, 1)), axis=1)
    if a.shape[1] == 3:
        near &= np.abs(se2.wrap_angle(a[:, 2] - b[:, 2])) <= heading
    return near


def _positions(held: IntArray, current: IntArray) -> IntArray | None:
    """Where each key of ``held`` is in ``current`` (both unique), None if one is missing."""
    order = np.argsort(current, kind="stable")
    where = np.searchsorted(current, held, sorter=order)
    where = np.minimum(where, len(current) - 1) if len(current) else where
    if len(held) and (len(current) == 0 or np.any(current[order[where]] != held)):
        return None
    return order[where] if len(held) else np.zeros(0, dtype=np.int64)


def map_changes(
    held: KeyedMap,
    current: KeyedMap,
    tolerance: UpdateTolerance,
    key_stamps: IntArray | None = None,
) -> KeyedMap | None:
    """What ``current`` adds to ``held`` beyond ``tolerance`` (``key_stamps``: the poses held
    to the key tolerance), or None when ``current`` is not a growth of ``held`` (then only a
    complete update will do)."""
    if (
        held.robust_kernel != current.robust_kernel
        or held.robust_parameter != current.robust_parameter
        or not np.array_equal(held.prior_sqrt_information, current.prior_sqrt_information)
    ):
        return None
    poses_at = _positions(held.pose_stamps, current.pose_stamps)
    features_at = _positions(held.feature_labels, current.feature_labels)
    factors_at = _positions(held.odometry_stamps[:, 0], current.odometry_stamps[:, 0])
    k = held.num_observations
    if (
        poses_at is None
        or features_at is None
        or factors_at is None
        or current.num_observations < k
    ):
        return None
    for name in (
        "observation_stamps",
        "observation_label",
        "observation_xy",
        "observation_sqrt_information",
    ):
        if not np.array_equal(getattr(held, name), getattr(current, name)[:k]):
            return None
    send_pose = np.ones(len(current.pose_stamps), dtype=bool)
    key = np.isin(held.pose_stamps, key_stamps if key_stamps is not None else [])
    send_pose[poses_at] = ~_within(
        current.poses[poses_at],
        held.poses,
        np.where(key, tolerance.key, tolerance.position),
        np.where(key, tolerance.key, tolerance.heading),
    )
    send_feature = np.ones(len(current.feature_labels), dtype=bool)
    send_feature[features_at] = ~_within(
        current.feature_xy[features_at], held.feature_xy, tolerance.key
    )
    send_factor = np.ones(len(current.odometry_stamps), dtype=bool)
    send_factor[factors_at] = ~(
        np.all(current.odometry_stamps[factors_at] == held.odometry_stamps, axis=1)
        & np.all(current.odometry_delta[factors_at] == held.odometry_delta, axis=1)
        & np.all(
            current.odometry_sqrt_information[factors_at] == held.odometry_sqrt_information,
            axis=1,
        )
    )
    return replace(
        current,
        pose_stamps=current.pose_stamps[send_pose],
        poses=current.poses[send_pose],
        feature_labels=current.feature_labels[send_feature],
        feature_xy=current.feature_xy[send_feature],
        odometry_stamps=current.odometry_stamps[send_factor],
        odometry_delta=current.odometry_delta[send_factor],
        odometry_sqrt_information=current.odometry_sqrt_information[send_factor],
        observation_stamps=current.observation_stamps[k:],
        observation_label=current.observation_label[k:],
        observation_xy=current.observation_xy[k:],
        observation_sqrt_information=current.observation_sqrt_information[k:],
    )


def _upsert(
    held_keys: IntArray, held_rows: list[Array], new_keys: IntArray, new_rows: list[Array]
) -> tuple[IntArray, list[Array]]:
    """Rows of ``held`` replaced or extended by ``new`` (unique keys): the held order, then
    the new keys in their own order."""
    known = np.isin(new_keys, held_keys)
    rows = [h.copy() for h in held_rows]
    if known.any():
        at = _positions(new_keys[known], held_keys)
        assert at is not None
        for r, n in zip(rows, new_rows, strict=True):
            r[at] = n[known]
    fresh = ~known
    return np.concatenate([held_keys, new_keys[fresh]]), [
        np.concatenate([r, n[fresh]]) for r, n in zip(rows, new_rows, strict=True)
    ]


def _apply_changes(held: KeyedMap, changes: KeyedMap) -> KeyedMap:
    pose_stamps, (poses,) = _upsert(
        held.pose_stamps, [held.poses], changes.pose_stamps, [changes.poses]
    )
    order = np.argsort(pose_stamps, kind="stable")
    labels, (feature_xy,) = _upsert(
        held.feature_labels, [held.feature_xy], changes.feature_labels, [changes.feature_xy]
    )
    firsts, (ends, delta, w) = _upsert(
        held.odometry_stamps[:, 0],
        [held.odometry_stamps, held.odometry_delta, held.odometry_sqrt_information],
        changes.odometry_stamps[:, 0],
        [changes.odometry_stamps, changes.odometry_delta, changes.odometry_sqrt_information],
    )
    by_first = np.argsort(firsts, kind="stable")
    return replace(
        changes,
        pose_stamps=pose_stamps[order],
        poses=poses[order],
        feature_labels=labels,
        feature_xy=feature_xy,
        odometry_stamps=ends[by_first],
        odometry_delta=delta[by_first],
        odometry_sqrt_information=w[by_first],
        observation_stamps=np.concatenate([held.observation_stamps, changes.observation_stamps]),
        observation_label=np.concatenate([held.observation_label, changes.observation_label]),
        observation_xy=np.concatenate([held.observation_xy, changes.observation_xy]),
        observation_sqrt_information=np.concatenate(
            [held.observation_sqrt_information, changes.observation_sqrt_information]
        ),
    )


def apply_update(held: HeldMap | None, update: MapUpdate) -> HeldMap:
    """The map after ``update``: ``held`` itself when it already includes the update; raises
    :class:`MissingBaseError` when ``update`` needs a base that is not ``held``."""
    if update.complete:
        if held is not None and (held.session, held.sequence) == (update.session, update.sequence):
            return held
        return HeldMap(update.session, update.sequence, update.changes)
    if held is None or held.session != update.session:
        raise MissingBaseError(
            f"update {update.sequence} applies to update {update.base_sequence} of session "
            f"{update.session}, and no update of that session is held"
        )
    if update.sequence <= held.sequence:
        return held  # delivered again
    if update.base_sequence != held.sequence:
        raise MissingBaseError(
            f"update {update.sequence} applies to update {update.base_sequence}, but update "
            f"{held.sequence} is held"
        )
    if update.observations_before != held.map.num_observations:
        raise ValueError(
            f"update {update.sequence} follows {update.observations_before} observation "
            f"factors, {held.map.num_observations} are held"
        )
    return HeldMap(update.session, update.sequence, _apply_changes(held.map, update.changes))


class UpdateSender:
    """The sending side: the map its receivers hold and the next update against it."""

    def __init__(self, session: int, tolerance: UpdateTolerance | None = None) -> None:
        self.session = session
        self.tolerance = tolerance or UpdateTolerance()
        self.held: HeldMap | None = None
        self.complete_updates = 0  # sent as complete maps (the first, resyncs, non-growth)

    def update(
        self,
        current: LocalMapArrays,
        exact: bool = False,
        complete: bool = False,
        key_poses: IntArray | None = None,
    ) -> MapUpdate:
        """The update that brings the receivers to ``current`` (``key_poses``: indices of the
        poses held to the key tolerance; every estimate exactly when ``exact``; the whole map
        when ``complete``, or when ``current`` is not a growth)."""
        keyed = KeyedMap.of(current)
        sequence = 1 if self.held is None else self.held.sequence + 1
        changes = None
        if self.held is not None and not complete:
            tolerance = UpdateTolerance.exact() if exact else self.tolerance
            keys = keyed.pose_stamps[key_poses] if key_poses is not None else None
            changes = map_changes(self.held.map, keyed, tolerance, keys)
        if changes is None:
            update = MapUpdate(self.session, sequence, 0, 0, keyed)
            self.complete_updates += 1
        else:
            assert self.held is not None
            update = MapUpdate(
                self.session, sequence, self.held.sequence, self.held.map.num_observations, changes
            )
        self.held = apply_update(self.held, update)
        return update

    def resend(self) -> MapUpdate | None:
        """The held map as a complete update (a receiver asked for a resync); None before the
        first update."""
        if self.held is None:
            return None
        self.complete_updates += 1
        update = MapUpdate(self.session, self.held.sequence + 1, 0, 0, self.held.map)
        self.held = apply_update(self.held, update)
        return update
