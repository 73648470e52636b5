"""The merger's joined maps put out: ``/csam/joined_map`` with its ``/tf`` transforms, then its
summary (``summary_path``) and ``/csam/markers``, both built by the message process
(:mod:`csam_ros.message_process`); and ``/csam/joined_map/provisional``."""

from __future__ import annotations

import threading
from collections.abc import Callable, Mapping
from pathlib import Path

from rclpy.node import Node

from csam_ros.core.joining.result import CsamResult, MergerStats, RunSummary, write_summary_text
from csam_ros.core.joining.warm_start import carried_forward
from csam_ros.core.merging.policy import ProvisionalMap
from csam_ros.message_process import MarkersRequest, MessageProcess
from csam_ros.nodes.common import publisher
from csam_ros.ros.map_messages import robot_map_transforms, serialized_joined_map
from csam_ros.ros.topics import JOINED_MAP, MARKERS, PROVISIONAL_MAP, TF


class MergerOutput:
    """The merger node's publishers of joined maps. Every publication holds ``lock`` and is
    not made once ``stopping`` is set (the node destroys itself holding the lock)."""

    def __init__(
        self,
        node: Node,
        summary_path: Path | None,
        lock: threading.Lock,
        stopping: threading.Event,
    ) -> None:
        self.node = node
        self.summary_path = summary_path
        self.lock = lock
        self.stopping = stopping
        self.message_process = MessageProcess(
            on_failure=lambda error: node.get_logger().warning(f"message process: {error}")
        )
        self.joined_pub = publisher(node, JOINED_MAP)
        self.provisional_pub = publisher(node, PROVISIONAL_MAP)
        self.markers_pub = publisher(node, MARKERS)
        self.tf_pub = publisher(node, TF)

    def joined_map(
        self,
        result: CsamResult,
        stamps: dict[str, int],
        robots: tuple[str, ...],
        stats: MergerStats | None = None,
    ) -> None:
        """Publish a joined map and its transforms, then write the summary (with ``stats``)
        and publish the markers (the summary is written even when the node stops meanwhile:
        the map it describes is out)."""
        stamp_ns = max(stamps.values())
        joined_map = serialized_joined_map(result, stamp_ns, stamps, robots)
        transforms = robot_map_transforms(result, stamp_ns)
        with self.lock:
            if self.stopping.is_set():
                return
            self.joined_pub.publish(joined_map)
            self.tf_pub.publish(transforms)
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

    def provisional_map(
        self, due: ProvisionalMap, outdated: Callable[[Mapping[str, int]], bool]
    ) -> bool:
        """Build and publish the provisional map ``due`` unless ``outdated(stamps)`` says a
        solved joined map holds its local maps by then; whether it went out."""
        result = carried_forward(due.last, due.maps, due.stamp_tolerance)
        stamps = due.stamps
        joined_map = serialized_joined_map(result, max(stamps.values()), stamps, due.robots)
        with self.lock:
            if self.stopping.is_set() or outdated(stamps):
                return False
            self.provisional_pub.publish(joined_map)
        return True
