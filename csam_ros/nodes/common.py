"""Small pieces every csam_ros node shares: parameter declaration, parameters set at run time,
signals, main().

Topics and their QoS are declared in :mod:`csam_ros.ros.topics`. A node declares its own
parameters as a table of :class:`Declared` (what :mod:`csam_ros.run.params_files` writes into
the params files) and those of its settings dataclasses from their fields; once all are
declared, :func:`watch_parameters` refuses parameters given that it has none of, and applies or
refuses each parameter set while it runs.
"""

from __future__ import annotations

import difflib
import functools
import math
import os
import signal
import sys
import threading
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any, TypeVar

import rclpy
from rcl_interfaces.msg import (
    FloatingPointRange,
    IntegerRange,
    ParameterDescriptor,
    SetParametersResult,
)
from rclpy.clock import Clock, ClockType
from rclpy.context import Context
from rclpy.executors import Executor, ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.publisher import Publisher
from rclpy.subscription import Subscription

from csam_ros.core.exchange.validation import CALLBACK_ERROR, DropCounter
from csam_ros.core.model.config_file import settings
from csam_ros.ros.topics import Topic

T = TypeVar("T")
N = TypeVar("N", bound=Node)
_INT64_MIN, _INT64_MAX = -(2**63), 2**63 - 1
# a drop reason: a parameter given to a node (params file, -p) that the node has none of
UNKNOWN_PARAMETER = "unknown_parameter"
START_ONLY = "takes effect only at start"  # why a parameter set at run time is refused


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
    constraints: str = "",
) -> Any:
    """Declare a parameter with a description (and a range for numbers, open-ended where a
    bound is None; ``constraints`` in words); return its value."""
    descriptor = ParameterDescriptor(description=description, additional_constraints=constraints)
    if minimum is not None or maximum is not None:
        if isinstance(default, int) and not isinstance(default, bool):
            low = _INT64_MIN if minimum is None else int(minimum)
            high = _INT64_MAX if maximum is None else int(maximum)
            descriptor.integer_range = [IntegerRange(from_value=low, to_value=high, step=0)]
        elif isinstance(default, float):
            low = -math.inf if minimum is None else float(minimum)
            high = math.inf if maximum is None else float(maximum)
            descriptor.floating_point_range = [
                FloatingPointRange(from_value=low, to_value=high, step=0.0)
            ]
    return node.declare_parameter(name, default, descriptor).value


def declare_settings(node: Node, cls: type[T], defaults: T | None = None) -> T:
    """Declare as ROS parameters the fields of a parameter dataclass that this node takes
    (their :class:`~csam_ros.core.model.config_file.Setting` names the node), with descriptions and
    ranges; return the dataclass built back from the values, checked (other fields keep
    ``defaults``)."""
    base = defaults if defaults is not None else cls()
    values = {
        name: declare(
            node,
            name,
            getattr(base, name),
            rule.description,
            rule.minimum,
            None,
            rule.constraint,
        )
        for name, (rule, _) in settings(cls).items()
        if rule.node == node.get_name()
    }
    checked = cls.from_dict(values, f"{node.get_name()} parameters")  # type: ignore[attr-defined]
    return replace(base, **{name: getattr(checked, name) for name in values})


@dataclass(frozen=True)
class Declared:
    """One of a node's own parameters (its settings dataclasses' fields declare theirs): what
    :func:`declare_each` declares and a params file lists."""

    name: str
    default: Any  # None: a parameter of any type, unset by default
    description: str
    minimum: float | None = None
    maximum: float | None = None
    made_at_start: str = ""  # the default is made at start from this (params files leave it out)


# a robot's node's name of its robot (the smoother's, the detections node's)
ROBOT_PARAMETER = Declared(
    "robot",
    "",
    "this robot's name (default: namespace)",
    made_at_start="the namespace: robot1 under -r __ns:=/robot1",
)


def declare_each(
    node: Node,
    table: Sequence[Declared],
    made: Mapping[str, Callable[[dict[str, Any]], Any]] | None = None,
) -> dict[str, Any]:
    """Declare a node's own parameters in the table's order; their values by name. ``made``
    gives the defaults made at start, each from the values declared before it."""
    values: dict[str, Any] = {}
    for entry in table:
        if entry.default is None:
            descriptor = ParameterDescriptor(description=entry.description, dynamic_typing=True)
            values[entry.name] = node.declare_parameter(entry.name, None, descriptor).value
            continue
        default = made[entry.name](values) if made and entry.name in made else entry.default
        values[entry.name] = declare(
            node, entry.name, default, entry.description, entry.minimum, entry.maximum
        )
    return values


@dataclass(frozen=True)
class Live:
    """A parameter its node applies while it runs: ``apply`` takes the value once it is set;
    ``check`` first, whose ValueError (or TypeError) refuses the value with its message."""

    apply: Callable[[Any], None]
    check: Callable[[Any], object] | None = None


def setting_check(cls: type, name: str) -> Callable[[Any], object]:
    """The check of a settings dataclass field's value by its Setting (ValueError naming it)."""
    rule, default = settings(cls)[name]
    return lambda value: rule.check(value, default, name)


def given_parameters(node: Node) -> list[str]:
    """The names of the parameters given to ``node``: its params files' sections that match
    it, ``-p`` and the ``parameter_overrides`` it was made with (rclpy keeps them in
    ``Node._parameter_overrides`` and has no public accessor)."""
    return sorted(getattr(node, "_parameter_overrides", {}))


def watch_parameters(
    node: Node, live: Mapping[str, Live] | None = None, drops: DropCounter | None = None
) -> list[str]:
    """Call once ``node`` has declared all its parameters. A parameter given to it that it has
    none of (a misspelt or misplaced key: rclpy would ignore it silently) is refused in one
    logged error line and counted under ``unknown_parameter`` in ``drops``; returns those
    names. From now on a parameter set while the node runs (``ros2 param set``) is applied
    when ``live`` names it, else refused: "NAME takes effect only at start"."""
    live = dict(live or {})
    declared = sorted(node.get_parameters_by_prefix(""))
    unknown = [name for name in given_parameters(node) if not node.has_parameter(name)]
    if unknown:
        hints = []
        for name in unknown:
            close = difflib.get_close_matches(name, declared, n=1)
            hints.append(f"{name} (did you mean {close[0]}?)" if close else name)
        node.get_logger().error(
            f"unknown parameter(s) refused: {', '.join(hints)}; "
            f"{node.get_fully_qualified_name()} has none of that name (see its params file)"
        )
        if drops is not None:
            drops.add(UNKNOWN_PARAMETER, len(unknown))
    settable = ", ".join(sorted(live)) or "none"

    def refuse_at_run_time(parameters: list[Parameter]) -> SetParametersResult:
        for parameter in parameters:
            if not node.has_parameter(parameter.name):  # being declared, not set
                continue
            entry = live.get(parameter.name)
            if entry is None:
                return SetParametersResult(
                    successful=False,
                    reason=f"{parameter.name} {START_ONLY} (restart the node with it); "
                    f"set at run time: {settable}",
                )
            if entry.check is not None:
                try:
                    entry.check(parameter.value)
                except (TypeError, ValueError) as error:
                    return SetParametersResult(successful=False, reason=str(error))
        return SetParametersResult(successful=True)

    def apply(parameters: list[Parameter]) -> None:
        for parameter in parameters:
            entry = live.get(parameter.name)
            if entry is None:
                continue
            try:
                entry.apply(parameter.value)
            except Exception as error:  # noqa: BLE001 - the boundary of a node: nothing escapes
                if drops is not None:
                    drops.add(CALLBACK_ERROR)
                node.get_logger().error(
                    f"parameter {parameter.name}: {type(error).__name__}: {error}"
                )
                continue
            node.get_logger().info(f"parameter {parameter.name} set to {parameter.value!r}")

    node.add_on_set_parameters_callback(refuse_at_run_time)
    node.add_post_set_parameters_callback(apply)
    return unknown


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


def guarded(node: Node, drops: DropCounter, callback: Callable[..., T]) -> Callable[..., T | None]:
    """``callback`` that never takes the node down: an unexpected exception is logged with
    the message that caused it, counted once under ``callback_error`` in ``drops``, and the
    node goes on with the data it had already accepted."""

    @functools.wraps(callback)
    def call(*args: Any) -> T | None:
        try:
            return callback(*args)
        except Exception as error:  # noqa: BLE001 - the boundary of a node: nothing escapes
            drops.add(CALLBACK_ERROR)
            shown = " ".join(repr(a) for a in args)
            if len(shown) > 500:
                shown = shown[:500] + "..."
            node.get_logger().error(
                f"{callback.__name__}: {type(error).__name__}: {error}; dropped {shown}"
            )
            return None

    return call


EXECUTOR_VARIABLE = "CSAM_EXECUTOR"  # environment: "events" (the default) or "single"


def make_executor(context: Context | None = None) -> Executor:
    """The executor a csam_ros process spins its node with: rclpy's EventsExecutor (its
    waiting and dispatch in C++), or the SingleThreadedExecutor with ``CSAM_EXECUTOR=single``.
    A raw subscription among 40 cost 54 us of CPU per message in the first and 956 us in the
    second (``python -m csam_ros.bench.executors``): the recorder of a five-robot run was a
    core's 44 % busy taking its 700 messages a second."""
    kind = os.environ.get(EXECUTOR_VARIABLE, "events")
    if kind == "single":
        return SingleThreadedExecutor(context=context)
    if kind != "events":
        raise ValueError(f"{EXECUTOR_VARIABLE}={kind!r}: expected 'events' or 'single'")
    from rclpy.experimental import EventsExecutor

    return EventsExecutor(context=context)


def spin_while_up(node: Node, executor: Executor, stop: threading.Event | None = None) -> None:
    """Spin ``node`` on ``executor`` while rclpy is up and ``stop`` is not set, by
    ``spin_once`` (``EventsExecutor.spin()`` outlives a shutdown)."""
    executor.add_node(node)
    while rclpy.ok(context=node.context) and not (stop is not None and stop.is_set()):
        executor.spin_once(timeout_sec=0.1)


def run_node(
    factory: Callable[[], Node],
    args: list[str] | None = None,
    doc: str = "",
    executor: Callable[[], Executor] = make_executor,
) -> int:
    """Init rclpy, spin the node with a new ``executor()`` until shutdown (Ctrl-C, SIGTERM, or
    the node finishing).

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

    def spin(node: Node) -> int:
        spin_while_up(node, executor())
        return 0

    return run_rclpy(factory, spin, args)


def run_rclpy(
    factory: Callable[[], N],
    work: Callable[[N], int],
    args: Sequence[str] | None = None,
    close: Callable[[N | None], None] | None = None,
    **init_options: Any,
) -> int:
    """Init rclpy (``args``, ``init_options``), make the node and return ``work(node)``; Ctrl-C
    and an external shutdown end the work quietly with 0. Whatever happens, ``close`` (given
    the node, or None when making it failed) runs, then the node is destroyed and rclpy shut
    down."""
    rclpy.init(args=args, **init_options)
    node = None
    try:
        node = factory()
        return work(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        return 0
    finally:
        if close is not None:
            close(node)
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
