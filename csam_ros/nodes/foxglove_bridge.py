"""foxglove_bridge: a run's topics served over the Foxglove WebSocket protocol, to watch a run
in Foxglove (web or desktop) without a ROS desktop.

    foxglove_bridge --ros-args -p port:=8765 -p robots:='["robot1","robot2"]'

Serves every topic declared in ``csam_ros/ros/topics.py`` but the smoothers' sensor inputs and
the local maps' update stream (changes that show nothing alone): the joined and provisional
maps, markers, status, ``/tf``, ``/clock``, the simulator's truth, and each robot's path, local
map and rendezvous poses. The robots are those of ``robots``, at once, and any other whose
topics appear on the ROS graph (looked for every second). Each topic is subscribed raw and
every message goes out exactly as received (CDR, not decoded) on a channel whose schema is the
type's ``ros2msg`` definition, the text the bag writer stores in MCAP files
(:mod:`csam_ros.bag.types`). A latched (transient local) topic keeps its latest message and
sends it again on its channel when a client subscribes, so a client that connects late sees
the joined map (clients already subscribed get it once more). Under ``use_sim_time`` the
server announces the time capability and sends each ``/clock``; a message's log time is the
node's clock when it arrived.

The server binds ``host`` (127.0.0.1: this machine only) and ``port`` (0: any free port; the
URL to open is logged either way) and speaks the subprotocol ``foxglove.sdk.v1`` (the
foxglove.websocket.v1 protocol under the name the Foxglove SDK gives it). Bad input never
stops it: the server answers a malformed or unknown client request with an error status, and
the node logs it and counts it (``drops``: ``client_request``); a topic on the graph with a
declared name and another type is logged once, counted (``wrong_type``) and not served.
"""

from __future__ import annotations

import logging
import sys
import threading
from dataclasses import dataclass, field
from functools import partial
from typing import Any

import foxglove
from foxglove.websocket import Capability, ChannelView, Client
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.exceptions import InvalidParameterValueException
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy
from rclpy.serialization import deserialize_message

from csam_ros.bag.types import MessageTypes
from csam_ros.core.exchange.validation import DropCounter
from csam_ros.nodes.common import declare, guarded, run_node, steady_clock, watch_parameters
from csam_ros.ros.topics import CLOCK, LOCAL_MAP_UPDATES, TOPICS, Topic, parse

NODE_NAME = "foxglove_bridge"
DEFAULT_PORT = 8765  # the port Foxglove's "Open connection" suggests
DISCOVERY_PERIOD_S = 1.0  # s between looks at the ROS graph for other robots' topics
SCHEMA_ENCODING = "ros2msg"
MESSAGE_ENCODING = "cdr"
CLIENT_REQUEST = "client_request"  # a client request the server refused (malformed, unknown)
WRONG_TYPE = "wrong_type"  # a topic with a declared name and another type
# the SDK's logger of each client connection: its warnings and errors are bad client requests
CLIENT_LOGGER = "foxglove.websocket.connected_client"


def served(topic: Topic) -> bool:
    """Whether the bridge serves ``topic``: all but the smoothers' sensor inputs and the local
    maps' update stream."""
    return not topic.sensor and topic is not LOCAL_MAP_UPDATES


SERVED: tuple[Topic, ...] = tuple(t for t in TOPICS if served(t))


def is_latched(topic: Topic) -> bool:
    """Whether ``topic``'s publishers keep their latest message for late subscribers."""
    return topic.qos.durability == DurabilityPolicy.TRANSIENT_LOCAL


class ServeError(RuntimeError):
    """The WebSocket server could not start (the port is taken, the host does not resolve)."""


@dataclass
class BridgedTopic:
    """One ROS topic served on one Foxglove channel."""

    name: str
    topic: Topic = field(repr=False)
    channel: foxglove.Channel = field(repr=False)
    # a latched topic's last message and its log time
    latest: tuple[bytes, int] | None = field(default=None, repr=False)
    received: int = 0

    @property
    def latched(self) -> bool:
        return is_latched(self.topic)


class _SdkLog(logging.Handler):
    """The SDK's log records (Python logging) into the node's ROS log, counting the warnings
    and errors of client connections (bad requests) in ``on_client_error``."""

    def __init__(self, node: Node, on_client_error: Any) -> None:
        super().__init__(logging.INFO)
        self.node = node
        self.on_client_error = on_client_error

    def emit(self, record: logging.LogRecord) -> None:
        text = f"{record.name}: {record.getMessage()}"
        logger = self.node.get_logger()
        if record.levelno >= logging.ERROR:
            logger.error(text)
        elif record.levelno >= logging.WARNING:
            logger.warning(text)
        else:
            logger.info(text)
        if record.levelno >= logging.WARNING and record.name.startswith(CLIENT_LOGGER):
            self.on_client_error()


@dataclass
class _Listener:
    """The server's callbacks (on its own thread): ``on_subscribe_to(channel id)`` when a
    client subscribes to a channel."""

    on_subscribe_to: Any

    def on_subscribe(self, client: Client, channel: ChannelView) -> None:
        self.on_subscribe_to(channel.id)

    def on_unsubscribe(self, client: Client, channel: ChannelView) -> None:
        return None


def _robot_names(node: Node) -> tuple[str, ...]:
    """The ``robots`` parameter: a list of names, or empty (any type, as ``[]`` reads as a byte
    array); ValueError for anything else."""
    value = node.declare_parameter(
        "robots",
        None,
        ParameterDescriptor(
            description="robots whose topics are served from the start (others are served "
            "as their topics appear on the graph)",
            dynamic_typing=True,
        ),
    ).value
    if value is None or (isinstance(value, list | tuple | bytes) and len(value) == 0):
        return ()
    if not (isinstance(value, list | tuple) and all(isinstance(r, str) and r for r in value)):
        raise ValueError(f"parameter robots: expected a list of robot names, got {value!r}")
    return tuple(value)


class FoxgloveBridge(Node):
    """The bridge (see the module docstring). Every message goes out from the executor's
    thread; the server's thread only marks latched channels to send again."""

    def __init__(self, **node_options: Any) -> None:
        super().__init__(NODE_NAME, **node_options)
        host = declare(
            self,
            "host",
            "127.0.0.1",
            "address the WebSocket server binds: 127.0.0.1 this machine only, 0.0.0.0 every "
            "interface",
        )
        port = declare(
            self, "port", DEFAULT_PORT, "the WebSocket server's port (0: any free port)", 0, 65535
        )
        robots = _robot_names(self)
        self.drops = DropCounter()
        watch_parameters(self, drops=self.drops)  # none is set live; before the server's thread
        self._drops_lock = threading.Lock()
        self.sim_time: bool = self.get_parameter("use_sim_time").value
        self.types = MessageTypes()
        self.bridged: dict[str, BridgedTopic] = {}  # by topic name
        self._by_channel: dict[int, BridgedTopic] = {}
        self._ignored: set[str] = set()
        self._resend: set[int] = set()  # latched channels a client subscribed to, to send again
        self._resend_lock = threading.Lock()
        self._resend_wake = self.create_guard_condition(
            guarded(self, self.drops, self.send_latest_again)
        )
        self._sdk_log = _SdkLog(self, partial(self._count, CLIENT_REQUEST))
        sdk_logger = logging.getLogger("foxglove")
        sdk_logger.addHandler(self._sdk_log)
        sdk_logger.setLevel(logging.INFO)
        sdk_logger.propagate = False
        self.foxglove_context = foxglove.Context()  # this node's channels and server only
        self.listener = _Listener(self._on_client_subscribe)
        try:
            self.server = foxglove.start_server(
                name="csam_ros",
                host=host,
                port=port,
                capabilities=[Capability.Time] if self.sim_time else [],
                server_listener=self.listener,
                context=self.foxglove_context,
            )
        except RuntimeError as error:
            sdk_logger.removeHandler(self._sdk_log)
            raise ServeError(f"cannot serve on {host}:{port}: {error}") from None
        self.url = f"ws://{host}:{self.server.port}"
        for topic in SERVED:
            if topic.per_robot:
                for robot in robots:
                    self._bridge(topic.of(robot), topic)
            else:
                self._bridge(topic.name, topic)
        self.create_timer(
            DISCOVERY_PERIOD_S, guarded(self, self.drops, self.discover), clock=steady_clock()
        )
        self.get_logger().info(f"serving {len(self.bridged)} topics; open {self.url} in Foxglove")

    @property
    def port(self) -> int:
        """The port the server listens on (the one taken when ``port`` was 0)."""
        return self.server.port

    def _count(self, reason: str) -> None:
        with self._drops_lock:
            self.drops.add(reason)

    def _bridge(self, name: str, topic: Topic) -> None:
        """Serve ``name`` (an instance of ``topic``) on a channel of its own."""
        definition = self.types.definition(topic.type_name)
        schema = foxglove.Schema(
            name=definition.msgtype, encoding=SCHEMA_ENCODING, data=definition.text.encode()
        )
        channel = foxglove.Channel(
            name, schema=schema, message_encoding=MESSAGE_ENCODING, context=self.foxglove_context
        )
        bridged = BridgedTopic(name, topic, channel)
        self.bridged[name] = bridged
        self._by_channel[channel.id()] = bridged
        on_message = guarded(self, self.drops, self.on_message)
        self.create_subscription(
            topic.msgtype,
            name,
            lambda data: on_message(bridged, data),
            topic.subscription_qos,
            raw=True,
        )

    def discover(self) -> None:
        """Serve each robot's topics that appeared on the graph since the last look."""
        for name, types in self.get_topic_names_and_types():
            if name in self.bridged or name in self._ignored:
                continue
            found = parse(name)
            if found is None or not served(found[0]):
                continue
            topic = found[0]
            if topic.type_name not in types:
                self._ignored.add(name)
                self._count(WRONG_TYPE)
                self.get_logger().error(
                    f"not serving {name}: its type is {', '.join(types)}, declared "
                    f"{topic.type_name} (csam_ros/ros/topics.py)"
                )
                continue
            self._bridge(name, topic)
            self.get_logger().info(f"serving {name} [{topic.type_name}]")

    def on_message(self, bridged: BridgedTopic, data: bytes) -> None:
        """Send a message as received; keep a latched topic's; under sim time, send /clock's
        time as the server's."""
        log_time = self.get_clock().now().nanoseconds
        bridged.received += 1
        if bridged.latched:
            bridged.latest = (data, log_time)
        bridged.channel.log(data, log_time=log_time)
        if self.sim_time and bridged.topic is CLOCK:
            clock = deserialize_message(data, CLOCK.msgtype).clock
            self.server.broadcast_time(clock.sec * 1_000_000_000 + clock.nanosec)

    def _on_client_subscribe(self, channel_id: int) -> None:
        """On the server's thread: a latched channel's latest message is due again."""
        bridged = self._by_channel.get(channel_id)
        if bridged is None or not bridged.latched:
            return
        with self._resend_lock:
            self._resend.add(channel_id)
        self._resend_wake.trigger()

    def send_latest_again(self) -> None:
        """Send the latest message of each latched channel a client subscribed to since."""
        with self._resend_lock:
            due, self._resend = self._resend, set()
        for channel_id in due:
            bridged = self._by_channel[channel_id]
            if bridged.latest is not None:
                data, log_time = bridged.latest
                bridged.channel.log(data, log_time=log_time)

    def destroy_node(self) -> None:
        # the ROS log may be gone already (Ctrl-C shuts rclpy down first): the SDK's shutdown
        # records are not forwarded
        logging.getLogger("foxglove").removeHandler(self._sdk_log)
        self.server.stop()
        for bridged in self.bridged.values():
            bridged.channel.close()
        super().destroy_node()


def main(args: list[str] | None = None) -> int:
    try:
        # its websocket threads wake the executor by a guard condition, which Jazzy's
        # EventsExecutor does not serve (its clients got no answer)
        return run_node(FoxgloveBridge, args, __doc__, SingleThreadedExecutor)
    except (ServeError, ValueError, InvalidParameterValueException) as error:
        print(f"{NODE_NAME}: {error}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
