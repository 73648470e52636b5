"""Small pieces every csam_ros node shares: parameter declaration, signals, main().

Topics and their QoS are declared in :mod:`csam_ros.ros.topics`.
"""

from __future__ import annotations

import signal
import sys
import threading
from collections.abc import Callable
from typing import Any

import rclpy
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.clock import Clock, ClockType
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.publisher import Publisher
from rclpy.subscription import Subscription

from csam_ros.ros.topics import Topic


def stop_on_signals() -> threading.Event:
    """An event set by SIGINT or SIGTERM, in place of rclpy's handlers (which would shut the
    context down under a running callback): the node's loop ends, then it finishes cleanly."""
    stop = threading.Event()
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, lambda *_: stop.set())
    return stop


def steady_clock() -> Clock:
    """A monotonic wall clock for timers that must not follow /clock (sim time)."""
    return Clock(clock_type=ClockType.STEADY_TIME)


def declare(
    node: Node,
    name: str,
    default: Any,
    description: str,
    minimum: float | None = None,
    maximum: float | None = None,
) -> Any:
    """Declare a parameter with a description (and a range for numbers); return its value."""
    descriptor = ParameterDescriptor(description=description)
    if minimum is not None or maximum is not None:
        if isinstance(default, int) and not isinstance(default, bool):
            descriptor.integer_range = [
                IntegerRange(from_value=int(minimum), to_value=int(maximum), step=0)
            ]
        elif isinstance(default, float):
            descriptor.floating_point_range = [
                FloatingPointRange(from_value=float(minimum), to_value=float(maximum), step=0.0)
            ]
    return node.declare_parameter(name, default, descriptor).value


def publisher(node: Node, topic: Topic, name: str | None = None) -> Publisher:
    """A publisher of a declared topic with its type and QoS. ``name`` defaults to the
    declared one: relative, so in the node's namespace, for a per-robot topic."""
    return node.create_publisher(topic.msgtype, name or topic.name, topic.qos)


def subscribe(
    node: Node, topic: Topic, callback: Callable[[Any], None], name: str | None = None
) -> Subscription:
    """A subscription to a declared topic with its type and subscription QoS (``name`` as in
    :func:`publisher`)."""
    return node.create_subscription(
        topic.msgtype, name or topic.name, callback, topic.subscription_qos
    )


def run_node(factory: Callable[[], Node], args: list[str] | None = None, doc: str = "") -> int:
    """Init rclpy, spin the node until shutdown (Ctrl-C, SIGTERM, or the node finishing).

    ``-h`` / ``--help`` (before ``--ros-args``) prints ``doc`` and returns at once.
    """
    argv = sys.argv if args is None else args
    own = argv[1 : argv.index("--ros-args")] if "--ros-args" in argv else argv[1:]
    if "-h" in own or "--help" in own:
        prog = argv[0].rsplit("/", 1)[-1] if argv else "node"
        print(f"usage: {prog} [-h] [--ros-args ...]\n")
        print(doc.strip() or "a csam_ros node")
        print(
            "\nROS arguments go after --ros-args, e.g. --ros-args -r __ns:=/robot1 "
            "-p name:=value --params-file config/FILE.yaml"
        )
        return 0
    rclpy.init(args=args)
    node = None
    try:
        node = factory()
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return 0
