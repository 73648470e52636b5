"""REP-105 frames of a run over DDS, as another program's tf sees them.

Smoothers and the merger run in one process with either a robot driver (this test: odometry
as the integrated pose with no twist and an all-zero covariance, and ``odom -> base_link`` on
/tf) or the simulator. A small tf buffer of this test, fed only from /tf, composes
``<reference>/map -> <robot>/base_link`` through ``<robot>/map -> <robot>/odom`` (smoother)
and ``<robot>/odom -> <robot>/base_link`` (driver or simulator) and finds the joined map's
latest pose of the robot; no frame ever has two parents.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
from node_group import (
    final_joined_result,
    simulation_taken,
    simulator_node,
    smoothers_and_merger,
)
from rclpy.executors import SingleThreadedExecutor

from csam_ros.core.joining.alignment import ALIGNED
from csam_ros.core.model import se2
from csam_ros.datasets.scenario import load_scenario
from csam_ros.datasets.simulation import simulate
from csam_ros.ros.conversions import stamp_to_ns, time_to_ns
from csam_ros.ros.topics import ODOM, TF, declaration

SCENARIO, SEED = "map_joining", 4


class TfBuffer:
    """Every transform received on /tf, by (parent, child) and stamp; a lookup composes the
    chain of parents, each link at the stamp asked for where it has one, else its latest
    (the corrections map -> odom and map -> map, sent when they change and at a rate)."""

    def __init__(self) -> None:
        self.links: dict[tuple[str, str], dict[int, np.ndarray]] = {}
        self.parents: dict[str, set[str]] = {}

    def add(self, msg: Any) -> None:
        for t in msg.transforms:
            r = t.transform.rotation
            pose = np.array(
                [t.transform.translation.x, t.transform.translation.y, 2 * np.arctan2(r.z, r.w)]
            )
            link = (t.header.frame_id, t.child_frame_id)
            self.links.setdefault(link, {})[time_to_ns(t.header.stamp)] = pose
            self.parents.setdefault(t.child_frame_id, set()).add(t.header.frame_id)

    def lookup(self, target: str, source: str, stamp_ns: int) -> np.ndarray:
        """The pose of frame ``source`` in frame ``target`` at ``stamp_ns``."""
        pose, frame = np.zeros(3), source
        while frame != target:
            (parent,) = self.parents[frame]
            stamped = self.links[(parent, frame)]
            link = stamped.get(stamp_ns, stamped[max(stamped)])
            pose, frame = se2.compose(link, pose), parent
        return pose


class Driver:
    """A robot driver for each robot of a simulated run: odometry as the integrated pose (twist
    zero, covariance all zero) and /tf ``odom -> base_link``, with the run's observations."""

    def __init__(self, context: Any, log: Any) -> None:
        import rclpy

        from csam_ros.ros.conversions import log_to_messages

        self.node = rclpy.create_node("driver", context=context)
        self.messages = log_to_messages(log, with_truth=False, with_poses=True)
        self.publishers = {
            m.topic: self.node.create_publisher(type(m.message), m.topic, declaration(m.topic).qos)
            for m in self.messages
        }
        self.tf = self.node.create_publisher(TF.msgtype, TF.name, TF.qos)
        self.next_index = 0

    def ready(self) -> bool:
        return all(p.get_subscription_count() > 0 for p in self.publishers.values())

    def publish(self, count: int) -> bool:
        """Publish the next ``count`` messages; whether all are out."""
        from geometry_msgs.msg import TransformStamped

        for m in self.messages[self.next_index : self.next_index + count]:
            msg = m.message
            if ODOM.robot_of(m.topic) is not None:
                t = msg.twist
                t.twist.linear.x = t.twist.linear.y = t.twist.angular.z = 0.0
                t.covariance = np.zeros(36)
                link = TransformStamped()
                link.header, link.child_frame_id = msg.header, msg.child_frame_id
                p = msg.pose.pose
                link.transform.translation.x, link.transform.translation.y = (
                    p.position.x,
                    p.position.y,
                )
                link.transform.rotation = p.orientation
                self.tf.publish(TF.msgtype(transforms=[link]))
            self.publishers[m.topic].publish(msg)
            self.next_index += 1
        return self.next_index == len(self.messages)


def _run(context: Any, spin: Callable[..., bool], source: str) -> tuple[Any, TfBuffer, dict]:
    """A whole run from ``source`` (driver or simulator) to the merger's final joined map."""
    import rclpy

    from csam_ros.ros.topics import TF as TF_TOPIC

    robots = [r.name for r in load_scenario(SCENARIO).robots]
    smoothers, merger = smoothers_and_merger(context, robots)
    listener = rclpy.create_node("tf_listener", context=context)
    tf = TfBuffer()
    deep = TF_TOPIC.qos.__class__(depth=100_000)  # keep every transform of the run
    listener.create_subscription(TF_TOPIC.msgtype, TF_TOPIC.name, tf.add, deep)
    driver = simulator = None
    if source == "driver":
        driver = Driver(context, simulate(load_scenario(SCENARIO), seed=SEED))
    else:
        simulator = simulator_node(context, SCENARIO, SEED)
    source_node = driver.node if driver is not None else simulator
    nodes = [source_node, merger, listener, *smoothers.values()]
    executor = SingleThreadedExecutor(context=context)
    for n in nodes:
        executor.add_node(n)
    try:
        if driver is not None:
            assert spin(executor, driver.ready, 10)
            spin(executor, lambda: False, 0.5)  # best effort: both sides see each other
            while not driver.publish(10):
                spin(executor, lambda: False, 0.02)
        else:
            assert spin(executor, lambda: simulation_taken(simulator, smoothers), 60)
        spin(executor, lambda: False, 1.0)
        result = final_joined_result(executor, smoothers, merger)
        assert result is not None
        # the joined map's transforms go out after its result is held (serialised with the
        # map, 0.1-1.7 s on a loaded machine): wait for them, then the timers' broadcasts
        joined = result.joined_robots() - {result.reference}
        links = {(f"{result.reference}/map", f"{r}/map") for r in joined}
        spin(executor, lambda: links <= set(tf.links), 10)
        spin(executor, lambda: False, 0.5)
        defaulted = {r: s.filter.defaulted.as_dict() for r, s in smoothers.items()}
        return merger.policy.last_result, tf, defaulted
    finally:
        for n in nodes:
            n.destroy_node()
        executor.shutdown()


@pytest.mark.parametrize("source", ["driver", "simulator"])
def test_tf_composes_the_joined_pose_through_odom_and_each_frame_has_one_parent(
    ros_context: Any, spin: Callable[..., bool], source: str
) -> None:
    result, tf, defaulted = _run(ros_context, spin, source)
    assert {child: len(parents) for child, parents in tf.parents.items()} == {
        child: 1 for child in tf.parents
    }
    assert set(tf.links) == {
        ("robot1/map", "robot2/map"),
        *((f"{r}/map", f"{r}/odom") for r in ("robot1", "robot2")),
        *((f"{r}/odom", f"{r}/base_link") for r in ("robot1", "robot2")),
    }
    robot = result.robots["robot2"]
    assert robot.alignment == ALIGNED and result.reference_frame == "robot1/map"
    stamp_ns = stamp_to_ns(robot.stamps[-1])
    assert stamp_ns in tf.links[("robot2/odom", "robot2/base_link")]  # a matching stamp
    composed = tf.lookup("robot1/map", "robot2/base_link", stamp_ns)
    joined = np.asarray(robot.poses_joined[-1])
    np.testing.assert_allclose(composed[:2], joined[:2], atol=1e-6)
    assert abs(se2.wrap_angle(composed[2] - joined[2])) < 1e-6
    if source == "driver":  # no covariance in the driver's odometry: the defaults, counted
        assert all(counts for counts in defaulted.values())
