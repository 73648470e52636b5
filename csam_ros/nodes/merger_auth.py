"""The merger's check of signed inputs (``team_key_file``; :mod:`csam_ros.ros.signing`): a
robot's local map update or rendezvous poses message is handed on only once the signature of
exactly that message came on its sibling topic, in either order. One whose signature has not
come ``AUTH_WAIT_S`` after it (none was sent, or it was made with another key) is dropped and
counted (``unauthenticated``). What is held is bounded per robot: the newest
``KEPT_SIGNATURES`` signatures, the oldest message waiting dropped (counted) beyond
``WAITING_MESSAGES``."""

from __future__ import annotations

import functools
import time
from collections import OrderedDict, deque
from collections.abc import Callable
from typing import Any

from rclpy.node import Node
from rclpy.subscription import Subscription
from std_msgs.msg import String

from csam_ros.core.exchange.validation import UNAUTHENTICATED, DropCounter
from csam_ros.nodes.common import guarded
from csam_ros.ros.signing import SIGNATURE_TOPICS, signature

AUTH_WAIT_S = 2.0  # s a message waits for its signature
KEPT_SIGNATURES = 64  # per robot and topic
WAITING_MESSAGES = 16  # per robot and topic


class _Topic:
    """One robot's signed topic: signatures come, messages wait for theirs."""

    def __init__(self, on_message: Callable[[Any], None]) -> None:
        self.on_message = on_message
        self.signatures: OrderedDict[str, None] = OrderedDict()
        self.waiting: deque[tuple[float, str, Any]] = deque()


class SignedInputs:
    """The signature subscriptions and waiting messages of every robot subscribed to (with
    no key: none, every message handed on)."""

    def __init__(self, node: Node, key: bytes | None, drops: DropCounter) -> None:
        self.node = node
        self.key = key
        self.drops = drops
        self.topics: dict[tuple[str, str], _Topic] = {}
        self.subscriptions: dict[str, list[Subscription]] = {}

    def gate(
        self, robot: str, topic_name: str, on: Callable[[str, Any], None]
    ) -> Callable[[Any], Any]:
        """The callback of ``robot``'s input topic ``topic_name`` (absolute): hands each
        message to ``on(robot, message)``, with a key once its signature came (guarded)."""
        on_message = functools.partial(on, robot)
        if self.key is None:
            return on_message
        topic = self.topics[(robot, topic_name)] = _Topic(on_message)
        kind = SIGNATURE_TOPICS[topic_name.rsplit("/", 1)[-1]]
        subscription = self.node.create_subscription(
            String,
            f"{topic_name}_hmac",
            guarded(self.node, self.drops, lambda s: self._on_signature(topic, s.data)),
            kind.subscription_qos,
        )
        self.subscriptions.setdefault(robot, []).append(subscription)
        return guarded(self.node, self.drops, lambda msg: self._on_message(topic, msg))

    def remove(self, robot: str) -> None:
        """``robot`` is no longer subscribed to: its signature subscriptions go."""
        for subscription in self.subscriptions.pop(robot, []):
            self.node.destroy_subscription(subscription)
        self.topics = {k: t for k, t in self.topics.items() if k[0] != robot}

    def _on_signature(self, topic: _Topic, text: str) -> None:
        for i, (_, expected, msg) in enumerate(topic.waiting):
            if expected == text:
                del topic.waiting[i]
                topic.on_message(msg)
                return
        topic.signatures[text] = None
        while len(topic.signatures) > KEPT_SIGNATURES:
            topic.signatures.popitem(last=False)

    def _on_message(self, topic: _Topic, msg: Any) -> None:
        assert self.key is not None
        expected = signature(self.key, msg)
        if expected in topic.signatures:
            del topic.signatures[expected]
            topic.on_message(msg)
            return
        topic.waiting.append((time.monotonic() + AUTH_WAIT_S, expected, msg))
        while len(topic.waiting) > WAITING_MESSAGES:
            topic.waiting.popleft()
            self._dropped()

    def expire(self) -> None:
        """Drop (and count) the messages whose signature did not come in time."""
        now = time.monotonic()
        for topic in self.topics.values():
            while topic.waiting and topic.waiting[0][0] <= now:
                topic.waiting.popleft()
                self._dropped()

    def _dropped(self) -> None:
        self.drops.add(UNAUTHENTICATED)
        self.node.get_logger().warning(
            f"dropped a message without a valid signature ({UNAUTHENTICATED}): not signed "
            "with the team key"
        )
