"""A merger node in-process with an injector node, and the messages of a simulated run.

Shared by the merger's boundary tests and its fuzz test: the local maps and rendezvous poses
two smoothers would publish for the map_joining scenario, built by the core from a
simulated run (as in test/ros/test_map_messages.py), and a harness that publishes them to a
real :class:`~csam_ros.nodes.merger.Merger` over DDS and reads its joined map.
"""

from __future__ import annotations

import copy
from collections.abc import Mapping
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from csam_msgs.msg import JoinedMap, LocalMap, RendezvousPoses
from diagnostic_msgs.msg import DiagnosticArray
from log_slices import robot_log_between
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter

from csam_ros.core.csam import robot_map_from_local_map
from csam_ros.core.local_map import build_local_map
from csam_ros.core.log import RobotLog
from csam_ros.core.rendezvous import required_stamps
from csam_ros.core.simulation import simulate
from csam_ros.datasets.scenario import load_scenario
from csam_ros.ros.map_messages import rendezvous_poses_message, robot_map_to_message

ROBOTS = ["robot1", "robot2"]
STAMP_NS = 10**12


@dataclass(frozen=True)
class RunMessages:
    """What each robot's smoother would publish at the end of a simulated run."""

    local_maps: dict[str, LocalMap]
    rendezvous: dict[str, RendezvousPoses]
    logs: dict[str, RobotLog]


def run_messages(
    restart_at: float | None = None, names: Mapping[str, str] | None = None
) -> RunMessages:
    """The smoothers' last messages of map_joining (seed 2); with ``restart_at``, robot2's
    smoother restarted at that time, so its map and measurements hold only what came after;
    with ``names``, the robots renamed (robot1 and robot2 to their names there)."""
    scenario = load_scenario("map_joining")
    if names is not None:
        scenario = replace(
            scenario,
            robots=tuple(
                replace(
                    r,
                    name=names[r.name],
                    observes=None if r.observes is None else tuple(names[o] for o in r.observes),
                )
                for r in scenario.robots
            ),
        )
    log = simulate(scenario, seed=2)
    logs = dict(log.robots)
    if restart_at is not None:
        logs["robot2"] = robot_log_between(logs["robot2"], start=restart_at)
    stamps = required_stamps({n: r.rendezvous for n, r in logs.items()})
    maps, rendezvous = {}, {}
    for name, robot_log in logs.items():
        extra = stamps[name][stamps[name] >= robot_log.odometry.stamps[0]]
        local = build_local_map(robot_log, extra)
        m = robot_map_from_local_map(local)
        maps[name] = robot_map_to_message(
            m, STAMP_NS, local.pose_covariances(), local.landmark_covariances()
        )
        indices = np.unique(local.pose_index(extra))
        rendezvous[name] = rendezvous_poses_message(m, STAMP_NS, indices, robot_log.rendezvous)
    return RunMessages(maps, rendezvous, logs)


def joined_view(msg: JoinedMap) -> tuple[Any, ...]:
    """What a joined map says, comparable exactly: features, associations, base nodes."""
    return (
        [(tuple(f.members), f.x, f.y, tuple(f.covariance)) for f in msg.features],
        [(a.a, a.b, a.mahalanobis) for a in msg.associations],
        [(n.robot, n.alignment, n.pose.x, n.pose.y, n.pose.theta) for n in msg.base_nodes],
        [(t.robot, len(t.poses)) for t in msg.trajectories],
    )


class MergerHarness:
    """A real merger and an injector node that publishes on every robot's map topics."""

    def __init__(self, context: Any, spin: Any, **parameters: Any) -> None:
        import rclpy

        from csam_ros.nodes.common import publisher
        from csam_ros.nodes.merger import Merger
        from csam_ros.ros.topics import JOINED_MAP, LOCAL_MAP, RENDEZVOUS_POSES, STATUS

        self.spin = spin
        overrides = {"robots": ROBOTS, "solve_period": 0.02, **parameters}
        self.merger = Merger(
            context=context,
            parameter_overrides=[Parameter(k, value=v) for k, v in overrides.items()],
        )
        self.injector = rclpy.create_node("injector", context=context)
        self.maps = {r: publisher(self.injector, LOCAL_MAP, LOCAL_MAP.of(r)) for r in ROBOTS}
        self.rendezvous = {
            r: publisher(self.injector, RENDEZVOUS_POSES, RENDEZVOUS_POSES.of(r)) for r in ROBOTS
        }
        self.joined: list[JoinedMap] = []
        self.injector.create_subscription(
            JOINED_MAP.msgtype, JOINED_MAP.of(), self.joined.append, JOINED_MAP.qos
        )
        self.status: list[DiagnosticArray] = []
        self.injector.create_subscription(
            STATUS.msgtype, STATUS.of(), self.status.append, STATUS.qos
        )
        self.executor = SingleThreadedExecutor(context=context)
        self.executor.add_node(self.merger)
        self.executor.add_node(self.injector)

    def close(self) -> None:
        self.merger.destroy_node()
        self.injector.destroy_node()
        self.executor.shutdown()

    def wait(self, condition: Any, timeout_s: float = 20.0) -> None:
        assert self.spin(self.executor, condition, timeout_s), "timed out"

    def settle(self, seconds: float = 0.3) -> None:
        self.spin(self.executor, lambda: False, seconds)

    def publish(self, topic_robot: str, msg: LocalMap | RendezvousPoses) -> None:
        """Publish ``msg`` on ``topic_robot``'s local map or rendezvous poses topic."""
        pubs = self.maps if isinstance(msg, LocalMap) else self.rendezvous
        pubs[topic_robot].publish(msg)

    def hold(self, messages: RunMessages) -> None:
        """Publish the good messages; wait until the merger holds every robot's."""
        for r in ROBOTS:
            self.publish(r, messages.rendezvous[r])
            self.publish(r, messages.local_maps[r])
        self.wait(
            lambda: (
                set(self.merger.local_maps) == set(ROBOTS)
                and set(self.merger.rendezvous) == set(ROBOTS)
            )
        )

    def start(self, messages: RunMessages) -> JoinedMap:
        """Publish the good messages; return the joined map of them all."""
        self.hold(messages)
        self.wait(lambda: not self.merger.dirty and self.merger.solves > 0 and len(self.joined) > 0)
        self.settle(0.1)
        return self.resolve()

    def resolve(self) -> JoinedMap:
        """Solve again on what the merger holds now; return the joined map it publishes."""
        solves, published = self.merger.solves, len(self.joined)
        self.merger.dirty = True
        self.wait(lambda: self.merger.solves > solves and len(self.joined) > published)
        return self.joined[-1]

    def send_and_wait_drop(self, topic_robot: str, msg: Any, drops: int = 1) -> dict[str, int]:
        """Publish ``msg``; wait until the merger counted ``drops`` more drops; the counts."""
        before = self.merger.drops.total
        self.publish(topic_robot, msg)
        self.wait(lambda: self.merger.drops.total >= before + drops)
        self.settle(0.2)
        return self.merger.drops.as_dict()


def status_values(array: DiagnosticArray, name: str) -> dict[str, str] | None:
    """The values of the status entry ``name`` (``merger``, ``merger/<robot>``), if there."""
    for status in array.status:
        if status.name == name:
            return {kv.key: kv.value for kv in status.values}
    return None


def copied(msg: Any) -> Any:
    """A deep copy of a message to mutate."""
    return copy.deepcopy(msg)
