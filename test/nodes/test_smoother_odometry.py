"""Odometry as robot drivers publish it, through a real smoother node: the integrated pose with
no twist and often an all-zero covariance gives the twist path's local map; pose jumps and bad
poses are dropped and counted in /csam/status."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
from nodes.test_smoother import assert_good_map_unchanged, deliver, fed_smoother

from csam_ros.core.exchange.validation import (
    NOT_FINITE,
    ODOMETRY_DEFAULT_SIGMAS,
    ODOMETRY_JUMP,
    QUATERNION_NOT_NORMALISED,
)
from csam_ros.ros.topics import ODOM

SECONDS = 25.0  # of the map-joining scenario: robot1 sees features, and drives and turns


def _messages(kind: str) -> list:
    """robot1's sensor messages up to SECONDS, the odometry as ``kind``: ``twist`` (v, v_lat,
    omega with their covariance, no pose), ``twist_no_covariance`` (an all-zero one),
    ``pose`` (the driver's integrated pose, twist zero, the covariance kept) or
    ``pose_no_covariance`` (and the covariance all zero: the stock diff-drive controller)."""
    from csam_ros.datasets.scenario import load_scenario
    from csam_ros.datasets.simulation import simulate
    from csam_ros.ros.conversions import log_to_messages

    log = simulate(load_scenario("map_joining"), seed=3)
    out = []
    for m in log_to_messages(log, with_truth=False, with_poses=True):
        if not m.topic.startswith("/robot1/") or m.stamp_ns > SECONDS * 1e9:
            continue
        if m.topic == ODOM.of("robot1"):
            odometry = m.message
            if kind.startswith("twist"):
                odometry.pose.covariance[0] = -1.0  # no pose: REP-145's unknown
            else:
                t = odometry.twist.twist
                t.linear.x = t.linear.y = t.angular.z = 0.0
            if kind.endswith("no_covariance"):
                odometry.twist.covariance = np.zeros(36)
        out.append(m)
    return out


def _status(ros_context: Any, spin: Callable[..., bool], node: Any) -> dict[str, str]:
    """The values of the smoother's /csam/status, as another node receives them."""
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.executors import SingleThreadedExecutor

    listener = rclpy.create_node("status_listener", context=ros_context)
    got: dict[str, str] = {}
    listener.create_subscription(
        DiagnosticArray,
        "/csam/status",
        lambda msg: got.update({kv.key: kv.value for kv in msg.status[0].values}),
        10,
    )
    executor = SingleThreadedExecutor(context=ros_context)
    executor.add_node(listener)
    try:
        assert spin(executor, lambda: node.status_pub.get_subscription_count() > 0, 10)
        node.publish_status()
        assert spin(executor, lambda: bool(got), 10)
        return got
    finally:
        executor.shutdown()
        listener.destroy_node()


@pytest.mark.parametrize("covariance", [True, False])
def test_driver_odometry_gives_the_local_map_of_the_twist(
    ros_context: Any, spin: Callable[..., bool], covariance: bool
) -> None:
    suffix = "" if covariance else "_no_covariance"
    twist, pose = _messages("twist" + suffix), _messages("pose" + suffix)
    odometry = sum(m.topic == ODOM.of("robot1") for m in pose)
    with fed_smoother(ros_context, twist) as (by_twist, expected):
        counted = by_twist.filter.defaulted.as_dict()
    with fed_smoother(ros_context, pose) as (node, (stamps, poses, landmarks)):
        assert len(stamps) > 20 and len(landmarks) > 5
        np.testing.assert_array_equal(stamps, expected[0])
        np.testing.assert_allclose(poses, expected[1], atol=1e-6)
        assert landmarks.keys() == expected[2].keys()
        for label, xy in landmarks.items():
            np.testing.assert_allclose(xy, expected[2][label], atol=1e-6)
        status = _status(ros_context, spin, node)
        assert node.drops.total == 0 and status["dropped"] == "0"
        assert status[ODOMETRY_DEFAULT_SIGMAS] == ("0" if covariance else str(odometry))
        assert counted == node.filter.defaulted.as_dict()


def test_pose_jumps_and_bad_poses_are_dropped_and_counted(
    ros_context: Any, spin: Callable[..., bool]
) -> None:
    from csam_ros.ros.conversions import yaw_quaternion

    good = _messages("pose_no_covariance")
    with fed_smoother(ros_context, good) as (node, expected):
        last = [m.message for m in good if m.topic == ODOM.of("robot1")][-1]
        stamp_ns = last.header.stamp.sec * 10**9 + last.header.stamp.nanosec
        p = last.pose.pose

        def odometry(dt_ns: int, x: float, y: float, yaw: float, norm: float = 1.0) -> Any:
            from csam_ros.ros.conversions import ns_to_time

            msg = type(last)()
            msg.header.stamp = ns_to_time(stamp_ns + dt_ns)
            msg.header.frame_id, msg.child_frame_id = last.header.frame_id, last.child_frame_id
            msg.pose.pose.position.x, msg.pose.pose.position.y = x, y
            q = yaw_quaternion(yaw)
            msg.pose.pose.orientation.z, msg.pose.pose.orientation.w = norm * q.z, norm * q.w
            return msg

        yaw = 2 * math.atan2(p.orientation.z, p.orientation.w)
        bad = [
            odometry(10**8, math.nan, p.position.y, yaw),
            odometry(10**8, p.position.x, math.inf, yaw),
            odometry(10**8, p.position.x, p.position.y, yaw, norm=1.3),  # not a rotation
            odometry(10**8, p.position.x, p.position.y, yaw, norm=0.0),
            odometry(10**8, p.position.x + 40.0, p.position.y, yaw),  # 400 m/s: a jump
        ]
        for msg in bad:
            deliver(node, "/robot1/odom", msg)
        assert node.drops.as_dict() == {
            NOT_FINITE: 2,
            QUATERNION_NOT_NORMALISED: 2,
            ODOMETRY_JUMP: 1,
        }
        assert_good_map_unchanged(node, expected)
        # the next difference starts from the pose after the jump: 0.1 m forward
        deliver(
            node,
            "/robot1/odom",
            odometry(
                2 * 10**8,
                p.position.x + 40.0 + 0.1 * math.cos(yaw),
                p.position.y + 0.1 * math.sin(yaw),
                yaw,
            ),
        )
        assert node.last_odometry_ns == stamp_ns + 2 * 10**8
        # over the 0.2 s since the last accepted sample: 0.5 m/s, and no 40 m
        inputs = node.map.state().odometry_inputs
        np.testing.assert_allclose(inputs[-1], [0.5, 0.0, 0.0], atol=1e-9)
        assert_good_map_unchanged(node, expected)
        status = _status(ros_context, spin, node)
        assert status[f"dropped/{ODOMETRY_JUMP}"] == "1"
        assert status[f"dropped/{QUATERNION_NOT_NORMALISED}"] == "2"
        assert status[f"dropped/{NOT_FINITE}"] == "2"
        assert node.errors == 0 and node.drops.counts["callback_error"] == 0


def test_offline_replay_reads_driver_odometry_as_the_node_does(ros_context: Any) -> None:
    """A bag's driver-style odometry through offline replay's reading (``LogBuilder``) gives
    the local map the smoother node makes of the same messages."""
    from csam_ros.core.smoothing.local_map import LocalMap
    from csam_ros.ros.conversions import LogBuilder

    messages = [m for m in _messages("pose_no_covariance") if "rendezvous" not in m.topic]
    builder = LogBuilder(robots=["robot1", "robot2"])
    for m in messages:
        builder.add(m.topic, m.message)
    offline = LocalMap("robot1")
    offline.add_log(builder.build().robots["robot1"])
    offline.update(converge=True)
    with fed_smoother(ros_context, messages) as (node, (stamps, poses, landmarks)):
        np.testing.assert_array_equal(stamps, offline.stamps)
        np.testing.assert_allclose(poses, offline.poses, atol=1e-6)
        for label, xy in zip(offline.landmark_labels, offline.landmarks, strict=True):
            np.testing.assert_allclose(landmarks[label], xy, atol=1e-6)
        assert builder.filter.defaulted.as_dict() == node.filter.defaulted.as_dict() != {}
