"""Round trip of a simulated run (and of Cartesian feature points with correlated odometry)
through ROS messages and bags and back, and boundary checks."""

from __future__ import annotations

import numpy as np
import pytest
from csam_msgs.msg import FeaturePoint

from csam_ros.bag import inspect_bag, read_bag_messages
from csam_ros.core.exchange.validation import (
    DUPLICATE,
    EMPTY,
    NON_POSITIVE_RANGE,
    NON_POSITIVE_SIGMA,
    NOT_FINITE,
    OUTSIDE_FIELD_OF_VIEW,
    SIGMA_OUT_OF_BOUNDS,
    STAMP_BACKWARDS,
    UNKNOWN_ROBOT,
)
from csam_ros.core.model.log import (
    FeaturePointLog,
    MultiRobotLog,
    OdometryLog,
    RobotLog,
    correlations_from_covariances,
    empty_features,
    empty_rendezvous,
)
from csam_ros.datasets.scenario import load_scenario
from csam_ros.datasets.simulation import simulate
from csam_ros.ros.conversions import LogBuilder, log_to_messages, yaw_quaternion
from csam_ros.run.bag_io import write_log_bag


@pytest.fixture(scope="module")
def log():
    return simulate(load_scenario("map_joining"), seed=3)


def test_log_round_trips_through_messages(log) -> None:
    builder = LogBuilder()
    for m in log_to_messages(log):
        builder.add(m.topic, m.message)
    back = builder.build()
    assert list(back.robots) == list(log.robots)
    for name, robot in log.robots.items():
        got = back.robots[name]
        np.testing.assert_allclose(got.odometry.stamps, robot.odometry.stamps, atol=1e-9)
        np.testing.assert_array_equal(got.odometry.inputs, robot.odometry.inputs)
        np.testing.assert_allclose(got.odometry.sigmas, robot.odometry.sigmas, rtol=1e-15)
        np.testing.assert_array_equal(got.features.labels, robot.features.labels)
        np.testing.assert_array_equal(got.features.ranges, robot.features.ranges)
        np.testing.assert_array_equal(got.features.bearings, robot.features.bearings)
        assert got.rendezvous.observed == list(robot.rendezvous.observed)
        np.testing.assert_array_equal(got.rendezvous.ranges, robot.rendezvous.ranges)
    assert back.truth is not None
    assert back.truth.label_to_feature == log.truth.label_to_feature
    assert sum(c.total for c in builder.filter.drops.values()) == 0


def test_bad_messages_are_dropped_and_counted(log) -> None:
    messages = log_to_messages(log, with_truth=False)
    features = [m for m in messages if m.topic == "/robot1/features"]
    first, second = features[0], features[1]
    builder = LogBuilder(robots=["robot1", "robot2"], field_of_view=np.deg2rad(240))
    builder.add(first.topic, first.message)
    builder.add(first.topic, first.message)  # duplicate
    builder.add(second.topic, second.message)
    builder.add(first.topic, first.message)  # stamp backwards
    bad = second.message.__class__()
    bad.header = second.message.header
    bad.header.stamp.sec += 1000
    obs = [o.__class__() for o in second.message.observations[:4]]
    for o, src in zip(obs, second.message.observations[:4], strict=True):
        o.label, o.range, o.bearing = src.label, src.range, src.bearing
        o.sigma_range, o.sigma_bearing = src.sigma_range, src.sigma_bearing
    obs[0].range = float("nan")
    obs[1].range = -1.0
    obs[2].bearing = 3.0  # beyond +-120 degrees
    bad.observations = obs
    builder.add("/robot1/features", bad)
    builder.add("/robot9/features", second.message)  # unknown robot
    empty = second.message.__class__()
    empty.header.stamp.sec = 5000
    builder.add("/robot1/features", empty)
    drops = builder.filter.drops
    assert drops["robot1"].counts[DUPLICATE] == 1
    assert drops["robot1"].counts[STAMP_BACKWARDS] == 1
    assert drops["robot1"].counts[NOT_FINITE] == 1
    assert drops["robot1"].counts[NON_POSITIVE_RANGE] == 1
    assert drops["robot1"].counts[OUTSIDE_FIELD_OF_VIEW] == 1
    assert drops["robot1"].counts[EMPTY] == 1
    assert drops["robot9"].counts[UNKNOWN_ROBOT] == 1
    built = builder.build().robots["robot1"].features
    # the two good scans and the one surviving observation of the bad scan
    expected = len(first.message.observations) + len(second.message.observations) + 1
    assert len(built.ranges) == expected


def test_yaw_quaternion_rotates_about_z() -> None:
    for yaw in (0.0, 0.7, -2.5, np.pi):
        q = yaw_quaternion(yaw)
        assert (q.x, q.y) == (0.0, 0.0)
        assert q.z**2 + q.w**2 == pytest.approx(1.0)
        assert 2 * np.arctan2(q.z, q.w) == pytest.approx(yaw)


def correlated_log() -> MultiRobotLog:
    """One robot with correlated odometry inputs and Cartesian feature points whose
    covariances are full (as a 2D SLAM file's import gives)."""
    rng = np.random.default_rng(4)
    n, k = 30, 40
    a = 0.1 * rng.standard_normal((n, 3, 3))
    sigmas, rho = correlations_from_covariances(a @ a.transpose(0, 2, 1) + 0.01 * np.eye(3))
    odometry = OdometryLog(np.arange(n) * 0.5, rng.standard_normal((n, 3)), sigmas, rho)
    b = 0.2 * rng.standard_normal((k, 2, 2))
    stamps = np.sort(rng.choice(np.arange(1, n) * 0.5, k))
    points = FeaturePointLog(
        stamps,
        rng.integers(0, 9, k),
        rng.uniform(-5, 5, (k, 2)),
        b @ b.transpose(0, 2, 1) + 0.01 * np.eye(2),
    )
    robot = RobotLog("robot1", odometry, empty_features(), empty_rendezvous(), points)
    return MultiRobotLog({"robot1": robot})


@pytest.mark.parametrize("decoder", ["rclpy", "rosbags"])
def test_feature_points_and_odometry_correlations_round_trip_through_a_bag(
    tmp_path, decoder
) -> None:
    log = correlated_log()
    write_log_bag(log, tmp_path / "bag")
    topics = ["/robot1/odom", "/robot1/feature_points"]
    assert set(inspect_bag(tmp_path / "bag").topics) == set(topics)
    builder = LogBuilder()
    for m in read_bag_messages(tmp_path / "bag", topics, decoder=decoder):
        builder.add(m.topic, m.message)
    got, sent = builder.build().robots["robot1"], log.robots["robot1"]
    np.testing.assert_array_equal(got.points.stamps, sent.points.stamps)
    np.testing.assert_array_equal(got.points.labels, sent.points.labels)
    np.testing.assert_array_equal(got.points.points, sent.points.points)
    np.testing.assert_array_equal(got.points.covariances, sent.points.covariances)
    np.testing.assert_allclose(got.odometry.sigmas, sent.odometry.sigmas, rtol=1e-15)
    np.testing.assert_allclose(got.odometry.correlations, sent.odometry.correlations, atol=1e-14)
    np.testing.assert_allclose(got.odometry.covariances(), sent.odometry.covariances(), rtol=1e-13)
    assert sum(c.total for c in builder.filter.drops.values()) == 0


def test_bad_feature_points_and_correlations_are_dropped_and_counted() -> None:
    log = correlated_log()
    messages = log_to_messages(log)
    builder = LogBuilder(robots=["robot1"], field_of_view=np.deg2rad(240))
    odometry = [m for m in messages if m.topic == "/robot1/odom"]
    for m in odometry[:3]:
        builder.add(m.topic, m.message)
    bad_odometry = odometry[3].message
    bad_odometry.twist.covariance[1] = bad_odometry.twist.covariance[6] = 1.0  # rho(v, v_lat) > 1
    builder.add("/robot1/odom", bad_odometry)
    points = [m for m in messages if m.topic == "/robot1/feature_points"][0].message
    points.header.stamp = odometry[2].message.header.stamp
    base = points.observations[0]
    bad = [
        FeaturePoint(label=base.label, x=base.x, y=base.y, covariance=base.covariance)
        for _ in range(5)
    ]
    bad[0].x = float("nan")
    bad[1].covariance = [1.0, 2.0, 1.0]  # not positive definite
    bad[2].x, bad[2].y = -3.0, 0.1  # behind the robot, beyond +-120 degrees
    bad[3].covariance = [1e8, 0.0, 1e8]  # sigma 1e4 m
    points.observations = bad
    builder.add("/robot1/feature_points", points)
    drops = builder.filter.drops["robot1"].counts
    assert drops[SIGMA_OUT_OF_BOUNDS] == 2  # the correlation and the sigma
    assert drops[NOT_FINITE] == 1
    assert drops[NON_POSITIVE_SIGMA] == 1
    assert drops[OUTSIDE_FIELD_OF_VIEW] == 1
    built = builder.build().robots["robot1"]
    assert len(built.points.stamps) == 1  # the unchanged copy
    assert len(built.odometry.stamps) == 3


def test_both_decoders_give_the_same_log(log, tmp_path) -> None:
    """Offline replay decodes with rosbags, the nodes receive rclpy messages: the same log."""
    write_log_bag(log, tmp_path / "bag")
    built = {}
    for decoder in ("rclpy", "rosbags"):
        builder = LogBuilder()
        for m in read_bag_messages(tmp_path / "bag", decoder=decoder):
            builder.add(m.topic, m.message)
        built[decoder] = builder.build()
    rclpy_log, rosbags_log = built["rclpy"], built["rosbags"]
    assert list(rclpy_log.robots) == list(rosbags_log.robots) == list(log.robots)
    for name, expected in rclpy_log.robots.items():
        got = rosbags_log.robots[name]
        for part in ("odometry", "features", "rendezvous", "points"):
            a, b = getattr(expected, part), getattr(got, part)
            for field_name in vars(a):
                left, right = getattr(a, field_name), getattr(b, field_name)
                if isinstance(left, np.ndarray):
                    np.testing.assert_array_equal(left, right, err_msg=f"{name} {part}")
                else:
                    assert left == right, (name, part, field_name)
    assert rclpy_log.truth is not None and rosbags_log.truth is not None
    np.testing.assert_array_equal(
        rclpy_log.truth.feature_positions, rosbags_log.truth.feature_positions
    )
    assert rclpy_log.truth.label_to_feature == rosbags_log.truth.label_to_feature


# -- odometry as robot drivers publish it ----------------------------------------------------


def _driver_odometry(log, covariance: bool) -> list:
    """robot1's odometry as a driver publishes it: the integrated pose, the twist zero, and
    the twist covariance zero (the stock diff-drive controller) or the log's."""
    from csam_ros.ros.topics import ODOM

    messages = [m for m in log_to_messages(log, with_poses=True) if m.topic == ODOM.of("robot1")]
    for m in messages:
        t = m.message.twist
        t.twist.linear.x = t.twist.linear.y = t.twist.angular.z = 0.0
        if not covariance:
            t.covariance = np.zeros(36)
    return messages


def test_odometry_messages_read_back_with_their_pose_or_none(log) -> None:
    from csam_ros.core.model.motion import odometry_poses
    from csam_ros.ros.conversions import odometry_message, odometry_reading_from_message
    from csam_ros.ros.topics import ODOM

    odo = log.robots["robot1"].odometry
    poses = odometry_poses(odo.stamps, odo.inputs)
    messages = [
        m.message for m in log_to_messages(log, with_poses=True) if m.topic == ODOM.of("robot1")
    ]
    readings = [odometry_reading_from_message(m) for m in messages]
    np.testing.assert_allclose([r.pose for r in readings], poses, atol=1e-12)
    assert max(r.quaternion_error for r in readings) < 1e-15
    bare = odometry_reading_from_message(
        odometry_message("robot1", 5, odo.inputs[1], odo.sigmas[1])
    )
    assert bare.pose is None and bare.twist == tuple(odo.inputs[1])
    np.testing.assert_allclose(bare.twist_covariance, [*odo.sigmas[1] ** 2, 0, 0, 0], rtol=1e-15)
    unknown = odometry_message("robot1", 5, odo.inputs[1], odo.sigmas[1])
    unknown.twist.covariance[0] = -1.0
    assert odometry_reading_from_message(unknown).twist_covariance is None


@pytest.mark.parametrize("covariance", [False, True])
def test_driver_odometry_builds_the_log_of_its_twist(log, tmp_path, covariance: bool) -> None:
    """Pose-only odometry (offline replay decodes it with rosbags) gives the twist's inputs and,
    where it has no covariance, the default sigmas, counted."""
    from csam_ros.bag import BagWriter
    from csam_ros.bag.types import msgtype_of
    from csam_ros.core.exchange.validation import InputBounds
    from csam_ros.core.model.motion import default_input_sigmas
    from csam_ros.ros.topics import qos_of

    odo = log.robots["robot1"].odometry
    with BagWriter(tmp_path / "bag") as bag:
        for m in _driver_odometry(log, covariance):
            if m.topic not in bag.topics:
                bag.add_topic(m.topic, msgtype_of(m.message), qos_of(m.topic))
            bag.write(m.topic, m.stamp_ns, m.message)
    for decoder in ("rclpy", "rosbags"):
        builder = LogBuilder()
        for m in read_bag_messages(tmp_path / "bag", decoder=decoder):
            builder.add(m.topic, m.message)
        got = builder.build().robots["robot1"].odometry
        np.testing.assert_array_equal(got.stamps, odo.stamps)
        np.testing.assert_allclose(got.inputs[1:], odo.inputs[1:], atol=1e-9)
        if covariance:
            np.testing.assert_allclose(got.sigmas, odo.sigmas, rtol=1e-15)
            assert builder.filter.defaulted.as_dict() == {}
        else:
            b = InputBounds()
            defaults = default_input_sigmas(
                odo.inputs[1:],
                np.diff(odo.stamps),
                b.odometry_sigma_per_m,
                b.odometry_sigma_per_rad,
                b.odometry_sigma_floor,
            )
            np.testing.assert_allclose(got.sigmas[1:], defaults, rtol=1e-6)
            assert builder.filter.defaulted.as_dict() == {"robot1": len(odo.stamps)}
        assert builder.filter.drops["robot1"].total == 0


def test_odometry_transforms_are_the_message_pose_or_the_dead_reckoning(log) -> None:
    from csam_ros.core.model.motion import odometry_poses
    from csam_ros.ros.conversions import OdometryTransforms, time_to_seconds
    from csam_ros.ros.topics import ODOM

    odo = log.robots["robot1"].odometry
    expected = odometry_poses(odo.stamps, odo.inputs)
    for with_poses in (True, False):
        transforms = OdometryTransforms()
        got = [
            transforms.transform("robot1", m.message)
            for m in log_to_messages(log, with_poses=with_poses)
            if m.topic == ODOM.of("robot1")
        ]
        assert [t.header.frame_id for t in got] == ["robot1/odom"] * len(expected)
        assert {t.child_frame_id for t in got} == {"robot1/base_link"}
        assert [time_to_seconds(t.header.stamp) for t in got] == list(odo.stamps)
        planar = [
            [
                t.transform.translation.x,
                t.transform.translation.y,
                2 * np.arctan2(t.transform.rotation.z, t.transform.rotation.w),
            ]
            for t in got
        ]
        np.testing.assert_allclose(
            np.unwrap(np.array(planar), axis=0), np.unwrap(expected, axis=0), atol=1e-9
        )
    first = [m.message for m in log_to_messages(log) if m.topic == ODOM.of("robot1")][0]
    assert transforms.transform("robot1", first) is None  # out of order: nothing
