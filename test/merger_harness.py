"""A merger node in-process with an injector node, and the messages of a simulated run.

Shared by the merger's boundary tests and its fuzz test: the local map updates and rendezvous
poses two smoothers would publish for the map_joining scenario, built by the core from a
simulated run (as in test/ros/test_map_messages.py), and a harness that publishes them to a
real :class:`~csam_ros.nodes.merger.Merger` over DDS, answers its resync requests as the
smoothers would, and reads its joined map.
"""

from __future__ import annotations

import copy
from collections import Counter
from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace
from functools import partial
from typing import Any

import numpy as np
from csam_msgs.msg import JoinedMap, LocalMapUpdate, RendezvousPoses
from diagnostic_msgs.msg import DiagnosticArray
from log_slices import robot_log_between
from rclpy.duration import Duration
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter

from csam_ros.core.exchange.map_arrays import robot_map_arrays
from csam_ros.core.exchange.map_updates import UpdateSender, resync_answer
from csam_ros.core.joining.pipeline import robot_map_from_local_map
from csam_ros.core.model.log import RobotLog
from csam_ros.core.model.rendezvous import required_stamps
from csam_ros.core.smoothing.local_map_build import build_local_map
from csam_ros.core.smoothing.robot_map import RobotMap
from csam_ros.datasets.scenario import load_scenario
from csam_ros.datasets.simulation import simulate
from csam_ros.ros.map_messages import local_map_update_message, rendezvous_poses_message

ROBOTS = ["robot1", "robot2"]
STAMP_NS = 10**12
MATCH_TIMEOUT_S = 20.0  # s a publisher waits for the merger's subscription to match it


@dataclass(frozen=True)
class RunMessages:
    """What each robot's smoother would publish at the end of a simulated run: its whole
    local map as a complete update (the first of its session), and its rendezvous poses."""

    local_maps: dict[str, LocalMapUpdate]
    rendezvous: dict[str, RendezvousPoses]
    logs: dict[str, RobotLog]
    robot_maps: dict[str, RobotMap]  # the maps of the updates


def complete_update(m: RobotMap, session: int, stamp_ns: int = STAMP_NS) -> LocalMapUpdate:
    """The first update a new smoother (``session``) sends of its map ``m``: the whole map."""
    return local_map_update_message(
        UpdateSender(session).update(robot_map_arrays(m)), m.name, stamp_ns
    )


def resent(msg: LocalMapUpdate, sequence: int | None = None) -> LocalMapUpdate:
    """``msg``, a complete update, sent again as a new one (next ``sequence``), as a resync
    does: the same map, taken again."""
    assert msg.base_sequence == 0, "only a complete update stands on its own"
    out = copy.deepcopy(msg)
    out.sequence = msg.sequence + 1 if sequence is None else sequence
    return out


def poses_of(msg: LocalMapUpdate) -> int:
    """How many poses an update carries (all of the map's for a complete one)."""
    return len(msg.pose_stamps)


def run_messages(
    restart_at: float | None = None,
    names: Mapping[str, str] | None = None,
    end: float | None = None,
    session: int = 1,
) -> RunMessages:
    """The smoothers' last messages of map_joining (seed 2); with ``restart_at``, robot2's
    smoother restarted at that time (a new session), so its map and measurements hold only
    what came after; with ``end``, robot2's cut there (an earlier moment of the run); with
    ``names``, the robots renamed (robot1 and robot2 to their names there)."""
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
    sessions = dict.fromkeys(logs, session)
    if restart_at is not None or end is not None:
        start = -np.inf if restart_at is None else restart_at
        logs["robot2"] = robot_log_between(logs["robot2"], start=start, end=end or np.inf)
    if restart_at is not None:
        sessions["robot2"] = session + 1
    stamps = required_stamps({n: r.rendezvous for n, r in logs.items()})
    maps, rendezvous, robot_maps = {}, {}, {}
    for name, robot_log in logs.items():
        odometry = robot_log.odometry.stamps
        extra = stamps[name][(stamps[name] >= odometry[0]) & (stamps[name] <= odometry[-1])]
        local = build_local_map(robot_log, extra)
        m = robot_maps[name] = robot_map_from_local_map(local)
        maps[name] = complete_update(m, sessions[name])
        indices = np.unique(local.pose_index(extra))
        rendezvous[name] = rendezvous_poses_message(m, STAMP_NS, indices, robot_log.rendezvous)
    return RunMessages(maps, rendezvous, logs, robot_maps)


def joined_view(msg: JoinedMap) -> tuple[Any, ...]:
    """What a joined map says, comparable exactly: features, associations, base nodes."""
    return (
        [(tuple(f.members), f.x, f.y, tuple(f.covariance)) for f in msg.features],
        [(a.a, a.b, a.mahalanobis) for a in msg.associations],
        [(n.robot, n.alignment, n.pose.x, n.pose.y, n.pose.theta) for n in msg.base_nodes],
        [(t.robot, len(t.poses)) for t in msg.trajectories],
    )


def input_publisher(node: Any, topic: Any, robot: str, key: bytes | None) -> Any:
    """A publisher of ``robot``'s merger input ``topic``, signing with ``key`` (if given)."""
    from csam_ros.nodes.common import publisher
    from csam_ros.ros.signing import SignedPublisher

    plain = publisher(node, topic, topic.of(robot))
    return plain if key is None else SignedPublisher(node, plain, key)


class Smoothers:
    """What the robots' smoothers offer a merger, on one node: a publisher of each robot's
    local map updates and its ``/<robot>/smoother/resync`` service, which publishes
    ``answer[robot]()`` (by default ``whole[robot]``, the map a test says the smoother has)
    and names its session and sequence."""

    def __init__(self, node: Any, robots: list[str], key: bytes | None = None) -> None:
        from std_srvs.srv import Trigger

        from csam_ros.ros.topics import LOCAL_MAP_UPDATES, RESYNC, smoother_service

        self.node = node
        self.updates = {r: input_publisher(node, LOCAL_MAP_UPDATES, r, key) for r in robots}
        self.whole: dict[str, LocalMapUpdate] = {}
        self.answer: dict[str, Callable[[], LocalMapUpdate | None]] = {}
        self.resyncs: Counter[str] = Counter()  # requests served, per robot
        self.services = {
            r: node.create_service(
                Trigger, smoother_service(r, RESYNC), partial(self._on_resync, r)
            )
            for r in robots
        }

    def _on_resync(self, robot: str, request: Any, response: Any) -> Any:
        self.resyncs[robot] += 1
        answer = self.answer.get(robot, lambda: self.whole.get(robot))
        msg = answer()
        if msg is not None:
            self.updates[robot].publish(msg)
        response.success = msg is not None
        # as a smoother answers: its session, and the sequence of the whole map sent
        response.message = resync_answer(msg.session, msg.sequence) if msg is not None else ""
        return response

    def destroy(self, robot: str) -> None:
        """The robot's smoother is gone: its publisher and service leave the graph."""
        self.node.destroy_publisher(self.updates.pop(robot))
        self.node.destroy_service(self.services.pop(robot))


class MergerHarness:
    """A real merger and an injector node that publishes on every robot's map topics and
    answers the merger's resync requests (:class:`Smoothers`)."""

    def __init__(
        self, context: Any, spin: Any, key: bytes | None = None, **parameters: Any
    ) -> None:
        """``key``: the team key the injector signs with (None: it does not sign)."""
        import rclpy

        from csam_ros.nodes.merger import Merger
        from csam_ros.ros.topics import JOINED_MAP, RENDEZVOUS_POSES, STATUS

        self.spin = spin
        overrides = {"robots": ROBOTS, "solve_period": 0.02, "solve_wait": 0.0, **parameters}
        self.merger = Merger(
            context=context,
            parameter_overrides=[Parameter(k, value=v) for k, v in overrides.items()],
        )
        self.injector = rclpy.create_node("injector", context=context)
        self.smoothers = Smoothers(self.injector, ROBOTS, key)
        self.rendezvous = {
            r: input_publisher(self.injector, RENDEZVOUS_POSES, r, key) for r in ROBOTS
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

    @property
    def maps(self) -> dict[str, Any]:
        """Each robot's local map update publisher."""
        return self.smoothers.updates

    def close(self) -> None:
        self.merger.destroy_node()
        self.injector.destroy_node()
        self.executor.shutdown()

    def wait(self, condition: Any, timeout_s: float = 20.0) -> None:
        assert self.spin(self.executor, condition, timeout_s), "timed out"

    def settle(self, seconds: float = 0.3) -> None:
        self.spin(self.executor, lambda: False, seconds)

    def publish(self, topic_robot: str, msg: LocalMapUpdate | RendezvousPoses) -> None:
        """Publish ``msg`` on ``topic_robot``'s local map updates or rendezvous poses topic.
        Updates are volatile: one goes out once the merger's subscription (when it has one
        to that robot) matched the publisher, and is waited for until acknowledged."""
        if not isinstance(msg, LocalMapUpdate):
            self.rendezvous[topic_robot].publish(msg)
            return
        pub = self.maps[topic_robot]
        if topic_robot in self.merger.policy.robots:
            self.wait(lambda: pub.get_subscription_count() > 0, MATCH_TIMEOUT_S)
        pub.publish(msg)
        if topic_robot in self.merger.policy.robots:
            assert pub.wait_for_all_acked(Duration(seconds=MATCH_TIMEOUT_S)), "never acknowledged"

    def hold(self, messages: RunMessages) -> None:
        """Publish the good messages (a resync answers with them from now on); wait until the
        merger holds every robot's."""
        for r in ROBOTS:
            self.smoothers.whole[r] = messages.local_maps[r]
            self.publish(r, messages.rendezvous[r])
            self.publish(r, messages.local_maps[r])
        self.wait(
            lambda: (
                set(self.merger.policy.local_maps) == set(ROBOTS)
                and set(self.merger.policy.rendezvous) == set(ROBOTS)
            )
        )

    def start(self, messages: RunMessages) -> JoinedMap:
        """Publish the good messages; return the joined map of them all."""
        self.hold(messages)
        self.wait(
            lambda: (
                not self.merger.policy.dirty
                and self.merger.policy.solves > 0
                and len(self.joined) > 0
            )
        )
        self.settle(0.1)
        return self.resolve()

    def resolve(self) -> JoinedMap:
        """Solve again on what the merger holds now; return the joined map it publishes."""
        solves, published = self.merger.policy.solves, len(self.joined)
        self.merger.policy.inputs_changed()
        self.wait(lambda: self.merger.policy.solves > solves and len(self.joined) > published)
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


def with_robot2(messages: RunMessages, update: Any) -> RunMessages:
    """``messages`` with robot2's local map update replaced by ``update``."""
    return RunMessages(
        {**messages.local_maps, "robot2": update},
        messages.rendezvous,
        messages.logs,
        messages.robot_maps,
    )
