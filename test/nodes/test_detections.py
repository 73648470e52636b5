"""The detections node over DDS: a simulated run's observations turned into tag poses on /tf (in
the camera optical frame, apriltag_ros's convention) come out of the adapters as the direct
path's messages and, through real smoothers and a merger, give the core's joined map; a
detector's Detection3DArray is converted alike; bad detections are dropped and counted."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import replace
from typing import Any

import numpy as np
import pytest
from node_group import final_joined_result, smoothers_and_merger
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile

from csam_ros.core.joining.pipeline import run_csam
from csam_ros.core.joining.rendezvous_filters import select_rendezvous
from csam_ros.core.joining.result import CsamResult
from csam_ros.core.model import detections as det
from csam_ros.core.model.detections import (
    DetectionModel,
    camera_positions,
    frame_observations,
    planar_positions,
)
from csam_ros.core.model.log import FeatureLog, MultiRobotLog
from csam_ros.datasets.scenario import load_scenario
from csam_ros.datasets.simulation import simulate

SCENARIO = "map_joining"
SEED = 4
# a camera ahead of the centre, a little right, turned a little left; range sigma grows
MODEL = DetectionModel(
    camera_x=0.12,
    camera_y=-0.03,
    camera_yaw=0.1,
    sigma_range_base=0.005,
    sigma_range_per_m=0.004,
    sigma_bearing=0.012,
)
ROBOT_TAG_IDS = {"robot1": 1001, "robot2": 1002}
FEATURE_HEIGHT = -0.15  # m above the camera (optical y is down)
ROBOT_TAG_HEIGHT = 0.3


def _model_parameters(model: DetectionModel) -> list[Parameter]:
    return [Parameter(k, value=v) for k, v in model.__dict__.items()]


def _in_view(ranges: np.ndarray, bearings: np.ndarray) -> np.ndarray:
    """Observations less than 85 degrees off the camera's axis: what one camera sees."""
    planar = planar_positions(camera_positions(ranges, bearings, MODEL), MODEL)
    return planar[:, 0] > np.cos(np.radians(85.0)) * np.hypot(planar[:, 0], planar[:, 1])


def _camera_log(log: MultiRobotLog) -> MultiRobotLog:
    """The run as one camera sees it: the observations in its view, each with the sigmas of
    the adapter's noise model."""
    robots = {}
    for name, robot in log.robots.items():
        f = robot.features
        keep = _in_view(f.ranges, f.bearings)
        features = FeatureLog(
            f.stamps[keep],
            f.labels[keep],
            f.ranges[keep],
            f.bearings[keep],
            MODEL.sigma_range(f.ranges[keep]),
            np.full(int(keep.sum()), MODEL.sigma_bearing),
        )
        rv = select_rendezvous(
            robot.rendezvous, _in_view(robot.rendezvous.ranges, robot.rendezvous.bearings)
        )
        rv.sigma_range = MODEL.sigma_range(rv.ranges)
        rv.sigma_bearing = np.full(len(rv.ranges), MODEL.sigma_bearing)
        robots[name] = replace(robot, features=features, rendezvous=rv)
    return MultiRobotLog(robots, log.truth)


@pytest.fixture(scope="module")
def camera_log() -> MultiRobotLog:
    return _camera_log(simulate(load_scenario(SCENARIO), seed=SEED))


def _tf_frames(log: MultiRobotLog) -> list[tuple[int, Any]]:
    """Each robot's observations of one stamp as one /tf message of tag poses in its camera
    optical frame (stamp order), with bad detections the adapters must drop."""
    from tf2_msgs.msg import TFMessage

    from csam_ros.ros.conversions import stamp_to_ns, transform_stamped

    frames: dict[tuple[int, str], list[tuple[str, np.ndarray, str]]] = {}
    for name, robot in log.robots.items():
        camera = f"{name}/camera_optical_frame"
        f, rv = robot.features, robot.rendezvous
        positions = camera_positions(f.ranges, f.bearings, MODEL, FEATURE_HEIGHT)
        for t, label, p in zip(f.stamps, f.labels, positions, strict=True):
            frames.setdefault((stamp_to_ns(t), name), []).append((f"tag36h11:{label}", p, camera))
        positions = camera_positions(rv.ranges, rv.bearings, MODEL, ROBOT_TAG_HEIGHT)
        for t, observed, p in zip(rv.stamps, rv.observed, positions, strict=True):
            tag = f"tag36h11:{ROBOT_TAG_IDS[observed]}"
            frames.setdefault((stamp_to_ns(t), name), []).append((tag, p, camera))
    bad = [
        ("tag36h11:77", np.array([np.nan, 0.0, 1.0])),
        ("tag36h11:78", np.array([0.0, 0.0, -1.0])),  # behind the camera
        ("marker_3", np.array([0.0, 0.0, 1.0])),
        ("tag16h5:3", np.array([0.0, 0.0, 1.0])),
        (f"tag36h11:{ROBOT_TAG_IDS['robot1']}", np.array([0.0, 0.0, 2.0])),  # own, for robot1
    ]
    for k, (key, tags) in enumerate(sorted(frames.items())):
        if k % 7 == 3 and key[1] == "robot1":  # now and then, one bad detection among good ones
            name, p = bad[(k // 7) % len(bad)]
            tags.insert(len(tags) // 2, (name, p, f"{key[1]}/camera_optical_frame"))
        if k % 11 == 5:  # not a tag of this camera: ignored, not counted
            tags.append(("tag36h11:3", np.array([0.0, 0.0, 1.0]), f"{key[1]}/map"))
    out = []
    for (stamp_ns, _), tags in sorted(frames.items()):
        transforms = [transform_stamped(parent, child, stamp_ns, p) for child, p, parent in tags]
        out.append((stamp_ns, TFMessage(transforms=transforms)))
    return out


class _Player(Node):
    """Publishes (topic, message) pairs in order, a few per tick, once each topic has the
    matched subscriptions ``subscribers`` names."""

    def __init__(
        self, context: Any, messages: list[tuple[str, Any]], subscribers: dict[str, int]
    ) -> None:
        from csam_ros.nodes.common import publisher
        from csam_ros.ros.topics import ODOM, TF

        super().__init__("detections_player", context=context)
        self.messages = messages
        self.next_index = 0
        self.topic_publishers = {
            topic: (
                self.create_publisher(type(msg), topic, QoSProfile(depth=1000))
                if topic == TF.name
                else publisher(self, ODOM, topic)
            )
            for topic, msg in messages
        }
        self.subscribers = subscribers
        self.create_timer(0.01, self._tick)

    def _tick(self) -> None:
        publishers = self.topic_publishers.items()
        if any(p.get_subscription_count() < self.subscribers[t] for t, p in publishers):
            return
        for topic, msg in self.messages[self.next_index : self.next_index + 10]:
            self.topic_publishers[topic].publish(msg)
            self.next_index += 1


class _Listener(Node):
    """Keeps every message of the given topics, and the newest status entries."""

    def __init__(self, context: Any, topics: dict[str, type]) -> None:
        from diagnostic_msgs.msg import DiagnosticArray

        from csam_ros.ros.topics import RELIABLE

        super().__init__("detections_listener", context=context)
        self.received: dict[str, list[Any]] = {t: [] for t in topics}
        for topic, msgtype in topics.items():
            self.create_subscription(msgtype, topic, self.received[topic].append, RELIABLE)
        self.status: dict[str, dict[str, str]] = {}
        self.create_subscription(DiagnosticArray, "/csam/status", self._on_status, 50)

    def _on_status(self, msg: Any) -> None:
        for s in msg.status:
            self.status[s.name] = {kv.key: kv.value for kv in s.values}


def _adapter(context: Any, robot: str, extra: list[Parameter] | None = None) -> Node:
    from csam_ros.nodes.detections import Detections

    tags = [f"{i}:{r}" for r, i in ROBOT_TAG_IDS.items()]
    return Detections(
        context=context,
        namespace=robot,
        parameter_overrides=[
            *_model_parameters(MODEL),
            Parameter("robot_tags", value=tags),
            Parameter("status_period", value=0.2),
            *(extra or []),
        ],
    )


def _assert_same_observations(got: list[Any], expected: list[Any], name_field: str) -> None:
    assert len(got) == len(expected)
    for g, e in zip(got, expected, strict=True):
        assert g.header == e.header
        assert [getattr(o, name_field) for o in g.observations] == [
            getattr(o, name_field) for o in e.observations
        ]
        for field in ("range", "bearing", "sigma_range", "sigma_bearing"):
            np.testing.assert_allclose(
                [getattr(o, field) for o in g.observations],
                [getattr(o, field) for o in e.observations],
                rtol=0,
                atol=1e-9,
                err_msg=field,
            )


@pytest.fixture
def executor(ros_context: Any) -> Iterator[SingleThreadedExecutor]:
    executor = SingleThreadedExecutor(context=ros_context)
    yield executor
    for node in executor.get_nodes():
        node.destroy_node()
    executor.shutdown()


def test_tags_on_tf_give_the_direct_messages_and_the_joined_map(
    ros_context: Any, spin: Any, executor: SingleThreadedExecutor, camera_log: MultiRobotLog
) -> None:
    from csam_msgs.msg import FeatureObservations, RendezvousObservations

    from csam_ros.ros.conversions import log_to_messages
    from csam_ros.ros.topics import ODOM, RENDEZVOUS, TF

    robots = list(camera_log.robots)
    direct = log_to_messages(camera_log, with_truth=False)
    expected = {m.topic: [] for m in direct if m.topic.endswith(("/features", "/rendezvous"))}
    for m in direct:
        if m.topic in expected:
            expected[m.topic].append(m.message)
    assert expected[RENDEZVOUS.of("robot1")] and expected[RENDEZVOUS.of("robot2")]
    # the odometry as a driver publishes it: the integrated pose, no twist (its covariance
    # kept: the smoother reads the motion from the poses, exactly, with the log's sigmas)
    driven = log_to_messages(camera_log, with_truth=False, with_poses=True)
    odometry = [(m.stamp_ns, m.topic, m.message) for m in driven if m.topic.endswith("/odom")]
    for _, _, msg in odometry:
        twist = msg.twist.twist
        twist.linear.x = twist.linear.y = twist.angular.z = 0.0
    frames = [(stamp_ns, TF.name, msg) for stamp_ns, msg in _tf_frames(camera_log)]
    # in stamp order, a frame's odometry before its tags
    played = [(topic, msg) for _, topic, msg in sorted(odometry + frames, key=lambda m: m[0])]

    smoothers, merger = smoothers_and_merger(ros_context, robots)
    adapters = {r: _adapter(ros_context, r) for r in robots}
    listener = _Listener(
        ros_context,
        {
            t: FeatureObservations if t.endswith("features") else RendezvousObservations
            for t in expected
        },
    )
    for node in (merger, listener, *smoothers.values(), *adapters.values()):
        executor.add_node(node)

    def matched() -> bool:  # every adapter's output reaches its smoother and the listener
        return all(
            a.features_pub.get_subscription_count() >= 2
            and a.rendezvous_pub.get_subscription_count() >= 1 + len(robots)
            for a in adapters.values()
        )

    assert spin(executor, matched, 10)
    needed = {TF.name: len(robots), **{ODOM.of(r): 1 for r in robots}}
    player = _Player(ros_context, played, needed)
    executor.add_node(player)

    def all_received() -> bool:
        return player.next_index == len(played) and all(
            len(listener.received[t]) == len(e) for t, e in expected.items()
        )

    assert spin(executor, all_received, 40), {t: len(m) for t, m in listener.received.items()}
    for topic, messages in expected.items():
        field = "label" if topic.endswith("features") else "observed_robot"
        _assert_same_observations(listener.received[topic], messages, field)

    # the bad detections: dropped, counted by reason, logged once each
    drops = adapters["robot1"].drops.as_dict()
    assert set(drops) == {
        det.NOT_FINITE,
        det.BEHIND_CAMERA,
        det.UNPARSEABLE_TAG,
        det.UNKNOWN_TAG_FAMILY,
        det.OWN_TAG,
    }
    assert adapters["robot2"].drops.as_dict() == {}
    assert spin(
        executor,
        lambda: (
            listener.status.get("detections/robot1", {}).get("dropped") == str(sum(drops.values()))
        ),
        5,
    )
    status = listener.status["detections/robot1"]
    assert {k: int(v) for k, v in status.items() if k.startswith("dropped/")} == {
        f"dropped/{k}": v for k, v in drops.items()
    }

    # through the smoothers and the merger: the core's joined map of the same observations
    spin(executor, lambda: False, 0.5)
    assert final_joined_result(executor, smoothers, merger) is not None
    spin(executor, lambda: False, 0.3)
    result: CsamResult = merger.policy.last_result
    core = run_csam(camera_log)
    for name, want in core.robots.items():
        got = result.robots[name]
        assert got.alignment == want.alignment == ("reference" if name == "robot1" else "aligned")
        np.testing.assert_allclose(got.stamps, want.stamps, atol=1e-9)
        np.testing.assert_allclose(got.poses_joined, want.poses_joined, atol=1e-6)
    assert {(a.a, a.b) for a in result.associations} == {(a.a, a.b) for a in core.associations}
    assert len(core.associations) > 0
    joined = {tuple(f.members): f.xy for f in result.features}
    for feature in core.features:
        np.testing.assert_allclose(joined[tuple(feature.members)], feature.xy, atol=1e-6)


def _detection(frame: str, stamp_ns: int, hypotheses: list[tuple[str, float, list[float]]]) -> Any:
    from vision_msgs.msg import Detection3D, ObjectHypothesisWithPose

    from csam_ros.ros.conversions import ns_to_time

    detection = Detection3D()
    detection.header.frame_id = frame
    detection.header.stamp = ns_to_time(stamp_ns)
    for class_id, score, (x, y, z) in hypotheses:
        h = ObjectHypothesisWithPose()
        h.hypothesis.class_id, h.hypothesis.score = class_id, score
        h.pose.pose.position.x, h.pose.pose.position.y, h.pose.pose.position.z = x, y, z
        detection.results.append(h)
    return detection


def _array(frame: str, stamp_ns: int, detections: list[Any]) -> Any:
    from vision_msgs.msg import Detection3DArray

    from csam_ros.ros.conversions import ns_to_time

    msg = Detection3DArray()
    msg.header.frame_id = frame
    msg.header.stamp = ns_to_time(stamp_ns)
    msg.detections = detections
    return msg


def test_detection_arrays_are_converted_and_bad_ones_counted(
    ros_context: Any, spin: Any, executor: SingleThreadedExecutor
) -> None:
    from csam_msgs.msg import FeatureObservations, RendezvousObservations

    from csam_ros.nodes.common import publisher
    from csam_ros.ros.conversions import time_to_ns
    from csam_ros.ros.topics import DETECTIONS

    camera = "robot1/front_camera"
    adapter = _adapter(ros_context, "robot1", [Parameter("camera_frame", value=camera)])
    listener = _Listener(
        ros_context,
        {"/robot1/features": FeatureObservations, "/robot1/rendezvous": RendezvousObservations},
    )
    source = Node("detector", context=ros_context)
    detections = publisher(source, DETECTIONS, DETECTIONS.of("robot1"))
    for node in (adapter, listener, source):
        executor.add_node(node)
    assert spin(executor, lambda: detections.get_subscription_count() >= 1, 10)
    assert spin(executor, lambda: adapter.features_pub.get_subscription_count() >= 1, 10)
    a, b, c, d = [0.4, -0.1, 2.0], [-0.3, 0.0, 1.5], [1.0, 0.2, 3.0], [0.0, 0.0, 2.5]
    nan = [float("nan"), 0.0, 1.0]
    arrays = [
        _array(
            camera,
            5_000_000_000,
            [
                # the best-scoring hypothesis names the tag (8 at b)
                _detection("", 0, [("tag36h11:4", 0.2, a), ("tag36h11:8", 0.9, b)]),
                _detection("", 0, [("12", 1.0, c)]),
                _detection("", 0, [("tag36h11:1002", 0.8, d)]),  # robot2's tag
                _detection("", 0, []),  # no hypothesis: no tag id
                _detection("", 0, [("tag36h11:13", 1.0, nan)]),
            ],
        ),
        # no stamp and no frame on the array: each detection's own, one message per stamp
        _array(
            "",
            0,
            [
                _detection(camera, 6_000_000_000, [("14", 1.0, a)]),
                _detection(camera, 7_000_000_000, [("15", 1.0, c)]),
            ],
        ),
        _array("robot1/base_link", 8_000_000_000, [_detection("", 0, [("16", 1.0, a)])] * 2),
        _array(camera, 9_000_000_000, [_detection("", 0, [("17", 1.0, [0.0, 0.0, -2.0])])]),
        # before the last frame published (7 s): the smoother would drop it
        _array(camera, 6_500_000_000, [_detection("", 0, [("18", 1.0, a)])]),
    ]
    for msg in arrays:
        detections.publish(msg)
        spin(executor, lambda: False, 0.05)
    received = listener.received
    assert spin(
        executor,
        lambda: len(received["/robot1/features"]) == 3 and len(received["/robot1/rendezvous"]) == 1,
        10,
    )
    spin(executor, lambda: False, 0.3)  # nothing else comes
    features = received["/robot1/features"]
    assert [time_to_ns(m.header.stamp) for m in features] == [5e9, 6e9, 7e9]
    assert {m.header.frame_id for m in features} == {"robot1/base_link"}
    expected = frame_observations(5.0, ["8", "12"], [b, c], MODEL, {}, "robot1").features
    assert [o.label for o in features[0].observations] == [8, 12]
    for field, want in [
        ("range", expected.ranges),
        ("bearing", expected.bearings),
        ("sigma_range", expected.sigma_range),
        ("sigma_bearing", expected.sigma_bearing),
    ]:
        np.testing.assert_allclose([getattr(o, field) for o in features[0].observations], want)
    assert [o.label for m in features[1:] for o in m.observations] == [14, 15]
    rendezvous = received["/robot1/rendezvous"][0]
    assert time_to_ns(rendezvous.header.stamp) == 5e9
    assert [o.observed_robot for o in rendezvous.observations] == ["robot2"]
    # 2.5 m ahead of the camera, which is at (0.12, -0.03) turned 0.1 rad left
    ahead = np.array([0.12 + 2.5 * np.cos(0.1), -0.03 + 2.5 * np.sin(0.1)])
    np.testing.assert_allclose(rendezvous.observations[0].range, np.hypot(*ahead), rtol=1e-14)
    np.testing.assert_allclose(
        rendezvous.observations[0].bearing, np.arctan2(ahead[1], ahead[0]), rtol=1e-14
    )

    counts = {
        "dropped/unparseable_tag": "1",
        "dropped/not_finite": "1",
        "dropped/wrong_frame": "2",
        "dropped/behind_camera": "1",
        "dropped/stale_stamp": "1",
    }
    assert spin(
        executor,
        lambda: {k: listener.status.get("detections/robot1", {}).get(k) for k in counts} == counts,
        5,
    ), listener.status
    status = listener.status["detections/robot1"]
    assert (status["frames"], status["features"], status["rendezvous"]) == ("4", "4", "1")


def test_bad_parameters_are_refused_by_name(ros_context: Any) -> None:
    with pytest.raises(ValueError, match="robot_tags: '5' is not"):
        _adapter(ros_context, "robot1", [Parameter("robot_tags", value=["5"])])
    with pytest.raises(ValueError, match="sigma_bearing: must be greater than 0"):
        _adapter(ros_context, "robot1", [Parameter("sigma_bearing", value=0.0)])


def test_every_model_field_is_a_parameter_with_its_description(ros_context: Any) -> None:
    from csam_ros.core.model.config_file import settings
    from csam_ros.nodes.detections import Detections

    plain = Detections(context=ros_context, namespace="robot3")
    adapter = _adapter(ros_context, "robot1")
    try:
        assert plain.model == DetectionModel() and adapter.model == MODEL
        assert plain.camera_frame == "robot3/camera_optical_frame"
        assert plain.robot_tags == {} and adapter.robot_tags == {1001: "robot1", 1002: "robot2"}
        for name, (rule, default) in settings(DetectionModel).items():
            assert rule.node == "detections"
            assert plain.describe_parameter(name).description == rule.description
            assert plain.get_parameter(name).value == default
            if rule.minimum is not None:
                ranges = plain.describe_parameter(name).floating_point_range
                assert [r.from_value for r in ranges] == [rule.minimum], name
    finally:
        plain.destroy_node()
        adapter.destroy_node()
    body = _adapter(ros_context, "robot1", [Parameter("camera_axes", value=det.BODY)])
    try:
        assert body.camera_frame == "robot1/camera_link"
    finally:
        body.destroy_node()
