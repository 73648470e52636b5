"""The executor the nodes spin (``nodes/common.py: make_executor``), over real DDS."""

from __future__ import annotations

from typing import Any

import pytest
from std_msgs.msg import String

from csam_ros.nodes.common import EXECUTOR_VARIABLE, make_executor


@pytest.mark.parametrize("kind", ["events", "single", None])
def test_the_executor_serves_subscriptions_and_timers(
    ros_context: Any, spin: Any, monkeypatch: pytest.MonkeyPatch, kind: str | None
) -> None:
    import rclpy
    from rclpy.executors import SingleThreadedExecutor

    if kind is None:
        monkeypatch.delenv(EXECUTOR_VARIABLE, raising=False)
    else:
        monkeypatch.setenv(EXECUTOR_VARIABLE, kind)
    executor = make_executor(ros_context)
    assert isinstance(executor, SingleThreadedExecutor) == (kind == "single")
    node = rclpy.create_node("executor_test", context=ros_context)
    taken: list[str] = []
    ticks: list[int] = []
    node.create_subscription(String, "/executor_test", lambda m: taken.append(m.data), 10)
    node.create_timer(0.05, lambda: ticks.append(1))
    publisher = node.create_publisher(String, "/executor_test", 10)
    executor.add_node(node)
    try:
        assert spin(executor, lambda: publisher.get_subscription_count() > 0)
        publisher.publish(String(data="hello"))
        assert spin(executor, lambda: taken == ["hello"] and len(ticks) >= 2)
    finally:
        executor.shutdown()
        node.destroy_node()


def test_an_unknown_executor_is_a_clear_error(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(EXECUTOR_VARIABLE, "multi")
    with pytest.raises(ValueError, match="CSAM_EXECUTOR='multi'"):
        make_executor()
