"""A solved local map as plain arrays
(:class:`~csam_ros.core.exchange.local_map_checks.LocalMapArrays`) and back: what a LocalMap
message carries and a saved merger state holds."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from csam_ros.core.exchange.local_map_checks import LocalMapArrays, local_map_fault
from csam_ros.core.exchange.map_updates import HeldMap, KeyedMap
from csam_ros.core.exchange.validation import LocalMapError
from csam_ros.core.model import se2
from csam_ros.core.model.stamps import corrected_poses, matching_stamp
from csam_ros.core.sam.factors import (
    POINT,
    POSE,
    PointObservation,
    PosePrior,
    RelativePose,
    robust_kernel,
    robust_kernel_name,
)
from csam_ros.core.sam.normal_equations import SingularProblemError
from csam_ros.core.sam.solver import Problem
from csam_ros.core.smoothing.local_map_config import LocalMapOptions
from csam_ros.core.smoothing.robot_map import RobotMap

Array = NDArray[np.float64]

# how a map built from updates is taken back to its sender's optimum (checked_robot_map)
REFINE = LocalMapOptions().online_solver
# the same from the robot's last refined map: until a step lowers the cost by less than half
# a unit of chi-square (under one standard deviation; csam_ros.core.sam.solver)
REFINE_FROM_LAST = replace(REFINE, cost_tolerance=0.5)


def robot_map_arrays(m: RobotMap) -> LocalMapArrays:
    """The numbers of a local map as the merger holds it (a gauge prior, relative poses and
    point observations), in its factors' order: :func:`robot_map_from_arrays` rebuilds it."""
    problem = m.problem
    pose_index = np.full(problem.num_variables, -1, dtype=np.int64)
    pose_index[m.pose_ids] = np.arange(len(m.pose_ids))
    label_of = np.zeros(problem.num_variables, dtype=np.int64)
    label_of[m.feature_ids] = m.feature_labels
    prior = np.zeros(9)
    odo_ends, odo_delta, odo_w = (
        [np.zeros((0, 2), np.int64)],
        [np.zeros((0, 3))],
        [np.zeros((0, 9))],
    )
    obs_pose, obs_label = [np.zeros(0, np.int64)], [np.zeros(0, np.int64)]
    obs_xy, obs_w = [np.zeros((0, 2))], [np.zeros((0, 4))]
    kernel = ""
    parameter = 0.0
    for i, f in enumerate(problem.factors):
        if i == m.gauge_factor:
            prior = f.sqrt_information[0].reshape(-1)
        elif isinstance(f, RelativePose):
            odo_ends.append(pose_index[f.variables])
            odo_delta.append(f.measured)
            odo_w.append(f.sqrt_information.reshape(-1, 9))
        elif isinstance(f, PointObservation):
            obs_pose.append(pose_index[f.variables[:, 0]])
            obs_label.append(label_of[f.variables[:, 1]])
            obs_xy.append(f.measured)
            obs_w.append(f.sqrt_information.reshape(-1, 4))
            named = robust_kernel_name(f.robust)
            if named is None:
                raise ValueError(f"{m.name}: robust kernel {type(f.robust).__name__} not saved")
            kernel, parameter = named
        else:
            raise ValueError(f"{m.name}: factor kind {type(f).__name__} is not saved")
    n_features = len(m.feature_ids)
    return LocalMapArrays(
        stamps=np.asarray(m.stamps, dtype=float),
        poses=m.poses,
        pose_covariances=np.zeros(0),
        feature_labels=np.asarray(m.feature_labels, dtype=np.int64),
        feature_xy=m.feature_positions,
        feature_cov=np.zeros((n_features, 3)),
        prior_sqrt_information=np.asarray(prior, dtype=float),
        odometry_ends=np.concatenate(odo_ends).astype(np.int64),
        odometry_delta=np.concatenate(odo_delta),
        odometry_sqrt_information=np.concatenate(odo_w),
        observation_pose=np.concatenate(obs_pose).astype(np.int64),
        observation_label=np.concatenate(obs_label).astype(np.int64),
        observation_xy=np.concatenate(obs_xy),
        observation_sqrt_information=np.concatenate(obs_w),
        robust_kernel=kernel,
        robust_parameter=parameter,
        cost=float(problem.cost()),
        odometry_calibration=(
            np.zeros(0)
            if m.odometry_calibration is None
            else np.asarray(m.odometry_calibration, dtype=float).reshape(-1)
        ),
    )


def robot_map_from_arrays(name: str, m: LocalMapArrays) -> RobotMap:
    """The local problem of ``m`` at its estimate, built as the merger builds one from a
    local map message (the same variables and factors in the same order). ValueError naming
    the fault of arrays C-SAM could not use."""
    fault = local_map_fault(m)
    if fault is not None:
        raise ValueError(f"{name}: {fault}")
    problem = Problem()
    n = len(m.poses)
    pose_ids = problem.add_variables(POSE, [(name, "pose", i) for i in range(n)], m.poses)
    feature_ids = problem.add_variables(
        POINT, [(name, "feature", int(k)) for k in m.feature_labels], m.feature_xy
    )
    feature_of = dict(zip(m.feature_labels.tolist(), feature_ids.tolist(), strict=True))
    problem.add_factor(
        PosePrior(
            pose_ids[:1],
            [[0.0, 0.0, 0.0]],
            m.prior_sqrt_information.reshape(1, 3, 3),
            name=f"{name} gauge",
        )
    )
    if len(m.odometry_ends):
        problem.add_factor(
            RelativePose(
                pose_ids[m.odometry_ends[:, 0]],
                pose_ids[m.odometry_ends[:, 1]],
                m.odometry_delta,
                m.odometry_sqrt_information.reshape(-1, 3, 3),
                name=f"{name} odometry",
            )
        )
    if len(m.observation_pose):
        problem.add_factor(
            PointObservation(
                pose_ids[m.observation_pose],
                np.array([feature_of[int(k)] for k in m.observation_label], dtype=np.int64),
                m.observation_xy,
                m.observation_sqrt_information.reshape(-1, 2, 2),
                robust=robust_kernel(m.robust_kernel, m.robust_parameter),
                name=f"{name} observations",
            )
        )
    calibration = np.asarray(m.odometry_calibration, dtype=float)
    return RobotMap(
        name,
        problem,
        m.stamps,
        pose_ids,
        m.feature_labels,
        feature_ids,
        gauge_factor=0,
        odometry_calibration=calibration.reshape(2, 3) if len(calibration) else None,
    )


def checked_robot_map(
    name: str,
    arrays: LocalMapArrays,
    refine: bool = False,
    start: tuple[Array, Array] | None = None,
) -> RobotMap:
    """The local problem of ``arrays``: every field is checked first
    (:func:`~csam_ros.core.exchange.local_map_checks.local_map_fault`), then the problem is
    linearised and factored once at the estimate (non-finite or singular information, which
    C-SAM would meet at every solve). Raises :class:`LocalMapError` naming the fault, with the
    reason to count it under (``malformed_local_map``).

    ``refine``: the estimate is within a tolerance of the sender's optimum (a map built from
    local map updates), so it is taken back to that optimum first by the online smoother's
    capped Gauss-Newton (:data:`REFINE`): between a pose sent again and a neighbour held back
    the odometry would otherwise disagree by up to the tolerance, which the local map check
    counts as outliers and the local views linearise at. ``start`` (poses and features in the
    order of ``arrays``, :func:`refine_start`): where it costs less than the estimate, the
    refine starts there and stops at a step under one standard deviation
    (:data:`REFINE_FROM_LAST`)."""
    try:
        robot_map = robot_map_from_arrays(name, arrays)
    except ValueError as error:
        raise LocalMapError(str(error)) from None
    problem = robot_map.problem
    with np.errstate(all="ignore"):  # values within bounds may still overflow together
        try:
            system = problem.normal_equations()
            system.linearize(problem.values)
            system.check_blocks()
            if refine:  # its first step factors at the estimate
                warm = start is not None and problem.take_if_cheaper(values_with(robot_map, *start))
                problem.solve(REFINE_FROM_LAST if warm else REFINE)
            else:
                system.factorize(0.0)
        except (FloatingPointError, SingularProblemError, np.linalg.LinAlgError) as error:
            raise LocalMapError(f"{name}: its factors at its estimate: {error}") from None
    if not np.isfinite(problem.values).all():
        raise LocalMapError(f"{name}: its estimate refined is not finite")
    return robot_map


@dataclass(frozen=True)
class Refined:
    """A robot's map as a merger refined it (:func:`held_robot_map`) and the map built from
    updates it was refined from: where the next refine of the robot's map starts."""

    robot_map: RobotMap
    held: KeyedMap


def values_with(robot_map: RobotMap, poses: Array, features: Array) -> Array:
    """The values of ``robot_map``'s problem with its poses and features replaced."""
    problem = robot_map.problem
    values = problem.values.copy()
    values[problem.scalar_indices(robot_map.pose_ids)] = poses.reshape(-1)
    values[problem.scalar_indices(robot_map.feature_ids)] = features.reshape(-1)
    return values


def refine_start(held: KeyedMap, last: Refined) -> tuple[Array, Array]:
    """The poses and features of ``held`` to refine it from:
    every pose and feature held as it was in ``last.held`` (not sent again since) at its
    value refined in ``last.robot_map``, every other as held; a pose new since, moved as the
    nearest pose before it that was held (the first one for those before all)."""
    previous = last.held
    at = matching_stamp(previous.pose_stamps, held.pose_stamps, 0)
    matched = at >= 0
    unchanged = matched.copy()
    unchanged[matched] = np.all(previous.poses[at[matched]] == held.poses[matched], axis=1)
    corrections = np.zeros((int(matched.sum()), 3))  # the identity for poses sent again
    refined = last.robot_map.poses[at[unchanged]]
    corrections[unchanged[matched]] = se2.compose(refined, se2.inverse(held.poses[unchanged]))
    stamps = held.pose_stamps
    poses = corrected_poses((stamps[matched], corrections), stamps, held.poses, 0)
    features = held.feature_xy.copy()
    before = {int(label): k for k, label in enumerate(previous.feature_labels)}
    for k, label in enumerate(held.feature_labels):
        j = before.get(int(label))
        if j is not None and np.array_equal(previous.feature_xy[j], held.feature_xy[k]):
            features[k] = last.robot_map.feature_positions[j]
    return (held.poses if poses is None else poses), features


def held_robot_map(
    name: str, held: HeldMap, refine: bool = True, last: Refined | None = None
) -> RobotMap:
    """The local problem of a map built from updates, with ``refine`` taken back to its
    sender's optimum (:func:`checked_robot_map`; from where ``last``, the robot's map refined
    before, leads: :func:`refine_start`); :class:`LocalMapError` when it is not usable."""
    try:
        arrays = held.map.arrays()
    except ValueError as error:  # a factor at a stamp with no pose
        raise LocalMapError(f"{name}: {error}") from None
    start = refine_start(held.map, last) if refine and last is not None else None
    return checked_robot_map(name, arrays, refine=refine, start=start)
