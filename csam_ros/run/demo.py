"""The live demo (``csam demo``): the simulator playing a scenario into smoothers and a merger,
recorded to a bag, on this host or with every robot on a host of its own."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from csam_ros.run.errors import RunError
from csam_ros.run.launch import executable
from csam_ros.run.params import merger_params, smoother_params

if TYPE_CHECKING:
    from csam_ros.core.joining.result import RunSummary
    from csam_ros.run.hosts import Links
    from csam_ros.run.live import LiveRun


def link_cut(text: str | None) -> tuple[str, float, float] | None:
    """``--cut ROBOT:START-END`` as (robot, start, end); ValueError naming what does not read."""
    if text is None:
        return None
    robot, _, window = text.partition(":")
    start, _, end = window.partition("-")
    try:
        return robot, float(start), float(end)
    except ValueError:
        raise ValueError(f"--cut: expected ROBOT:START-END (seconds), got {text!r}") from None


def demo_links(
    hosts: bool, loss: float, link_rate: float, base_link_rate: float, cut: str | None
) -> Links | None:
    """The links between hosts that ``--hosts`` and its link options give (None: no hosts),
    checked, with what this machine needs for them."""
    from csam_ros.run.hosts import Links, missing_requirements

    if (loss or link_rate or base_link_rate or cut) and not hosts:
        raise RunError(
            "--loss, --link-rate, --base-link-rate and --cut need --hosts (links between hosts)"
        )
    if not hosts:
        return None
    try:
        links = Links(loss, link_rate, link_cut(cut), base_link_rate)
    except ValueError as err:
        raise RunError(f"--hosts: {err}") from None
    if (reason := missing_requirements(links)) is not None:
        raise RunError(f"--hosts: {reason}")
    return links


def demo_live_run(
    scenario_name: str | Path, out: Path, seed: int, rate: float, isolated: bool = False
) -> LiveRun:
    """The live run of ``csam demo``: the simulator playing a scenario (a name in config/ or
    a YAML file, whose ``csam:``, ``local_map:``, ``input:`` and ``merger:`` sections
    configure the nodes) into smoothers and a merger, recorded to ``out/bag``."""
    from csam_ros.datasets.scenario import load_document, load_scenario
    from csam_ros.run.live import LiveRun

    scenario = load_scenario(scenario_name)
    document = load_document(scenario_name)
    fov = max(np.rad2deg(r.feature_sensor.field_of_view) for r in scenario.robots)
    return LiveRun(
        out_dir=out,
        robots=[r.name for r in scenario.robots],
        source_name="simulator",
        source_argv=[executable("simulator")],
        source_ros_args=[
            "-p",
            f"scenario:={scenario_name}",
            "-p",
            f"seed:={seed}",
            "-p",
            f"rate:={rate}",
            "-p",
            "exit_when_done:=true",
            # every sensor topic: the recorder and at least the robot's own smoother
            "-p",
            "min_subscribers:=2",
            "-p",
            'required_subscriber_nodes:=["recorder"]',
        ],
        smoother_params={"field_of_view_deg": float(fov), **smoother_params(document)},
        merger_params=merger_params(document),
        isolated=isolated,
    )


def run_demo(run: LiveRun, links: Links | None) -> RunSummary:
    """The demo's live run, with every robot on a host of its own if ``links`` are given;
    the merger's summary."""
    from csam_ros.run.hosts import HostsError, run_hosts
    from csam_ros.run.live import run_live

    if links is None:
        return run_live(run)
    try:
        return run_hosts(run, links)
    except HostsError as err:
        raise RunError(f"--hosts: {err}") from None
