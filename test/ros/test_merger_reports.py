"""The merger's reports as messages: a robot's pose with its covariance in ROS's 6x6 layout,
and one status as both ``/csam/status`` and ``/diagnostics`` (levels, names, values)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticStatus

from csam_ros.core.merging.robot_poses import RobotPose
from csam_ros.core.merging.status import MergerStatus, RobotStatus
from csam_ros.ros.conversions import time_to_ns
from csam_ros.ros.merger_reports import (
    UNESTIMATED_VARIANCE,
    diagnostics_array,
    pose_message,
    status_array,
)

# a robot's counts in these tests: ten poses, the third update, nothing restarted or asked for
COUNTS = {"poses": 10, "solve_seconds": 0.1, "update": 3}
NONE = dict.fromkeys(("restarts", "restart_poses_lost", "resync_requests"), 0)


def _robot(name: str, alignment: str, stale: bool = False) -> RobotStatus:
    since = 42.0 if stale else 1.0
    return RobotStatus(name, alignment, stale, seconds_since_map=since, **COUNTS, **NONE)


def _status(robots: tuple[RobotStatus, ...], last_error: str = "") -> MergerStatus:
    return MergerStatus(
        robots=robots,
        reference="robot1",
        solves=4,
        features=7,
        associations=2,
        solve_seconds=0.1,
        solving=False,
        solves_given_up=0,
        provisional_maps=1,
        converged=True,
        dropped={"malformed_local_map": 1},
        restarts=0,
        resync_requests=0,
        outside_trajectory=0,
        last_error=last_error,
    )


def test_a_pose_message_holds_the_planar_covariance_in_the_x_y_yaw_rows() -> None:
    cov = np.array([[0.04, 0.01, 0.002], [0.01, 0.09, -0.003], [0.002, -0.003, 0.01]])
    pose = RobotPose("robot2", 12.345678901, np.array([1.5, -2.0, 3.0]), cov)
    msg = pose_message(pose, "robot1/map")
    assert msg.header.frame_id == "robot1/map"
    assert time_to_ns(msg.header.stamp) == 12_345_678_901
    assert (msg.pose.pose.position.x, msg.pose.pose.position.y) == (1.5, -2.0)
    assert msg.pose.pose.position.z == 0.0
    q = msg.pose.pose.orientation
    assert q.x == q.y == 0.0
    assert abs(2.0 * np.arctan2(q.z, q.w) - 3.0) < 1e-15
    full = np.asarray(msg.pose.covariance).reshape(6, 6)
    planar = [0, 1, 5]
    np.testing.assert_array_equal(full[np.ix_(planar, planar)], cov)
    unestimated = [2, 3, 4]
    np.testing.assert_array_equal(np.diag(full)[unestimated], UNESTIMATED_VARIANCE)
    off = ~np.eye(6, dtype=bool)
    off[np.ix_(planar, planar)] = False
    assert not full[off].any()
    np.testing.assert_array_equal(full, full.T)
    assert np.linalg.eigvalsh(full).min() >= 0.0


def test_one_status_gives_both_arrays_with_a_stale_robot_stale_in_diagnostics() -> None:
    robots = (
        _robot("robot1", "reference"),
        _robot("robot2", "aligned"),
        _robot("robot3", "pending: no rendezvous with a joined robot"),
        _robot("robot4", "aligned", stale=True),
    )
    stamp = Time(sec=5, nanosec=7)
    status = _status(robots)
    diagnostics = diagnostics_array(status, stamp)
    legacy = status_array(status, stamp)
    assert diagnostics.header.stamp == stamp == legacy.header.stamp
    names = [s.name for s in diagnostics.status]
    assert names == ["csam/robot1", "csam/robot2", "csam/robot3", "csam/robot4", "csam"]
    assert [s.name for s in legacy.status] == [
        "merger/robot1",
        "merger/robot2",
        "merger/robot3",
        "merger/robot4",
        "merger",
    ]
    levels = [s.level for s in diagnostics.status]
    ok, warn, stale = DiagnosticStatus.OK, DiagnosticStatus.WARN, DiagnosticStatus.STALE
    assert levels == [ok, ok, warn, stale, ok]
    assert [s.level for s in legacy.status] == [ok, ok, warn, warn, ok]
    assert diagnostics.status[2].message == "pending: no rendezvous with a joined robot"
    assert "stale" in diagnostics.status[3].message
    assert [s.hardware_id for s in diagnostics.status[:4]] == [r.robot for r in robots]
    for d, s in zip(diagnostics.status, legacy.status, strict=True):
        assert d.message == s.message
        assert [(kv.key, kv.value) for kv in d.values] == [(kv.key, kv.value) for kv in s.values]


def test_a_robots_entry_gives_its_odometry_calibration_when_estimated() -> None:
    calibrated = replace(
        _robot("robot2", "aligned"), odometry_calibration=(1.01, 0.65, 0.98, 0.01, 0.02, 0.03)
    )
    array = diagnostics_array(_status((_robot("robot1", "reference"), calibrated)), Time())
    values = [{kv.key: kv.value for kv in s.values} for s in array.status[:2]]
    assert "odometry_calibration" not in values[0]
    assert (
        values[1]["odometry_calibration"]
        == "s 1.0100+-0.0100 k_d 0.6500+-0.0200 k_s 0.9800+-0.0300"
    )


def test_the_mergers_entry_takes_its_status_level() -> None:
    failed = diagnostics_array(_status((), last_error="RuntimeError: boom"), Time())
    assert [(s.name, s.level) for s in failed.status] == [("csam", DiagnosticStatus.ERROR)]
