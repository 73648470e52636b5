"""player: publish a recorded bag again, like ``ros2 bag play``, with /clock.

    player BAG [--rate R] [--topics T ...] [--loop] [--wait-for-subscribers [T ...]]
           [--min-subscribers N]

Messages go out raw (the recorded CDR bytes) with their recorded log-time spacing divided by
``--rate`` (2 = twice as fast, 0 = as fast as possible). /clock (rosgraph_msgs/Clock) carries
the recorded log time in steps of ``--clock-period`` seconds, as ``ros2 bag play --clock`` does
at a fixed rate: before a message logged at least that long after the last /clock, and every
``--clock-period`` seconds while waiting between messages (a message leads /clock by less
than a period of log time). Before each message instead, a bag of five
robots' odometry made hundreds of /clock messages a second, each one a callback in every node
under sim time. A /clock recorded in the bag is not replayed (``--no-clock`` replays it
instead). Each topic is published with the recorded QoS (reliability and durability, when all
recorded publishers agree; transient local with the recorded depth).

BAG is a bag directory or an .mcap file. A bag whose recorder was killed plays up to its last
complete chunk (with a warning); a bag without metadata.yaml plays from its .mcap files.

Like the simulator, the player stands in for the robots' drivers: for each played
``/<robot>/odom`` it publishes ``/tf`` ``<robot>/odom -> <robot>/base_link`` at the message's
stamp, from the message's pose, or where the message has none the dead reckoning of its twists
(``--no-odom-tf``: not, e.g. for a bag whose recorded /tf already holds them). The transforms
go out together, one /tf message with each /clock step (as a tf2 broadcaster sends a list):
five robots' odometry at 66 Hz made 330 /tf messages a second, each one a publish here and a
message for every /tf subscriber (the recorder among them).
"""

from __future__ import annotations

import argparse
import sys
import threading
import time
from collections.abc import Iterable, Sequence
from pathlib import Path

from geometry_msgs.msg import TransformStamped
from rclpy.duration import Duration
from rclpy.node import Node
from rclpy.publisher import Publisher
from rclpy.qos import ReliabilityPolicy
from rclpy.serialization import deserialize_message
from rclpy.signals import SignalHandlerOptions
from rclpy.utilities import remove_ros_args
from rosgraph_msgs.msg import Clock

from csam_ros.bag import BagError, BagInfo, BagMessage, inspect_bag, publisher_qos, read_bag
from csam_ros.bag.types import UnknownMessageTypeError, message_class
from csam_ros.nodes.common import run_rclpy, stop_on_signals, watch_parameters
from csam_ros.ros.conversions import OdometryTransforms
from csam_ros.ros.topics import CLOCK, ODOM, TF


class PlayerNode(Node):
    """Publishers for the played topics and /clock, and the timed playback loop."""

    def __init__(
        self,
        bag: BagInfo,
        topics: Sequence[str],
        publish_clock: bool = True,
        stop: threading.Event | None = None,
        odometry_tf: bool = True,
    ) -> None:
        super().__init__("player")
        self.bag = bag
        self.stop = stop or threading.Event()
        self.published = 0
        self.skipped_topics: list[str] = []
        self._topic_publishers: dict[str, Publisher] = {}
        self._odometry: dict[str, tuple[str, type]] = {}  # odometry topics: robot, type
        for topic in topics:
            info = bag.topics[topic]
            try:
                cls = message_class(info.msgtype)
            except UnknownMessageTypeError as error:
                self.get_logger().error(f"not playing {topic}: {error}")
                self.skipped_topics.append(topic)
                continue
            qos = publisher_qos(info.offered_qos_profiles)
            self._topic_publishers[topic] = self.create_publisher(cls, topic, qos)
            robot = ODOM.robot_of(topic)
            if odometry_tf and robot is not None and info.msgtype == ODOM.type_name:
                self._odometry[topic] = (robot, cls)
        self._odometry_transforms = OdometryTransforms()
        self._transforms: list[TransformStamped] = []  # for the next /tf message
        self._tf_publisher = (
            self.create_publisher(TF.msgtype, TF.name, TF.qos) if self._odometry else None
        )
        self._clock_publisher = (
            self.create_publisher(CLOCK.msgtype, CLOCK.name, CLOCK.qos) if publish_clock else None
        )
        self._last_clock = -1
        watch_parameters(self)  # its options are command-line arguments: none is set live

    @property
    def topics(self) -> list[str]:
        """Topics this player publishes (bag topics with an installed message type)."""
        return list(self._topic_publishers)

    def wait_for_subscribers(
        self, topics: Iterable[str], timeout_s: float, count: int = 1
    ) -> list[str]:
        """Wait until each of ``topics`` (played topics, /clock or /tf) has ``count`` matched
        subscriptions; returns those short of it when ``timeout_s`` ran out."""
        publishers = dict(self._topic_publishers)
        if self._clock_publisher is not None:
            publishers[CLOCK.name] = self._clock_publisher
        if self._tf_publisher is not None:
            publishers[TF.name] = self._tf_publisher
        waiting = [topic for topic in topics if topic in publishers]
        deadline = time.monotonic() + timeout_s
        while not self.stop.is_set():
            waiting = [t for t in waiting if publishers[t].get_subscription_count() < count]
            if not waiting or time.monotonic() >= deadline:
                break
            self.stop.wait(0.02)
        return waiting

    def _publish_clock(self, stamp_ns: int) -> None:
        """/clock at ``stamp_ns`` (once per stamp), and the odometry's transforms since the
        last one."""
        self._publish_transforms()
        if self._clock_publisher is None or stamp_ns == self._last_clock:
            return
        clock = Clock()
        clock.clock.sec, clock.clock.nanosec = divmod(stamp_ns, 1_000_000_000)
        self._clock_publisher.publish(clock)
        self._last_clock = stamp_ns

    def _publish_transforms(self) -> None:
        """The odometry's transforms held since the last /tf message, in one."""
        if self._transforms:
            assert self._tf_publisher is not None
            self._tf_publisher.publish(TF.msgtype(transforms=self._transforms))
            self._transforms = []

    def _sleep_until(
        self, due: float, start_wall: float, start_log_ns: int, rate: float, clock_period_s: float
    ) -> None:
        """Sleep until monotonic time ``due``, publishing the interpolated /clock."""
        while not self.stop.is_set():
            now = time.monotonic()
            if now >= due:
                return
            self.stop.wait(min(due - now, clock_period_s))
            if time.monotonic() < due and not self.stop.is_set():
                elapsed_ns = int((time.monotonic() - start_wall) * rate * 1e9)
                self._publish_clock(start_log_ns + elapsed_ns)

    def play(self, messages: Iterable[BagMessage], rate: float, clock_period_s: float) -> None:
        """Publish ``messages`` (in log-time order) with their spacing divided by ``rate``."""
        start_wall = time.monotonic()
        start_log_ns: int | None = None
        self._last_clock = -1  # each pass (--loop) starts the clock again
        for message in messages:
            publisher = self._topic_publishers.get(message.topic)
            if publisher is None:
                continue
            if start_log_ns is None:
                start_log_ns = message.log_time_ns
            if rate > 0:
                due = start_wall + (message.log_time_ns - start_log_ns) / 1e9 / rate
                self._sleep_until(due, start_wall, start_log_ns, rate, clock_period_s)
            if self.stop.is_set():
                return
            if message.log_time_ns - self._last_clock >= clock_period_s * 1e9:
                self._publish_clock(message.log_time_ns)
            publisher.publish(message.data)
            self.published += 1
            if message.topic in self._odometry:
                self._add_odometry_tf(message)
        self._publish_transforms()

    def _add_odometry_tf(self, message: BagMessage) -> None:
        """``odom -> base_link`` of one played odometry message, for the next /tf message
        (none for one without a usable pose or twist, or that does not decode)."""
        robot, cls = self._odometry[message.topic]
        try:
            odometry = deserialize_message(message.data, cls)
        except Exception as error:  # noqa: BLE001 - a damaged message is played, not turned
            self.get_logger().warning(f"no /tf of {message.topic}: {error}", once=True)
            return
        transform = self._odometry_transforms.transform(robot, odometry)
        if transform is not None:
            self._transforms.append(transform)

    def finish(self, linger_s: float) -> None:
        """Wait until reliable subscribers have acknowledged everything, then ``linger_s``
        more seconds (transient local late joiners), then log a summary; when stopped by a
        signal, only log."""
        publishers = dict(self._topic_publishers)
        if self._tf_publisher is not None:
            publishers[TF.name] = self._tf_publisher
        for topic, publisher in publishers.items():
            if (
                self.stop.is_set()
                or publisher.qos_profile.reliability != ReliabilityPolicy.RELIABLE
            ):
                continue
            if not publisher.wait_for_all_acked(Duration(seconds=5)):
                self.get_logger().warning(f"not every subscriber of {topic} acknowledged")
        self.stop.wait(linger_s)
        skipped = f"; skipped {', '.join(self.skipped_topics)}" if self.skipped_topics else ""
        self.get_logger().info(
            f"published {self.published} messages on {len(self._topic_publishers)} topics from "
            f"{self.bag.path}{skipped}"
        )


def parse_arguments(argv: Sequence[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="player",
        description="Publish a recorded rosbag2 (MCAP) bag with its recorded timing and /clock.",
        epilog="ROS arguments go after --ros-args.",
    )
    parser.add_argument("bag", type=Path, help="bag directory or .mcap file")
    parser.add_argument(
        "--rate", type=float, default=1.0, help="speed factor (0: as fast as possible)"
    )
    parser.add_argument("--topics", nargs="+", metavar="TOPIC", help="play only these topics")
    parser.add_argument("--loop", action="store_true", help="play again from the start forever")
    parser.add_argument(
        "--no-clock", action="store_true", help="do not publish /clock (replay a recorded one)"
    )
    parser.add_argument(
        "--no-odom-tf",
        action="store_true",
        help="do not publish /tf <robot>/odom -> <robot>/base_link of the played odometry",
    )
    parser.add_argument(
        "--clock-period",
        type=float,
        default=0.05,
        metavar="S",
        help="/clock period (s of log time)",
    )
    parser.add_argument(
        "--delay",
        type=float,
        default=0.5,
        metavar="S",
        help="wait S s (after any --wait-for-subscribers) for discovery to settle",
    )
    parser.add_argument(
        "--wait-for-subscribers",
        nargs="*",
        metavar="TOPIC",
        help="before playing, wait until these topics (none named: all) have a subscriber",
    )
    parser.add_argument(
        "--min-subscribers",
        type=int,
        default=1,
        metavar="N",
        help="subscribers each of those topics needs (e.g. 2: a recorder and a smoother)",
    )
    parser.add_argument(
        "--wait-timeout", type=float, default=10.0, metavar="S", help="longest wait for them"
    )
    parser.add_argument(
        "--linger", type=float, default=0.0, metavar="S", help="stay S s after the last message"
    )
    options = parser.parse_args(argv)
    if options.rate < 0:
        parser.error(f"--rate must be >= 0, got {options.rate}")
    if options.min_subscribers < 1:
        parser.error(f"--min-subscribers must be >= 1, got {options.min_subscribers}")
    for name in ("clock_period", "delay", "wait_timeout", "linger"):
        if getattr(options, name) < 0 or (name == "clock_period" and options.clock_period == 0):
            parser.error(f"--{name.replace('_', '-')} must be positive")
    return options


def _news(node: PlayerNode, bag: BagInfo, line: str) -> None:
    """Log a warning about the bag unless inspect_bag already reported it."""
    if line not in bag.warnings:
        node.get_logger().warning(line)


def select_topics(bag: BagInfo, requested: Sequence[str] | None, publish_clock: bool) -> list[str]:
    """The bag topics to play; BagError for a requested topic the bag lacks or no messages."""
    if requested is not None:
        missing = [topic for topic in requested if topic not in bag.topics]
        if missing:
            raise BagError(
                f"{bag.path} has no topic {', '.join(missing)} "
                f"(it has {', '.join(bag.topics) or 'none'})"
            )
        topics = list(dict.fromkeys(requested))
    else:
        topics = list(bag.topics)
    if publish_clock:
        topics = [topic for topic in topics if topic != CLOCK.name]
    if not any(bag.topics[topic].message_count for topic in topics):
        raise BagError(f"{bag.path} holds no messages to play")
    return topics


def main(args: Sequence[str] | None = None) -> int:
    argv = list(sys.argv if args is None else args)
    options = parse_arguments(remove_ros_args(argv)[1:])
    publish_clock = not options.no_clock
    try:
        bag = inspect_bag(options.bag)
        topics = select_topics(bag, options.topics, publish_clock)
        odometry_tf = not options.no_odom_tf and any(ODOM.robot_of(t) for t in topics)
        published = {*topics, CLOCK.name, *([TF.name] if odometry_tf else [])}
        unknown = set(options.wait_for_subscribers or ()) - published
        if unknown:
            raise BagError(f"--wait-for-subscribers names unplayed topic(s) {sorted(unknown)}")
    except BagError as error:
        print(f"player: {error}", file=sys.stderr)
        return 1
    stop = stop_on_signals()

    def play(node: PlayerNode) -> int:
        for warning in bag.warnings:
            node.get_logger().warning(warning)
        if not node.topics:
            node.get_logger().error("no topic of the bag can be played")
            return 1
        if options.wait_for_subscribers is not None:
            wanted = options.wait_for_subscribers or node.topics
            unmatched = node.wait_for_subscribers(
                wanted, options.wait_timeout, options.min_subscribers
            )
            if unmatched:
                node.get_logger().warning(
                    f"fewer than {options.min_subscribers} subscriber(s) on "
                    f"{', '.join(unmatched)}; playing"
                )
        # after the publisher sees a subscriber, the subscriber may not see the publisher yet;
        # a best-effort sample sent in that gap is lost, so let discovery settle both ways
        stop.wait(options.delay)
        while True:
            # what is cut or damaged was logged above from inspect_bag; log only news here
            messages = read_bag(
                bag.path, node.topics, on_damage=lambda line: _news(node, bag, line)
            )
            node.play(messages, options.rate, options.clock_period)
            if not options.loop or stop.is_set():
                break
        node.finish(options.linger)
        return 0

    return run_rclpy(
        lambda: PlayerNode(bag, topics, publish_clock, stop, not options.no_odom_tf),
        play,
        args=argv,
        signal_handler_options=SignalHandlerOptions.NO,
    )


if __name__ == "__main__":
    sys.exit(main())
