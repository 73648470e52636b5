"""csam_msgs over DDS: every custom message between two nodes of one process, and one message
between two processes, each compared field by field."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[2]

# Builds the message both in this test and in the publishing subprocess.
BUILD_RENDEZVOUS_POSES = textwrap.dedent(
    """
    from builtin_interfaces.msg import Time
    from geometry_msgs.msg import Pose2D
    from csam_msgs.msg import (RendezvousObservation, RendezvousObservations,
                               RendezvousPoses)

    def build():
        msg = RendezvousPoses(robot="robot2", pose_indices=[4, 9])
        msg.header.frame_id = "robot2/map"
        msg.header.stamp = Time(sec=12, nanosec=345)
        msg.stamps = [Time(sec=3, nanosec=7), Time(sec=8, nanosec=1)]
        msg.poses = [Pose2D(x=1.5, y=-2.25, theta=0.125), Pose2D(x=-3.0, y=4.5, theta=-3.0)]
        observation = RendezvousObservations(observations=[RendezvousObservation(
            observed_robot="robot1", range=2.5, bearing=-0.75, sigma_range=0.1,
            sigma_bearing=0.02)])
        observation.header.stamp = Time(sec=8, nanosec=1)
        observation.header.frame_id = "robot2/base_link"
        msg.measurements = [observation]
        return msg
    """
)

PUBLISHER_SCRIPT = BUILD_RENDEZVOUS_POSES + textwrap.dedent(
    """
    import time
    import rclpy
    from rclpy.duration import Duration

    rclpy.init()
    node = rclpy.create_node("rendezvous_publisher")
    publisher = node.create_publisher(RendezvousPoses, "/robot2/rendezvous_poses", 10)
    deadline = time.monotonic() + 20
    while publisher.get_subscription_count() == 0 and time.monotonic() < deadline:
        time.sleep(0.02)
    publisher.publish(build())
    acked = publisher.wait_for_all_acked(Duration(seconds=10))
    print("acked" if acked else "not acked", flush=True)
    node.destroy_node()
    rclpy.shutdown()
    """
)


def test_sample_messages_cover_every_custom_type(
    sample_messages: dict[str, Any], no_default_leaf: Any
) -> None:
    installed = sorted(
        f"csam_msgs/msg/{p.stem}" for p in (Path(sys.prefix) / "share/csam_msgs/msg").glob("*.msg")
    )
    assert sorted(sample_messages) == installed, "msg_defs/msg and the installed csam_msgs differ"
    for msgtype, message in sample_messages.items():
        no_default_leaf(message, msgtype)


def test_every_custom_message_between_two_nodes(
    ros_context: Any, sample_messages: dict[str, Any], fields_equal: Any, spin: Any
) -> None:
    import rclpy
    from rclpy.executors import SingleThreadedExecutor

    sender = rclpy.create_node("sender", context=ros_context)
    receiver = rclpy.create_node("receiver", context=ros_context)
    executor = SingleThreadedExecutor(context=ros_context)
    executor.add_node(sender)
    executor.add_node(receiver)
    received: dict[str, Any] = {}
    publishers = {}
    for msgtype, message in sample_messages.items():
        topic = f"/sample/{msgtype.split('/')[-1]}"
        publishers[msgtype] = sender.create_publisher(type(message), topic, 10)
        receiver.create_subscription(
            type(message), topic, lambda m, key=msgtype: received.setdefault(key, m), 10
        )
    assert spin(
        executor,
        lambda: all(p.get_subscription_count() > 0 for p in publishers.values()),
    ), "the publishers did not match their subscriptions"
    for msgtype, message in sample_messages.items():
        publishers[msgtype].publish(message)
    assert spin(executor, lambda: len(received) == len(sample_messages)), (
        f"missing: {sorted(set(sample_messages) - set(received))}"
    )
    for msgtype, message in sample_messages.items():
        assert received[msgtype] is not message
        fields_equal(message, received[msgtype], msgtype)
        assert received[msgtype] == message
    executor.shutdown()
    sender.destroy_node()
    receiver.destroy_node()


def test_custom_message_between_two_processes(
    ros_context: Any, fields_equal: Any, spin: Any, tmp_path: Path
) -> None:
    import rclpy
    from rclpy.executors import SingleThreadedExecutor

    namespace: dict[str, Any] = {}
    exec(BUILD_RENDEZVOUS_POSES, namespace)
    expected = namespace["build"]()
    node = rclpy.create_node("rendezvous_subscriber", context=ros_context)
    executor = SingleThreadedExecutor(context=ros_context)
    executor.add_node(node)
    received: list[Any] = []
    node.create_subscription(type(expected), "/robot2/rendezvous_poses", received.append, 10)
    publisher = subprocess.Popen(
        [sys.executable, "-c", PUBLISHER_SCRIPT],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        cwd=tmp_path,
    )
    try:
        assert spin(executor, lambda: len(received) == 1, timeout_s=30)
        output = publisher.communicate(timeout=30)[0].decode()
    finally:
        publisher.kill()
        publisher.wait()
    assert "acked" in output.split(), output
    fields_equal(expected, received[0], "RendezvousPoses")
    executor.shutdown()
    node.destroy_node()
