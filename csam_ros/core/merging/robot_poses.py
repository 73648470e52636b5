"""Each joined robot's latest pose in the reference frame, with its covariance: what the merger
tells a robot, and anyone else, of where the joined map has it (``/<robot>/pose``).

A robot's pose is its latest local pose ``x`` (in its frame ``G_r``) moved by its base node
``b`` (the pose of ``G_r`` in the reference frame): ``p = b (+) x``. The local map held may be
newer than the last join: ``x`` is then the newest local map's latest pose, placed by the last
join's base node, as a provisional joined map places it; when the join holds that very pose,
``x`` is the join's own estimate of it (the local map refined to its smoother's optimum), so
the pose is the base node and the last local pose of the joined map and of ``summary.json``.

Its covariance, to first order: ``P = J_b S_b J_b^T + J_x S_x J_x^T``, with ``J_b`` and ``J_x``
the Jacobians of the composition (:func:`~csam_ros.core.model.se2.compose_jacobians`), ``S_b``
the base node's marginal covariance from the joint solve and ``S_x`` the latest pose's marginal
covariance in its local map. The two are taken as independent: the correlation the joint solve
gives them is left out. The reference robot's base node is the identity with zero covariance,
so its pose is its latest local pose with the local marginal.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from csam_ros.core.joining.result import CsamResult
from csam_ros.core.model import se2
from csam_ros.core.sam.covariance import covariance_block
from csam_ros.core.sam.solver import NormalEquations
from csam_ros.core.smoothing.robot_map import RobotMap

Array = NDArray[np.float64]


@dataclass(frozen=True)
class RobotPose:
    """A robot's latest pose in the reference frame."""

    robot: str
    stamp: float  # s: the local pose's own stamp
    pose: Array  # (3,) x, y, phi in the reference frame
    covariance: Array  # (3, 3) of x, y, phi


def composed(
    base: ArrayLike, base_cov: ArrayLike, local: ArrayLike, local_cov: ArrayLike
) -> tuple[Array, Array]:
    """``base (+) local`` and its first-order covariance (3, 3), ``base`` and ``local`` taken
    as independent with covariances ``base_cov`` and ``local_cov``."""
    j_base, j_local = se2.compose_jacobians(base, local)
    base_cov = np.asarray(base_cov, dtype=float)
    local_cov = np.asarray(local_cov, dtype=float)
    cov = j_base @ base_cov @ j_base.T + j_local @ local_cov @ j_local.T
    return se2.compose(base, local), 0.5 * (cov + cov.T)


def latest_pose_covariance(m: RobotMap) -> Array:
    """The marginal covariance (3, 3) of ``m``'s latest pose in its frame ``G_r``, from a
    factorisation of its own at the estimate: ``m`` is only read, so threads may share it."""
    problem = m.problem
    system = NormalEquations(problem)
    system.linearize(problem.values)
    system.factorize(0.0)
    return covariance_block(system, problem.scalar_indices(m.pose_ids[-1:]))


class LatestPoseCovariances:
    """:func:`latest_pose_covariance` of each robot's map, computed once per map: a map held
    is replaced by a new one when its robot sends one, never changed."""

    def __init__(self) -> None:
        self._held: dict[str, tuple[RobotMap, Array]] = {}

    def __call__(self, m: RobotMap) -> Array:
        held = self._held.get(m.name)
        if held is not None and held[0] is m:
            return held[1]
        cov = latest_pose_covariance(m)
        self._held[m.name] = (m, cov)
        return cov


def robot_poses(
    result: CsamResult,
    maps: Mapping[str, RobotMap],
    covariance: Callable[[RobotMap], Array] = latest_pose_covariance,
) -> list[RobotPose]:
    """The pose of each robot ``result`` joined (the reference and the aligned ones) from its
    newest local map in ``maps`` (module docstring), in ``result``'s robot order; the local
    marginal of its latest pose is ``covariance(map)``.

    A pending robot has none; nor has a robot without a map in ``maps``, or whose map there
    starts at another stamp than the one joined (its smoother restarted: a frame no join has
    placed yet)."""
    poses = []
    for name, robot in result.robots.items():
        m = maps.get(name)
        if (
            m is None
            or not robot.joined
            or robot.base_node is None
            or robot.base_node_cov is None
            or len(robot.stamps) == 0
            or m.stamps[0] != robot.stamps[0]
        ):
            continue
        same_pose = m.stamps[-1] == robot.stamps[-1]
        local = robot.poses_local[-1] if same_pose else m.poses[-1]
        pose, cov = composed(robot.base_node, robot.base_node_cov, local, covariance(m))
        poses.append(RobotPose(name, float(m.stamps[-1]), pose, cov))
    return poses
