"""The merger's rendezvous input: each ``/<robot>/rendezvous_poses`` message's valid
measurements (:func:`~csam_ros.ros.map_messages.rendezvous_log_from_message`) taken into its
policy. A measurement may name only a robot the merger knows (the allow-list, else a robot
found or heard from): one naming another is dropped and counted (``unknown_robot``), and a
message whose measurements are all dropped changes nothing. Without an allow-list, the last
message of a robot with such measurements is kept, and taken again (nothing counted twice)
when a robot it names is found."""

from __future__ import annotations

from typing import Any

from csam_msgs.msg import RendezvousPoses

from csam_ros.core.exchange.validation import UNKNOWN_ROBOT, DropCounter, RefusedMessageError
from csam_ros.ros.map_messages import rendezvous_log_from_message


class RendezvousInput:
    """Rendezvous poses messages into ``merger``'s policy (under its lock); ``merger`` is the
    node (:class:`~csam_ros.nodes.merger.Merger`)."""

    def __init__(self, merger: Any) -> None:
        self.merger = merger
        # each robot's last message naming a robot not known then (no allow-list only)
        self.naming_unknown: dict[str, RendezvousPoses] = {}

    def arrived(self, robot: str, msg: RendezvousPoses, rows: DropCounter | None = None) -> bool:
        """Take the valid measurements of ``msg`` on ``robot``'s topic (the robot's last ones
        if it has none); ``rows``: where its dropped measurements are counted (None: the
        node's counts, with a logged line). Whether the policy took any."""
        merger = self.merger
        policy = merger.policy
        robot_map = policy.local_maps.get(robot)
        counted = rows is None
        rows = DropCounter() if rows is None else rows
        try:
            log = rendezvous_log_from_message(
                msg,
                robot,
                policy.known_robots(),
                robot_map.stamps if robot_map is not None else None,
                merger.config.stamp_tolerance,
                rows,
            )
        except RefusedMessageError as error:
            if counted:
                merger._refuse(robot, "rendezvous poses message", error)
            return False
        if counted and not policy.settings.robots:
            if rows.counts.get(UNKNOWN_ROBOT):
                self.naming_unknown[robot] = msg
            else:
                self.naming_unknown.pop(robot, None)
        with merger._lock:
            held = policy.rendezvous.get(robot)
            notices = policy.rendezvous_arrived(robot, log, rows.as_dict() if counted else {})
            taken = policy.rendezvous.get(robot) is not held
        for notice in notices:
            merger._note(notice)
        return taken

    def robot_found(self, robot: str) -> None:
        """``robot`` was found: the last messages that named it are taken again."""
        for observer, msg in list(self.naming_unknown.items()):
            if any(o.observed_robot == robot for g in msg.measurements for o in g.observations):
                self.arrived(observer, msg, DropCounter())
