"""In-process smoothers and a merger for tests: one smoother per robot that publishes only
when asked (``solve_and_publish``), and a merger that solves every 50 ms."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from rclpy.parameter import Parameter


def smoothers_and_merger(
    context: Any,
    robots: list[str],
    extra_smoother: list[Parameter] | None = None,
    summary_path: Path | None = None,
) -> tuple[dict[str, Any], Any]:
    from csam_ros.nodes.merger import Merger
    from csam_ros.nodes.smoother import Smoother

    smoothers = {
        r: Smoother(
            context=context,
            namespace=r,
            parameter_overrides=[
                Parameter("robots", value=robots),
                Parameter("publish_period", value=1000.0),
                *(extra_smoother or []),
            ],
        )
        for r in robots
    }
    merger = Merger(
        context=context,
        parameter_overrides=[
            Parameter("robots", value=robots),
            Parameter("solve_period", value=0.05),
            Parameter("solve_wait", value=0.0),
            *([Parameter("summary_path", value=str(summary_path))] if summary_path else []),
        ],
    )
    return smoothers, merger


def final_joined_result(
    executor: Any, smoothers: dict[str, Any], merger: Any, timeout_s: float = 60.0
) -> Any:
    """Every smoother's converged map published, then the merger's result once it holds all of
    them (each robot with as many poses as its smoother's map); None when that takes longer."""
    from waiting import wait_until

    for smoother in smoothers.values():
        smoother.solve_and_publish(converge=True)

    def merged_final() -> bool:
        result = merger.policy.last_result
        return result is not None and all(
            r in result.robots and len(result.robots[r].stamps) == len(s.map.stamps)
            for r, s in smoothers.items()
        )

    spin_once = lambda: executor.spin_once(timeout_sec=0.02)  # noqa: E731
    return merger.policy.last_result if wait_until(merged_final, timeout_s, spin_once) else None


def simulation_taken(simulator: Any, smoothers: dict[str, Any]) -> bool:
    """Whether the simulator has sent everything and every smoother has taken its robot's last
    odometry message (a scenario sent at full speed waits in the smoothers' queues for as long
    as the machine's load says)."""
    if simulator.next_index < len(simulator.messages):
        return False
    odometry = [m for m in simulator.messages if m.topic.endswith("/odom")]
    last = {m.topic.split("/")[1]: m.stamp_ns for m in odometry}
    return all(s.last_odometry_ns == last[r] for r, s in smoothers.items() if r in last)


def simulator_node(context: Any, scenario: str, seed: int, *extra: Parameter) -> Any:
    """The simulator of ``scenario`` at full speed (rate 0), in-process."""
    from csam_ros.nodes.simulator import Simulator

    return Simulator(
        context=context,
        parameter_overrides=[
            Parameter("scenario", value=scenario),
            Parameter("seed", value=seed),
            Parameter("rate", value=0.0),
            *extra,
        ],
    )
