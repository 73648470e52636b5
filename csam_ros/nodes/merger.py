"""merger: joins every robot's local map by C-SAM and publishes the joined map.

Subscribes to ``/<robot>/local_map`` and ``/<robot>/rendezvous_poses`` (transient local) of
every robot in ``robots`` (the first one is the reference). When a local map or rendezvous part
changes it re-solves (at most every ``solve_period`` wall-clock seconds) with the core's
:func:`~csam_ros.core.csam.join_maps`, then writes ``summary_path`` (when set) and publishes
``/csam/joined_map`` and ``/csam/markers`` (transient local) and ``/csam/status``.

The topic says which robot a message belongs to. Every message is checked whole when it
arrives (``ros/map_messages.py``); a malformed one, or one naming another robot than its
topic's, is dropped and counted once under its reason, and the robot's last valid local map
and rendezvous measurements stay in use. Single bad rendezvous measurements are dropped and
the rest of their message kept. A robot whose new local map starts later or holds fewer poses
than its last one has had its smoother restarted: the new map is its current truth and
replaces the old one, and the restart and the poses lost are logged once and counted in
``/csam/status`` and the summary.
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
from csam_ros.core.joining import RobotMap
from csam_ros.core.log import RendezvousLog
from csam_ros.core.result import CsamResult, MergerStats, RunSummary
from csam_ros.core.validation import FAILED_SOLVE, DropCounter
from csam_ros.nodes.common import (
    declare,
    declare_settings,
    guarded,
    publisher,
    run_node,
    steady_clock,
    subscribe,
)
from csam_ros.ros.conversions import time_to_ns
from csam_ros.ros.map_messages import (
    RefusedMessageError,
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
        # the last valid local map (and its message's stamp) and rendezvous measurements
        self.local_maps: dict[str, RobotMap] = {}
        self.local_map_stamps: dict[str, int] = {}
        self.rendezvous: dict[str, RendezvousLog] = {}
        self.drops = DropCounter()
        self.restarts: dict[str, int] = {}
        self.restart_poses_lost: dict[str, int] = {}
        self.dirty = False
        self.last_result: CsamResult | None = None
        self.solves = 0
        self.solve_seconds = 0.0
        self.last_error = ""
        on_map = guarded(self, self.drops, self.on_local_map)
        on_rendezvous = guarded(self, self.drops, self.on_rendezvous_poses)
        for robot in self.robots:  # each subscription knows its robot from its topic
            subscribe(self, LOCAL_MAP, lambda m, r=robot: on_map(r, m), LOCAL_MAP.of(robot))
            subscribe(
                self,
                RENDEZVOUS_POSES,
                lambda m, r=robot: on_rendezvous(r, m),
                RENDEZVOUS_POSES.of(robot),
            )
        self.joined_pub = publisher(self, JOINED_MAP)
        self.markers_pub = publisher(self, MARKERS)
        self.status_pub = publisher(self, STATUS)
        self.create_timer(
            max(period, 0.01), guarded(self, self.drops, self.on_timer), clock=steady_clock()
        )

    def _refuse(self, robot: str, what: str, error: RefusedMessageError) -> None:
        self.drops.add(error.reason)
        self.get_logger().warning(f"dropped a {what} on {robot}'s topic ({error.reason}): {error}")

    def on_local_map(self, robot: str, msg: LocalMap) -> None:
        """Keep the local map on ``robot``'s topic if it is valid (else the last valid one)."""
        try:
            new = robot_map_from_message(msg, robot)
        except RefusedMessageError as error:
            self._refuse(robot, "local map", error)
            return
        old = self.local_maps.get(robot)
        if old is not None:
            self._note_restart(robot, old, new)
        self.local_maps[robot] = new
        self.local_map_stamps[robot] = time_to_ns(msg.header.stamp)
        self.dirty = True

    def _note_restart(self, robot: str, old: RobotMap, new: RobotMap) -> None:
        """Log and count once a new map that starts later or holds fewer poses than the last.

        The new map replaces the old one all the same: it is the robot's current truth (a
        restarted smoother has a new frame G_r), while the old one is frozen history that its
        rendezvous measurements and later poses no longer refer to. What was lost is reported.
        """
        tolerance = self.config.stamp_tolerance
        later = new.stamps[0] > old.stamps[0] + tolerance
        if not (later or len(new.stamps) < len(old.stamps)):
            return
        gap = np.abs(old.stamps[:, None] - new.stamps[None, :]).min(axis=1) > tolerance
        lost = int(gap.sum())
        self.restarts[robot] = self.restarts.get(robot, 0) + 1
        self.restart_poses_lost[robot] = self.restart_poses_lost.get(robot, 0) + lost
        self.get_logger().warning(
            f"{robot}: smoother restarted: the new local map holds {len(new.stamps)} poses from "
            f"{new.stamps[0]:.3f} s, the last one held {len(old.stamps)} from "
            f"{old.stamps[0]:.3f} s to {old.stamps[-1]:.3f} s; {lost} poses of its history are "
            "lost and no longer joined"
        )

    def on_rendezvous_poses(self, robot: str, msg: RendezvousPoses) -> None:
        """Keep the valid rendezvous measurements on ``robot``'s topic (the last ones if none)."""
        robot_map = self.local_maps.get(robot)
        rows = DropCounter()
        try:
            log = rendezvous_log_from_message(
                msg,
                robot,
                self.robots,
                robot_map.stamps if robot_map is not None else None,
                self.config.stamp_tolerance,
                rows,
            )
        except RefusedMessageError as error:
            self._refuse(robot, "rendezvous poses message", error)
            return
        for reason, n in rows.as_dict().items():
            self.drops.add(reason, n)
        if rows.total:
            self.get_logger().warning(
                f"dropped rendezvous measurements on {robot}'s topic: {rows.as_dict()}"
            )
        if len(log.stamps) == 0 and robot in self.rendezvous:
            return  # a message with no usable measurement never replaces usable ones
        self.rendezvous[robot] = log
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
        maps = [self.local_maps[r] for r in self.robots if r in self.local_maps]
        logs = {r: self.rendezvous[r] for r in self.robots if r in self.rendezvous}
        try:
            result = join_maps(maps, logs, self.config)
            fault = _non_finite(result)
            if fault:
                raise ValueError(f"the joined map has non-finite numbers ({fault})")
        except Exception as err:  # noqa: BLE001 - a solve never takes the merger down
            self.last_error = f"{type(err).__name__}: {err}"
            self.drops.add(FAILED_SOLVE)
            self.get_logger().error(f"C-SAM failed, the last joined map stays: {self.last_error}")
            return
        self.last_error = ""
        self.solve_seconds = time.perf_counter() - start
        self.solves += 1
        result.timing_s["merger_solve"] = self.solve_seconds
        self.last_result = result
        stamps = dict(self.local_map_stamps)
        if self.summary_path is not None:
            RunSummary(result, merger=self.stats()).write(self.summary_path)
        newest = max(stamps.values())
        self.joined_pub.publish(joined_map_message(result, newest, stamps, self.robots))
        self.markers_pub.publish(joined_map_markers(result, self.get_clock().now().to_msg()))

    def stats(self) -> MergerStats:
        """What the merger counted so far, as the summary carries it."""
        return MergerStats(
            dropped=self.drops.as_dict(),
            solves=self.solves,
            restarts=dict(self.restarts),
            restart_poses_lost=dict(self.restart_poses_lost),
        )

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
                "restarts": self.restarts.get(robot, 0),
                "restart_poses_lost": self.restart_poses_lost.get(robot, 0),
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
            "restarts": sum(self.restarts.values()),
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


def _non_finite(result: CsamResult) -> str:
    """The first part of a result holding a non-finite number ("" when none)."""
    for name, r in result.robots.items():
        for part in ("base_node", "base_node_cov", "poses_joined", "sigma_phi_joined"):
            value = getattr(r, part)
            if value is not None and not np.all(np.isfinite(np.asarray(value, dtype=float))):
                return f"{name} {part}"
    for f in result.features:
        if not (np.all(np.isfinite(f.xy)) and np.all(np.isfinite(f.cov))):
            return f"feature {'+'.join(f.members)}"
    return ""


def main(args: list[str] | None = None) -> int:
    return run_node(Merger, args, __doc__)


if __name__ == "__main__":
    sys.exit(main())
