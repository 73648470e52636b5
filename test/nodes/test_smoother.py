"""The smoother node's rendezvous thinning: its own and its peers' measurements, as offline."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import numpy as np
from rclpy.parameter import Parameter

from csam_ros.core.exchange.map_updates import resync_answer
from csam_ros.core.joining.rendezvous_filters import select_rendezvous, thin_rendezvous
from csam_ros.core.model.log import RendezvousLog
from csam_ros.ros.conversions import rendezvous_message, stamp_to_ns

ROBOTS = ["robot1", "robot2", "robot3"]


def _log(observer: str, rng: np.random.Generator, n: int) -> RendezvousLog:
    stamps = np.sort(rng.choice(np.arange(0.0, 300.0, 0.25), n, replace=False))
    others = [r for r in ROBOTS if r != observer]
    return RendezvousLog(
        stamps,
        list(rng.choice(others, n)),
        rng.uniform(0.5, 4.0, n),
        rng.uniform(-1.0, 1.0, n),
        np.full(n, 0.05),
        np.full(n, 0.02),
    )


def _messages(robot: str, log: RendezvousLog):
    for i in range(log.stamps.size):
        sl = slice(i, i + 1)
        yield rendezvous_message(
            robot,
            stamp_to_ns(log.stamps[i]),
            log.observed[sl],
            log.ranges[sl],
            log.bearings[sl],
            log.sigma_range[sl],
            log.sigma_bearing[sl],
        )


def test_smoother_keeps_the_offline_thinned_rendezvous(ros_context) -> None:
    from csam_ros.nodes.smoother import Smoother

    rng = np.random.default_rng(7)
    logs = {r: _log(r, rng, 150) for r in ROBOTS}
    logs["robot2"].ranges[5] = -1.0  # a bad peer measurement: its own smoother drops it
    valid = {r: select_rendezvous(log, log.ranges > 0) for r, log in logs.items()}
    expected, _ = thin_rendezvous(valid, 2.0, 6)
    smoother = Smoother(
        context=ros_context,
        namespace="robot1",
        parameter_overrides=[
            Parameter("robots", value=ROBOTS),
            Parameter("rendezvous_min_interval", value=2.0),
            Parameter("rendezvous_max_per_pair", value=6),
        ],
    )
    try:
        for msg in _messages("robot1", logs["robot1"]):
            smoother.on_own_rendezvous(msg)
        for peer in ("robot2", "robot3"):
            for msg in _messages(peer, logs[peer]):
                smoother.on_peer_rendezvous(peer, msg)
        own, stamps = smoother.kept_rendezvous()
        np.testing.assert_allclose(own.stamps, expected["robot1"].stamps, atol=1e-9)
        assert own.observed == expected["robot1"].observed
        of_me = [
            t
            for peer in ("robot2", "robot3")
            for t, o in zip(expected[peer].stamps, expected[peer].observed, strict=True)
            if o == "robot1"
        ]
        np.testing.assert_allclose(
            stamps, np.unique(np.concatenate([own.stamps, of_me])), atol=1e-9
        )
        assert 0 < own.stamps.size <= 12  # two peers, at most 6 each
    finally:
        smoother.destroy_node()


# -- the boundary: bad sensor messages through the node's own (guarded) callbacks -------------

GOOD_SECONDS = 12.0


def _good_messages() -> list:
    """robot1's sensor messages of the map-joining scenario's first seconds, in stamp order."""
    from csam_ros.datasets.scenario import load_scenario
    from csam_ros.datasets.simulation import simulate
    from csam_ros.ros.conversions import log_to_messages

    log = simulate(load_scenario("map_joining"), seed=3)
    return [
        m
        for m in log_to_messages(log, with_truth=False)
        if m.topic.startswith("/robot1/") and m.stamp_ns <= GOOD_SECONDS * 1e9
    ]


def deliver(node, topic: str, msg) -> None:
    """Hand ``msg`` to the node's subscription of ``topic`` as its executor would."""
    (subscription,) = [s for s in node.subscriptions if s.topic_name == topic]
    subscription.callback(msg)


def flushed_map(node) -> tuple[np.ndarray, np.ndarray, dict[int, np.ndarray]]:
    """Flush (as the service does) and return the stamps, poses and landmarks of the map."""
    from std_srvs.srv import Trigger

    response = node.on_flush(Trigger.Request(), Trigger.Response())
    assert response.success
    local = node.map
    landmarks = dict(zip(local.landmark_labels, local.landmarks, strict=True))
    return local.stamps.copy(), local.poses.copy(), landmarks


def assert_good_map_unchanged(node, good) -> None:
    stamps, poses, landmarks = flushed_map(node)
    good_stamps, good_poses, good_landmarks = good
    index = node.map.pose_index(good_stamps)
    np.testing.assert_allclose(stamps[index], good_stamps, atol=1e-9)
    np.testing.assert_allclose(poses[index], good_poses, atol=1e-6)
    for label, xy in good_landmarks.items():
        np.testing.assert_allclose(landmarks[label], xy, atol=1e-6)


def new_smoother(ros_context, **parameters):
    from csam_ros.nodes.smoother import Smoother

    overrides = [Parameter("robots", value=["robot1", "robot2"])]
    overrides += [Parameter(k, value=v) for k, v in parameters.items()]
    return Smoother(context=ros_context, namespace="robot1", parameter_overrides=overrides)


@contextmanager
def fed_smoother(ros_context, messages, **parameters) -> Iterator[tuple[Any, tuple]]:
    """A smoother fed ``messages`` and flushed, with its map; destroyed on leaving."""
    node = new_smoother(ros_context, **parameters)
    try:
        for m in messages:
            deliver(node, m.topic, m.message)
        yield node, flushed_map(node)
    finally:
        node.destroy_node()


def _features(stamp_s: float, r: float, sr: float, sb: float, label: int = 1):
    from csam_ros.ros.conversions import features_message

    return features_message("robot1", stamp_to_ns(stamp_s), [label], [r], [0.1], [sr], [sb])


def _odometry(stamp_s: float, v: float = 0.5):
    from csam_ros.ros.conversions import odometry_message

    return odometry_message(
        "robot1", stamp_to_ns(stamp_s), np.array([v, 0.0, 0.02]), np.full(3, 0.02)
    )


def test_smoother_drops_features_beyond_the_bounds(ros_context) -> None:
    """Issue 15 case 2: each of these killed the node with a ValueError from add_features."""
    with fed_smoother(ros_context, _good_messages()) as (node, good):
        t = GOOD_SECONDS + 0.05
        for i, (r, sr, sb) in enumerate(
            [(1e8, 0.01, 0.01), (1e300, 0.01, 0.01), (3.0, 1e-10, 0.01), (3.0, 1e-300, 1e-300)]
        ):
            deliver(node, "/robot1/features", _features(t + 0.01 * i, r, sr, sb, label=900 + i))
        assert node.drops.as_dict() == {"range_out_of_bounds": 2, "sigma_out_of_bounds": 2}
        assert_good_map_unchanged(node, good)
        assert node.errors == 0


def test_smoother_outlier_stamp_neither_stalls_nor_blocks_odometry(ros_context) -> None:
    """Issue 15 case 3: one odometry message stamped 1e6 s made a million poses and blocked
    every later one as stamp_backwards."""
    messages = _good_messages()
    with fed_smoother(ros_context, messages) as (node, good):
        deliver(node, "/robot1/odom", _odometry(1e6))
        stamps, _, _ = flushed_map(node)
        assert len(stamps) == len(good[0])
        for k in range(1, 6):
            deliver(node, "/robot1/odom", _odometry(GOOD_SECONDS + 0.1 * k))
        stamps, _, _ = flushed_map(node)
        assert node.last_odometry_ns == stamp_to_ns(GOOD_SECONDS + 0.5)
        assert node.drops.as_dict() == {"stamp_jump": 1}
        # a real gap: the stream resumes 1e6 s later and goes on there, with a few poses
        for k in range(3):
            deliver(node, "/robot1/odom", _odometry(1e6 + 0.1 * k))
        stamps, _, _ = flushed_map(node)
        assert node.last_odometry_ns == stamp_to_ns(1e6 + 0.2)
        assert stamps[-1] == 1e6 and len(stamps) <= len(good[0]) + 4
        assert node.drops.as_dict() == {"stamp_jump": 1, "stamp_gap": 1}
        assert_good_map_unchanged(node, good)
        assert node.errors == 0


def test_smoother_drops_odometry_beyond_the_speed_bound_and_keeps_updating(ros_context) -> None:
    """Issue 15 case 4: v = 1e300 was accepted, and every later update then failed."""
    with fed_smoother(ros_context, _good_messages()) as (node, good):
        deliver(node, "/robot1/odom", _odometry(GOOD_SECONDS + 0.1, v=1e300))
        for k in range(2, 12):
            deliver(node, "/robot1/odom", _odometry(GOOD_SECONDS + 0.1 * k))
        stamps, _, _ = flushed_map(node)
        assert node.last_odometry_ns == stamp_to_ns(GOOD_SECONDS + 1.1)
        assert stamps[-1] == GOOD_SECONDS + 1  # the map went on after the bad sample
        assert node.drops.as_dict() == {"speed_out_of_bounds": 1}
        assert node.errors == 0
        assert_good_map_unchanged(node, good)


def test_offline_replay_drops_the_same_messages(tmp_path) -> None:
    """Cases 2-4 in a bag: ``csam replay --offline`` finishes, counts each drop once, and
    the robot's map is the one of the good data."""
    from csam_ros.bag import BagWriter
    from csam_ros.bag.types import msgtype_of
    from csam_ros.cli import main
    from csam_ros.core.joining.result import RunSummary
    from csam_ros.ros.conversions import StampedMessage
    from csam_ros.ros.topics import qos_of

    good = _good_messages()
    t = GOOD_SECONDS - 2.05
    bad = [
        StampedMessage(stamp_to_ns(t), "/robot1/features", _features(t, 1e8, 0.01, 0.01)),
        StampedMessage(
            stamp_to_ns(t + 0.01), "/robot1/features", _features(t + 0.01, 3.0, 1e-10, 0.01)
        ),
        StampedMessage(stamp_to_ns(t + 0.02), "/robot1/odom", _odometry(1e6)),
        StampedMessage(stamp_to_ns(t + 0.03), "/robot1/odom", _odometry(t + 0.03, v=1e300)),
    ]
    summaries = {}
    for name, messages in (("good", good), ("bad", sorted(good + bad, key=lambda m: m.stamp_ns))):
        bag = tmp_path / f"{name}_bag"
        with BagWriter(bag) as writer:
            for m in messages:
                if m.topic not in writer.topics:
                    writer.add_topic(m.topic, msgtype_of(m.message), qos_of(m.topic))
                writer.write(m.topic, m.stamp_ns, m.message)
        assert main(["replay", str(bag), "--offline", "--out", str(tmp_path / name)]) == 0
        summaries[name] = RunSummary.read(tmp_path / name / "summary.json")
    assert summaries["bad"].dropped == {
        "robot1": {
            "range_out_of_bounds": 1,
            "sigma_out_of_bounds": 1,
            "speed_out_of_bounds": 1,
            "stamp_jump": 1,
        }
    }
    a, b = (summaries[k].result.robots["robot1"] for k in ("good", "bad"))
    np.testing.assert_allclose(b.stamps, a.stamps)
    np.testing.assert_allclose(b.poses_local, a.poses_local, atol=1e-9)


def test_smoother_takes_feature_points_and_correlated_odometry_as_offline(ros_context) -> None:
    """A 2D SLAM file's messages: Cartesian feature points with full covariances and odometry
    whose inputs are correlated (in the twist covariance). The smoother's map is the offline
    build's, which keeps both."""
    from csam_ros.core.model import log, se2
    from csam_ros.core.model.motion import dead_reckoning, increment
    from csam_ros.core.smoothing.local_map_build import build_local_map
    from csam_ros.ros.conversions import log_to_messages

    rng = np.random.default_rng(8)
    n = 40
    inputs = np.column_stack([np.full(n, 0.5), np.zeros(n), np.full(n, 0.15)])
    a = 0.05 * rng.standard_normal((n, 3, 3))
    sigmas, rho = log.correlations_from_covariances(a @ a.transpose(0, 2, 1) + 1e-3 * np.eye(3))
    truth = dead_reckoning(increment(inputs[1:], np.ones(n - 1)))
    landmarks = rng.uniform(-4, 4, (6, 2)) + truth[:, :2].mean(axis=0)
    pose, label = np.nonzero(np.ones((n, 6), dtype=bool))
    b = 0.1 * rng.standard_normal((len(pose), 2, 2))
    covariance = b @ b.transpose(0, 2, 1) + 1e-3 * np.eye(2)
    seen = se2.inverse_transform_point(truth[pose], landmarks[label])
    points = seen + 0.05 * rng.standard_normal(seen.shape)
    measured = inputs + 0.01 * rng.standard_normal(inputs.shape)
    robot = log.RobotLog(
        "robot1",
        log.OdometryLog(np.arange(n, dtype=float), measured, sigmas, rho),
        log.empty_features(),
        log.empty_rendezvous(),
        log.FeaturePointLog(pose.astype(float), label, points, covariance),
    )
    messages = log_to_messages(log.MultiRobotLog({"robot1": robot}))
    assert {m.topic for m in messages} == {"/robot1/odom", "/robot1/feature_points"}
    offline = build_local_map(robot)
    with fed_smoother(ros_context, messages) as (node, (stamps, poses, landmark_xy)):
        assert node.drops.total == 0
        np.testing.assert_allclose(stamps, offline.stamps, atol=1e-9)
        np.testing.assert_allclose(poses, offline.poses, atol=1e-7)
        for k, xy in zip(offline.landmark_labels, offline.landmarks, strict=True):
            np.testing.assert_allclose(landmark_xy[k], xy, atol=1e-7)
    # without the correlations the map is another one
    independent = build_local_map(
        log.RobotLog(
            "robot1",
            log.OdometryLog(np.arange(n, dtype=float), measured, sigmas),
            robot.features,
            robot.rendezvous,
            robot.points,
        )
    )
    assert np.abs(independent.poses[:, :2] - offline.poses[:, :2]).max() > 1e-4


@contextmanager
def update_receiver(ros_context, spin) -> Iterator[tuple[Any, Any, list]]:
    """A smoother, and an executor spinning a node that keeps every ``local_map_updates``
    message it receives over DDS: (smoother, executor, received)."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor

    from csam_ros.ros.topics import LOCAL_MAP_UPDATES

    node = new_smoother(ros_context)
    receiver = rclpy.create_node("receiver", context=ros_context)
    received: list = []
    receiver.create_subscription(
        LOCAL_MAP_UPDATES.msgtype,
        LOCAL_MAP_UPDATES.of("robot1"),
        received.append,
        LOCAL_MAP_UPDATES.qos,
    )
    executor = SingleThreadedExecutor(context=ros_context)
    executor.add_node(receiver)
    try:
        assert spin(executor, lambda: node.update_pub.get_subscription_count() == 1)
        yield node, executor, received
    finally:
        receiver.destroy_node()
        node.destroy_node()
        executor.shutdown()


def held_arrays(received: list) -> Any:
    """The map a receiver holds after applying every update in ``received``, as arrays."""
    from csam_ros.core.exchange.map_updates import apply_update
    from csam_ros.ros.map_messages import map_update_from_message

    held = None
    for msg in received:
        held = apply_update(held, map_update_from_message(msg, "robot1"))
    return held.map.arrays()


def current_arrays(node) -> Any:
    """The smoother's own local map, as arrays."""
    from csam_ros.core.exchange.map_arrays import robot_map_arrays
    from csam_ros.core.joining.pipeline import robot_map_from_local_map

    return robot_map_arrays(robot_map_from_local_map(node.map))


def test_smoother_updates_build_its_map_at_a_receiver_and_resync_resends_it(
    ros_context, spin
) -> None:
    """A receiver over DDS that applies every ``local_map_updates`` message holds the
    smoother's map: factors exactly, estimates within the tolerance, exactly after a flush.
    A resync is one complete update, and the updates after it apply on top of it."""
    from std_srvs.srv import Trigger

    messages = _good_messages()
    with update_receiver(ros_context, spin) as (node, executor, received):
        chunks = np.array_split(np.arange(len(messages)), 6)
        for chunk in chunks:
            for i in chunk:
                deliver(node, messages[i].topic, messages[i].message)
            node.solve_and_publish()
            assert spin(executor, lambda: len(received) == node.sender.held.sequence)
        tolerance = node.sender.tolerance
        current = current_arrays(node)
        within = held_arrays(received)
        np.testing.assert_array_equal(within.odometry_delta, current.odometry_delta)
        np.testing.assert_array_equal(within.observation_xy, current.observation_xy)
        assert np.abs(within.poses[:, :2] - current.poses[:, :2]).max() <= tolerance.position
        assert [m.base_sequence for m in received][:2] == [0, 1]  # the first is the whole map
        assert sum(len(m.observation_labels) for m in received) == len(current.observation_xy)

        response = node.on_resync(Trigger.Request(), Trigger.Response())
        assert response.success and node.resyncs == 1
        assert spin(executor, lambda: len(received) == len(chunks) + 1)
        assert received[-1].base_sequence == 0
        assert len(received[-1].pose_stamps) == len(current.poses)
        flushed_map(node)  # converged: every estimate exactly
        assert spin(executor, lambda: len(received) == len(chunks) + 2)
        assert received[-1].base_sequence == received[-2].sequence
        exact, final = held_arrays(received), current_arrays(node)
        np.testing.assert_array_equal(exact.poses, final.poses)
        np.testing.assert_array_equal(exact.feature_xy, final.feature_xy)


def test_smoother_defers_updates_until_the_last_is_acknowledged_but_never_a_resync(
    ros_context, spin
) -> None:
    """While the last update is unacknowledged no update goes out; the next update holds
    every change since, so a receiver still builds the smoother's map; a flush is never
    deferred. A resync is answered by the whole map at once all the same (the last update may
    be the one lost), the answer naming the session and its sequence."""
    from std_srvs.srv import Trigger

    messages = _good_messages()
    with update_receiver(ros_context, spin) as (node, executor, received):
        publisher = node.update_pub
        chunks = np.array_split(np.arange(len(messages)), 4)
        acknowledged = [True, False, False, True]
        for chunk, acked in zip(chunks, acknowledged, strict=True):
            for i in chunk:
                deliver(node, messages[i].topic, messages[i].message)
            publisher.wait_for_all_acked = lambda timeout, acked=acked: acked
            node.solve_and_publish()
        assert node.deferred_updates == 2
        assert spin(executor, lambda: len(received) == 2)
        assert [m.base_sequence for m in received] == [0, 1]
        current, within = current_arrays(node), held_arrays(received)
        np.testing.assert_array_equal(within.odometry_delta, current.odometry_delta)
        np.testing.assert_array_equal(within.observation_xy, current.observation_xy)
        tolerance = node.sender.tolerance.position
        assert np.abs(within.poses[:, :2] - current.poses[:, :2]).max() <= tolerance
        publisher.wait_for_all_acked = lambda timeout: False
        response = node.on_resync(Trigger.Request(), Trigger.Response())
        sent = node.sender.held
        assert response.success and node.resyncs == 1
        assert response.message == resync_answer(node.sender.session, sent.sequence)
        assert spin(executor, lambda: len(received) == 3)
        assert received[-1].base_sequence == 0 and received[-1].sequence == sent.sequence
        flushed_map(node)
        assert spin(executor, lambda: len(received) == 4)
        assert received[-1].base_sequence == received[-2].sequence
        np.testing.assert_array_equal(held_arrays(received).poses, current_arrays(node).poses)
        assert node.deferred_updates == 2


def test_smoother_flush_again_without_new_data_publishes_nothing(ros_context, spin) -> None:
    """A run's end flushes until the smoothers settle: a flush with nothing new since the last
    one answers the same stamp and sends no second (whole-map sized) update; new data makes
    the next flush publish again."""
    messages = _good_messages()
    half = len(messages) // 2
    with update_receiver(ros_context, spin) as (node, executor, received):
        for m in messages[:half]:
            deliver(node, m.topic, m.message)
        flushed_map(node)
        assert spin(executor, lambda: len(received) == 1)
        stamp = node.published_ns
        flushed_map(node)
        flushed_map(node)
        assert not spin(executor, lambda: len(received) > 1, 1.0)
        assert node.published_ns == stamp
        for m in messages[half:]:
            deliver(node, m.topic, m.message)
        flushed_map(node)
        assert spin(executor, lambda: len(received) == 2)
        assert node.published_ns > stamp
        np.testing.assert_array_equal(held_arrays(received).poses, current_arrays(node).poses)
