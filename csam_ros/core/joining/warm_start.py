"""Starting a join from the last one: initial values from the previous solve.

A live merger joins maps that grow a little between solves. :func:`~csam_ros.core.joining.join.
join_maps` takes the previous :class:`~csam_ros.core.joining.result.CsamResult` as a
:class:`WarmStart`: initial values only, the problem solved is the same, so converged a
warm join equals a cold one on the same inputs.

Initial values (docs/METHOD.md section 6.4):

- Algorithm 1 starts each robot that was aligned before at its previous base node ``b_r``
  (the pairwise initialisation still decides whether it can be placed at all);
- the joint solve starts each pose at its local pose moved by the correction
  ``C = x_joined (+) x_local^-1`` the previous join made at the same stamp, so that what the
  smoother changed in the local map since (it re-solves as data arrives) is carried over; a
  new pose takes the correction of the nearest earlier pose held before (the nearest later
  one when there is none), so a trajectory that grew at its end continues smoothly;
- each feature starts at its previous joined position plus its local change since, rotated
  into the reference frame, when it was in the joined map, else at its local position moved
  by the base node.

:func:`carried_forward` publishes these starting values as they are: the newest local maps
placed by the last join, a provisional joined map for the time a join takes
(docs/METHOD.md section 6.4).
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from csam_ros.core.joining.notes import Note
from csam_ros.core.joining.result import CsamResult, FeatureResult, RobotResult
from csam_ros.core.model import se2
from csam_ros.core.model.stamps import corrected_poses, matching_stamp
from csam_ros.core.smoothing.robot_map import RobotMap

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]


@dataclass(frozen=True)
class WarmStart:
    """The previous join's estimates, by robot name, stamp and feature member."""

    reference: str
    base_nodes: Mapping[str, Array]  # Algorithm 1 base node of each robot aligned before
    corrections: Mapping[str, tuple[Array, Array]]  # robot -> (stamps, C = joined (+) local^-1)
    features: Mapping[str, tuple[Array, Array]]  # "robot/label" -> (joined, local) position
    # robot -> (rendezvous stamps, Algorithm 1's rendezvous poses (+) their local ones^-1)
    rendezvous: Mapping[str, tuple[Array, Array]] = field(default_factory=dict)

    @classmethod
    def from_result(cls, result: CsamResult) -> WarmStart:
        """The estimates of a result (only its joined robots and features)."""
        base_nodes: dict[str, Array] = {}
        corrections: dict[str, tuple[Array, Array]] = {}
        rendezvous: dict[str, tuple[Array, Array]] = {}
        local: dict[str, Array] = {}
        for name, robot in result.robots.items():
            if not robot.joined or robot.poses_joined is None:
                continue
            joined = np.asarray(robot.poses_joined, dtype=float)
            correction = se2.compose(joined, se2.inverse(robot.poses_local))
            corrections[name] = (np.asarray(robot.stamps, dtype=float), correction)
            if robot.alignment_base_node is not None:
                base_nodes[name] = np.asarray(robot.alignment_base_node, dtype=float)
            if robot.alignment_rendezvous_poses is not None:
                stamps = np.asarray(robot.rendezvous_stamps, dtype=float)
                held = matching_stamp(np.asarray(robot.stamps, dtype=float), stamps, 0.0)
                rendezvous[name] = (
                    stamps,
                    se2.compose(
                        robot.alignment_rendezvous_poses, se2.inverse(robot.poses_local[held])
                    ),
                )
            for label, xy in zip(robot.feature_labels_local, robot.features_local, strict=True):
                local[f"{name}/{int(label)}"] = np.asarray(xy, dtype=float)
        features = {
            m: (np.asarray(f.xy, dtype=float), local[m])
            for f in result.features
            for m in f.members
            if m in local
        }
        return cls(result.reference, base_nodes, corrections, features, rendezvous)

    def base_node_starts(self, names: Sequence[str]) -> Array:
        """(R, 3) previous base nodes of ``names`` in order, NaN rows for robots without."""
        starts = np.full((len(names), 3), np.nan)
        for r, name in enumerate(names):
            if name in self.base_nodes:
                starts[r] = self.base_nodes[name]
        return starts

    def pose_start(
        self, name: str, stamps: Array, local_poses: Array, base_node: Array, tolerance: float
    ) -> Array:
        """(N, 3) initial joined poses of robot ``name`` (module docs)."""
        corrected = corrected_poses(self.corrections.get(name), stamps, local_poses, tolerance)
        if corrected is None:
            return se2.compose(np.broadcast_to(base_node, local_poses.shape), local_poses)
        return corrected

    def rendezvous_start(
        self, name: str, stamps: Array, local_poses: Array, tolerance: float
    ) -> Array:
        """(k, 3) initial Algorithm 1 rendezvous poses of robot ``name`` at ``stamps`` (in
        its own frame): their local estimates moved as the last join's Algorithm 1 moved
        them (a new one as the last one before it), or the local estimates alone."""
        corrected = corrected_poses(self.rendezvous.get(name), stamps, local_poses, tolerance)
        return local_poses if corrected is None else corrected

    def feature_start(
        self, name: str, labels: IntArray, local_xy: Array, base_node: Array
    ) -> Array:
        """(F, 2) initial joined positions of robot ``name``'s features (module docs)."""
        start = se2.transform_point(np.broadcast_to(base_node, (len(labels), 3)), local_xy)
        c, s = np.cos(base_node[2]), np.sin(base_node[2])
        for i, label in enumerate(labels):
            before = self.features.get(f"{name}/{int(label)}")
            if before is not None:
                joined, local = before
                dx, dy = local_xy[i] - local
                start[i] = joined + [c * dx - s * dy, s * dx + c * dy]
        return start


def carried_forward(previous: CsamResult, maps: Sequence[RobotMap], tolerance: float) -> CsamResult:
    """The joined map of ``maps`` as the join ``previous`` placed their robots, unsolved.

    A robot joined in ``previous`` keeps its base node, alignment and base node covariance;
    its poses and features are the next join's starting values (:class:`WarmStart`: its
    local poses moved by the corrections at their stamps, its features by their local change
    since), an associated feature at the mean of its members, as
    :func:`~csam_ros.core.joining.joint_solve` starts it. Features first seen since
    ``previous`` enter alone; they and every pose have no marginals yet (NaN covariances, no
    heading sigmas). A robot not joined in ``previous`` stays pending. Given ``previous``'s
    own maps, the result is ``previous``'s estimate; ``tolerance`` [s] matches stamps.
    """
    start = time.perf_counter()
    warm = WarmStart.from_result(previous)
    robots: dict[str, RobotResult] = {}
    carried: dict[str, Array] = {}  # "robot/label" -> position in the reference frame
    for m in maps:
        before = previous.robots.get(m.name)
        stamps = np.asarray(m.stamps, dtype=float)
        labels = np.asarray(m.feature_labels, dtype=np.int64)
        robot = RobotResult(
            name=m.name,
            alignment="pending: not in the last join",
            stamps=stamps,
            poses_local=m.poses,
            sigma_phi_local=np.full(len(stamps), np.nan),
            feature_labels_local=labels,
            features_local=m.feature_positions,
            feature_covariances_local=np.full((len(labels), 2, 2), np.nan),
        )
        robots[m.name] = robot
        if before is None:
            continue
        robot.alignment = before.alignment
        if not before.joined or before.base_node is None:
            continue
        base = np.asarray(before.base_node, dtype=float)
        robot.base_node, robot.base_node_cov = base, before.base_node_cov
        robot.alignment_method = before.alignment_method
        robot.poses_joined = warm.pose_start(m.name, stamps, robot.poses_local, base, tolerance)
        xy = warm.feature_start(m.name, labels, robot.features_local, base)
        carried.update((f"{m.name}/{int(k)}", p) for k, p in zip(labels, xy, strict=True))
    features: list[FeatureResult] = []
    for f in previous.features:
        members = [k for k in f.members if k in carried]
        if members:
            xy = np.mean([carried[k] for k in members], axis=0)
            features.append(FeatureResult(members, xy, np.asarray(f.cov, dtype=float)))
    placed = {k for f in features for k in f.members}
    features.extend(
        FeatureResult([k], xy, np.full((2, 2), np.nan))
        for k, xy in carried.items()
        if k not in placed
    )
    return CsamResult(
        reference_frame=previous.reference_frame,
        robots=robots,
        features=features,
        associations=[a for a in previous.associations if a.a in carried and a.b in carried],
        timing_s={"carried_forward": time.perf_counter() - start},
        notes=[Note.provisional("the local maps placed by the last join, not solved")],
    )
