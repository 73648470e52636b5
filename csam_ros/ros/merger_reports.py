"""What the merger reports, as ROS has it: its status
(:class:`~csam_ros.core.merging.status.MergerStatus`) as the DiagnosticArray it publishes on
``/csam/status`` (an entry ``merger/<robot>`` per robot, then ``merger``, each value a string),
and its policy's notices (:mod:`csam_ros.core.merging.notices`) as log lines."""

from __future__ import annotations

from typing import Any

from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

from csam_ros.core.merging.notices import Notice
from csam_ros.core.merging.status import Health, MergerStatus, RobotStatus

LEVELS = {
    Health.OK: DiagnosticStatus.OK,
    Health.WARN: DiagnosticStatus.WARN,
    Health.ERROR: DiagnosticStatus.ERROR,
}


def status_array(status: MergerStatus, stamp: Time) -> DiagnosticArray:
    """The status message of ``status``, stamped ``stamp``."""
    array = DiagnosticArray()
    array.header.stamp = stamp
    array.status = [_robot_entry(r) for r in status.robots]
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
    array.status.append(
        DiagnosticStatus(
            level=LEVELS[status.health],
            name="merger",
            message=status.message,
            values=_key_values(values),
        )
    )
    return array


def _robot_entry(r: RobotStatus) -> DiagnosticStatus:
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
    return DiagnosticStatus(
        level=LEVELS[r.health],
        name=f"merger/{r.robot}",
        hardware_id=r.robot,
        message=r.message,
        values=_key_values(values),
    )


def _key_values(values: dict[str, Any]) -> list[KeyValue]:
    return [KeyValue(key=k, value=str(v)) for k, v in values.items()]


def log_notice(logger: Any, notice: Notice) -> None:
    """Log ``notice`` at its level (a call site per level: rclpy keeps each site's severity)."""
    if notice.level == "error":
        logger.error(str(notice))
    elif notice.level == "warning":
        logger.warning(str(notice))
    else:
        logger.info(str(notice))
