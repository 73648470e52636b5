"""Conversions of local maps, rendezvous poses and C-SAM results to and from messages.

A smoother publishes its :class:`~csam_ros.core.smoothing.robot_map.RobotMap` as a
``csam_msgs/LocalMap``: the estimate, marginal pose covariances, feature estimates, and the local
problem as whitened factors; the merger rebuilds the same ``RobotMap`` from it
(:func:`robot_map_from_message`), so the merger runs exactly the core's
:func:`~csam_ros.core.joining.join.join_maps` on what offline replay computes in-process.
"""

from __future__ import annotations

import array
import struct
from collections.abc import Sequence

import numpy as np
from csam_msgs.msg import (
    Association,
    BaseNode,
    FeatureEstimate,
    JoinedMap,
    LocalMap,
    LocalMapUpdate,
    ObservationFactor,
    OdometryFactor,
    RendezvousPoses,
    RobotTrajectory,
)
from geometry_msgs.msg import Pose2D
from rclpy.serialization import serialize_message
from tf2_msgs.msg import TFMessage

from csam_ros.core.exchange.local_map_checks import LocalMapArrays, rendezvous_row_mask
from csam_ros.core.exchange.map_arrays import checked_robot_map
from csam_ros.core.exchange.map_updates import KeyedMap, MapUpdate
from csam_ros.core.exchange.validation import (
    MALFORMED_RENDEZVOUS_POSES,
    ROBOT_MISMATCH,
    DropCounter,
    LocalMapError,
    RefusedMessageError,
)
from csam_ros.core.joining.alignment import ALIGNED
from csam_ros.core.joining.result import CsamResult
from csam_ros.core.model import se2
from csam_ros.core.model.log import RendezvousLog
from csam_ros.core.sam.factors import (
    PointObservation,
    RelativePose,
    RobustKernel,
    robust_kernel_name,
)
from csam_ros.core.smoothing.robot_map import RobotMap
from csam_ros.ros.conversions import (
    ns_to_time,
    rendezvous_message,
    stamp_fields,
    stamp_to_ns,
    tf_message,
    time_to_ns,
    times_from_seconds,
)


def _kernel_to_message(kernel: RobustKernel | None) -> tuple[str, float]:
    named = robust_kernel_name(kernel)
    if named is None:
        raise LocalMapError(f"robust kernel {type(kernel).__name__} has no message form")
    return named


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
    msg.pose_stamps = times_from_seconds(m.stamps)
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
    if m.odometry_calibration is not None:
        msg.odometry_calibration = np.asarray(m.odometry_calibration, dtype=float).reshape(-1)
    return msg


def _robot_of(msg: LocalMap | RendezvousPoses, robot: str | None, error: type) -> str:
    """The robot a message belongs to: ``robot`` (its topic's) when given, which the
    message's own ``robot`` field and frame must then name."""
    if robot is None:
        return msg.robot
    if msg.robot != robot:
        raise error(f"{robot}: message names robot {msg.robot!r}", ROBOT_MISMATCH)
    if msg.header.frame_id != f"{robot}/map":
        raise error(f"{robot}: frame {msg.header.frame_id!r} is not '{robot}/map'", ROBOT_MISMATCH)
    return robot


def _feature_label(member: list[str] | tuple[str, ...], robot: str) -> int:
    if len(member) != 1:
        raise LocalMapError(f"{robot}: a feature of a local map has {len(member)} members, not 1")
    owner, _, label = member[0].rpartition("/")
    if owner != robot:
        raise LocalMapError(f"{robot}: feature {member[0]!r} is not labelled '{robot}/<label>'")
    try:
        value = int(label)
    except ValueError:
        raise LocalMapError(f"{robot}: feature {member[0]!r} has no integer label") from None
    if not -(2**63) <= value < 2**63:
        raise LocalMapError(f"{robot}: feature label {value} is out of range")
    return value


def local_map_arrays(msg: LocalMap, robot: str) -> LocalMapArrays:
    """The numbers of a local map message, unchecked (only the feature labels are parsed)."""

    def rows(values: list[list[float]], width: int) -> np.ndarray:
        return np.array(values, dtype=float).reshape(-1, width)

    odo, obs = msg.odometry_factors, msg.observation_factors
    return LocalMapArrays(
        stamps=np.array([time_to_ns(t) / 1e9 for t in msg.pose_stamps], dtype=float),
        poses=rows([[p.x, p.y, p.theta] for p in msg.poses], 3),
        pose_covariances=np.asarray(msg.pose_covariances, dtype=float),
        feature_labels=np.array(
            [_feature_label(f.members, robot) for f in msg.features], dtype=np.int64
        ),
        feature_xy=rows([[f.x, f.y] for f in msg.features], 2),
        feature_cov=rows([list(f.covariance) for f in msg.features], 3),
        prior_sqrt_information=np.asarray(msg.first_pose_prior_sqrt_information, dtype=float),
        odometry_ends=np.array([[f.from_pose, f.to_pose] for f in odo], dtype=np.int64).reshape(
            -1, 2
        ),
        odometry_delta=rows([[f.delta.x, f.delta.y, f.delta.theta] for f in odo], 3),
        odometry_sqrt_information=rows([list(f.sqrt_information) for f in odo], 9),
        observation_pose=np.array([f.pose for f in obs], dtype=np.int64),
        observation_label=np.array([f.label for f in obs], dtype=np.int64),
        observation_xy=rows([[f.x, f.y] for f in obs], 2),
        observation_sqrt_information=rows([list(f.sqrt_information) for f in obs], 4),
        robust_kernel=msg.observation_robust_kernel,
        robust_parameter=float(msg.observation_robust_parameter),
        cost=float(msg.cost),
        odometry_calibration=np.asarray(msg.odometry_calibration, dtype=float),
    )


def robot_map_from_message(msg: LocalMap, robot: str | None = None) -> RobotMap:
    """Rebuild the local problem of a local map message at its published estimate.

    ``robot`` is the robot of the topic it came on (None: trust the message's ``robot``).
    A message C-SAM could not use raises :class:`LocalMapError` (:func:`checked_robot_map`).
    """
    name = _robot_of(msg, robot, LocalMapError)
    return checked_robot_map(name, local_map_arrays(msg, name))


def _numbers(values: np.ndarray, typecode: str) -> array.array:
    """A flat message field of ``values`` (``'d'`` float64, ``'q'`` int64), copied at once."""
    field = array.array(typecode)
    field.frombytes(
        np.ascontiguousarray(values, dtype=np.float64 if typecode == "d" else np.int64).tobytes()
    )
    return field


def local_map_update_message(
    update: MapUpdate, robot: str, stamp_ns: int, iterations: int = 0
) -> LocalMapUpdate:
    """The message of one update of ``robot``'s local map (the latest odometry at ``stamp_ns``)."""
    c = update.changes
    msg = LocalMapUpdate()
    msg.header.stamp = ns_to_time(stamp_ns)
    msg.header.frame_id = f"{robot}/map"
    msg.robot = robot
    msg.session, msg.sequence = update.session, update.sequence
    msg.base_sequence = update.base_sequence
    msg.pose_stamps = _numbers(c.pose_stamps, "q")
    msg.poses = _numbers(c.poses, "d")
    msg.feature_labels = _numbers(c.feature_labels, "q")
    msg.features = _numbers(c.feature_xy, "d")
    msg.first_pose_prior_sqrt_information = np.asarray(c.prior_sqrt_information, dtype=float)
    msg.odometry_stamps = _numbers(c.odometry_stamps, "q")
    msg.odometry_deltas = _numbers(c.odometry_delta, "d")
    msg.odometry_sqrt_information = _numbers(c.odometry_sqrt_information, "d")
    msg.observations_before = update.observations_before
    msg.observation_stamps = _numbers(c.observation_stamps, "q")
    msg.observation_labels = _numbers(c.observation_label, "q")
    msg.observation_points = _numbers(c.observation_xy, "d")
    msg.observation_sqrt_information = _numbers(c.observation_sqrt_information, "d")
    msg.observation_robust_kernel = c.robust_kernel
    msg.observation_robust_parameter = float(c.robust_parameter)
    msg.iterations = int(iterations)
    msg.cost = float(c.cost)
    msg.odometry_calibration = _numbers(c.odometry_calibration, "d")
    return msg


def map_update_from_message(msg: LocalMapUpdate, robot: str | None = None) -> MapUpdate:
    """The update a message carries; :class:`LocalMapError` when its fields do not fit
    together, or its sequence numbers cannot be a sender's (an update on top of another is
    the next after it); the map it leads to is checked where it is applied
    (:func:`checked_robot_map`)."""
    name = _robot_of(msg, robot, LocalMapError)

    def rows(
        values: Sequence[float] | Sequence[int], width: int, what: str, dtype: type
    ) -> np.ndarray:
        flat = np.asarray(values, dtype=dtype)
        if len(flat) % width:
            raise LocalMapError(f"{name}: {len(flat)} {what} values, not {width} per row")
        return flat.reshape(-1, width)

    pose_stamps = rows(msg.pose_stamps, 1, "pose stamp", np.int64)[:, 0]
    odometry_stamps = rows(msg.odometry_stamps, 2, "odometry stamp", np.int64)
    changes = KeyedMap(
        pose_stamps=pose_stamps,
        poses=rows(msg.poses, 3, "pose", float),
        feature_labels=rows(msg.feature_labels, 1, "feature label", np.int64)[:, 0],
        feature_xy=rows(msg.features, 2, "feature", float),
        prior_sqrt_information=np.asarray(msg.first_pose_prior_sqrt_information, dtype=float),
        odometry_stamps=odometry_stamps,
        odometry_delta=rows(msg.odometry_deltas, 3, "odometry delta", float),
        odometry_sqrt_information=rows(
            msg.odometry_sqrt_information, 9, "odometry information", float
        ),
        observation_stamps=rows(msg.observation_stamps, 1, "observation stamp", np.int64)[:, 0],
        observation_label=rows(msg.observation_labels, 1, "observation label", np.int64)[:, 0],
        observation_xy=rows(msg.observation_points, 2, "observation", float),
        observation_sqrt_information=rows(
            msg.observation_sqrt_information, 4, "observation information", float
        ),
        robust_kernel=msg.observation_robust_kernel,
        robust_parameter=float(msg.observation_robust_parameter),
        cost=float(msg.cost),
        odometry_calibration=np.asarray(msg.odometry_calibration, dtype=float),
    )
    counts = {
        "poses": (len(changes.pose_stamps), len(changes.poses)),
        "features": (len(changes.feature_labels), len(changes.feature_xy)),
        "odometry factors": (
            len(changes.odometry_stamps),
            len(changes.odometry_delta),
            len(changes.odometry_sqrt_information),
        ),
        "observation factors": (
            len(changes.observation_stamps),
            len(changes.observation_label),
            len(changes.observation_xy),
            len(changes.observation_sqrt_information),
        ),
    }
    for what, lengths in counts.items():
        if len(set(lengths)) > 1:
            raise LocalMapError(f"{name}: the fields of its {what} differ in length {lengths}")
    if np.any(np.diff(pose_stamps) <= 0):
        raise LocalMapError(f"{name}: pose stamps do not increase")
    if msg.sequence == 0 or msg.base_sequence >= msg.sequence:
        raise LocalMapError(
            f"{name}: update {msg.sequence} cannot apply to update {msg.base_sequence}"
        )
    if msg.base_sequence and msg.sequence != msg.base_sequence + 1:  # a sender's next is base + 1
        raise LocalMapError(
            f"{name}: update {msg.sequence} on update {msg.base_sequence} skips sequence numbers"
        )
    return MapUpdate(
        int(msg.session),
        int(msg.sequence),
        int(msg.base_sequence),
        int(msg.observations_before),
        changes,
    )


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
    msg.stamps = times_from_seconds(m.stamps[pose_indices])
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


def rendezvous_log_from_message(
    msg: RendezvousPoses,
    robot: str | None = None,
    robots: Sequence[str] | None = None,
    pose_stamps: np.ndarray | None = None,
    tolerance: float = 1e-6,
    drops: DropCounter | None = None,
) -> RendezvousLog:
    """The rendezvous measurements a robot made, from its rendezvous poses message.

    ``robot`` is the robot of the topic it came on (None: trust the message). A message
    whose robot or frame is not the topic's, or whose stamps, poses and pose indices do not
    match, raises :class:`RefusedMessageError` (``robot_mismatch``, ``malformed_rendezvous_poses``).
    Single measurements with bad numbers, of the robot itself, of a robot not in ``robots``
    (when given) or at a stamp inside the robot's map (``pose_stamps``) where it holds no
    pose are left out, each counted once in ``drops`` under its reason.
    """
    name = _robot_of(msg, robot, RefusedMessageError)
    k = len(msg.stamps)
    if len(msg.poses) != k or len(msg.pose_indices) != k:
        raise RefusedMessageError(
            f"{name}: {k} stamps, {len(msg.poses)} poses and {len(msg.pose_indices)} indices",
            MALFORMED_RENDEZVOUS_POSES,
        )
    poses = np.array([[p.x, p.y, p.theta] for p in msg.poses], dtype=float)
    if not np.all(np.isfinite(poses)):
        raise RefusedMessageError(
            f"{name}: a rendezvous pose is not finite", MALFORMED_RENDEZVOUS_POSES
        )
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
    keep = rendezvous_row_mask(
        name,
        list(robots) if robots is not None else sorted(set(observed) - {name}),
        stamps,
        observed,
        r,
        b,
        sr,
        sb,
        pose_stamps,
        tolerance,
        drops if drops is not None else DropCounter(),
    )
    order = np.argsort(np.array(stamps, dtype=float)[keep], kind="stable")
    index = np.flatnonzero(keep)[order]
    return RendezvousLog(
        np.array(stamps, dtype=float)[index],
        [observed[i] for i in index],
        np.array(r, dtype=float)[index],
        np.array(b, dtype=float)[index],
        np.array(sr, dtype=float)[index],
        np.array(sb, dtype=float)[index],
    )


def joined_map_message(
    result: CsamResult, stamp_ns: int, local_map_stamps: dict[str, int], robots: Sequence[str]
) -> JoinedMap:
    """The joined map message of a C-SAM result."""
    msg = _joined_map_without_trajectories(result, stamp_ns, local_map_stamps, robots)
    msg.trajectories = [
        RobotTrajectory(
            robot=name,
            stamps=times_from_seconds(stamps),
            poses=[Pose2D(x=x, y=y, theta=phi) for x, y, phi in poses.tolist()],
            sigma_phi=sigma.tolist(),
        )
        for name, stamps, poses, sigma in joined_trajectories(result, robots)
    ]
    return msg


CDR_LITTLE_ENDIAN = b"\x00\x01\x00\x00"  # the encapsulation header rclpy writes


def serialized_joined_map(
    result: CsamResult, stamp_ns: int, local_map_stamps: dict[str, int], robots: Sequence[str]
) -> bytes:
    """:func:`joined_map_message` serialized as rclpy does (CDR, little-endian), in a
    fraction of the time: the message without its trajectories, the last field, is serialized
    by rclpy, and the trajectories (most of the message: every pose of every robot) are
    appended from their arrays."""
    head = serialize_message(
        _joined_map_without_trajectories(result, stamp_ns, local_map_stamps, robots)
    )
    if head[:4] != CDR_LITTLE_ENDIAN or head[-4:] != bytes(4):
        raise ValueError("serialized JoinedMap does not end in its empty trajectories")
    out = _CdrTail(head[:-4])
    trajectories = joined_trajectories(result, robots)
    out.uint32(len(trajectories))
    for name, stamps, poses, sigma in trajectories:
        out.string(name)
        times = np.empty(len(stamps), dtype=[("sec", "<i4"), ("nanosec", "<u4")])
        times["sec"], times["nanosec"] = stamp_fields(stamps)
        out.sequence(times, 4)
        out.sequence(poses.astype("<f8"), 8)
        out.sequence(sigma.astype("<f8"), 8)
    return out.data()


class _CdrTail:
    """Appends CDR fields to a serialized message: each primitive aligned to its size from
    the start of the payload (after the 4-byte encapsulation header)."""

    def __init__(self, head: bytes) -> None:
        self.parts = [head]
        self.size = len(head) - 4

    def _align(self, size: int) -> None:
        pad = -self.size % size
        if pad:
            self.parts.append(bytes(pad))
            self.size += pad

    def _raw(self, data: bytes) -> None:
        self.parts.append(data)
        self.size += len(data)

    def uint32(self, value: int) -> None:
        self._align(4)
        self._raw(struct.pack("<I", value))

    def string(self, text: str) -> None:
        data = text.encode() + b"\x00"
        self.uint32(len(data))
        self._raw(data)

    def sequence(self, items: np.ndarray, alignment: int) -> None:
        """A sequence of fixed-size items whose fields all align to ``alignment``."""
        self.uint32(len(items))
        if len(items):
            self._align(alignment)
            self._raw(np.ascontiguousarray(items).tobytes())

    def data(self) -> bytes:
        return b"".join(self.parts)


def joined_trajectories(
    result: CsamResult, robots: Sequence[str]
) -> list[tuple[str, np.ndarray, np.ndarray, np.ndarray]]:
    """``(robot, stamps [s], joined poses (N, 3), heading sigmas (N,) or none)`` of each of
    ``robots`` joined with poses, in that order: the joined map's trajectories."""
    out = []
    for name in robots:
        r = result.robots.get(name)
        if r is None or r.poses_joined is None or not len(r.poses_joined):
            continue
        sigma = r.sigma_phi_joined if r.sigma_phi_joined is not None else []
        out.append(
            (
                name,
                np.asarray(r.stamps, dtype=float).reshape(-1),
                np.asarray(r.poses_joined, dtype=float).reshape(-1, 3),
                np.asarray(sigma, dtype=float).reshape(-1),
            )
        )
    return out


def _joined_map_without_trajectories(
    result: CsamResult, stamp_ns: int, local_map_stamps: dict[str, int], robots: Sequence[str]
) -> JoinedMap:
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


def robot_map_transforms(result: CsamResult, stamp_ns: int) -> TFMessage:
    """``/tf`` ``<reference>/map -> <robot>/map`` of each aligned robot: the transform that
    takes the robot's latest local pose to its joined pose, so that with the smoother's
    ``<robot>/map -> <robot>/base_link`` the robot is where the joined map has it now (as
    REP-105's ``map -> odom`` corrects odometry). At the first pose it is the base node; the
    joint solve bends a local map slightly, so the two differ a little later on."""
    transforms = []
    for name, robot in result.robots.items():
        if robot.alignment == ALIGNED and robot.poses_joined is not None:
            latest = se2.compose(robot.poses_joined[-1], se2.inverse(robot.poses_local[-1]))
            transforms.append((result.reference_frame, f"{name}/map", latest))
    return tf_message(transforms, stamp_ns)
