"""Conversions of local maps, rendezvous poses and C-SAM results to and from messages.

A smoother publishes its :class:`~csam_ros.core.joining.RobotMap` as a ``csam_msgs/LocalMap``:
the estimate, marginal pose covariances, feature estimates, and the local problem as whitened
factors; the merger rebuilds the same ``RobotMap`` from it (:func:`robot_map_from_message`), so
the merger runs exactly the core's :func:`~csam_ros.core.csam.join_maps` on what offline replay
computes in-process.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from csam_msgs.msg import (
    Association,
    BaseNode,
    FeatureEstimate,
    JoinedMap,
    LocalMap,
    ObservationFactor,
    OdometryFactor,
    RendezvousPoses,
    RobotTrajectory,
)
from geometry_msgs.msg import Pose2D

from csam_ros.core.factors import (
    POINT,
    POSE,
    Cauchy,
    Huber,
    PointObservation,
    PosePrior,
    RelativePose,
    RobustKernel,
)
from csam_ros.core.joining import RobotMap
from csam_ros.core.log import RendezvousLog
from csam_ros.core.result import CsamResult
from csam_ros.core.solver import Problem
from csam_ros.ros.conversions import ns_to_time, rendezvous_message, stamp_to_ns, time_to_ns


class LocalMapError(ValueError):
    """A local map message that cannot be turned into a local problem."""


def _kernel_to_message(kernel: RobustKernel | None) -> tuple[str, float]:
    if kernel is None:
        return "", 0.0
    name = {Huber: "huber", Cauchy: "cauchy"}.get(type(kernel))
    if name is None:
        raise LocalMapError(f"robust kernel {type(kernel).__name__} has no message form")
    return name, float(kernel.threshold if isinstance(kernel, Huber) else kernel.scale)


def _kernel_from_message(name: str, parameter: float) -> RobustKernel | None:
    if name == "":
        return None
    if name == "huber":
        return Huber(parameter)
    if name == "cauchy":
        return Cauchy(parameter)
    raise LocalMapError(f"unknown robust kernel {name!r}")


def robot_map_to_message(
    m: RobotMap,
    stamp_ns: int,
    pose_covariances: np.ndarray | None = None,
    feature_covariances: np.ndarray | None = None,
    iterations: int = 0,
) -> LocalMap:
    """A local map message of ``m`` (its problem must hold only the gauge prior, relative
    poses and point observations; covariances (N,3,3) and (F,2,2) when known)."""
    problem = m.problem
    pose_index = np.full(problem.num_variables, -1, dtype=np.int64)
    pose_index[m.pose_ids] = np.arange(len(m.pose_ids))
    label_of = dict(zip(m.feature_ids.tolist(), m.feature_labels.tolist(), strict=True))
    msg = LocalMap()
    msg.header.stamp = ns_to_time(stamp_ns)
    msg.header.frame_id = f"{m.name}/map"
    msg.robot = m.name
    msg.pose_stamps = [ns_to_time(stamp_to_ns(t)) for t in m.stamps]
    msg.poses = [Pose2D(x=float(p[0]), y=float(p[1]), theta=float(p[2])) for p in m.poses]
    if pose_covariances is not None:
        msg.pose_covariances = np.asarray(pose_covariances, dtype=float).reshape(-1).tolist()
    fcov = (
        np.zeros((len(m.feature_ids), 2, 2))
        if feature_covariances is None
        else np.asarray(feature_covariances)
    )
    msg.features = [
        FeatureEstimate(
            members=[f"{m.name}/{label}"],
            x=float(p[0]),
            y=float(p[1]),
            covariance=[float(c[0, 0]), float(c[0, 1]), float(c[1, 1])],
        )
        for label, p, c in zip(m.feature_labels, m.feature_positions, fcov, strict=True)
    ]
    kernel: tuple[str, float] | None = None
    for i, f in enumerate(problem.factors):
        if i == m.gauge_factor:
            msg.first_pose_prior_sqrt_information = f.sqrt_information[0].reshape(-1).tolist()
        elif isinstance(f, RelativePose):
            ends = pose_index[f.variables]
            msg.odometry_factors.extend(
                OdometryFactor(
                    from_pose=int(a),
                    to_pose=int(b),
                    delta=Pose2D(x=float(z[0]), y=float(z[1]), theta=float(z[2])),
                    sqrt_information=w.reshape(-1).tolist(),
                )
                for (a, b), z, w in zip(ends, f.measured, f.sqrt_information, strict=True)
            )
        elif isinstance(f, PointObservation):
            this_kernel = _kernel_to_message(f.robust)
            if kernel is not None and this_kernel != kernel:
                raise LocalMapError(f"{m.name}: observation factors with different kernels")
            kernel = this_kernel
            msg.observation_factors.extend(
                ObservationFactor(
                    pose=int(pose_index[a]),
                    label=int(label_of[int(b)]),
                    x=float(z[0]),
                    y=float(z[1]),
                    sqrt_information=w.reshape(-1).tolist(),
                )
                for (a, b), z, w in zip(f.variables, f.measured, f.sqrt_information, strict=True)
            )
        else:
            raise LocalMapError(f"{m.name}: factor kind {type(f).__name__} has no message form")
    msg.observation_robust_kernel, msg.observation_robust_parameter = kernel or ("", 0.0)
    msg.iterations = int(iterations)
    msg.cost = float(problem.cost())
    return msg


def robot_map_from_message(msg: LocalMap) -> RobotMap:
    """Rebuild the local problem of a local map message at its published estimate."""
    name = msg.robot
    n = len(msg.poses)
    if n == 0 or len(msg.pose_stamps) != n:
        raise LocalMapError(f"{name}: {n} poses with {len(msg.pose_stamps)} stamps")
    problem = Problem()
    poses = np.array([[p.x, p.y, p.theta] for p in msg.poses], dtype=float)
    pose_ids = problem.add_variables(POSE, [(name, "pose", i) for i in range(n)], poses)
    labels = np.array([int(f.members[0].rpartition("/")[2]) for f in msg.features], dtype=np.int64)
    xy = np.array([[f.x, f.y] for f in msg.features], dtype=float).reshape(-1, 2)
    feature_ids = problem.add_variables(POINT, [(name, "feature", int(k)) for k in labels], xy)
    feature_of = dict(zip(labels.tolist(), feature_ids.tolist(), strict=True))
    problem.add_factor(
        PosePrior(
            pose_ids[:1],
            [[0.0, 0.0, 0.0]],
            np.asarray(msg.first_pose_prior_sqrt_information, dtype=float).reshape(1, 3, 3),
            name=f"{name} gauge",
        )
    )
    odo = msg.odometry_factors
    if odo:
        ends = np.array([[f.from_pose, f.to_pose] for f in odo], dtype=np.int64)
        if ends.max() >= n:
            raise LocalMapError(f"{name}: odometry factor names pose {ends.max()} of {n}")
        problem.add_factor(
            RelativePose(
                pose_ids[ends[:, 0]],
                pose_ids[ends[:, 1]],
                np.array([[f.delta.x, f.delta.y, f.delta.theta] for f in odo]),
                np.array([f.sqrt_information for f in odo], dtype=float).reshape(-1, 3, 3),
                name=f"{name} odometry",
            )
        )
    obs = msg.observation_factors
    if obs:
        pose = np.array([f.pose for f in obs], dtype=np.int64)
        if pose.max() >= n:
            raise LocalMapError(f"{name}: observation factor names pose {pose.max()} of {n}")
        try:
            points = np.array([feature_of[int(f.label)] for f in obs], dtype=np.int64)
        except KeyError as err:
            raise LocalMapError(f"{name}: observation of unknown feature {err}") from None
        problem.add_factor(
            PointObservation(
                pose_ids[pose],
                points,
                np.array([[f.x, f.y] for f in obs]),
                np.array([f.sqrt_information for f in obs], dtype=float).reshape(-1, 2, 2),
                robust=_kernel_from_message(
                    msg.observation_robust_kernel, msg.observation_robust_parameter
                ),
                name=f"{name} observations",
            )
        )
    stamps = np.array([time_to_ns(t) / 1e9 for t in msg.pose_stamps])
    return RobotMap(name, problem, stamps, pose_ids, labels, feature_ids, gauge_factor=0)


def rendezvous_poses_message(
    m: RobotMap, stamp_ns: int, pose_indices: np.ndarray, measurements: RendezvousLog
) -> RendezvousPoses:
    """The rendezvous measurements a robot made, with its poses at rendezvous stamps (the
    merger reads only the measurements: it takes the rendezvous parts from the local map)."""
    msg = RendezvousPoses()
    msg.header.stamp = ns_to_time(stamp_ns)
    msg.header.frame_id = f"{m.name}/map"
    msg.robot = m.name
    poses = m.poses[pose_indices]
    msg.stamps = [ns_to_time(stamp_to_ns(t)) for t in m.stamps[pose_indices]]
    msg.poses = [Pose2D(x=float(p[0]), y=float(p[1]), theta=float(p[2])) for p in poses]
    msg.pose_indices = np.asarray(pose_indices, dtype=np.uint32).tolist()
    stamps = measurements.stamps
    if len(stamps):
        starts = np.flatnonzero(np.r_[True, np.diff(stamps) != 0])
        for s, e in zip(starts, np.r_[starts[1:], len(stamps)], strict=True):
            sl = slice(int(s), int(e))
            msg.measurements.append(
                rendezvous_message(
                    m.name,
                    stamp_to_ns(stamps[s]),
                    measurements.observed[sl],
                    measurements.ranges[sl],
                    measurements.bearings[sl],
                    measurements.sigma_range[sl],
                    measurements.sigma_bearing[sl],
                )
            )
    return msg


def rendezvous_log_from_message(msg: RendezvousPoses) -> RendezvousLog:
    """The rendezvous measurements a robot made, from its rendezvous poses message."""
    stamps, observed, r, b, sr, sb = [], [], [], [], [], []
    for group in msg.measurements:
        t = time_to_ns(group.header.stamp) / 1e9
        for o in group.observations:
            stamps.append(t)
            observed.append(o.observed_robot)
            r.append(o.range)
            b.append(o.bearing)
            sr.append(o.sigma_range)
            sb.append(o.sigma_bearing)
    return RendezvousLog(
        np.array(stamps, dtype=float),
        observed,
        np.array(r, dtype=float),
        np.array(b, dtype=float),
        np.array(sr, dtype=float),
        np.array(sb, dtype=float),
    )


def joined_map_message(
    result: CsamResult, stamp_ns: int, local_map_stamps: dict[str, int], robots: Sequence[str]
) -> JoinedMap:
    """The joined map message of a C-SAM result."""
    msg = JoinedMap()
    msg.header.stamp = ns_to_time(stamp_ns)
    msg.header.frame_id = result.reference_frame
    msg.reference_robot = result.reference
    for name in robots:
        r = result.robots.get(name)
        node = BaseNode(robot=name, local_map_stamp=ns_to_time(local_map_stamps.get(name, 0)))
        if r is None:
            node.alignment = "pending: no local map yet"
            msg.base_nodes.append(node)
            continue
        node.alignment = r.alignment
        if r.base_node is not None:
            x, y, phi = r.base_node
            node.pose = Pose2D(x=float(x), y=float(y), theta=float(phi))
        if r.base_node_cov is not None:
            node.covariance = np.asarray(r.base_node_cov, dtype=float).reshape(-1).tolist()
        msg.base_nodes.append(node)
        if r.poses_joined is not None and len(r.poses_joined):
            sigma = r.sigma_phi_joined if r.sigma_phi_joined is not None else []
            msg.trajectories.append(
                RobotTrajectory(
                    robot=name,
                    stamps=[ns_to_time(stamp_to_ns(float(t))) for t in r.stamps],
                    poses=[
                        Pose2D(x=float(p[0]), y=float(p[1]), theta=float(p[2]))
                        for p in r.poses_joined
                    ],
                    sigma_phi=[float(s) for s in sigma],
                )
            )
    msg.features = [
        FeatureEstimate(
            members=list(f.members),
            x=float(f.xy[0]),
            y=float(f.xy[1]),
            covariance=[float(f.cov[0][0]), float(f.cov[0][1]), float(f.cov[1][1])],
        )
        for f in result.features
    ]
    msg.associations = [
        Association(a=a.a, b=a.b, mahalanobis=float(a.mahalanobis)) for a in result.associations
    ]
    return msg
