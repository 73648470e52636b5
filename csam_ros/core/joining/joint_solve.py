"""The joint solve of C-SAM (paper section IV-B, last step of Algorithm 2; docs/METHOD.md
sections 6-7).

After alignment and association, one nonlinear least-squares problem holds every pose and
every feature of every aligned robot, all factors of their local maps, the rendezvous rows
and the associations, and is solved once to convergence. Its result is the joined map in the
reference robot's frame with every robot's full trajectory.

Parametrisation (global). Each aligned robot's poses and features are unknowns in the
reference frame, initialised from its local map moved by its base node. The reference robot
keeps its local gauge prior (first pose at the origin); every other robot's gauge prior is
dropped, so its base node *is* its first pose in the reference frame (``G_r`` is defined by
that pose). This is the same problem as local unknowns plus base nodes with every gauge prior
kept (any global configuration has exactly one such representation with zero gauge cost), but
it has no redundant unknowns. An association merges its features into one unknown (no
association rows with an artificial sigma). Rendezvous rows are the relative position of one
pose seen from another (:class:`~csam_ros.core.sam.factors.RelativePosition`). Given the same
associations this is the centralised maximum a posteriori estimate of everything all robots
measured (tested against GTSAM).
"""

from __future__ import annotations

import copy
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from csam_ros.core.model import se2
from csam_ros.core.model.rendezvous import RendezvousSet
from csam_ros.core.sam.factors import POINT, POSE, RelativePosition
from csam_ros.core.sam.normal_equations import NormalEquations
from csam_ros.core.sam.selected_inverse import BlockInverse, SelectedInverse
from csam_ros.core.sam.solver import Problem, SolveReport, SolverOptions
from csam_ros.core.smoothing.robot_map import RobotMap

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]


@dataclass
class JointSolution:
    """The joint problem after its solve, with where each robot's unknowns are in it."""

    problem: Problem
    robots: list[int]  # aligned robots, in order
    pose_ids: dict[int, IntArray]  # robot -> joint ids of its poses (stamp order)
    feature_ids: dict[int, IntArray]  # robot -> joint id of each of its local features
    features: list[list[tuple[int, int]]]  # joint feature -> (robot, label) members
    feature_var_ids: IntArray  # joint ids of the features, in the order of ``features``
    report: SolveReport
    warm_start: bool = False  # solved from the initial values given (lower cost), not cold


def joint_solve(
    maps: Sequence[RobotMap],
    robots: Sequence[int],
    base_nodes: Array,
    clusters: Sequence[Sequence[tuple[int, int]]],
    measurements: RendezvousSet,
    options: SolverOptions | None = None,
    initial_poses: Mapping[int, Array] | None = None,
    initial_features: Mapping[int, Array] | None = None,
) -> JointSolution:
    """Build and solve the joint problem of the aligned ``robots`` (module docs).

    ``robots`` lists the aligned robot indices, the reference (index 0) first;
    ``base_nodes[r]`` places ``G_r`` in the reference frame; each cluster lists the
    ``(robot, label)`` members of one associated feature (:func:`aligned_clusters` orders
    them). Cold start: each robot's local map moved by its base node (an associated feature
    at the mean of its members). Warm start: robot ``r``'s poses (N, 3) and features (F, 2)
    in the reference frame from ``initial_poses[r]`` and ``initial_features[r]`` where given,
    taken only when it costs less than the cold start (maps that changed much since can make
    it the worse start, and the robust cost has more than one minimum).
    """
    initial_poses = initial_poses or {}
    initial_features = initial_features or {}
    robots = list(robots)
    if not robots or robots[0] != 0:
        raise ValueError("joint_solve: the reference robot (index 0) must come first")
    problem = Problem()
    pose_ids: dict[int, IntArray] = {}
    cold_poses: dict[int, Array] = {}
    for r in robots:
        m = maps[r]
        cold_poses[r] = se2.compose(np.broadcast_to(base_nodes[r], (len(m.pose_ids), 3)), m.poses)
        pose_ids[r] = problem.add_variables(
            POSE,
            [(m.name, "pose", i) for i in range(len(m.pose_ids))],
            initial_poses.get(r, cold_poses[r]),
        )

    # features: one unknown per cluster, then one per remaining feature, robot by robot
    label_index = {r: {int(lab): k for k, lab in enumerate(maps[r].feature_labels)} for r in robots}
    cold_xy = {
        r: se2.transform_point(
            np.broadcast_to(base_nodes[r], (len(maps[r].feature_ids), 3)),
            maps[r].feature_positions,
        )
        for r in robots
    }
    owner: dict[int, IntArray] = {r: np.full(len(maps[r].feature_ids), -1) for r in robots}
    members: list[list[tuple[int, int]]] = []
    cluster_index: list[list[tuple[int, int]]] = []  # (robot, local index) of the members
    for inside in aligned_clusters(clusters, robots):
        k = len(members)
        for r, lab in inside:
            if lab not in label_index[r]:
                raise ValueError(f"association names unknown feature {maps[r].name}/{lab}")
            if owner[r][label_index[r][lab]] >= 0:
                raise ValueError(f"feature {maps[r].name}/{lab} is in two associations")
            owner[r][label_index[r][lab]] = k
        members.append(inside)
        cluster_index.append([(r, label_index[r][lab]) for r, lab in inside])
    free: dict[int, IntArray] = {}
    for r in robots:
        free[r] = np.flatnonzero(owner[r] < 0)
        owner[r][free[r]] = len(members) + np.arange(len(free[r]))
        members.extend([(r, int(maps[r].feature_labels[i]))] for i in free[r])

    def feature_starts(xy: Mapping[int, Array]) -> Array:
        """Each joint feature's start: its member's position, or the mean of its members'."""
        clustered = [np.mean([xy[r][i] for r, i in index], axis=0) for index in cluster_index]
        return np.concatenate(
            [np.reshape(clustered, (-1, 2)), *(np.reshape(xy[r][free[r]], (-1, 2)) for r in robots)]
        )

    keys = [
        ("feature",) + tuple(x for rl in mem for x in (maps[rl[0]].name, rl[1])) for mem in members
    ]
    feature_var_ids = (
        problem.add_variables(POINT, keys, feature_starts({**cold_xy, **initial_features}))
        if members
        else np.zeros(0, dtype=np.int64)
    )
    feature_ids = {r: feature_var_ids[owner[r]] for r in robots}

    # every local factor, with its variables renamed; non-reference gauges dropped
    for r in robots:
        m = maps[r]
        id_map = np.full(m.problem.num_variables, -1, dtype=np.int64)
        id_map[m.pose_ids] = pose_ids[r]
        id_map[m.feature_ids] = feature_ids[r]
        for i, factor in enumerate(m.problem.factors):
            if i == m.gauge_factor and r != 0:
                continue
            renamed = copy.copy(factor)
            renamed.variables = id_map[factor.variables]
            if np.any(renamed.variables < 0):
                raise ValueError(
                    f"robot {m.name!r}: factor {factor.name!r} uses a variable that is neither "
                    "a pose nor a feature of the map"
                )
            problem.add_factor(renamed)

    inside = np.isin(measurements.observer, robots) & np.isin(measurements.observed, robots)
    rows = measurements.subset(inside)
    if len(rows):
        observer = np.empty(len(rows), dtype=np.int64)
        observed = np.empty(len(rows), dtype=np.int64)
        for r in robots:
            sel = rows.observer == r
            observer[sel] = pose_ids[r][rows.observer_pose[sel]]
            sel = rows.observed == r
            observed[sel] = pose_ids[r][rows.observed_pose[sel]]
        problem.add_factor(
            RelativePosition(
                observer, observed, rows.position, covariance=rows.covariance, name="rendezvous"
            )
        )
    problem.variable_blocks = _robot_blocks(robots, pose_ids, members, feature_var_ids)
    warm_start = False
    if initial_poses or initial_features:
        warm = problem.values.copy()
        for r in robots:
            problem.set_values(pose_ids[r], cold_poses[r])
        if members:
            problem.set_values(feature_var_ids, feature_starts(cold_xy))
        warm_start = problem.take_if_cheaper(warm)
    report = problem.solve(options or SolverOptions())
    return JointSolution(
        problem, robots, pose_ids, feature_ids, members, feature_var_ids, report, warm_start
    )


def aligned_clusters(
    clusters: Sequence[Sequence[tuple[int, int]]], robots: Sequence[int]
) -> list[list[tuple[int, int]]]:
    """The members of ``clusters`` among the aligned ``robots``, each sorted, the clusters in
    the order of their members (not of Algorithm 2's decisions): equal sets of clusters give
    the same joint problem."""
    aligned = set(robots)
    inside = [
        sorted((int(r), int(lab)) for r, lab in cluster if r in aligned) for cluster in clusters
    ]
    return sorted(members for members in inside if members)


def _robot_blocks(
    robots: Sequence[int],
    pose_ids: Mapping[int, IntArray],
    members: list[list[tuple[int, int]]],
    feature_var_ids: IntArray,
) -> list[IntArray]:
    """The joint problem's variables by robot: its poses and the features whose first member
    is its own, for a factorisation by blocks where that is cheaper
    (:meth:`~csam_ros.core.sam.normal_equations.NormalEquations.factorize`)."""
    first = np.array([min(r for r, _ in mem) for mem in members], dtype=np.int64)
    return [
        np.concatenate([pose_ids[r], np.asarray(feature_var_ids)[first == r]]).astype(np.int64)
        for r in robots
    ]


def _solved_columns(system: NormalEquations, scalar_indices: IntArray) -> Array:
    """Columns ``(A^T A)^-1 e_j`` (n, k) for the given scalar positions, one solve each."""
    cols = np.asarray(scalar_indices, dtype=np.int64)
    out = np.empty((system.n, len(cols)))
    unit = np.zeros(system.n)
    for j, c in enumerate(cols):
        unit[c] = 1.0
        out[:, j] = system.solve(unit)
        unit[c] = 0.0
    return out


def heading_sigmas(
    problem: Problem,
    system: NormalEquations,
    pose_ids: IntArray,
    inverse: SelectedInverse | BlockInverse | None = None,
) -> tuple[Array, Array]:
    """Heading standard deviation of each pose, in the problem's frame and relative to the
    first of ``pose_ids`` (the robot's own frame), both (N,).

    The variances come from ``inverse`` (or one solve per pose without it); the covariances
    with the first heading from ``inverse`` where it holds them, else from one solve.
    """
    heading = problem.scalar_indices(pose_ids).reshape(-1, 3)[:, 2]
    if inverse is not None:
        var = inverse.entries(heading, heading)
        try:  # on the factor's pattern when the robot's poses are one block of it
            cross = inverse.entries(heading, np.full_like(heading, heading[0]))
        except ValueError:
            cross = _solved_columns(system, heading[:1])[heading, 0]
    else:
        sub = _solved_columns(system, heading)[heading]
        var = np.diag(sub).copy()
        cross = sub[:, 0]
    relative = var + var[0] - 2.0 * cross
    return np.sqrt(np.maximum(var, 0.0)), np.sqrt(np.maximum(relative, 0.0))
