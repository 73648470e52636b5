"""The topic declarations: what the nodes publish and subscribe to is declared, recorded and
offered with the declared QoS."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import pytest
from rclpy.node import Node
from rclpy.parameter import Parameter

from csam_ros.bag import inspect_bag, qos_to_dict
from csam_ros.datasets.scenario import load_scenario
from csam_ros.datasets.simulation import simulate
from csam_ros.ros.conversions import log_to_messages
from csam_ros.ros.topics import (
    DIAGNOSTICS,
    FEATURE_POINTS,
    FEATURES_TRUTH,
    LATCHED,
    ODOM,
    POSE,
    SENSOR_DATA,
    TOPICS,
    base_station_topics,
    declaration,
    parse,
    qos_of,
    recorded_topics,
    robot_host_topics,
    sensor_topics,
)
from csam_ros.run.bag_io import write_log_bag

ROBOTS = ["robot1", "robot2"]
ROS_INTERNAL = {"/rosout", "/parameter_events"}


@contextmanager
def _run_nodes(context: Any) -> Iterator[list[Node]]:
    """A simulator, a smoother per robot and a merger in this process (never spun)."""
    from csam_ros.nodes.merger import Merger
    from csam_ros.nodes.simulator import Simulator
    from csam_ros.nodes.smoother import Smoother

    robots = Parameter("robots", value=ROBOTS)
    nodes: list[Node] = []
    try:
        nodes.append(Simulator(context=context))
        for robot in ROBOTS:
            nodes.append(Smoother(context=context, namespace=robot, parameter_overrides=[robots]))
        nodes.append(Merger(context=context, parameter_overrides=[robots]))
        yield nodes
    finally:
        for node in nodes:
            node.destroy_node()


def test_every_topic_a_live_run_publishes_is_declared_and_recorded(ros_context: Any) -> None:
    recorded = set(recorded_topics(ROBOTS))
    with _run_nodes(ros_context) as nodes:
        published = [(p.topic_name, p.msg_type, p.qos_profile) for n in nodes for p in n.publishers]
        subscribed = [
            (s.topic_name, s.msg_type, s.qos_profile) for n in nodes for s in n.subscriptions
        ]
    published = [p for p in published if p[0] not in ROS_INTERNAL]
    subscribed = [s for s in subscribed if s[0] not in ROS_INTERNAL]
    assert published, "the nodes published nothing"
    for name, msgtype, qos in published:
        topic = declaration(name)
        assert name in recorded or not topic.recorded, f"{name} is published but not recorded"
        assert (msgtype, qos) == (topic.msgtype, topic.qos), name
    for name, msgtype, qos in subscribed:
        topic = declaration(name)
        assert (msgtype, qos) == (topic.msgtype, topic.subscription_qos), name
        if topic is FEATURE_POINTS:
            continue  # a 2D SLAM file's bag has them (played); the simulator never does
        assert name in {p[0] for p in published}, f"nobody publishes {name}"
    assert set(sensor_topics(ROBOTS)) <= {s[0] for s in subscribed}


def test_a_topic_name_leads_back_to_its_declaration() -> None:
    for topic in TOPICS:
        name = topic.of("robot7") if topic.per_robot else topic.of()
        assert parse(name) == (topic, "robot7" if topic.per_robot else None)
    assert parse("/robot1/unknown") is None
    assert parse("odom") is None  # relative: not an absolute name
    with pytest.raises(ValueError, match="/robot1/unknown"):
        qos_of("/robot1/unknown")
    with pytest.raises(ValueError, match="per robot"):
        ODOM.of()


def test_messages_and_bags_take_type_and_qos_from_the_declarations(tmp_path) -> None:
    log = simulate(load_scenario("sensor_extension"), seed=1)
    messages = log_to_messages(log)
    for m in messages:
        assert type(m.message) is declaration(m.topic).msgtype, m.topic
    write_log_bag(log, tmp_path / "bag")
    info = inspect_bag(tmp_path / "bag")
    assert set(info.topics) == {m.topic for m in messages}
    for name, topic in info.topics.items():
        assert topic.offered_qos_profiles == [qos_to_dict(qos_of(name))], name
    assert info.topics[ODOM.of("robot1")].offered_qos_profiles == [qos_to_dict(SENSOR_DATA)]
    assert info.topics[FEATURES_TRUTH.name].offered_qos_profiles == [qos_to_dict(LATCHED)]


def test_with_robots_on_hosts_every_topic_is_recorded_once_the_mergers_at_the_base() -> None:
    """A robot's host records its own data; the base station what the merger takes and
    publishes (a robot's pose too: it is made there), and the global topics."""
    base = base_station_topics(ROBOTS)
    hosts = [name for robot in ROBOTS for name in robot_host_topics(robot)]
    assert sorted(base + hosts) == sorted(recorded_topics(ROBOTS))
    assert {POSE.of(r) for r in ROBOTS} | {DIAGNOSTICS.name} <= set(base)
    assert ODOM.of("robot1") in robot_host_topics("robot1")
