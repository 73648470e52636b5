"""The merger's requests for a robot's whole local map: its clients of
``/<robot>/smoother/resync`` (std_srvs/Trigger), asking when the merger's policy says a request
may be made (:meth:`~csam_ros.core.merging.policy.MergerPolicy.resync_due`), and the answers:
the smoother's session and the sequence of the whole map it sent
(:func:`~csam_ros.core.exchange.map_updates.resync_answer`), which say whether a whole map of
another session set aside is its own
(:meth:`~csam_ros.core.merging.policy.MergerPolicy.resync_answered`).
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any

from rclpy.node import Node
from std_srvs.srv import Trigger

from csam_ros.core.exchange.map_updates import read_resync_answer
from csam_ros.core.merging.policy import MergerPolicy
from csam_ros.core.merging.policy_inputs import MapTaken
from csam_ros.ros.topics import RESYNC, smoother_service


class ResyncClients:
    """One resync client per robot subscribed to; the policy is read and written under
    ``lock`` (the node's); ``taken(robot, what)`` handles a map an answer (or a smoother's
    absence) made the policy take or drop."""

    def __init__(
        self,
        node: Node,
        policy: MergerPolicy,
        lock: threading.Lock,
        taken: Callable[[str, MapTaken], None],
    ) -> None:
        self.node = node
        self.policy = policy
        self.lock = lock
        self.taken = taken
        self.clients: dict[str, Any] = {}

    def add(self, robot: str) -> None:
        self.clients[robot] = self.node.create_client(Trigger, smoother_service(robot, RESYNC))

    def remove(self, robot: str) -> None:
        """``robot`` is no longer subscribed to: its client goes."""
        client = self.clients.pop(robot, None)
        if client is not None:
            self.node.destroy_client(client)

    def ready(self, robot: str) -> bool:
        """Whether ``robot``'s smoother's resync service is there to ask."""
        client = self.clients.get(robot)
        return client is not None and client.service_is_ready()

    def ask(self, robot: str, reason: str) -> None:
        """Ask ``robot``'s smoother for its whole local map (``reason``: why), unless a request
        stands or its service is not there (then a map of another session set aside is taken
        if the one held is stale)."""
        client = self.clients.get(robot)
        with self.lock:
            if client is None or not self.policy.resync_due(robot):
                return
            if not client.service_is_ready():
                absent = self.policy.smoother_absent(robot)
            else:
                absent = None
                self.policy.resync_asked(robot)
        if absent is not None:
            self.taken(robot, absent)
            return
        self.node.get_logger().info(f"{robot}: asking for its whole local map ({reason})")
        future = client.call_async(Trigger.Request())
        future.add_done_callback(lambda done: self._on_reply(robot, done))

    def _on_reply(self, robot: str, future: Any) -> None:
        """A smoother that had sent nothing yet is asked again later; the session and
        update its answer names go to the policy."""
        reply = future.result()
        if reply is None:
            return
        answer = read_resync_answer(reply.message)
        with self.lock:
            if not reply.success:
                self.policy.resync_refused(robot)
            taken = (
                None
                if answer is None
                else self.policy.resync_answered(robot, reply.success, *answer)
            )
        if taken is not None:
            self.taken(robot, taken)
