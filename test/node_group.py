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
            *([Parameter("summary_path", value=str(summary_path))] if summary_path else []),
        ],
    )
    return smoothers, merger
