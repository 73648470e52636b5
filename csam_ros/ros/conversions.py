"""Conversions between the core's measurement logs and ROS messages, in both directions.

The simulator node and the importers publish or write a :class:`MultiRobotLog` through
:func:`log_to_messages`; offline replay turns a bag's messages back into a log with
:class:`LogBuilder`, through the same :class:`MeasurementFilter` the smoother nodes apply, so a
bag gives the same input to the core offline as through the nodes.

Topics (docs/ARCHITECTURE.md): ``/<robot>/odom`` (nav_msgs/Odometry, twist = measured v, v_lat,
omega in the body frame with their covariance: variances on the diagonal, covariances of
correlated inputs off it; or, as drivers publish it, the integrated pose, read as differences
by the core), ``/<robot>/features``, ``/<robot>/feature_points`` (Cartesian),
``/<robot>/rendezvous``, ``/<robot>/ground_truth`` and ``/sim/features_truth``.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass

import numpy as np
from builtin_interfaces.msg import Time
from csam_msgs.msg import (
    FeatureObservation,
    FeatureObservations,
    FeaturePoint,
    FeaturePoints,
    FeaturesTruth,
    FeatureTruth,
    RendezvousObservation,
    RendezvousObservations,
)
from geometry_msgs.msg import Quaternion, TransformStamped
from nav_msgs.msg import Odometry
from numpy.typing import ArrayLike, NDArray
from tf2_msgs.msg import TFMessage

from csam_ros.core.exchange.measurement_filter import MeasurementFilter
from csam_ros.core.exchange.validation import (
    InputBounds,
    OdometryReading,
    OdometrySample,
    pose_fault,
)
from csam_ros.core.model.log import (
    CORRELATION_PAIRS,
    FeatureLog,
    FeaturePointLog,
    GroundTruth,
    MultiRobotLog,
    OdometryLog,
    RendezvousLog,
    RobotLog,
    empty_points,
)
from csam_ros.core.model.motion import odometry_poses
from csam_ros.core.model.odometry_frame import (
    OdometryFrame,
    quaternion_norm_error,
    quaternion_yaw,
)
from csam_ros.ros.topics import (
    FEATURE_POINTS,
    FEATURES,
    FEATURES_TRUTH,
    GROUND_TRUTH,
    ODOM,
    RENDEZVOUS,
    parse,
)

# Indices of vx, vy and wz in a row-major 6x6 twist covariance, and of the covariances of
# their pairs (log.CORRELATION_PAIRS) above and below the diagonal.
_TWIST_AXES = np.array([0, 1, 5])
_PAIR_I, _PAIR_J = np.array(CORRELATION_PAIRS).T
_TWIST_VARIANCE = 7 * _TWIST_AXES
_TWIST_UPPER = 6 * _TWIST_AXES[_PAIR_I] + _TWIST_AXES[_PAIR_J]
_TWIST_LOWER = 6 * _TWIST_AXES[_PAIR_J] + _TWIST_AXES[_PAIR_I]
_TWIST_PICKED = np.concatenate([_TWIST_VARIANCE, _TWIST_UPPER, _TWIST_LOWER])


def stamp_to_ns(seconds: float) -> int:
    """Seconds to integer nanoseconds (the exact form stamps travel in)."""
    return int(round(seconds * 1e9))


def ns_to_time(ns: int) -> Time:
    return Time(sec=int(ns // 1_000_000_000), nanosec=int(ns % 1_000_000_000))


def times_from_seconds(seconds: ArrayLike) -> list[Time]:
    """Stamps of many times in seconds, each as :func:`ns_to_time` of :func:`stamp_to_ns`."""
    sec, nanosec = stamp_fields(seconds)
    return [Time(sec=s, nanosec=n) for s, n in zip(sec.tolist(), nanosec.tolist(), strict=True)]


def stamp_fields(seconds: ArrayLike) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """The ``sec`` and ``nanosec`` fields of the stamps of many times in seconds
    (:func:`times_from_seconds` as arrays)."""
    ns = np.rint(np.asarray(seconds, dtype=float).reshape(-1) * 1e9).astype(np.int64)
    return np.divmod(ns, 1_000_000_000)


def time_to_ns(stamp: Time) -> int:
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def time_to_seconds(stamp: Time) -> float:
    """A message stamp in seconds, computed the same way on every path."""
    return time_to_ns(stamp) / 1e9


def yaw_quaternion(yaw: float) -> Quaternion:
    """The orientation of a planar pose: rotation by ``yaw`` [rad] about z."""
    return Quaternion(z=float(np.sin(yaw / 2)), w=float(np.cos(yaw / 2)))


def tf_message(transforms: Sequence[tuple[str, str, np.ndarray]], stamp_ns: int) -> TFMessage:
    """``/tf`` of planar transforms ``(parent, child, pose)``: frame ``child`` at ``pose``
    (x, y, yaw) in frame ``parent``, all at ``stamp_ns``."""
    return TFMessage(
        transforms=[
            transform_stamped(parent, child, stamp_ns, (pose[0], pose[1], 0.0), float(pose[2]))
            for parent, child, pose in transforms
        ]
    )


def transform_stamped(
    parent: str, child: str, stamp_ns: int, translation: Sequence[float], yaw: float = 0.0
) -> TransformStamped:
    """Frame ``child`` at ``translation`` (x, y, z) in frame ``parent``, turned by ``yaw``."""
    t = TransformStamped()
    t.header.stamp = ns_to_time(stamp_ns)
    t.header.frame_id, t.child_frame_id = parent, child
    x, y, z = (float(c) for c in translation)
    t.transform.translation.x, t.transform.translation.y, t.transform.translation.z = x, y, z
    t.transform.rotation = yaw_quaternion(yaw)
    return t


def odometry_message(
    robot: str,
    stamp_ns: int,
    inputs: np.ndarray,
    sigmas: np.ndarray,
    correlations: np.ndarray | None = None,
    pose: np.ndarray | None = None,
) -> Odometry:
    """One odometry sample: mean (v, v_lat, omega) over the interval ending at the stamp, its
    sigmas and, if given, the correlations of its pairs (log.CORRELATION_PAIRS); with
    ``pose`` (x, y, yaw in ``<robot>/odom``) the integrated pose as a driver publishes it,
    else the pose marked unknown."""
    msg = Odometry()
    msg.header.stamp = ns_to_time(stamp_ns)
    msg.header.frame_id = f"{robot}/odom"
    msg.child_frame_id = f"{robot}/base_link"
    msg.twist.twist.linear.x = float(inputs[0])
    msg.twist.twist.linear.y = float(inputs[1])
    msg.twist.twist.angular.z = float(inputs[2])
    cov = np.zeros(36)
    sigmas = np.asarray(sigmas, dtype=float)
    cov[_TWIST_VARIANCE] = np.square(sigmas)
    if correlations is not None:
        pairs = np.asarray(correlations, dtype=float) * sigmas[_PAIR_I] * sigmas[_PAIR_J]
        cov[_TWIST_UPPER] = cov[_TWIST_LOWER] = pairs
    msg.twist.covariance = cov
    if pose is None:
        msg.pose.covariance[0] = -1.0  # REP-145 style: the pose part is not estimated here
    else:
        msg.pose.pose.position.x, msg.pose.pose.position.y = float(pose[0]), float(pose[1])
        msg.pose.pose.orientation = yaw_quaternion(float(pose[2]))
    return msg


def odometry_reading_from_message(msg: Odometry) -> OdometryReading:
    """What the core reads of an odometry message (:class:`OdometryReading`): the twist with
    its covariance (the variances of v, v_lat, omega and the covariances of their pairs, the
    mean of both sides; None when its first entry is -1, unknown), and the integrated pose
    with how far its quaternion is off unit norm (None when the pose covariance's first
    entry is -1). The pose's covariance (the integrated drift) is not used."""
    t = msg.twist.twist
    # one indexing of the 36 entries, then plain floats: once per odometry message
    twist_cov = np.asarray(msg.twist.covariance, dtype=float)
    covariance = None
    if twist_cov[0] != -1.0:
        v0, v1, v2, *pairs = twist_cov[_TWIST_PICKED].tolist()
        upper = [0.5 * (a + b) for a, b in zip(pairs[:3], pairs[3:], strict=True)]
        covariance = (v0, v1, v2, *upper)
    pose = None
    error = 0.0
    if msg.pose.covariance[0] != -1.0:
        p, q = msg.pose.pose.position, msg.pose.pose.orientation
        pose = (float(p.x), float(p.y), quaternion_yaw(q.x, q.y, q.z, q.w))
        error = quaternion_norm_error(q.x, q.y, q.z, q.w)
    return OdometryReading(
        time_to_seconds(msg.header.stamp),
        (float(t.linear.x), float(t.linear.y), float(t.angular.z)),
        covariance,
        pose,
        error,
    )


class OdometryTransforms:
    """``odom -> base_link`` on ``/tf`` for a source of odometry without a driver of its own
    (the simulator, the player): each message's own pose, or where the message marks it
    unknown the dead reckoning of the twists in that odometry frame, from its first sample
    at the origin (:class:`~csam_ros.core.model.odometry_frame.OdometryFrame`, as the smoother
    takes it). Frames are the message's (``<robot>/odom``, ``<robot>/base_link`` where empty).
    """

    def __init__(self) -> None:
        self.frames: dict[str, OdometryFrame] = {}

    def transform(self, robot: str, msg: Odometry) -> TransformStamped | None:
        """The transform of one odometry message in stamp order, or None for one with no
        usable pose (not finite, no rotation, out of order)."""
        parent = msg.header.frame_id or f"{robot}/odom"
        child = msg.child_frame_id or f"{robot}/base_link"
        reading = odometry_reading_from_message(msg)
        frame = self.frames.setdefault(parent, OdometryFrame(keep=2))
        latest = frame.latest
        if latest is not None and reading.stamp <= latest[0]:
            return None
        if reading.pose is not None:
            if pose_fault(reading) is not None:
                return None
            frame.add(reading.stamp, reading.twist, reading.pose)
            t = TransformStamped()
            t.header.stamp, t.header.frame_id, t.child_frame_id = msg.header.stamp, parent, child
            p, q = msg.pose.pose.position, msg.pose.pose.orientation
            t.transform.translation.x, t.transform.translation.y = p.x, p.y
            t.transform.translation.z = p.z
            t.transform.rotation = q
            return t
        if not (math.isfinite(reading.stamp) and all(map(math.isfinite, reading.twist))):
            return None
        pose = frame.add(reading.stamp, reading.twist)
        stamp_ns = time_to_ns(msg.header.stamp)
        return transform_stamped(parent, child, stamp_ns, (pose[0], pose[1], 0.0), pose[2])


def _observations_message(
    msg, robot: str, stamp_ns: int, observation, ids, ranges, bearings, sigma_range, sigma_bearing
):
    """``msg`` (features or rendezvous) stamped in the robot's body frame, with one
    ``observation(id, range=, bearing=, sigma_range=, sigma_bearing=)`` per row."""
    msg.header.stamp = ns_to_time(stamp_ns)
    msg.header.frame_id = f"{robot}/base_link"
    msg.observations = [
        observation(
            i,
            range=float(r),
            bearing=float(b),
            sigma_range=float(sr),
            sigma_bearing=float(sb),
        )
        for i, r, b, sr, sb in zip(ids, ranges, bearings, sigma_range, sigma_bearing, strict=True)
    ]
    return msg


def _observation_arrays(obs) -> dict[str, np.ndarray]:
    """Arrays ranges, bearings, sigma_range, sigma_bearing of observations in a message."""
    return {
        "ranges": np.array([o.range for o in obs], dtype=float),
        "bearings": np.array([o.bearing for o in obs], dtype=float),
        "sigma_range": np.array([o.sigma_range for o in obs], dtype=float),
        "sigma_bearing": np.array([o.sigma_bearing for o in obs], dtype=float),
    }


def features_message(
    robot: str, stamp_ns: int, labels, ranges, bearings, sigma_range, sigma_bearing
) -> FeatureObservations:
    return _observations_message(
        FeatureObservations(),
        robot,
        stamp_ns,
        lambda k, **measured: FeatureObservation(label=int(k), **measured),
        labels,
        ranges,
        bearings,
        sigma_range,
        sigma_bearing,
    )


def features_from_message(msg: FeatureObservations) -> tuple[float, dict[str, np.ndarray]]:
    """(stamp [s], arrays labels, ranges, bearings, sigma_range, sigma_bearing)."""
    obs = msg.observations
    arrays = {
        "labels": np.array([o.label for o in obs], dtype=np.int64),
        **_observation_arrays(obs),
    }
    return time_to_seconds(msg.header.stamp), arrays


def feature_points_message(robot: str, stamp_ns: int, labels, points, covariances) -> FeaturePoints:
    """Cartesian feature observations ``points`` ``(K, 2)`` with ``covariances`` ``(K, 2, 2)``
    at one stamp, in the robot's body frame."""
    msg = FeaturePoints()
    msg.header.stamp = ns_to_time(stamp_ns)
    msg.header.frame_id = f"{robot}/base_link"
    msg.observations = [
        FeaturePoint(
            label=int(k), x=float(p[0]), y=float(p[1]), covariance=[c[0, 0], c[0, 1], c[1, 1]]
        )
        for k, p, c in zip(labels, points, covariances, strict=True)
    ]
    return msg


def feature_points_from_message(msg: FeaturePoints) -> tuple[float, dict[str, np.ndarray]]:
    """(stamp [s], arrays labels (K,), points (K, 2), covariances (K, 2, 2))."""
    obs = msg.observations
    c = np.array([o.covariance for o in obs], dtype=float).reshape(-1, 3)
    return time_to_seconds(msg.header.stamp), {
        "labels": np.array([o.label for o in obs], dtype=np.int64),
        "points": np.array([[o.x, o.y] for o in obs], dtype=float).reshape(-1, 2),
        "covariances": np.stack([c[:, 0], c[:, 1], c[:, 1], c[:, 2]], axis=1).reshape(-1, 2, 2),
    }


def rendezvous_message(
    robot: str, stamp_ns: int, observed, ranges, bearings, sigma_range, sigma_bearing
) -> RendezvousObservations:
    return _observations_message(
        RendezvousObservations(),
        robot,
        stamp_ns,
        lambda q, **measured: RendezvousObservation(observed_robot=str(q), **measured),
        observed,
        ranges,
        bearings,
        sigma_range,
        sigma_bearing,
    )


def rendezvous_from_message(msg: RendezvousObservations) -> tuple[float, dict[str, object]]:
    """(stamp [s], observed names and arrays ranges, bearings, sigma_range, sigma_bearing)."""
    obs = msg.observations
    arrays: dict[str, object] = {
        "observed": np.array([o.observed_robot for o in obs], dtype=object),
        **_observation_arrays(obs),
    }
    return time_to_seconds(msg.header.stamp), arrays


def ground_truth_message(robot: str, stamp_ns: int, pose: np.ndarray) -> Odometry:
    msg = Odometry()
    msg.header.stamp = ns_to_time(stamp_ns)
    msg.header.frame_id = "world"
    msg.child_frame_id = f"{robot}/base_link"
    msg.pose.pose.position.x = float(pose[0])
    msg.pose.pose.position.y = float(pose[1])
    msg.pose.pose.orientation = yaw_quaternion(pose[2])
    return msg


def features_truth_message(truth: GroundTruth) -> FeaturesTruth:
    """All true features with the robot labels that name each (for scoring only)."""
    labels: dict[int, list[str]] = {int(f): [] for f in truth.feature_ids}
    for robot, mapping in truth.label_to_feature.items():
        for label, feature in sorted(mapping.items()):
            labels.setdefault(int(feature), []).append(f"{robot}/{label}")
    msg = FeaturesTruth()
    msg.header.frame_id = "world"
    msg.features = [
        FeatureTruth(feature_id=int(f), x=float(p[0]), y=float(p[1]), labels=labels[int(f)])
        for f, p in zip(truth.feature_ids, truth.feature_positions, strict=True)
    ]
    return msg


def truth_from_message(msg: FeaturesTruth) -> GroundTruth:
    """Ground truth of features back from its message (no trajectories)."""
    ids = np.array([f.feature_id for f in msg.features], dtype=np.int64)
    xy = np.array([[f.x, f.y] for f in msg.features], dtype=float).reshape(-1, 2)
    label_to_feature: dict[str, dict[int, int]] = {}
    for f in msg.features:
        for member in f.labels:
            robot, _, label = member.rpartition("/")
            label_to_feature.setdefault(robot, {})[int(label)] = int(f.feature_id)
    return GroundTruth(ids, xy, label_to_feature)


@dataclass(frozen=True)
class StampedMessage:
    """A message to publish or write at ``stamp_ns`` on ``topic``."""

    stamp_ns: int
    topic: str
    message: object


def _groups(stamps: np.ndarray) -> Iterator[tuple[float, slice]]:
    """Runs of equal stamps in a sorted stamp array."""
    if len(stamps) == 0:
        return
    starts = np.flatnonzero(np.r_[True, np.diff(stamps) != 0])
    ends = np.r_[starts[1:], len(stamps)]
    for s, e in zip(starts, ends, strict=True):
        yield float(stamps[s]), slice(int(s), int(e))


def log_to_messages(
    log: MultiRobotLog, with_truth: bool = True, with_poses: bool = False
) -> list[StampedMessage]:
    """Every robot's measurements as messages in stamp order (stable: robots in log order).

    Feature and rendezvous observations sharing a stamp travel in one message. With
    ``with_truth``, the features' ground truth comes first (stamped at the first stamp) and each
    robot's true pose follows each of its odometry samples. With ``with_poses`` the odometry
    also carries its integrated pose in ``<robot>/odom`` (the dead reckoning of the samples
    from the first one, at the origin), as a robot driver's does.
    """
    out: list[StampedMessage] = []
    for name, robot in log.robots.items():
        odo = robot.odometry
        poses: list[np.ndarray | None] = [None] * len(odo.stamps)
        if with_poses and len(odo.stamps):
            poses = list(odometry_poses(odo.stamps, odo.inputs))
        truth_poses = None
        if with_truth and log.truth is not None and name in log.truth.trajectories:
            truth_stamps = log.truth.trajectory_stamps[name]
            truth_poses = dict(
                zip(truth_stamps.tolist(), log.truth.trajectories[name], strict=True)
            )
        rho = odo.correlations if odo.correlations is not None else [None] * len(odo.stamps)
        samples = zip(odo.stamps, odo.inputs, odo.sigmas, rho, poses, strict=True)
        for t, u, s, c, p in samples:
            ns = stamp_to_ns(t)
            msg = odometry_message(name, ns, u, s, c, p)
            out.append(StampedMessage(ns, ODOM.of(name), msg))
            if truth_poses is not None and float(t) in truth_poses:
                pose = truth_poses[float(t)]
                out.append(
                    StampedMessage(ns, GROUND_TRUTH.of(name), ground_truth_message(name, ns, pose))
                )
        f = robot.features
        for t, g in _groups(f.stamps):
            ns = stamp_to_ns(t)
            msg = features_message(
                name,
                ns,
                f.labels[g],
                f.ranges[g],
                f.bearings[g],
                f.sigma_range[g],
                f.sigma_bearing[g],
            )
            out.append(StampedMessage(ns, FEATURES.of(name), msg))
        p = robot.points
        for t, g in _groups(p.stamps):
            ns = stamp_to_ns(t)
            msg = feature_points_message(name, ns, p.labels[g], p.points[g], p.covariances[g])
            out.append(StampedMessage(ns, FEATURE_POINTS.of(name), msg))
        rv = robot.rendezvous
        for t, g in _groups(rv.stamps):
            ns = stamp_to_ns(t)
            msg = rendezvous_message(
                name,
                ns,
                rv.observed[g],
                rv.ranges[g],
                rv.bearings[g],
                rv.sigma_range[g],
                rv.sigma_bearing[g],
            )
            out.append(StampedMessage(ns, RENDEZVOUS.of(name), msg))
    out.sort(key=lambda m: m.stamp_ns)  # stable: per stamp, robots and topics keep their order
    if with_truth and log.truth is not None:
        first = out[0].stamp_ns if out else 0
        truth_msg = features_truth_message(log.truth)
        truth_msg.header.stamp = ns_to_time(first)
        out.insert(0, StampedMessage(first, FEATURES_TRUTH.name, truth_msg))
    return out


class LogBuilder:
    """Collects sensor messages (in arrival order) into a :class:`MultiRobotLog`.

    Every message passes the same :class:`MeasurementFilter` (with the same ``bounds``) as in
    the smoother nodes; drops are in ``filter.drops``. Robots appear in the order of ``robots``
    (or of first accepted data).
    """

    def __init__(
        self,
        robots: list[str] | None = None,
        field_of_view: float = 2 * np.pi,
        bounds: InputBounds | None = None,
    ) -> None:
        self.filter = MeasurementFilter(robots, field_of_view, bounds)
        self._order: list[str] = list(robots or [])
        self._odometry: dict[str, list[OdometrySample]] = {}
        self._features: dict[str, list[tuple[float, dict[str, np.ndarray]]]] = {}
        self._points: dict[str, list[tuple[float, dict[str, np.ndarray]]]] = {}
        self._rendezvous: dict[str, list[tuple[float, dict[str, object]]]] = {}
        self.truth: GroundTruth | None = None

    def _robot(self, name: str) -> None:
        if name not in self._order and self.filter.robots is None:
            self._order.append(name)

    def add(self, topic_name: str, msg: object) -> None:
        """Add one message of any sensor or truth topic; other topics are ignored."""
        declared = parse(topic_name)
        if declared is None:
            return
        topic, robot = declared
        if topic is FEATURES_TRUTH:
            self.truth = truth_from_message(msg)  # type: ignore[arg-type]
        elif topic is ODOM:
            reading = odometry_reading_from_message(msg)  # type: ignore[arg-type]
            samples = self.filter.odometry_reading(robot, reading)
            if samples:
                self._robot(robot)
                self._odometry.setdefault(robot, []).extend(s for s, _ in samples)
        elif topic is FEATURE_POINTS:
            stamp, a = feature_points_from_message(msg)  # type: ignore[arg-type]
            keep = self.filter.points(robot, stamp, a["points"], a["covariances"])
            if keep is not None:
                self._robot(robot)
                self._points.setdefault(robot, []).append(
                    (stamp, {k: v[keep] for k, v in a.items()})
                )
        elif topic is FEATURES:
            stamp, a = features_from_message(msg)  # type: ignore[arg-type]
            keep = self.filter.features(
                robot, stamp, a["ranges"], a["bearings"], a["sigma_range"], a["sigma_bearing"]
            )
            if keep is not None:
                self._robot(robot)
                self._features.setdefault(robot, []).append(
                    (stamp, {k: v[keep] for k, v in a.items()})
                )
        elif topic is RENDEZVOUS:
            stamp, a = rendezvous_from_message(msg)  # type: ignore[arg-type]
            keep = self.filter.rendezvous(
                robot,
                stamp,
                a["observed"],
                a["ranges"],
                a["bearings"],
                a["sigma_range"],
                a["sigma_bearing"],
            )
            if keep is not None:
                self._robot(robot)
                kept = {k: v[keep] for k, v in a.items()}
                self._rendezvous.setdefault(robot, []).append((stamp, kept))

    def build(self) -> MultiRobotLog:
        robots: dict[str, RobotLog] = {}
        for name in self._order:
            odo = self._odometry.get(name, [])
            rho = np.array([o[3] for o in odo], dtype=float).reshape(-1, 3)
            odometry = OdometryLog(
                np.array([o[0] for o in odo], dtype=float),
                np.array([o[1] for o in odo], dtype=float).reshape(-1, 3),
                np.array([o[2] for o in odo], dtype=float).reshape(-1, 3),
                rho if rho.any() else None,
            )
            robots[name] = RobotLog(
                name,
                odometry,
                _feature_log(self._features.get(name, [])),
                rendezvous_log_from_chunks(self._rendezvous.get(name, [])),
                _point_log(self._points.get(name, [])),
            )
        return MultiRobotLog(robots, self.truth)


def _stacked(chunks: list[tuple[float, dict]], key: str, dtype) -> np.ndarray:
    if not chunks:
        return np.zeros(0, dtype=dtype)
    return np.concatenate([np.asarray(c[1][key], dtype=dtype) for c in chunks])


def _feature_log(chunks: list[tuple[float, dict[str, np.ndarray]]]) -> FeatureLog:
    stamps = (
        np.concatenate([np.full(len(c[1]["ranges"]), c[0]) for c in chunks])
        if chunks
        else np.zeros(0)
    )
    return FeatureLog(
        stamps,
        _stacked(chunks, "labels", np.int64),
        _stacked(chunks, "ranges", float),
        _stacked(chunks, "bearings", float),
        _stacked(chunks, "sigma_range", float),
        _stacked(chunks, "sigma_bearing", float),
    )


def _point_log(chunks: list[tuple[float, dict[str, np.ndarray]]]) -> FeaturePointLog:
    """Feature points accepted message by message, as one log."""
    if not chunks:
        return empty_points()
    return FeaturePointLog(
        np.concatenate([np.full(len(c[1]["labels"]), c[0]) for c in chunks]),
        _stacked(chunks, "labels", np.int64),
        np.concatenate([c[1]["points"] for c in chunks]).reshape(-1, 2),
        np.concatenate([c[1]["covariances"] for c in chunks]).reshape(-1, 2, 2),
    )


def rendezvous_log_from_chunks(chunks: list[tuple[float, dict[str, object]]]) -> RendezvousLog:
    """Rendezvous observations accepted message by message, as one log."""
    stamps = (
        np.concatenate([np.full(len(c[1]["ranges"]), c[0]) for c in chunks])
        if chunks
        else np.zeros(0)
    )
    observed = [str(q) for c in chunks for q in c[1]["observed"]]
    return RendezvousLog(
        stamps,
        observed,
        _stacked(chunks, "ranges", float),
        _stacked(chunks, "bearings", float),
        _stacked(chunks, "sigma_range", float),
        _stacked(chunks, "sigma_bearing", float),
    )
