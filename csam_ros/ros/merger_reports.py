"""What the merger reports, as ROS has it: its status
(:class:`~csam_ros.core.merging.status.MergerStatus`) as the DiagnosticArray it publishes on
``/csam/status`` (an entry ``merger/<robot>`` per robot, then ``merger``, each value a string)
and on ``/diagnostics`` (``csam/<robot>`` per robot, then ``csam``, the same values, a stale
robot at level STALE); each joined robot's pose
(:class:`~csam_ros.core.merging.robot_poses.RobotPose`) as the PoseWithCovarianceStamped of
``/<robot>/pose``; and its policy's notices (:mod:`csam_ros.core.merging.notices`) as log
lines."""

from __future__ import annotations

from typing import Any

import numpy as np
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import PoseWithCovarianceStamped

from csam_ros.core.merging.notices import Notice
from csam_ros.core.merging.robot_poses import RobotPose
from csam_ros.core.merging.status import Health, MergerStatus, RobotStatus
from csam_ros.ros.conversions import ns_to_time, stamp_to_ns, yaw_quaternion

LEVELS = {
    Health.OK: DiagnosticStatus.OK,
    Health.WARN: DiagnosticStatus.WARN,
    Health.ERROR: DiagnosticStatus.ERROR,
}
STATUS_PREFIX = "merger"  # /csam/status: merger/<robot>, then merger
DIAGNOSTICS_PREFIX = "csam"  # /diagnostics: csam/<robot>, then csam (the merger itself)

# A pose's covariance in ROS's 6x6 row-major layout (x, y, z, roll, pitch, yaw): the planar
# estimate fills the rows and columns of x, y and yaw. z, roll and pitch are not estimated (a
# planar robot's are 0 by its model): their variances and every covariance with them are 0,
# as Nav2's AMCL (amcl_pose) and slam_toolbox (pose) publish their planar poses.
PLANAR_AXES = np.array([0, 1, 5])  # x, y, yaw
UNESTIMATED_VARIANCE = 0.0  # of z, roll and pitch


def status_array(status: MergerStatus, stamp: Time) -> DiagnosticArray:
    """The ``/csam/status`` message of ``status``, stamped ``stamp``."""
    array = DiagnosticArray()
    array.header.stamp = stamp
    array.status = [_robot_entry(r, STATUS_PREFIX, LEVELS[r.health]) for r in status.robots]
    array.status.append(_merger_entry(status, STATUS_PREFIX))
    return array


def diagnostics_array(status: MergerStatus, stamp: Time) -> DiagnosticArray:
    """The ``/diagnostics`` message of ``status``, stamped ``stamp``: per robot OK when it
    is joined (the reference or aligned), WARN when pending (the message says why), STALE
    when no local map came for ``stale_after`` s; then the merger's own entry, at its
    ``/csam/status`` level. The values are ``/csam/status``'s."""
    array = DiagnosticArray()
    array.header.stamp = stamp
    array.status = [_robot_entry(r, DIAGNOSTICS_PREFIX, robot_level(r)) for r in status.robots]
    array.status.append(_merger_entry(status, DIAGNOSTICS_PREFIX))
    return array


def robot_level(r: RobotStatus) -> bytes:
    """A robot's ``/diagnostics`` level: STALE when stale, else its status entry's."""
    return DiagnosticStatus.STALE if r.stale else LEVELS[r.health]


def _merger_entry(status: MergerStatus, name: str) -> DiagnosticStatus:
    values = {
        "reference": status.reference,
        "solves": status.solves,
        "features": status.features,
        "associations": status.associations,
        "solve_seconds": round(status.solve_seconds, 4),
        "solving": status.solving,
        "solves_given_up": status.solves_given_up,
        "provisional_maps": status.provisional_maps,
        "converged": "" if status.converged is None else status.converged,
        "dropped": sum(status.dropped.values()),
        "restarts": status.restarts,
        "resync_requests": status.resync_requests,
        "outside_trajectory": status.outside_trajectory,
        "last_error": status.last_error,
        **{f"dropped/{k}": v for k, v in status.dropped.items()},
    }
    return DiagnosticStatus(
        level=LEVELS[status.health],
        name=name,
        message=status.message,
        values=_key_values(values),
    )


def _robot_entry(r: RobotStatus, prefix: str, level: bytes) -> DiagnosticStatus:
    since = r.seconds_since_map
    values = {
        "alignment": r.alignment,
        "stale": r.stale,
        "seconds_since_map": round(since, 1) if since is not None else "",
        "poses": r.poses,
        "solve_seconds": round(r.solve_seconds, 4),
        "restarts": r.restarts,
        "restart_poses_lost": r.restart_poses_lost,
        "update": r.update,
        "resync_requests": r.resync_requests,
    }
    if r.odometry_calibration:
        scale, sigma = r.odometry_calibration[:3], r.odometry_calibration[3:]
        values["odometry_calibration"] = " ".join(
            f"{name} {v:.4f}+-{s:.4f}"
            for name, v, s in zip(("s", "k_d", "k_s"), scale, sigma, strict=True)
        )
    return DiagnosticStatus(
        level=level,
        name=f"{prefix}/{r.robot}",
        hardware_id=r.robot,
        message=r.message,
        values=_key_values(values),
    )


def _key_values(values: dict[str, Any]) -> list[KeyValue]:
    return [KeyValue(key=k, value=str(v)) for k, v in values.items()]


def pose_covariance(covariance: np.ndarray) -> np.ndarray:
    """The 36 entries (6x6 row-major) of a planar pose's (3, 3) covariance of x, y, yaw."""
    full = np.zeros((6, 6))
    full[np.diag_indices(6)] = UNESTIMATED_VARIANCE
    full[np.ix_(PLANAR_AXES, PLANAR_AXES)] = covariance
    return full.reshape(-1)


def pose_message(pose: RobotPose, frame_id: str) -> PoseWithCovarianceStamped:
    """``/<robot>/pose`` of ``pose``, in ``frame_id`` (the reference robot's map), stamped
    with the local pose's own stamp."""
    msg = PoseWithCovarianceStamped()
    msg.header.frame_id = frame_id
    msg.header.stamp = ns_to_time(stamp_to_ns(pose.stamp))
    msg.pose.pose.position.x = float(pose.pose[0])
    msg.pose.pose.position.y = float(pose.pose[1])
    msg.pose.pose.orientation = yaw_quaternion(float(pose.pose[2]))
    msg.pose.covariance = pose_covariance(pose.covariance)
    return msg


def log_notice(logger: Any, notice: Notice) -> None:
    """Log ``notice`` at its level (a call site per level: rclpy keeps each site's severity)."""
    if notice.level == "error":
        logger.error(str(notice))
    elif notice.level == "warning":
        logger.warning(str(notice))
    else:
        logger.info(str(notice))
