"""The foxglove_bridge node, in-process, between real publishers over DDS and independent
WebSocket clients (the ``websockets`` package) that speak the Foxglove protocol themselves:
server info, channels advertised with their ros2msg schemas, subscriptions, binary message
frames whose payload is the CDR as published and decodes with the advertised schema alone
(mcap_ros2's decoder, not the rclpy class); latched messages for clients that come late; bad
requests and topics of the wrong type logged, counted and survived; sim time."""

from __future__ import annotations

import json
import struct
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest
from waiting import wait_until

from csam_ros.bag import MessageTypes
from csam_ros.ros.topics import CLOCK, JOINED_MAP, LOCAL_MAP, PATH, STATUS, TF

SUBPROTOCOL = "foxglove.sdk.v1"  # foxglove.websocket.v1 under the Foxglove SDK's name
MESSAGE_DATA, TIME = 0x01, 0x02  # server binary opcodes
ERROR_LEVEL = 2


class Client:
    """A Foxglove WebSocket client: what the server advertised, said and sent, by reading
    frames as they come."""

    def __init__(self, port: int) -> None:
        from websockets.sync.client import connect

        self.connection = connect(
            f"ws://127.0.0.1:{port}", subprotocols=[SUBPROTOCOL], open_timeout=10
        )
        self.server_info: dict[str, Any] | None = None
        self.channels: dict[str, dict[str, Any]] = {}  # by topic
        self.statuses: list[dict[str, Any]] = []
        self.messages: list[tuple[int, int, bytes]] = []  # subscription id, log time, payload
        self.times: list[int] = []

    def read(self) -> None:
        """Take one frame if one comes within 50 ms."""
        try:
            frame = self.ws.recv(timeout=0.05)
        except TimeoutError:
            return
        if isinstance(frame, bytes):
            if frame[0] == MESSAGE_DATA:
                subscription, log_time = struct.unpack_from("<IQ", frame, 1)
                self.messages.append((subscription, log_time, frame[13:]))
            elif frame[0] == TIME:
                self.times.append(struct.unpack_from("<Q", frame, 1)[0])
            return
        message = json.loads(frame)
        if message["op"] == "serverInfo":
            self.server_info = message
        elif message["op"] == "advertise":
            self.channels.update({c["topic"]: c for c in message["channels"]})
        elif message["op"] == "status":
            self.statuses.append(message)

    def wait(self, condition: Callable[[], Any], timeout_s: float = 10.0) -> bool:
        return wait_until(condition, timeout_s, self.read)

    def subscribe(self, subscription: int, topic: str) -> None:
        assert self.wait(lambda: topic in self.channels), f"{topic} not advertised"
        channel = self.channels[topic]["id"]
        self.send(
            {"op": "subscribe", "subscriptions": [{"id": subscription, "channelId": channel}]}
        )

    def send(self, message: dict[str, Any]) -> None:
        self.ws.send(json.dumps(message))

    def payloads(self, subscription: int) -> list[bytes]:
        return [data for sub, _, data in self.messages if sub == subscription]

    def decoded(self, topic: str, payload: bytes) -> Any:
        """``payload`` decoded with the schema advertised for ``topic``, and nothing else."""
        from mcap.records import Schema
        from mcap_ros2.decoder import DecoderFactory

        channel = self.channels[topic]
        assert (channel["encoding"], channel["schemaEncoding"]) == ("cdr", "ros2msg")
        schema = Schema(
            id=1,
            name=channel["schemaName"],
            encoding="ros2msg",
            data=channel["schema"].encode(),
        )
        decoder = DecoderFactory().decoder_for("cdr", schema)
        assert decoder is not None
        return decoder(payload)

    def __enter__(self) -> Client:
        self.ws = self.connection.__enter__()
        return self

    def __exit__(self, *exc: object) -> None:
        self.connection.__exit__(*exc)


@contextmanager
def _bridge(context: Any, **parameters: Any) -> Iterator[tuple[Any, Any]]:
    """A bridge on a free port and a source node, spun by one executor on a thread of their
    own while the test talks to the server."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter

    from csam_ros.nodes.foxglove_bridge import FoxgloveBridge

    overrides = [Parameter(k, value=v) for k, v in {"port": 0, **parameters}.items()]
    bridge = FoxgloveBridge(context=context, parameter_overrides=overrides)
    source = rclpy.create_node("foxglove_source", context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(bridge)
    executor.add_node(source)
    stop = threading.Event()

    def spin() -> None:
        while not stop.is_set():
            executor.spin_once(timeout_sec=0.02)

    spinner = threading.Thread(target=spin, daemon=True)
    spinner.start()
    try:
        yield bridge, source
    finally:
        stop.set()
        spinner.join(timeout=10)
        executor.shutdown()
        source.destroy_node()
        bridge.destroy_node()


def _publisher(source: Any, topic: Any, name: str | None = None) -> Any:
    from csam_ros.nodes.common import publisher

    return publisher(source, topic, name or topic.name)


def test_latched_and_live_messages_reach_clients_with_schemas_that_decode_them(
    ros_context: Any, make_sample: Any, fields_equal: Any
) -> None:
    joined = make_sample("csam_msgs/msg/JoinedMap")
    path = make_sample("nav_msgs/msg/Path")
    transforms = make_sample("tf2_msgs/msg/TFMessage")
    with _bridge(ros_context, robots=["robot7"]) as (bridge, source):
        assert bridge.url == f"ws://127.0.0.1:{bridge.port}" and bridge.port > 0
        joined_pub = _publisher(source, JOINED_MAP)
        path_pub = _publisher(source, PATH, PATH.of("robot7"))
        tf_pub = _publisher(source, TF)
        on_dds: list[bytes] = []  # the joined map's CDR as DDS delivers it to anyone
        source.create_subscription(
            JOINED_MAP.msgtype, JOINED_MAP.name, on_dds.append, JOINED_MAP.qos, raw=True
        )
        joined_pub.publish(joined)  # latched, before any client is there
        assert wait_until(lambda: bridge.bridged[JOINED_MAP.name].received == 1 and on_dds)

        with Client(bridge.port) as early:
            assert early.wait(lambda: early.server_info is not None)
            assert early.server_info["name"] == "csam_ros"
            assert "time" not in early.server_info["capabilities"]  # no sim time
            served = {JOINED_MAP.name, STATUS.name, TF.name, CLOCK.name, PATH.of("robot7")}
            assert early.wait(lambda: served <= set(early.channels)), early.channels.keys()
            assert LOCAL_MAP.of("robot7") in early.channels
            assert not any(t.endswith(("/odom", "/local_map_updates")) for t in early.channels)
            channel = early.channels[JOINED_MAP.name]
            assert channel["schemaName"] == "csam_msgs/msg/JoinedMap"
            # the ros2msg text the bag writer stores in MCAP files
            definition = MessageTypes().definition("csam_msgs/msg/JoinedMap").text
            assert channel["schema"] == definition

            early.subscribe(1, JOINED_MAP.name)
            early.subscribe(2, TF.name)
            assert early.wait(lambda: early.payloads(1)), "no latched joined map on subscribe"
            [payload] = early.payloads(1)
            assert payload == on_dds[0], "the CDR as received, not encoded again"
            fields_equal(joined, early.decoded(JOINED_MAP.name, payload))

            assert wait_until(lambda: tf_pub.get_subscription_count() > 0)
            tf_pub.publish(transforms)
            assert early.wait(lambda: early.payloads(2)), "no live /tf message"
            fields_equal(transforms, early.decoded(TF.name, early.payloads(2)[0]))
            path_pub.publish(path)  # a robot's latched topic, while nobody subscribes
            assert wait_until(lambda: bridge.bridged[PATH.of("robot7")].received == 1)

            with Client(bridge.port) as late:
                late.subscribe(5, JOINED_MAP.name)
                late.subscribe(6, PATH.of("robot7"))
                assert late.wait(lambda: late.payloads(5) and late.payloads(6))
                assert late.payloads(5) == [payload]
                fields_equal(joined, late.decoded(JOINED_MAP.name, late.payloads(5)[0]))
                fields_equal(path, late.decoded(PATH.of("robot7"), late.payloads(6)[0]))
            assert early.statuses == [] and bridge.drops.as_dict() == {}


def test_bad_requests_and_wrong_types_are_logged_counted_and_survived(
    ros_context: Any, make_sample: Any, fields_equal: Any
) -> None:
    from rclpy.qos import QoSProfile
    from std_msgs.msg import String

    from csam_ros.nodes.foxglove_bridge import CLIENT_REQUEST, WRONG_TYPE

    joined = make_sample("csam_msgs/msg/JoinedMap")
    path = make_sample("nav_msgs/msg/Path")
    with _bridge(ros_context) as (bridge, source), Client(bridge.port) as client:
        _publisher(source, JOINED_MAP).publish(joined)
        assert client.wait(lambda: JOINED_MAP.name in client.channels)
        client.ws.send("{not json")
        client.send({"op": "subscribe", "subscriptions": [{"id": 1, "channelId": 99999}]})
        client.send({"op": "no such operation"})
        assert client.wait(lambda: len(client.statuses) == 3), client.statuses
        assert all(s["level"] == ERROR_LEVEL for s in client.statuses)
        assert "99999" in client.statuses[1]["message"]
        assert wait_until(lambda: bridge.drops.as_dict().get(CLIENT_REQUEST) == 3)

        # a robot found on the graph: its path is served, a declared name of another type not
        path_pub = _publisher(source, PATH, PATH.of("robot8"))
        wrong = source.create_publisher(String, LOCAL_MAP.of("robot8"), QoSProfile(depth=1))
        path_pub.publish(path)
        client.subscribe(2, PATH.of("robot8"))
        client.subscribe(3, JOINED_MAP.name)  # the same connection goes on
        assert client.wait(lambda: client.payloads(2) and client.payloads(3))
        fields_equal(path, client.decoded(PATH.of("robot8"), client.payloads(2)[0]))
        fields_equal(joined, client.decoded(JOINED_MAP.name, client.payloads(3)[0]))
        assert wait_until(lambda: bridge.drops.as_dict().get(WRONG_TYPE) == 1)
        wrong.publish(String(data="not a local map"))
        assert LOCAL_MAP.of("robot8") not in bridge.bridged
        assert LOCAL_MAP.of("robot8") not in client.channels


def test_sim_time_is_the_servers_time_and_the_messages_log_time(
    ros_context: Any, make_sample: Any
) -> None:
    from builtin_interfaces.msg import Time
    from rosgraph_msgs.msg import Clock

    with _bridge(ros_context, use_sim_time=True) as (bridge, source), Client(bridge.port) as client:
        clock_pub = _publisher(source, CLOCK)
        status_pub = _publisher(source, STATUS)
        assert client.wait(lambda: client.server_info is not None)
        assert "time" in client.server_info["capabilities"]
        client.subscribe(1, CLOCK.name)
        client.subscribe(2, STATUS.name)
        assert wait_until(lambda: clock_pub.get_subscription_count() > 0)
        assert wait_until(lambda: status_pub.get_subscription_count() > 0)
        stamp_ns = 1234 * 10**9 + 5678

        def clock_served() -> bool:  # sent again until served: the client's subscription and
            # the bridge's may still be settling on a busy machine
            clock_pub.publish(Clock(clock=Time(sec=1234, nanosec=5678)))
            return bool(client.times and client.payloads(1))

        assert client.wait(clock_served)
        assert set(client.times) == {stamp_ns}
        # the bridge's clock follows /clock, and a message carries it as its log time
        assert wait_until(lambda: bridge.get_clock().now().nanoseconds == stamp_ns)
        status_pub.publish(make_sample("diagnostic_msgs/msg/DiagnosticArray"))
        assert client.wait(lambda: client.payloads(2))
        assert [t for sub, t, _ in client.messages if sub == 2] == [stamp_ns]


@pytest.mark.parametrize("port", [-1, 70000])
def test_a_port_out_of_range_is_refused(ros_context: Any, port: int) -> None:
    from rclpy.exceptions import InvalidParameterValueException

    with pytest.raises(InvalidParameterValueException), _bridge(ros_context, port=port):
        pass


def test_the_executable_serves_as_the_demo_starts_it_and_a_taken_port_is_one_error(
    tmp_path: Path,
) -> None:
    import os
    import sys

    from csam_ros.run.demo import BRIDGE, bridge_url
    from csam_ros.run.errors import RunError
    from csam_ros.run.launch import ProcessGroup

    def argv(port: int) -> list[str]:
        module = [sys.executable, "-m", "csam_ros.nodes.foxglove_bridge"]
        return [*module, "--ros-args", "-p", f"port:={port}", "-p", "use_sim_time:=true"]

    with ProcessGroup(tmp_path / "first", dict(os.environ)) as first:
        first.start(BRIDGE, argv(0))
        url = bridge_url(first)
        port = int(url.rpartition(":")[2])
        assert url == f"ws://127.0.0.1:{port}" and port > 0
        with Client(port) as client:
            assert client.wait(lambda: JOINED_MAP.name in client.channels)
            assert "time" in client.server_info["capabilities"]
        with ProcessGroup(tmp_path / "second", dict(os.environ)) as second:
            second.start(BRIDGE, argv(port))
            with pytest.raises(RunError, match="(?s)exited.*Address already in use"):
                bridge_url(second)
            assert second.processes[BRIDGE].returncode == 1
        assert first.stop(BRIDGE) == 0, first.log_tail(BRIDGE)
