"""simulator: runs a scenario from config/ and publishes every robot's measurements.

Publishes per robot ``/<robot>/odom``, ``/<robot>/features``, ``/<robot>/rendezvous`` and
``/<robot>/ground_truth``, the features' truth on ``/sim/features_truth`` (transient local) and
``/clock``. The whole run is simulated by the core at start; the node only paces it out. The
odometry carries its integrated pose as a robot driver's does, and like a driver the simulator
publishes ``/tf`` ``<robot>/odom -> <robot>/base_link`` from it, at each odometry stamp (REP-105:
the smoothers publish ``<robot>/map -> <robot>/odom``).

With robots on their own hosts, each host runs a simulator of the same scenario and seed that
publishes only its own robots' topics (``emit_robots``); exactly one of them publishes /clock
and the truth (``publish_clock``), so the run has one source of sim time.
"""

from __future__ import annotations

import sys
import time
from typing import Any

from rclpy.duration import Duration
from rclpy.node import Node
from rclpy.publisher import Publisher
from rosgraph_msgs.msg import Clock
from tf2_msgs.msg import TFMessage

from csam_ros.datasets.scenario import load_scenario
from csam_ros.datasets.simulation import simulate
from csam_ros.nodes.common import (
    Declared,
    Live,
    declare_each,
    publisher,
    run_node,
    steady_clock,
    watch_parameters,
)
from csam_ros.ros.conversions import OdometryTransforms, log_to_messages, ns_to_time
from csam_ros.ros.topics import (
    CLOCK,
    FEATURES_TRUTH,
    ODOM,
    TF,
    TOPICS,
    declaration,
    robot_topics,
    sensor_topics,
)

# log lines others time the run by (run.hosts reads them from the node's log file)
LOG_PUBLISHING = "publishing"  # the first message goes out
LOG_ALL_PUBLISHED = "all messages published"
DRAIN_TIMEOUT_S = 30.0  # the longest wait for acknowledgements before exiting when done
SIMULATOR_NODE = "simulator"
# the simulator's parameters, in the order they are declared
SIMULATOR_PARAMETERS = (
    Declared("scenario", "map_joining", "scenario name in config/ or path to a YAML file"),
    Declared("seed", -1, "noise seed; -1 uses the scenario's", -1, 2**31 - 1),
    Declared(
        "rate", 1.0, "speed relative to real time; 0 publishes as fast as possible", 0.0, 1000.0
    ),
    Declared(
        "wait_for_subscribers",
        True,
        "start only once every robot's sensor topics have a subscriber",
    ),
    Declared("min_subscribers", 1, "subscribers each sensor topic needs before the start", 1, 100),
    Declared(
        "start_delay",
        1.0,
        "seconds between seeing the subscribers and the start: a best-effort subscriber "
        "may see the publisher later than the publisher sees it",
        0.0,
        60.0,
    ),
    Declared(
        "required_subscriber_nodes",
        [""],
        "node names that must subscribe to every topic before the start (a recorder)",
    ),
    Declared("exit_when_done", False, "shut down once everything is published"),
    Declared(
        "emit_robots",
        [""],
        "robots whose topics this simulator publishes (robots on their own hosts); "
        "empty: every robot of the scenario",
    ),
    Declared(
        "publish_clock",
        True,
        "publish /clock and the features' truth: one simulator per run does, the run's "
        "single source of sim time",
    ),
    Declared(
        "clock_period",
        0.01,
        "wall-clock s between /clock messages (longer on slow links: every node of every "
        "host gets each one)",
        0.001,
        1.0,
    ),
)


class Simulator(Node):
    """Publishes a simulated run at ``rate`` times real time (0: as fast as possible)."""

    def __init__(self, **node_options: Any) -> None:
        super().__init__(SIMULATOR_NODE, **node_options)
        own = declare_each(self, SIMULATOR_PARAMETERS)
        scenario_name, seed = own["scenario"], own["seed"]
        self.rate = own["rate"]
        self.wait_for_subscribers = own["wait_for_subscribers"]
        self.min_subscribers = own["min_subscribers"]
        self.start_delay = own["start_delay"]
        self.ready_since: float | None = None
        self.required_nodes = list(own["required_subscriber_nodes"])
        self.exit_when_done = own["exit_when_done"]
        emit = [r for r in own["emit_robots"] if r]
        publish_clock = own["publish_clock"]
        self.clock_period = own["clock_period"]
        self._clock_sent = float("-inf")
        scenario = load_scenario(scenario_name)
        names = [r.name for r in scenario.robots]
        unknown = sorted(set(emit) - set(names))
        if unknown:
            raise ValueError(f"emit_robots: {unknown} not in scenario {scenario.name} ({names})")
        self.robots = emit or names
        log = simulate(scenario, None if seed < 0 else seed)
        emitted = set(robot_topics(self.robots, TOPICS))
        if publish_clock:
            emitted.add(FEATURES_TRUTH.name)
        self.messages = [m for m in log_to_messages(log, with_poses=True) if m.topic in emitted]
        self.topic_publishers: dict[str, Publisher] = {}
        for m in self.messages:
            if m.topic not in self.topic_publishers:
                self.topic_publishers[m.topic] = publisher(self, declaration(m.topic), m.topic)
        self.clock = publisher(self, CLOCK) if publish_clock else None
        self.tf = publisher(self, TF)  # odom -> base_link of the odometry published
        # odom -> base_link of each odometry message, made once (None: not odometry)
        transforms = OdometryTransforms()
        self.odometry_tf = [
            transforms.transform(robot, m.message)  # type: ignore[arg-type]
            if (robot := ODOM.robot_of(m.topic)) is not None
            else None
            for m in self.messages
        ]
        self.next_index = 0
        self.start_stamp_ns = self.messages[0].stamp_ns if self.messages else 0
        self.end_stamp_ns = self.messages[-1].stamp_ns if self.messages else 0
        self.wall_start: float | None = None
        self.get_logger().info(
            f"scenario {scenario.name}: {len(self.robots)} of {len(names)} robots "
            f"({', '.join(self.robots)}), {len(self.messages)} messages, "
            f"{(self.end_stamp_ns - self.start_stamp_ns) / 1e9:.1f} s at rate {self.rate}"
        )
        # the simulator is the clock source: pace by the steady wall clock, never by /clock
        self.timer = self.create_timer(0.01, self._tick, clock=steady_clock())
        watch_parameters(self, {"clock_period": Live(self.set_clock_period)})

    def set_clock_period(self, seconds: float) -> None:
        """Publish /clock every ``seconds`` of the wall clock from now on (set at run time)."""
        self.clock_period = seconds

    def _subscribers_ready(self) -> bool:
        # matched subscriptions of this node's publishers, not the graph's count (which can
        # list a subscription before the middleware has matched it)
        sensors = sensor_topics(self.robots)
        if any(
            self.topic_publishers[t].get_subscription_count() < self.min_subscribers
            for t in sensors
            if t in self.topic_publishers
        ):
            return False
        required = {n for n in self.required_nodes if n}
        return all(
            required <= {i.node_name for i in self.get_subscriptions_info_by_topic(t)}
            for t in self.topic_publishers
        )

    def _tick(self) -> None:
        if self.wall_start is None:
            if self.wait_for_subscribers and not self._subscribers_ready():
                return
            if self.ready_since is None:
                self.ready_since = time.monotonic()
            if time.monotonic() - self.ready_since < self.start_delay:
                return
            self.wall_start = time.monotonic()
            self.get_logger().info(LOG_PUBLISHING)
        if self.rate > 0:
            elapsed_ns = int((time.monotonic() - self.wall_start) * self.rate * 1e9)
            horizon = self.start_stamp_ns + elapsed_ns
        else:
            horizon = self.end_stamp_ns
        published = 0
        transforms = TFMessage()
        while self.next_index < len(self.messages):
            m = self.messages[self.next_index]
            if m.stamp_ns > horizon or (self.rate == 0 and published >= 200):
                break
            self.topic_publishers[m.topic].publish(m.message)
            transform = self.odometry_tf[self.next_index]
            if transform is not None:
                transforms.transforms.append(transform)
            self.next_index += 1
            published += 1
        if transforms.transforms:
            self.tf.publish(transforms)
        now_ns = self.messages[self.next_index - 1].stamp_ns if self.next_index else horizon
        done = self.next_index == len(self.messages)
        if self.clock is not None and (
            done or time.monotonic() - self._clock_sent >= self.clock_period
        ):
            now = min(max(now_ns, horizon), self.end_stamp_ns)
            self.clock.publish(Clock(clock=ns_to_time(now)))
            self._clock_sent = time.monotonic()
        if done:
            self.timer.cancel()
            self.get_logger().info(LOG_ALL_PUBLISHED)
            if self.exit_when_done:
                # let reliable messages drain before the process goes away
                self.create_timer(0.2, self._finish, clock=steady_clock())

    def _finish(self) -> None:
        # a reliable sample to another host may still wait for a resend on a lossy link
        # (waited in short slices: SIGINT still ends the node at once)
        deadline = time.monotonic() + DRAIN_TIMEOUT_S
        waiting = {**self.topic_publishers, TF.name: self.tf}
        while waiting and time.monotonic() < deadline and self.context.ok():
            for topic in list(waiting):
                if waiting[topic].wait_for_all_acked(Duration(seconds=0.1)):
                    del waiting[topic]
        if waiting:
            self.get_logger().warning(f"not every subscriber acknowledged {sorted(waiting)}")
        raise SystemExit(0)


def main(args: list[str] | None = None) -> int:
    try:
        return run_node(Simulator, args, __doc__)
    except SystemExit as done:
        return int(done.code or 0)


if __name__ == "__main__":
    sys.exit(main())
