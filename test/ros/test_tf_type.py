"""/tf's type, built from tf2_msg_defs/ where the wheels have no tf2_msgs, is the one of a
ROS 2 Jazzy install: its type hashes equal those of rosbags' Jazzy type store."""

from __future__ import annotations

import pytest
from rosbags.typesys import Stores, get_typestore

from csam_ros.bag.types import MessageTypes


@pytest.mark.parametrize("name", ["tf2_msgs/msg/TFMessage", "tf2_msgs/msg/TF2Error"])
def test_tf2_msgs_hash_is_jazzys(name: str) -> None:
    jazzy = get_typestore(Stores.ROS2_JAZZY)
    assert MessageTypes().definition(name).type_hash == jazzy.hash_rihs01(name)
