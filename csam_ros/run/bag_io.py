"""Measurement logs to bags: what the importers write, with no DDS involved."""

from __future__ import annotations

from pathlib import Path

from csam_ros.bag import BagWriter
from csam_ros.bag.types import msgtype_of
from csam_ros.core.log import MultiRobotLog
from csam_ros.nodes.common import LATCHED, RELIABLE, SENSOR_DATA
from csam_ros.ros.conversions import FEATURES_TRUTH_TOPIC, log_to_messages


def topic_qos(topic: str):
    """The QoS a topic is offered with in a live run (docs/ARCHITECTURE.md)."""
    if topic == FEATURES_TRUTH_TOPIC:
        return LATCHED
    if topic.endswith(("/odom", "/ground_truth")):
        return SENSOR_DATA
    return RELIABLE


def write_log_bag(log: MultiRobotLog, path: Path) -> int:
    """Write every robot's measurements (and the ground truth) as a new bag; message count."""
    messages = log_to_messages(log)
    with BagWriter(path) as bag:
        for m in messages:
            if m.topic not in bag.topics:
                bag.add_topic(m.topic, msgtype_of(m.message), topic_qos(m.topic))
            bag.write(m.topic, m.stamp_ns, m.message)
    return len(messages)
