"""merger: joins every robot's local map by C-SAM and publishes the joined map.

Subscribes to ``/<robot>/local_map`` and ``/<robot>/rendezvous_poses`` (transient local) of
every robot in ``robots`` (the first one is the reference). When a local map or rendezvous part
changes it re-solves (at most every ``solve_period`` wall-clock seconds) with the core's
:func:`~csam_ros.core.csam.join_maps`, then writes ``summary_path`` (when set) and publishes
``/csam/joined_map`` and ``/csam/markers`` (transient local) and ``/csam/status``.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
from csam_msgs.msg import LocalMap, RendezvousPoses
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.node import Node

from csam_ros.core.csam import CsamConfig, join_maps
from csam_ros.core.result import CsamResult, MergerStats, RunSummary
from csam_ros.core.validation import DropCounter
from csam_ros.nodes.common import (
    declare,
    declare_settings,
    publisher,
    run_node,
    steady_clock,
    subscribe,
)
from csam_ros.ros.conversions import time_to_ns
from csam_ros.ros.map_messages import (
    LocalMapError,
    joined_map_message,
    rendezvous_log_from_message,
    robot_map_from_message,
)
from csam_ros.ros.markers import joined_map_markers
from csam_ros.ros.topics import JOINED_MAP, LOCAL_MAP, MARKERS, RENDEZVOUS_POSES, STATUS


class Merger(Node):
    """C-SAM merger node (see the module docstring)."""

    def __init__(self, **node_options: Any) -> None:
        super().__init__("merger", **node_options)
        self.robots: list[str] = list(
            declare(self, "robots", ["robot1", "robot2"], "robot names; the first is the reference")
        )
        summary = declare(self, "summary_path", "", "write summary.json here after each solve")
        self.summary_path = Path(summary) if summary else None
        period = declare(
            self, "solve_period", 0.5, "minimum wall-clock seconds between solves", 0.0, 3600.0
        )
        # online, a rendezvous stamp may reach the merger before the observed robot's map has
        # its pose: leave such a measurement out until the next solve instead of failing
        self.config = declare_settings(self, CsamConfig, CsamConfig(skip_missing_poses=True))
        self.local_maps: dict[str, LocalMap] = {}
        self.rendezvous: dict[str, RendezvousPoses] = {}
        self.drops = DropCounter()
        self.dirty = False
        self.last_result: CsamResult | None = None
        self.solves = 0
        self.solve_seconds = 0.0
        self.last_error = ""
        for robot in self.robots:
            subscribe(self, LOCAL_MAP, self.on_local_map, LOCAL_MAP.of(robot))
            subscribe(self, RENDEZVOUS_POSES, self.on_rendezvous_poses, RENDEZVOUS_POSES.of(robot))
        self.joined_pub = publisher(self, JOINED_MAP)
        self.markers_pub = publisher(self, MARKERS)
        self.status_pub = publisher(self, STATUS)
        self.create_timer(max(period, 0.01), self.on_timer, clock=steady_clock())

    def _known(self, robot: str) -> bool:
        if robot not in self.robots:
            self.drops.add("unknown_robot")
            self.get_logger().warning(f"dropped a message of unknown robot {robot!r}")
            return False
        return True

    def on_local_map(self, msg: LocalMap) -> None:
        if self._known(msg.robot):
            self.local_maps[msg.robot] = msg
            self.dirty = True

    def on_rendezvous_poses(self, msg: RendezvousPoses) -> None:
        if self._known(msg.robot):
            self.rendezvous[msg.robot] = msg
            self.dirty = True

    def on_timer(self) -> None:
        if self.dirty:
            self.dirty = False
            self.solve()
        self.publish_status()

    def solve(self) -> None:
        reference = self.robots[0]
        if reference not in self.local_maps:
            return
        start = time.perf_counter()
        maps, logs = [], {}
        for robot in self.robots:
            msg = self.local_maps.get(robot)
            if msg is None:
                continue
            try:
                maps.append(robot_map_from_message(msg))
            except (LocalMapError, ValueError) as err:
                self.drops.add("malformed_local_map")
                self.get_logger().warning(f"dropped the local map of {robot}: {err}")
                if robot == reference:
                    return
                continue
            if robot in self.rendezvous:
                logs[robot] = rendezvous_log_from_message(self.rendezvous[robot])
        try:
            result = join_maps(maps, logs, self.config)
        except (ValueError, np.linalg.LinAlgError) as err:
            self.last_error = str(err)
            self.drops.add("failed_solve")
            self.get_logger().error(f"C-SAM failed: {err}")
            return
        self.last_error = ""
        self.solve_seconds = time.perf_counter() - start
        self.solves += 1
        result.timing_s["merger_solve"] = self.solve_seconds
        self.last_result = result
        stamps = {r: time_to_ns(m.header.stamp) for r, m in self.local_maps.items()}
        if self.summary_path is not None:
            merger = MergerStats(dropped=self.drops.as_dict(), solves=self.solves)
            RunSummary(result, merger=merger).write(self.summary_path)
        newest = max(stamps.values())
        self.joined_pub.publish(joined_map_message(result, newest, stamps, self.robots))
        self.markers_pub.publish(joined_map_markers(result, self.get_clock().now().to_msg()))

    def publish_status(self) -> None:
        array = DiagnosticArray()
        array.header.stamp = self.get_clock().now().to_msg()
        result = self.last_result
        for robot in self.robots:
            r = result.robots.get(robot) if result is not None else None
            if robot not in self.local_maps:
                alignment = "pending: no local map received"
            elif r is None:
                alignment = "pending: not solved yet"
            else:
                alignment = r.alignment
            ok = alignment in ("reference", "aligned")
            values = {
                "alignment": alignment,
                "poses": len(r.stamps) if r is not None else 0,
                "solve_seconds": round(self.solve_seconds, 4),
            }
            array.status.append(
                DiagnosticStatus(
                    level=DiagnosticStatus.OK if ok else DiagnosticStatus.WARN,
                    name=f"merger/{robot}",
                    hardware_id=robot,
                    message=alignment,
                    values=[KeyValue(key=k, value=str(v)) for k, v in values.items()],
                )
            )
        values = {
            "solves": self.solves,
            "features": len(result.features) if result is not None else 0,
            "associations": len(result.associations) if result is not None else 0,
            "solve_seconds": round(self.solve_seconds, 4),
            "dropped": self.drops.total,
            "last_error": self.last_error,
            **{f"dropped/{k}": v for k, v in self.drops.as_dict().items()},
        }
        array.status.append(
            DiagnosticStatus(
                level=DiagnosticStatus.OK if not self.last_error else DiagnosticStatus.ERROR,
                name="merger",
                message=f"{values['solves']} solves, {values['associations']} associations",
                values=[KeyValue(key=k, value=str(v)) for k, v in values.items()],
            )
        )
        self.status_pub.publish(array)


def main(args: list[str] | None = None) -> int:
    return run_node(Merger, args, __doc__)


if __name__ == "__main__":
    sys.exit(main())
