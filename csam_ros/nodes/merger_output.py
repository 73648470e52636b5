"""The merger's outputs: ``/csam/joined_map`` with its ``/tf`` transforms and each joined
robot's ``/<robot>/pose``, then its summary (``summary_path``) and ``/csam/markers``, both
built by the message process (:mod:`csam_ros.message_process`); ``/csam/joined_map/provisional``
with the poses it places; and the status on ``/csam/status`` and ``/diagnostics``."""

from __future__ import annotations

import threading
from collections.abc import Callable, Mapping
from pathlib import Path

from builtin_interfaces.msg import Time
from rclpy.node import Node
from rclpy.publisher import Publisher

from csam_ros.core.exchange.validation import CALLBACK_ERROR, DropCounter
from csam_ros.core.joining.result import CsamResult, MergerStats, RunSummary, write_summary_text
from csam_ros.core.joining.warm_start import carried_forward
from csam_ros.core.merging.policy import MergerPolicy
from csam_ros.core.merging.policy_inputs import ProvisionalMap
from csam_ros.core.merging.robot_poses import LatestPoseCovariances, robot_poses
from csam_ros.core.merging.status import MergerStatus
from csam_ros.core.smoothing.robot_map import RobotMap
from csam_ros.message_process import MarkersRequest, MessageProcess
from csam_ros.nodes.common import publisher
from csam_ros.ros.map_messages import robot_map_transforms, serialized_joined_map
from csam_ros.ros.merger_reports import diagnostics_array, pose_message, status_array
from csam_ros.ros.topics import (
    DIAGNOSTICS,
    JOINED_MAP,
    MARKERS,
    POSE,
    PROVISIONAL_MAP,
    STATUS,
    TF,
)


class MergerOutput:
    """The merger node's publishers. Every publication of a joined map holds ``lock`` and is
    not made once ``stopping`` is set (the node destroys itself holding the lock); a fault in
    making the robots' poses is logged and counted in ``drops`` (``callback_error``), and the
    rest goes out."""

    def __init__(
        self,
        node: Node,
        summary_path: Path | None,
        lock: threading.Lock,
        stopping: threading.Event,
        drops: DropCounter,
    ) -> None:
        self.node = node
        self.summary_path = summary_path
        self.lock = lock
        self.stopping = stopping
        self.drops = drops
        self.message_process = MessageProcess(
            on_failure=lambda error: node.get_logger().warning(f"message process: {error}")
        )
        self.joined_pub = publisher(node, JOINED_MAP)
        self.provisional_pub = publisher(node, PROVISIONAL_MAP)
        self.markers_pub = publisher(node, MARKERS)
        self.tf_pub = publisher(node, TF)
        self.status_pub = publisher(node, STATUS)
        self.diagnostics_pub = publisher(node, DIAGNOSTICS)
        self.pose_pubs: dict[str, Publisher] = {}
        self.covariances = LatestPoseCovariances()

    def add_robot(self, robot: str) -> None:
        """A robot is joined from now on: its ``/<robot>/pose`` publisher (call in the
        executor's thread, before any of its maps can be joined)."""
        if robot not in self.pose_pubs:
            self.pose_pubs = {**self.pose_pubs, robot: publisher(self.node, POSE, POSE.of(robot))}

    def status(self, status: MergerStatus, stamp: Time) -> None:
        """Publish ``status`` on ``/csam/status`` and ``/diagnostics``."""
        self.status_pub.publish(status_array(status, stamp))
        self.diagnostics_pub.publish(diagnostics_array(status, stamp))

    def joined_map(
        self,
        result: CsamResult,
        stamps: dict[str, int],
        robots: tuple[str, ...],
        stats: MergerStats | None = None,
        maps: Mapping[str, RobotMap] | None = None,
    ) -> None:
        """Publish a joined map and its transforms, and the poses of its robots from their
        newest local ``maps`` (when given); then write the summary (with ``stats``) and publish
        the markers (the summary is written even when the node stops meanwhile: the map it
        describes is out)."""
        stamp_ns = max(stamps.values())
        joined_map = serialized_joined_map(result, stamp_ns, stamps, robots)
        transforms = robot_map_transforms(result, stamp_ns)
        with self.lock:
            if self.stopping.is_set():
                return
            self.joined_pub.publish(joined_map)
            self.tf_pub.publish(transforms)
        if maps is not None:
            self.poses(result, maps)
        summary = (
            RunSummary(result, merger=stats)
            if self.summary_path is not None and stats is not None
            else None
        )
        now_ns = self.node.get_clock().now().nanoseconds
        out = self.message_process.build(MarkersRequest(result, now_ns, summary))
        with self.lock:
            if self.summary_path is not None and out.summary_text is not None:
                write_summary_text(self.summary_path, out.summary_text)
            if not self.stopping.is_set():
                self.markers_pub.publish(out.markers)

    def resumed(self, policy: MergerPolicy) -> None:
        """Publish the joined map of a merger state taken up (``policy.last_result``; none
        when it has none), and the poses of its robots."""
        if policy.last_result is not None:
            stamps, robots = dict(policy.local_map_stamps), tuple(policy.robots)
            self.joined_map(policy.last_result, stamps, robots, maps=policy.local_maps)

    def provisional_map(
        self, due: ProvisionalMap, outdated: Callable[[Mapping[str, int]], bool]
    ) -> bool:
        """Build and publish the provisional map ``due`` unless ``outdated(stamps)`` says a
        solved joined map holds its local maps by then, and the poses it places; whether it
        went out."""
        result = carried_forward(due.last, due.maps, due.stamp_tolerance)
        stamps = due.stamps
        joined_map = serialized_joined_map(result, max(stamps.values()), stamps, due.robots)
        with self.lock:
            if self.stopping.is_set() or outdated(stamps):
                return False
            self.provisional_pub.publish(joined_map)
        self.poses(result, {m.name: m for m in due.maps})
        return True

    def poses(self, result: CsamResult, maps: Mapping[str, RobotMap]) -> None:
        """Publish ``/<robot>/pose`` of each robot ``result`` joined, from its newest local
        map in ``maps`` (:func:`~csam_ros.core.merging.robot_poses.robot_poses`)."""
        try:
            poses = robot_poses(result, maps, self.covariances)
        except Exception as error:  # noqa: BLE001 - the joined map's other outputs go on
            self.drops.add(CALLBACK_ERROR)
            self.node.get_logger().error(f"robot poses: {type(error).__name__}: {error}")
            return
        messages = [(p.robot, pose_message(p, result.reference_frame)) for p in poses]
        pubs = self.pose_pubs
        with self.lock:
            if self.stopping.is_set():
                return
            for robot, msg in messages:
                if robot in pubs:
                    pubs[robot].publish(msg)
