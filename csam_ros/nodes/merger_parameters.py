"""The merger node's parameters: its own (:class:`~csam_ros.core.merging.policy.MergerSettings`,
the files it writes, the solve process's priority) and the C-SAM settings it takes
(:class:`~csam_ros.core.joining.config.CsamConfig`), declared with descriptions and ranges."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from rcl_interfaces.msg import ParameterDescriptor
from rclpy.node import Node

from csam_ros.core.joining.config import CsamConfig
from csam_ros.core.merging.policy import MergerSettings
from csam_ros.nodes.common import declare, declare_settings


@dataclass(frozen=True)
class MergerParameters:
    """The merger's parameters as it uses them."""

    settings: MergerSettings
    config: CsamConfig
    summary_path: Path | None  # write summary.json here after each solve
    state_path: Path | None  # write the merger's state here, and resume from it
    solve_niceness: int


def declare_merger_parameters(node: Node) -> MergerParameters:
    """Declare the merger's parameters on ``node``; their values."""
    defaults = MergerSettings()
    # an empty list has no element type: ROS reads `robots:=[]` as a byte array, so the
    # parameter takes any type and is checked here
    allowed = node.declare_parameter(
        "robots",
        None,
        ParameterDescriptor(
            description="allow-list of robot names (empty or unset: every robot that "
            "publishes a local map); its first is the reference when `reference` is empty",
            dynamic_typing=True,
        ),
    ).value
    if allowed is not None and not (
        isinstance(allowed, list | tuple) and all(isinstance(r, str) and r for r in allowed)
    ):
        raise ValueError(f"parameter robots: expected a list of robot names, got {allowed!r}")
    reference = declare(
        node,
        "reference",
        defaults.reference,
        "reference robot if it has a map, else the first one heard",
    )
    reference_wait = declare(
        node,
        "reference_wait",
        defaults.reference_wait,
        "wall-clock s the first solve waits, after the first local map, for the configured "
        "reference's and every listed robot's (0: none)",
        0.0,
    )
    stale_after = declare(
        node,
        "stale_after",
        defaults.stale_after,
        "wall-clock s without a local map after which a robot is reported stale (0: never)",
        0.0,
    )
    summary = declare(node, "summary_path", "", "write summary.json here after each solve")
    state = declare(
        node,
        "state_path",
        "",
        "write the merger's state here after each solve and resume from it at start ('': off)",
    )
    solve_period = declare(
        node,
        "solve_period",
        defaults.solve_period,
        "minimum wall-clock seconds between solves",
        0.0,
        3600.0,
    )
    provisional_period = declare(
        node,
        "provisional_period",
        defaults.provisional_period,
        "minimum wall-clock seconds between provisional joined maps (the newest local maps "
        "placed by the last join), and the most a new local map waits for one (0: none)",
        0.0,
        3600.0,
    )
    provisional_quiet = declare(
        node,
        "provisional_quiet",
        defaults.provisional_quiet,
        "wall-clock seconds without a new local map after which the provisional joined map "
        "goes out (local maps that arrive together go out in one); it goes out at once when "
        "every robot's map is new",
        0.0,
        3600.0,
    )
    niceness = declare(
        node,
        "solve_niceness",
        10,
        "how much lower the solve process's CPU priority is than the node's (nice; 0: the "
        "same): the node, and nodes beside it, take and publish messages first",
        0,
        19,
    )
    # online, a rendezvous stamp may reach the merger before the observed robot's map has
    # its pose: leave such a measurement out until the next solve instead of failing
    config = declare_settings(node, CsamConfig, CsamConfig(skip_missing_poses=True))
    settings = MergerSettings(
        robots=tuple(allowed or ()),
        reference=reference,
        reference_wait=reference_wait,
        stale_after=stale_after,
        solve_period=solve_period,
        provisional_period=provisional_period,
        provisional_quiet=provisional_quiet,
    )
    return MergerParameters(
        settings=settings,
        config=config,
        summary_path=Path(summary) if summary else None,
        state_path=Path(state) if state else None,
        solve_niceness=niceness,
    )
