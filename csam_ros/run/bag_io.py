"""Measurement logs to bags: what the importers write, with no DDS involved."""

from __future__ import annotations

from pathlib import Path

from csam_ros.bag import BagWriter
from csam_ros.bag.types import msgtype_of
from csam_ros.core.model.log import MultiRobotLog
from csam_ros.ros.conversions import log_to_messages
from csam_ros.ros.topics import qos_of


def write_log_bag(log: MultiRobotLog, path: Path) -> int:
    """Write every robot's measurements (and the ground truth) as a new bag; message count."""
    messages = log_to_messages(log)
    with BagWriter(path) as bag:
        for m in messages:
            if m.topic not in bag.topics:
                bag.add_topic(m.topic, msgtype_of(m.message), qos_of(m.topic))
            bag.write(m.topic, m.stamp_ns, m.message)
    return len(messages)
