"""The recorder executable against real publishers over DDS: what it records (every field,
read back by rosbags and by mcap + mcap_ros2), offered QoS, topics appearing later, SIGINT /
SIGTERM / SIGKILL, and bad output paths."""

from __future__ import annotations

import signal
import time
from pathlib import Path
from typing import Any

import pytest
import yaml
from waiting import wait_until

from csam_ros.bag import MessageTypes, inspect_bag, read_bag

LATCHED = "/rec/latched_map"


def _node(context: Any, name: str) -> Any:
    import rclpy

    return rclpy.create_node(name, context=context)


def test_records_every_field_and_offered_qos(
    ros_context: Any,
    nodes: Any,
    sample_messages: dict[str, Any],
    fields_equal: Any,
    tmp_path: Path,
) -> None:
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory
    from rclpy.duration import Duration
    from rclpy.qos import DurabilityPolicy, QoSProfile
    from rosbags.rosbag2 import Reader

    node = _node(ros_context, "rec_source")
    latched_message = sample_messages["csam_msgs/msg/LocalMap"]
    latched = node.create_publisher(
        type(latched_message),
        LATCHED,
        QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL),
    )
    latched.publish(latched_message)  # before the recorder exists: only durability brings it

    bag = tmp_path / "bag"
    start_ns = time.time_ns()
    recorder = nodes.start(
        "recorder", "-o", bag, "--all", "--exclude", "^/(rosout|parameter_events)$"
    )
    assert wait_until(lambda: (bag / "metadata.yaml").exists())
    # topics that appear after the recorder started
    publishers = {
        msgtype: node.create_publisher(type(m), f"/rec/{msgtype.split('/')[-1]}", 10)
        for msgtype, m in sample_messages.items()
    }
    everything = [*publishers.values(), latched]
    assert wait_until(lambda: all(p.get_subscription_count() > 0 for p in everything)), (
        nodes.output(recorder) if recorder.poll() is not None else "recorder did not subscribe"
    )
    for msgtype, publisher in publishers.items():
        publisher.publish(sample_messages[msgtype])
    for publisher in everything:
        assert publisher.wait_for_all_acked(Duration(seconds=10))
    assert nodes.stop(recorder, signal.SIGINT) == 0, nodes.output(recorder)
    end_ns = time.time_ns()

    info = inspect_bag(bag)
    assert info.truncated_files == [], "SIGINT must finish the MCAP file"
    expected = {f"/rec/{t.split('/')[-1]}": (t, sample_messages[t]) for t in sample_messages}
    expected[LATCHED] = ("csam_msgs/msg/LocalMap", latched_message)
    assert {name: t.msgtype for name, t in info.topics.items()} == {
        name: msgtype for name, (msgtype, _) in expected.items()
    }
    assert all(topic.message_count == 1 for topic in info.topics.values())
    assert all(start_ns <= m.log_time_ns <= end_ns for m in read_bag(bag)), "log time: wall"

    metadata = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    offered = {
        t["topic_metadata"]["name"]: t["topic_metadata"]["offered_qos_profiles"]
        for t in metadata["topics_with_message_count"]
    }
    assert [q["durability"] for q in offered[LATCHED]] == ["transient_local"]
    assert [q["durability"] for q in offered["/rec/LocalMap"]] == ["volatile"]

    typestore = MessageTypes().register_custom_types()
    with Reader(bag) as reader:
        rows = list(reader.messages())
    assert len(rows) == len(expected)
    for connection, _, raw in rows:
        msgtype, message = expected[connection.topic]
        fields_equal(message, typestore.deserialize_cdr(raw, msgtype), connection.topic)

    with info.files[0].open("rb") as stream:
        decoded = list(
            make_reader(stream, decoder_factories=[DecoderFactory()]).iter_decoded_messages()
        )
    assert len(decoded) == len(expected)
    for _, channel, _, message in decoded:
        fields_equal(expected[channel.topic][1], message, channel.topic)
    node.destroy_node()


def test_sigterm_finishes_and_sigkill_leaves_a_readable_bag(
    ros_context: Any, nodes: Any, tmp_path: Path
) -> None:
    from csam_msgs.msg import FeatureObservation, FeatureObservations
    from rclpy.serialization import deserialize_message

    node = _node(ros_context, "counter_source")
    publisher = node.create_publisher(FeatureObservations, "/rec/counter", 100)
    bags = {"terminated": tmp_path / "terminated", "killed": tmp_path / "killed"}
    recorders = {
        name: nodes.start(
            "recorder", "-o", bag, "--topics", "/rec/counter", "--flush-period", "0.2"
        )
        for name, bag in bags.items()
    }
    assert wait_until(lambda: publisher.get_subscription_count() == 2)
    for label in range(60):
        publisher.publish(FeatureObservations(observations=[FeatureObservation(label=label)]))
        time.sleep(0.02)
    time.sleep(0.5)  # a flush period or two: some chunks are on disk
    for label in range(60, 70):  # and these are still pending in the killed recorder
        publisher.publish(FeatureObservations(observations=[FeatureObservation(label=label)]))
    assert nodes.stop(recorders["killed"], signal.SIGKILL) == -signal.SIGKILL

    def flushed(bag: Path) -> int:  # what metadata.yaml counts: refreshed at every flush
        text = (bag / "metadata.yaml").read_text()
        return yaml.safe_load(text)["rosbag2_bagfile_information"]["message_count"]

    assert wait_until(lambda: flushed(bags["terminated"]) == 70)
    assert nodes.stop(recorders["terminated"], signal.SIGTERM) == 0

    def labels(bag: Path) -> list[int]:
        return [
            deserialize_message(m.data, FeatureObservations).observations[0].label
            for m in read_bag(bag)
        ]

    assert inspect_bag(bags["terminated"]).truncated_files == []
    assert labels(bags["terminated"]) == list(range(70))

    killed = inspect_bag(bags["killed"])
    assert killed.truncated_files == [bags["killed"] / "killed_0.mcap"]
    recovered = labels(bags["killed"])
    assert 0 < len(recovered) <= 70  # (all 70 only if a flush beat the SIGKILL)
    assert recovered == list(range(len(recovered))), "the messages of the complete chunks"
    metadata = yaml.safe_load((bags["killed"] / "metadata.yaml").read_text())
    assert 0 < metadata["rosbag2_bagfile_information"]["message_count"] <= len(recovered)
    node.destroy_node()


@pytest.mark.parametrize("case", ["existing_directory", "existing_file", "under_a_file", "proc"])
def test_bad_output_path_is_a_one_line_error(nodes: Any, tmp_path: Path, case: str) -> None:
    existing = tmp_path / "old_bag"
    existing.mkdir()
    (existing / "metadata.yaml").write_text("keep me")
    plain_file = tmp_path / "plain"
    plain_file.write_text("keep me too")
    output = {
        "existing_directory": existing,
        "existing_file": plain_file,
        "under_a_file": plain_file / "bag",
        "proc": Path("/proc/csam_ros_bag"),
    }[case]
    recorder = nodes.start("recorder", "-o", output, "--all")
    assert recorder.wait(timeout=30) != 0
    stderr = nodes.stderr(recorder)
    assert "Traceback" not in stderr
    assert len(stderr.strip().splitlines()) == 1, stderr
    assert stderr.startswith("recorder: ") and str(output) in stderr
    assert sorted(p.name for p in existing.iterdir()) == ["metadata.yaml"]
    assert (existing / "metadata.yaml").read_text() == "keep me"
    assert plain_file.read_text() == "keep me too"


def test_log_time_is_the_clock_time_under_sim_time(
    ros_context: Any, nodes: Any, tmp_path: Path
) -> None:
    from csam_msgs.msg import FeatureObservation, FeatureObservations
    from rclpy.duration import Duration
    from rclpy.serialization import deserialize_message
    from rosgraph_msgs.msg import Clock

    node = _node(ros_context, "sim_source")
    clock = node.create_publisher(Clock, "/clock", 10)
    features = node.create_publisher(FeatureObservations, "/sim/features", 10)
    bag = tmp_path / "bag"
    recorder = nodes.start(
        "recorder", "-o", bag, "--topics", "/sim/features",
        "--ros-args", "-p", "use_sim_time:=true",
    )  # fmt: skip
    assert wait_until(lambda: clock.get_subscription_count() and features.get_subscription_count())

    def send(label: int | None = None, clock_s: int | None = None) -> None:
        if clock_s is not None:
            message = Clock()
            message.clock.sec = clock_s
            clock.publish(message)
        if label is not None:
            features.publish(FeatureObservations(observations=[FeatureObservation(label=label)]))
        time.sleep(0.2)

    send(label=0)  # before any /clock: held back until the first clock time
    send(clock_s=42)
    send(label=1)
    send(clock_s=50)
    send(label=2)
    assert features.wait_for_all_acked(Duration(seconds=10))
    assert nodes.stop(recorder, signal.SIGINT) == 0, nodes.output(recorder)
    recorded = [
        (deserialize_message(m.data, FeatureObservations).observations[0].label, m.log_time_ns)
        for m in read_bag(bag)
    ]
    second = 1_000_000_000
    assert recorded == [(0, 42 * second), (1, 42 * second), (2, 50 * second)]
    node.destroy_node()
