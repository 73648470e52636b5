"""A node's parameter services called over DDS, as ``ros2 param get`` and ``ros2 param set``
call them (import as ``parameter_services``)."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter, parameter_value_to_python
from rclpy.parameter_client import AsyncParameterClient
from waiting import wait_until


class Parameters:
    """A node's parameter services, called from a client node of the test over DDS."""

    def __init__(self, client_node: Any, executor: SingleThreadedExecutor, node: str) -> None:
        self.client = AsyncParameterClient(client_node, node)
        self.executor = executor
        self.node = node
        ready = wait_until(
            self.client.services_are_ready, 60.0, lambda: executor.spin_once(timeout_sec=0.05)
        )
        assert ready, f"{node}: no parameter services"

    def _wait(self, future: Any) -> Any:
        self.executor.spin_until_future_complete(future, timeout_sec=30.0)
        assert future.done(), f"{self.node}: no answer"
        return future.result()

    def get(self, *names: str) -> list[Any]:
        values = self._wait(self.client.get_parameters(list(names))).values
        assert len(values) == len(names)
        return [parameter_value_to_python(value) for value in values]

    def set(self, name: str, value: Any) -> Any:
        """The SetParametersResult of setting one parameter (as `ros2 param set` does)."""
        results = self._wait(self.client.set_parameters([Parameter(name, value=value)])).results
        assert len(results) == 1
        return results[0]


@contextmanager
def client_node(context: Any) -> Iterator[tuple[Any, SingleThreadedExecutor]]:
    """A node of the test's own in ``context`` and an executor that spins it."""
    from rclpy.node import Node

    node = Node("parameter_test_client", context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    try:
        yield node, executor
    finally:
        executor.shutdown()
        node.destroy_node()
