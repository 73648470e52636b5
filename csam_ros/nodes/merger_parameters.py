"""The merger node's parameters: its own (:class:`~csam_ros.core.merging.policy.MergerSettings`,
the files it writes, the solve process's priority) and the C-SAM settings it takes
(:class:`~csam_ros.core.joining.config.CsamConfig`), declared with descriptions and ranges; and
those of its own it applies while it runs (:func:`live_merger_parameters`)."""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rclpy.node import Node

from csam_ros.core.joining.config import CsamConfig
from csam_ros.core.merging.policy_inputs import MergerSettings
from csam_ros.nodes.common import Declared, Live, declare_each, declare_settings
from csam_ros.ros.signing import read_team_key

_DEFAULTS = MergerSettings()
# the merger's own parameters, in the order they are declared
MERGER_PARAMETERS = (
    # an empty list has no element type: ROS reads `robots:=[]` as a byte array, so the
    # parameter takes any type and is checked here
    Declared(
        "robots",
        None,
        "allow-list of robot names (empty or unset: every robot that publishes a local map); "
        "its first is the reference when `reference` is empty",
    ),
    Declared(
        "reference",
        _DEFAULTS.reference,
        "reference robot if it has a map, else the first one heard",
    ),
    Declared(
        "reference_wait",
        _DEFAULTS.reference_wait,
        "wall-clock s the first solve waits, after the first local map, for the configured "
        "reference's and every listed robot's (0: none)",
        0.0,
    ),
    Declared(
        "stale_after",
        _DEFAULTS.stale_after,
        "wall-clock s without a local map after which a robot is reported stale (0: never)",
        0.0,
    ),
    Declared(
        "max_robots",
        _DEFAULTS.max_robots,
        "most robots found (not listed) joined at once; one found beyond them is refused and "
        "counted (too_many_robots) until one is forgotten",
        1,
        100000,
    ),
    Declared(
        "robot_pattern",
        _DEFAULTS.robot_pattern,
        "regular expression every robot's whole name must match to be joined (with the "
        "allow-list, both must admit it)",
    ),
    Declared(
        "forget_after",
        _DEFAULTS.forget_after,
        "wall-clock s without a local map after which a robot found (not listed) leaves the "
        "status and is unsubscribed from, its map kept joined; found again after as long "
        "(0: never)",
        0.0,
    ),
    Declared(
        "team_key_file",
        "",
        "file of the team key (at least 16 bytes): take only local map updates and rendezvous "
        "poses signed with it, as smoothers given it sign them ('': any)",
    ),
    Declared("summary_path", "", "write summary.json here after each solve"),
    Declared(
        "state_path",
        "",
        "write the merger's state here after each solve and resume from it at start ('': off)",
    ),
    Declared(
        "solve_period",
        _DEFAULTS.solve_period,
        "minimum wall-clock seconds between solves: the merger looks this often whether one "
        "is to start, and a local map that makes every robot's map new starts one at once",
        0.0,
        3600.0,
    ),
    Declared(
        "solve_wait",
        _DEFAULTS.solve_wait,
        "wall-clock seconds a solve waits, after the first input newer than the last solve's, "
        "for the other robots' new local maps (local maps that arrive together are solved in "
        "one); it starts at once when every robot's map is new (0: never waits)",
        0.0,
        3600.0,
    ),
    Declared(
        "provisional_period",
        _DEFAULTS.provisional_period,
        "minimum wall-clock seconds between provisional joined maps (the newest local maps "
        "placed by the last join), and the most a new local map waits for one (0: none)",
        0.0,
        3600.0,
    ),
    Declared(
        "provisional_quiet",
        _DEFAULTS.provisional_quiet,
        "wall-clock seconds without a new local map after which the provisional joined map "
        "goes out (local maps that arrive together go out in one); it goes out at once when "
        "every robot's map is new",
        0.0,
        3600.0,
    ),
    Declared(
        "solve_niceness",
        10,
        "how much lower the solve process's CPU priority is than the node's (nice; 0: the "
        "same): the node, and nodes beside it, take and publish messages first",
        0,
        19,
    ),
)
# the MergerSettings the merger applies while it runs (a parameter set at run time)
LIVE_SETTINGS = (
    "reference_wait",
    "stale_after",
    "solve_period",
    "solve_wait",
    "provisional_period",
    "provisional_quiet",
)
# the MergerSettings of robots found, set at start
FOUND_SETTINGS = ("max_robots", "robot_pattern", "forget_after")
# online, a rendezvous stamp may reach the merger before the observed robot's map has its pose:
# leave such a measurement out until the next solve instead of failing
MERGER_CSAM_DEFAULTS = CsamConfig(skip_missing_poses=True)


@dataclass(frozen=True)
class MergerParameters:
    """The merger's parameters as it uses them."""

    settings: MergerSettings
    config: CsamConfig
    summary_path: Path | None  # write summary.json here after each solve
    state_path: Path | None  # write the merger's state here, and resume from it
    solve_niceness: int
    team_key: bytes | None  # take only inputs signed with it


def declare_merger_parameters(node: Node) -> MergerParameters:
    """Declare the merger's parameters on ``node``; their values."""
    own = declare_each(node, MERGER_PARAMETERS)
    allowed = own["robots"]
    if allowed is not None and not (
        isinstance(allowed, list | tuple) and all(isinstance(r, str) and r for r in allowed)
    ):
        raise ValueError(f"parameter robots: expected a list of robot names, got {allowed!r}")
    try:
        re.compile(own["robot_pattern"])
    except re.error as error:
        raise ValueError(f"parameter robot_pattern: not a regular expression: {error}") from None
    config = declare_settings(node, CsamConfig, MERGER_CSAM_DEFAULTS)
    settings = MergerSettings(
        robots=tuple(allowed or ()),
        **{name: own[name] for name in ("reference", *LIVE_SETTINGS, *FOUND_SETTINGS)},
    )
    return MergerParameters(
        settings=settings,
        config=config,
        summary_path=Path(own["summary_path"]) if own["summary_path"] else None,
        state_path=Path(own["state_path"]) if own["state_path"] else None,
        solve_niceness=own["solve_niceness"],
        team_key=read_team_key(own["team_key_file"]) if own["team_key_file"] else None,
    )


def live_merger_parameters(
    apply: Callable[[str, Any], None], provisional_maps: bool
) -> dict[str, Live]:
    """The merger's parameters it applies while it runs: ``apply(name, value)`` puts a
    :data:`LIVE_SETTINGS` value into its settings. Provisional maps off at start
    (``provisional_period`` 0) stay off: turning them on takes a restart."""

    def provisional_check(value: float) -> None:
        if value > 0.0 and not provisional_maps:
            raise ValueError(
                "provisional_period: provisional maps were off at start (0); turning them on "
                "takes effect only at start"
            )

    return {
        name: Live(
            lambda value, name=name: apply(name, value),
            provisional_check if name == "provisional_period" else None,
        )
        for name in LIVE_SETTINGS
    }
