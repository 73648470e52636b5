"""The merger's requests for a robot's whole local map: its clients of
``/<robot>/smoother/resync`` (std_srvs/Trigger), asking when the merger's policy says a request
may be made (:meth:`~csam_ros.core.merging.policy.MergerPolicy.resync_due`)."""

from __future__ import annotations

import threading
from typing import Any

from rclpy.node import Node
from std_srvs.srv import Trigger

from csam_ros.core.merging.policy import MergerPolicy
from csam_ros.ros.topics import RESYNC, smoother_service


class ResyncClients:
    """One resync client per robot subscribed to; the policy is read and written under
    ``lock`` (the node's)."""

    def __init__(self, node: Node, policy: MergerPolicy, lock: threading.Lock) -> None:
        self.node = node
        self.policy = policy
        self.lock = lock
        self.clients: dict[str, Any] = {}

    def add(self, robot: str) -> None:
        self.clients[robot] = self.node.create_client(Trigger, smoother_service(robot, RESYNC))

    def ask(self, robot: str, reason: str) -> None:
        """Ask ``robot``'s smoother for its whole local map (``reason``: why), unless a request
        stands or its service is not there yet."""
        client = self.clients.get(robot)
        with self.lock:
            if client is None or not self.policy.resync_due(robot):
                return
            if not client.service_is_ready():
                return
            self.policy.resync_asked(robot)
        self.node.get_logger().info(f"{robot}: asking for its whole local map ({reason})")
        future = client.call_async(Trigger.Request())
        future.add_done_callback(lambda done: self._on_reply(robot, done))

    def _on_reply(self, robot: str, future: Any) -> None:
        """A smoother that had sent nothing yet is asked again later."""
        reply = future.result()
        if reply is not None and not reply.success:
            with self.lock:
                self.policy.resync_refused(robot)
