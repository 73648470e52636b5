"""Signatures of the merger's inputs (csam_ros/ros/signing.py): the same for a message and the
message as it arrives, another for any change or another key; a team key file that cannot be
used is refused naming it."""

from __future__ import annotations

import math

import pytest
from csam_msgs.msg import LocalMapUpdate, RendezvousPoses
from merger_harness import copied, run_messages
from rclpy.serialization import deserialize_message, serialize_message

from csam_ros.ros.signing import TeamKeyError, read_team_key, signature

KEY = b"k" * 32


@pytest.fixture(scope="module")
def messages() -> list:
    run = run_messages()
    return [run.local_maps["robot1"], run.rendezvous["robot2"]]


def test_a_message_as_it_arrives_has_the_signature_it_was_sent_with(messages) -> None:
    for msg, kind in zip(messages, (LocalMapUpdate, RendezvousPoses), strict=True):
        arrived = deserialize_message(serialize_message(msg), kind)
        assert signature(KEY, arrived) == signature(KEY, msg)
        # the bytes CDR gives differ (its padding is not set): signing them would fail
        assert signature(KEY, deserialize_message(serialize_message(arrived), kind)) == (
            signature(KEY, msg)
        )


def test_any_change_or_another_key_gives_another_signature(messages) -> None:
    update, rendezvous = messages
    signed = signature(KEY, update)
    assert signature(b"j" + KEY[1:], update) != signed
    changed = copied(update)
    changed.sequence += 1
    assert signature(KEY, changed) != signed
    changed = copied(update)
    changed.poses = [math.nextafter(changed.poses[0], 1.0), *list(changed.poses)[1:]]
    assert signature(KEY, changed) != signed
    changed = copied(rendezvous)
    changed.measurements[0].observations[0].observed_robot = "robot9"
    assert signature(KEY, changed) != signature(KEY, rendezvous)


def test_a_team_key_file_is_read_or_refused_naming_it(tmp_path) -> None:
    path = tmp_path / "key"
    path.write_bytes(KEY + b"\n")
    assert read_team_key(path) == KEY
    path.write_bytes(b"short\n")
    with pytest.raises(TeamKeyError, match=f"{path}: 5 bytes"):
        read_team_key(path)
    with pytest.raises(TeamKeyError, match="none"):
        read_team_key(tmp_path / "none")
