"""recorder: record topics to a rosbag2 bag (metadata.yaml + MCAP), like ``ros2 bag record``.

    recorder -o DIR --topics /robot1/odom /robot1/features
    recorder -o DIR --all [--exclude REGEX]

Topics are found by polling the ROS graph, so topics that appear later are picked up. Each is
subscribed raw (serialized CDR bytes, no deserialization) with a QoS compatible with every
publisher seen at that time: reliable and transient local are kept when all publishers offer
them, and the publishers' offered profiles are stored in metadata.yaml as rosbag2 does.

Log time is the recorder node's clock at reception: wall time by default; with
``--ros-args -p use_sim_time:=true`` it is the /clock time at reception (messages arriving
before the first /clock are held back and stamped with it). Header stamps are not used.

SIGINT or SIGTERM finishes the bag. Chunks are written at least every ``--flush-period``
seconds, with metadata.yaml refreshed each time, so a recorder killed by SIGKILL leaves a bag
that reads up to its last written chunk.
"""

from __future__ import annotations

import argparse
import re
import sys
from collections.abc import Sequence
from functools import partial
from pathlib import Path

from rclpy.clock import Clock, ClockType
from rclpy.event_handler import (
    QoSMessageLostInfo,
    QoSRequestedIncompatibleQoSInfo,
    SubscriptionEventCallbacks,
)
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions
from rclpy.subscription import Subscription
from rclpy.utilities import remove_ros_args

from csam_ros.bag import BagError, BagWriter, message_class, subscription_qos
from csam_ros.bag.types import UnknownMessageTypeError
from csam_ros.nodes.common import (
    make_executor,
    run_rclpy,
    spin_while_up,
    stop_on_signals,
    watch_parameters,
)

MAX_HELD_BACK = 100_000  # messages kept while waiting for the first /clock under sim time


class RecorderNode(Node):
    """Subscribes to the wanted topics as they appear and writes every message to a bag."""

    def __init__(
        self,
        writer: BagWriter,
        topics: Sequence[str] | None,
        exclude: str | None = None,
        poll_period_s: float = 0.1,
        flush_period_s: float = 1.0,
    ) -> None:
        super().__init__("recorder")
        self.writer = writer
        self._wanted = (
            None if topics is None else {self.resolve_topic_name(topic) for topic in topics}
        )
        self._exclude = re.compile(exclude) if exclude else None
        self._recorded: dict[str, Subscription] = {}
        self._ignored: set[str] = set()
        self._held_back: list[tuple[str, bytes]] = []
        self.received = 0
        self.lost = 0
        self.held_back_dropped = 0
        self._discover()
        steady = Clock(clock_type=ClockType.STEADY_TIME)  # runs under sim time before /clock
        self.create_timer(poll_period_s, self._discover, clock=steady)
        self.create_timer(flush_period_s, self.writer.flush, clock=steady)
        what = "every topic" if self._wanted is None else ", ".join(sorted(self._wanted))
        self.get_logger().info(f"recording {what} to {writer.path}")
        watch_parameters(self)  # its options are command-line arguments: none is set live

    def _wants(self, topic: str) -> bool:
        if self._wanted is not None:
            return topic in self._wanted
        hidden = any(part.startswith("_") for part in topic.split("/"))
        return not hidden and not (self._exclude and self._exclude.search(topic))

    def _discover(self) -> None:
        """Subscribe to every wanted topic that now has a publisher."""
        for topic, types in self.get_topic_names_and_types():
            if topic in self._recorded or topic in self._ignored or not self._wants(topic):
                continue
            publishers = self.get_publishers_info_by_topic(topic)
            if not publishers:
                continue
            if len(types) > 1:
                self.get_logger().warning(f"{topic} has several types {types}; using {types[0]}")
            self._subscribe(topic, types[0], [info.qos_profile for info in publishers])

    def _subscribe(self, topic: str, msgtype: str, offered: list) -> None:
        try:
            cls = message_class(msgtype)
            self.writer.add_topic(topic, msgtype, offered)
        except (UnknownMessageTypeError, ValueError) as error:
            self.get_logger().error(f"not recording {topic}: {error}")
            self._ignored.add(topic)
            return
        events = SubscriptionEventCallbacks(
            message_lost=partial(self._on_lost, topic),
            incompatible_qos=partial(self._on_incompatible, topic),
        )
        self._recorded[topic] = self.create_subscription(
            cls,
            topic,
            partial(self._on_message, topic),
            subscription_qos(offered),
            event_callbacks=events,
            raw=True,
        )
        self.get_logger().info(f"subscribed to {topic} [{msgtype}]")

    def _on_message(self, topic: str, data: bytes) -> None:
        self.received += 1
        stamp = self.get_clock().now().nanoseconds
        if stamp == 0:  # sim time before the first /clock
            if len(self._held_back) < MAX_HELD_BACK:
                self._held_back.append((topic, data))
            else:
                self.held_back_dropped += 1
            return
        for held_topic, held_data in self._held_back:
            self.writer.write(held_topic, stamp, held_data)
        self._held_back.clear()
        self.writer.write(topic, stamp, data)

    def _on_lost(self, topic: str, info: QoSMessageLostInfo) -> None:
        self.lost += info.total_count_change
        self.get_logger().warning(f"lost {info.total_count_change} message(s) on {topic}")

    def _on_incompatible(self, topic: str, info: QoSRequestedIncompatibleQoSInfo) -> None:
        self.get_logger().warning(
            f"a publisher of {topic} offers a QoS incompatible with the recording subscription "
            f"(policy {info.last_policy_kind}); its messages are not recorded"
        )

    def finish(self) -> None:
        """Close the bag and log what was recorded and dropped."""
        dropped = len(self._held_back) + self.held_back_dropped
        self._held_back.clear()
        self.writer.close()
        summary = (
            f"bag {self.writer.path}: {self.writer.message_count} of {self.received} received "
            f"messages written on "
            f"{len(self.writer.topics)} topics; {self.lost} lost by the middleware, {dropped} "
            "dropped waiting for /clock"
        )
        self.get_logger().info(summary)


def parse_arguments(argv: Sequence[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="recorder",
        description="Record topics to a rosbag2 bag directory (metadata.yaml + MCAP).",
        epilog="ROS arguments go after --ros-args, e.g. --ros-args -p use_sim_time:=true",
    )
    parser.add_argument("-o", "--output", required=True, type=Path, help="new bag directory")
    which = parser.add_mutually_exclusive_group(required=True)
    which.add_argument("--topics", nargs="+", metavar="TOPIC", help="topics to record")
    which.add_argument("-a", "--all", action="store_true", help="record every topic")
    parser.add_argument("--exclude", metavar="REGEX", help="with --all: topics not to record")
    parser.add_argument(
        "--flush-period", type=float, default=1.0, metavar="S", help="write a chunk every S s"
    )
    parser.add_argument(
        "--poll-period", type=float, default=0.1, metavar="S", help="look for topics every S s"
    )
    options = parser.parse_args(argv)
    if options.flush_period <= 0 or options.poll_period <= 0:
        parser.error("--flush-period and --poll-period must be positive")
    if options.exclude is not None:
        try:
            re.compile(options.exclude)
        except re.error as error:
            parser.error(f"--exclude {options.exclude!r} is not a regular expression: {error}")
    return options


def main(args: Sequence[str] | None = None) -> int:
    argv = list(sys.argv if args is None else args)
    options = parse_arguments(remove_ros_args(argv)[1:])
    try:
        writer = BagWriter(options.output, flush_period_s=options.flush_period)
    except BagError as error:
        print(f"recorder: {error}", file=sys.stderr)
        return 1
    stop = stop_on_signals()

    def record(node: RecorderNode) -> int:
        spin_while_up(node, make_executor(), stop)
        return 0

    def close(node: RecorderNode | None) -> None:
        if node is not None:
            node.finish()
        else:
            writer.close()

    return run_rclpy(
        lambda: RecorderNode(
            writer,
            options.topics,
            options.exclude,
            poll_period_s=options.poll_period,
            flush_period_s=options.flush_period,
        ),
        record,
        args=argv,
        close=close,
        signal_handler_options=SignalHandlerOptions.NO,
    )


if __name__ == "__main__":
    sys.exit(main())
