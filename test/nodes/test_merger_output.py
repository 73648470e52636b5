"""What the merger tells robots and ROS tools, through a real merger node over DDS: each joined
robot's ``/<robot>/pose`` (its base node composed with its newest local pose, with the
covariance propagated to first order), none for a pending robot, and ``/diagnostics`` (OK for a
joined robot, WARN for a pending one, STALE for one without a map for ``stale_after`` s)."""

from __future__ import annotations

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import PoseWithCovarianceStamped
from merger_harness import ROBOTS, STAMP_NS, MergerHarness, run_messages, with_robot2

from csam_ros.core.exchange.map_arrays import robot_map_arrays
from csam_ros.core.exchange.map_updates import UpdateSender
from csam_ros.core.joining.result import RunSummary
from csam_ros.core.merging.robot_poses import composed, latest_pose_covariance
from csam_ros.core.model import se2
from csam_ros.ros.conversions import stamp_to_ns, time_to_ns
from csam_ros.ros.map_messages import local_map_update_message
from csam_ros.ros.topics import DIAGNOSTICS, POSE

PLANAR = [0, 1, 5]  # x, y, yaw in the 6x6 covariance
OK, WARN, STALE = DiagnosticStatus.OK, DiagnosticStatus.WARN, DiagnosticStatus.STALE


class Listener:
    """The injector's subscriptions to every robot's pose and to ``/diagnostics``."""

    def __init__(self, harness: MergerHarness) -> None:
        self.poses: dict[str, list[PoseWithCovarianceStamped]] = {r: [] for r in ROBOTS}
        self.diagnostics: list[DiagnosticArray] = []
        node = harness.injector
        for robot in ROBOTS:
            node.create_subscription(
                POSE.msgtype, POSE.of(robot), self.poses[robot].append, POSE.qos
            )
        node.create_subscription(
            DIAGNOSTICS.msgtype, DIAGNOSTICS.of(), self.diagnostics.append, DIAGNOSTICS.qos
        )

    def levels(self) -> dict[str, tuple[bytes, str]]:
        """The last ``/diagnostics`` message's entries: name -> (level, message)."""
        if not self.diagnostics:
            return {}
        return {s.name: (s.level, s.message) for s in self.diagnostics[-1].status}


def _pose_of(msg: PoseWithCovarianceStamped) -> np.ndarray:
    p, q = msg.pose.pose.position, msg.pose.pose.orientation
    return np.array([p.x, p.y, 2.0 * np.arctan2(q.z, q.w)])


def _covariance_of(msg: PoseWithCovarianceStamped) -> np.ndarray:
    """The 6x6 covariance, checked symmetric, positive semi-definite and planar (nothing
    outside the x, y, yaw rows and columns); its x, y, yaw block."""
    full = np.asarray(msg.pose.covariance).reshape(6, 6)
    np.testing.assert_array_equal(full, full.T)
    assert np.linalg.eigvalsh(full).min() >= -1e-15 * np.abs(full).max()
    others = np.ones((6, 6), dtype=bool)
    others[np.ix_(PLANAR, PLANAR)] = False
    assert not full[others].any()
    return full[np.ix_(PLANAR, PLANAR)]


def _assert_pose_close(msg: PoseWithCovarianceStamped, expected: np.ndarray, atol: float) -> None:
    difference = _pose_of(msg) - expected
    difference[2] = se2.wrap_angle(difference[2])
    np.testing.assert_allclose(difference, 0.0, rtol=0, atol=atol)


@pytest.fixture
def harness(ros_context, spin, tmp_path):
    h = MergerHarness(ros_context, spin, summary_path=str(tmp_path / "summary.json"))
    yield h
    h.close()


def test_an_aligned_robots_pose_is_its_base_node_composed_with_its_latest_local_pose(
    harness, tmp_path
) -> None:
    """Of the summary the same solve wrote: base node (+) last local pose to 1e-9, at the last
    local stamp, in the reference's map; the covariance the base node's and the held map's
    latest marginal propagated (its yaw variance their sum)."""
    listener = Listener(harness)
    harness.start(run_messages())
    policy = harness.merger.policy
    summary_path = tmp_path / "summary.json"

    def settled() -> bool:
        if policy.solving or policy.dirty or not summary_path.exists():
            return False
        merger = RunSummary.read(summary_path).merger
        return merger is not None and merger.solves == policy.solves

    harness.wait(lambda: settled() and all(listener.poses.values()))
    harness.settle(0.3)
    summary = RunSummary.read(summary_path).result
    assert summary.reference_frame == "robot1/map"
    assert [summary.robots[r].alignment for r in ROBOTS] == ["reference", "aligned"]
    for robot in ROBOTS:
        msg = listener.poses[robot][-1]
        joined = summary.robots[robot]
        assert msg.header.frame_id == "robot1/map"
        assert time_to_ns(msg.header.stamp) == stamp_to_ns(joined.stamps[-1])
        _assert_pose_close(msg, se2.compose(joined.base_node, joined.poses_local[-1]), 1e-9)
        covariance = _covariance_of(msg)
        held = policy.local_maps[robot]
        local_cov = latest_pose_covariance(held)
        _, expected = composed(joined.base_node, joined.base_node_cov, held.poses[-1], local_cov)
        np.testing.assert_allclose(covariance, expected, rtol=1e-6, atol=1e-12)
        yaw_variance = joined.base_node_cov[2, 2] + joined.sigma_phi_local[-1] ** 2
        assert covariance[2, 2] == pytest.approx(yaw_variance, rel=1e-6)
    assert harness.merger.drops.total == 0


def test_a_pending_robot_gets_no_pose_and_a_warning_in_diagnostics(harness) -> None:
    """robot2's map ends before any rendezvous: it stays pending, with no pose; /diagnostics
    has robot1 OK, robot2 WARN saying why, and the merger's own entry."""
    listener = Listener(harness)
    harness.start(run_messages(end=10.0))
    result = harness.merger.policy.last_result
    assert result is not None and result.robots["robot2"].alignment.startswith("pending")
    harness.wait(lambda: bool(listener.poses["robot1"]) and "csam/robot2" in listener.levels())
    harness.settle(0.5)
    assert listener.poses["robot2"] == []
    levels = listener.levels()
    assert levels["csam/robot1"] == (OK, "reference")
    assert levels["csam/robot2"] == (WARN, result.robots["robot2"].alignment)
    assert levels["csam"][0] == OK
    statuses = {s.name for s in listener.diagnostics[-1].status}
    assert statuses == {"csam/robot1", "csam/robot2", "csam"}


def test_a_robot_without_a_map_for_stale_after_is_stale_in_diagnostics(ros_context, spin) -> None:
    """With stale_after 1 s and no map after the first ones, both robots go STALE on
    /diagnostics (WARN on /csam/status, from the same status) and stay joined."""
    harness = MergerHarness(ros_context, spin, stale_after=1.0)
    try:
        listener = Listener(harness)
        harness.start(run_messages())
        solved = len(listener.diagnostics)  # from here on both robots are joined

        def stale(array: DiagnosticArray) -> bool:
            levels = {s.name: s.level for s in array.status}
            return all(levels.get(f"csam/{r}") == STALE for r in ROBOTS)

        harness.wait(lambda: any(stale(a) for a in listener.diagnostics[solved:]))
        found = next(a for a in listener.diagnostics[solved:] if stale(a))
        entries = {s.name: s for s in found.status}
        for robot in ROBOTS:
            assert "stale: no local map for" in entries[f"csam/{robot}"].message
            values = {kv.key: kv.value for kv in entries[f"csam/{robot}"].values}
            assert values["stale"] == "True"
            assert values["alignment"] in ("reference", "aligned")
        harness.wait(lambda: _stale_status(harness.status))
    finally:
        harness.close()


def _stale_status(arrays: list[DiagnosticArray]) -> bool:
    """Whether a /csam/status message has every robot's entry stale at level WARN."""
    for array in arrays:
        entries = {s.name: s for s in array.status}
        robots = [entries.get(f"merger/{r}") for r in ROBOTS]
        if all(e is not None and e.level == WARN and "stale" in e.message for e in robots):
            return True
    return False


def test_a_newer_local_map_moves_the_pose_before_any_solve(ros_context, spin) -> None:
    """robot2's grown map, while no solve runs (solve_period far off: the test solves when it
    means to), goes out provisionally and moves robot2's pose: the last join's base node
    composed with the newest local pose, at its stamp, the covariance of the newest map."""
    harness = MergerHarness(ros_context, spin, solve_period=3600.0)
    try:
        listener = Listener(harness)
        middle, last = run_messages(end=30.0), run_messages()
        sender = UpdateSender(11)
        first = sender.update(robot_map_arrays(middle.robot_maps["robot2"]))
        harness.hold(with_robot2(middle, local_map_update_message(first, "robot2", STAMP_NS)))
        policy = harness.merger.policy
        assert harness.merger.solve_pending() and policy.solves == 1
        harness.wait(lambda: all(listener.poses.values()))
        solved = listener.poses["robot2"][-1]
        assert time_to_ns(solved.header.stamp) == stamp_to_ns(
            middle.robot_maps["robot2"].stamps[-1]
        )
        update = sender.update(robot_map_arrays(last.robot_maps["robot2"]))
        harness.publish("robot2", local_map_update_message(update, "robot2", STAMP_NS + 10**9))
        newest = stamp_to_ns(last.robot_maps["robot2"].stamps[-1])
        harness.wait(lambda: time_to_ns(listener.poses["robot2"][-1].header.stamp) == newest)
        assert policy.solves == 1 and policy.provisional_maps == 1
        joined = policy.last_result.robots["robot2"]
        held = policy.local_maps["robot2"]
        msg = listener.poses["robot2"][-1]
        _assert_pose_close(msg, se2.compose(joined.base_node, held.poses[-1]), 1e-12)
        _, expected = composed(
            joined.base_node, joined.base_node_cov, held.poses[-1], latest_pose_covariance(held)
        )
        np.testing.assert_allclose(_covariance_of(msg), expected, rtol=1e-12, atol=0)
        assert _pose_of(msg)[0] != _pose_of(solved)[0]
    finally:
        harness.close()
