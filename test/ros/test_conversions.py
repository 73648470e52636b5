"""Round trip of a simulated run through ROS messages and back, and boundary checks."""

from __future__ import annotations

import numpy as np
import pytest

from csam_ros.core.simulation import simulate
from csam_ros.core.validation import (
    DUPLICATE,
    EMPTY,
    NON_POSITIVE_RANGE,
    NOT_FINITE,
    OUTSIDE_FIELD_OF_VIEW,
    STAMP_BACKWARDS,
    UNKNOWN_ROBOT,
)
from csam_ros.datasets.scenario import load_scenario
from csam_ros.ros.conversions import LogBuilder, log_to_messages, yaw_quaternion


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
