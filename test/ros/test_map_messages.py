"""Local maps and their updates survive the trip through their messages: the merger sees what
the smoother had."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from csam_msgs.msg import JoinedMap
from visualization_msgs.msg import Marker

from csam_ros.core.exchange.local_map_checks import local_map_fault
from csam_ros.core.exchange.map_arrays import robot_map_arrays, robot_map_from_arrays
from csam_ros.core.exchange.map_updates import KeyedMap, MapUpdate, UpdateSender
from csam_ros.core.exchange.validation import LocalMapError
from csam_ros.core.joining.join import join_maps
from csam_ros.core.joining.pipeline import robot_map_from_local_map
from csam_ros.core.joining.warm_start import carried_forward
from csam_ros.core.model.rendezvous import required_stamps
from csam_ros.core.sam.factors import Cauchy, Huber
from csam_ros.core.smoothing.local_map_build import build_local_map
from csam_ros.core.smoothing.local_map_config import LocalMapOptions
from csam_ros.datasets.scenario import load_scenario
from csam_ros.datasets.simulation import simulate
from csam_ros.ros.conversions import time_to_ns
from csam_ros.ros.map_messages import (
    joined_map_message,
    local_map_update_message,
    map_update_from_message,
    rendezvous_log_from_message,
    rendezvous_poses_message,
    robot_map_from_message,
    robot_map_to_message,
    serialized_joined_map,
)
from csam_ros.ros.markers import joined_map_markers


@pytest.fixture(scope="module")
def maps_and_logs():
    log = simulate(load_scenario("map_joining"), seed=2)
    logs = {n: r.rendezvous for n, r in log.robots.items()}
    stamps = required_stamps(logs)
    maps = [robot_map_from_local_map(build_local_map(r, stamps[n])) for n, r in log.robots.items()]
    return maps, logs


def test_local_map_round_trip_gives_the_same_problem(maps_and_logs) -> None:
    maps, _ = maps_and_logs
    for m in maps:
        back = robot_map_from_message(robot_map_to_message(m, 123))
        np.testing.assert_array_equal(back.poses, m.poses)
        np.testing.assert_array_equal(back.stamps, np.round(m.stamps * 1e9) / 1e9)
        np.testing.assert_array_equal(back.feature_labels, m.feature_labels)
        np.testing.assert_array_equal(back.feature_positions, m.feature_positions)
        assert back.problem.cost() == pytest.approx(m.problem.cost(), rel=1e-12)


@pytest.mark.parametrize("kernel", [Huber(2.0), Cauchy(), Cauchy(1.5)])
def test_robust_kernels_survive_the_message(kernel) -> None:
    log = simulate(load_scenario("map_joining"), seed=2).robots["robot1"]
    m = robot_map_from_local_map(build_local_map(log, options=LocalMapOptions(robust=kernel)))
    back = robot_map_from_message(robot_map_to_message(m, 1))
    kernels = [f.robust for f in back.problem.factors if f.robust is not None]
    assert kernels and all(k == kernel for k in kernels)
    assert back.problem.cost() == pytest.approx(m.problem.cost(), rel=1e-12)


def test_join_from_messages_equals_join_in_process(maps_and_logs) -> None:
    maps, logs = maps_and_logs
    direct = join_maps(maps, logs)
    rebuilt = [robot_map_from_message(robot_map_to_message(m, 1)) for m in maps]
    logs_back = {}
    for m in maps:
        msg = rendezvous_poses_message(m, 1, np.arange(2), logs[m.name])
        logs_back[m.name] = rendezvous_log_from_message(msg)
        assert logs_back[m.name].observed == list(logs[m.name].observed)
    via = join_maps(rebuilt, logs_back)
    for name, robot in direct.robots.items():
        assert via.robots[name].alignment == robot.alignment
        if robot.poses_joined is not None:
            np.testing.assert_allclose(via.robots[name].poses_joined, robot.poses_joined, atol=1e-9)
    assert [a.a for a in via.associations] == [a.a for a in direct.associations]


def test_joined_map_message_and_markers_carry_the_result(maps_and_logs) -> None:
    maps, logs = maps_and_logs
    result = join_maps(maps, logs)
    stamps = {"robot1": 5_000_000_000}
    msg = joined_map_message(result, 7_000_000_000, stamps, ["robot1", "robot2", "robot3"])
    assert msg.header.frame_id == "robot1/map" and msg.reference_robot == "robot1"
    assert time_to_ns(msg.header.stamp) == 7_000_000_000
    nodes = {n.robot: n for n in msg.base_nodes}
    assert time_to_ns(nodes["robot1"].local_map_stamp) == 5_000_000_000
    assert nodes["robot3"].alignment == "pending: no local map yet"
    robot2 = result.robots["robot2"]
    assert nodes["robot2"].alignment == "aligned"
    assert robot2.base_node is not None and robot2.base_node_cov is not None
    pose = nodes["robot2"].pose
    np.testing.assert_array_equal([pose.x, pose.y, pose.theta], robot2.base_node)
    np.testing.assert_array_equal(nodes["robot2"].covariance, robot2.base_node_cov.ravel())
    trajectory = {t.robot: t for t in msg.trajectories}["robot2"]
    assert robot2.poses_joined is not None and robot2.sigma_phi_joined is not None
    np.testing.assert_array_equal(
        [[p.x, p.y, p.theta] for p in trajectory.poses], robot2.poses_joined
    )
    np.testing.assert_array_equal(trajectory.sigma_phi, robot2.sigma_phi_joined)
    np.testing.assert_allclose(
        [time_to_ns(t) * 1e-9 for t in trajectory.stamps], robot2.stamps, atol=1e-9
    )
    assert [f.members for f in msg.features] == [f.members for f in result.features]
    feature = result.features[0]
    assert (msg.features[0].x, msg.features[0].y) == tuple(feature.xy)
    np.testing.assert_array_equal(msg.features[0].covariance, feature.cov[np.triu_indices(2)])
    assert [(a.a, a.b, a.mahalanobis) for a in msg.associations] == [
        (a.a, a.b, a.mahalanobis) for a in result.associations
    ]

    markers = {(m.ns, m.id): m for m in joined_map_markers(result, msg.header.stamp).markers}
    assert markers[("", 0)].action == Marker.DELETEALL
    lines = [m for m in markers.values() if m.ns == "trajectories"]
    assert {m.text for m in lines} == {"robot1", "robot2"}
    shared = sum(len(f.members) > 1 for f in result.features)
    assert len(markers[("features/shared", 0)].points) == shared > 0
    assert len(markers[("features/single", 1)].points) == len(result.features) - shared
    assert all(m.header.frame_id == "robot1/map" for m in lines)


@pytest.mark.parametrize("provisional", [False, True])
def test_the_serialized_joined_map_is_the_message_rclpy_serializes(
    maps_and_logs, provisional
) -> None:
    from rclpy.serialization import deserialize_message, serialize_message

    maps, logs = maps_and_logs
    result = join_maps(maps, logs)
    if provisional:  # no heading sigmas, NaN covariances of the features first seen
        result = carried_forward(result, maps, 1e-6)
    # robots heard of without a map lengthen the base nodes before the trajectories: their
    # doubles start at other offsets modulo 8
    for robots in (
        ["robot1", "robot2", "robot3"],
        ["robot2", "r", "robot1", "robot10x"],
        ["none"],
    ):
        stamps = {"robot1": 5_000_000_000, "robot2": 6_123_456_789}
        built = joined_map_message(result, 7_000_000_001, stamps, robots)
        data = serialized_joined_map(result, 7_000_000_001, stamps, robots)
        assert len(built.trajectories) == len([r for r in robots if r in result.robots])
        # padding bytes and rclpy's slack at the end are no part of the message: the
        # messages read back are compared
        assert _nan_free(deserialize_message(data, JoinedMap)) == _nan_free(
            deserialize_message(serialize_message(built), JoinedMap)
        )


def _nan_free(message: JoinedMap) -> JoinedMap:
    """``message`` with NaN feature covariances made -1 (NaN != NaN)."""
    for f in message.features:
        f.covariance = np.nan_to_num(f.covariance, nan=-1.0).tolist()
    return message


@pytest.fixture(scope="module")
def robot2_updates() -> list[MapUpdate]:
    """robot2's local map at 25 s, then at the end of the run, as one smoother sends them:
    the whole map, then what changed."""
    from log_slices import robot_log_between

    log = simulate(load_scenario("map_joining"), seed=2).robots["robot2"]
    sender = UpdateSender(12345)
    return [
        sender.update(robot_map_arrays(robot_map_from_local_map(build_local_map(part))))
        for part in (robot_log_between(log, end=25.0), log)
    ]


def _assert_updates_equal(a: MapUpdate, b: MapUpdate) -> None:
    assert (a.session, a.sequence, a.base_sequence, a.observations_before) == (
        b.session,
        b.sequence,
        b.base_sequence,
        b.observations_before,
    )
    for name in KeyedMap.__dataclass_fields__:
        x, y = getattr(a.changes, name), getattr(b.changes, name)
        if isinstance(x, np.ndarray):
            assert x.dtype == y.dtype and x.shape == y.shape, name
            np.testing.assert_array_equal(x, y, err_msg=name)
        else:
            assert x == y, name


def test_local_map_updates_round_trip_field_for_field(robot2_updates) -> None:
    whole, changes = robot2_updates
    assert whole.complete and not changes.complete
    assert len(changes.changes.pose_stamps) > 0 and changes.base_sequence == whole.sequence
    assert changes.changes.num_observations > 0
    for update in (whole, changes):
        msg = local_map_update_message(update, "robot2", 7_000_000_000, iterations=3)
        assert msg.header.frame_id == "robot2/map" and msg.iterations == 3
        assert time_to_ns(msg.header.stamp) == 7_000_000_000
        _assert_updates_equal(map_update_from_message(msg, "robot2"), update)


@pytest.mark.parametrize(
    ("field", "width"),
    [
        ("pose_stamps", 1),
        ("poses", 3),
        ("poses", 1),
        ("feature_labels", 1),
        ("features", 2),
        ("features", 1),
        ("odometry_stamps", 2),
        ("odometry_stamps", 1),
        ("odometry_deltas", 3),
        ("odometry_sqrt_information", 9),
        ("observation_stamps", 1),
        ("observation_labels", 1),
        ("observation_points", 2),
        ("observation_sqrt_information", 4),
        ("observation_sqrt_information", 1),
    ],
)
def test_an_update_whose_fields_differ_in_length_is_refused(robot2_updates, field, width) -> None:
    """One row (or one value: a row cut in two) less in one field of a group."""
    msg = local_map_update_message(robot2_updates[1], "robot2", 1)
    setattr(msg, field, list(getattr(msg, field))[:-width])
    with pytest.raises(LocalMapError, match="robot2: .*(differ in length|per row)"):
        map_update_from_message(msg, "robot2")


@pytest.fixture(scope="module")
def calibrated_map():
    log = simulate(load_scenario("map_joining"), seed=2).robots["robot1"]
    local = build_local_map(log, options=LocalMapOptions(odometry_calibration=True))
    return robot_map_from_local_map(local)


def test_the_odometry_calibration_travels_in_both_local_map_messages(calibrated_map) -> None:
    m = calibrated_map
    assert m.odometry_calibration is not None
    expected = np.asarray(m.odometry_calibration).reshape(-1)
    whole = robot_map_from_message(robot_map_to_message(m, 123))
    np.testing.assert_array_equal(np.asarray(whole.odometry_calibration).reshape(-1), expected)
    update = UpdateSender(session=5).update(robot_map_arrays(m))
    msg = local_map_update_message(update, m.name, 123)
    np.testing.assert_array_equal(msg.odometry_calibration, expected)
    received = map_update_from_message(msg, m.name).changes.arrays()
    np.testing.assert_array_equal(received.odometry_calibration, expected)
    held = robot_map_from_arrays(m.name, received)
    np.testing.assert_array_equal(np.asarray(held.odometry_calibration).reshape(-1), expected)


@pytest.mark.parametrize(
    ("calibration", "fault"),
    [
        ([1.0, 0.9, 1.0], "shape"),
        ([1.0, 0.9, 1.0, 0.01, 0.02, -0.03], "not positive"),
        ([1.0, np.nan, 1.0, 0.01, 0.02, 0.03], "not finite"),
        ([1.0, 0.9, 1.0, 0.01, np.inf, 0.03], "not finite"),
    ],
)
def test_a_bad_odometry_calibration_is_refused(calibrated_map, calibration, fault) -> None:
    arrays = robot_map_arrays(calibrated_map)
    bad = replace(arrays, odometry_calibration=np.asarray(calibration))
    assert fault in (local_map_fault(bad) or "")
    assert local_map_fault(arrays) is None
