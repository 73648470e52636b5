"""The live demo (``csam demo``): the simulator playing a scenario into smoothers and a merger,
recorded to a bag, on this host or with every robot on a host of its own; with ``--foxglove``
served to Foxglove by a foxglove_bridge beside the run."""

from __future__ import annotations

import os
import re
import time
from contextlib import ExitStack
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from csam_ros.run.errors import RunError
from csam_ros.run.launch import ProcessGroup, executable
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


def run_demo(run: LiveRun, links: Links | None, foxglove_port: int | None = None) -> RunSummary:
    """The demo's live run, with every robot on a host of its own if ``links`` are given, or
    served to Foxglove on ``foxglove_port`` (0: any free port) if that is given; the merger's
    summary."""
    from csam_ros.run.hosts import HostsError, run_hosts
    from csam_ros.run.live import run_live

    if foxglove_port is not None:
        if links is not None:
            raise RunError(
                "--foxglove: not with --hosts (the base station's network namespace is not "
                "reachable from this host's 127.0.0.1)"
            )
        if not 0 <= foxglove_port <= 65535:
            raise RunError(f"--foxglove: a port is 0..65535 (0: any free one), not {foxglove_port}")
        return watched_run(run, foxglove_port)
    if links is None:
        return run_live(run)
    try:
        return run_hosts(run, links)
    except HostsError as err:
        raise RunError(f"--hosts: {err}") from None


BRIDGE = "foxglove_bridge"
BRIDGE_START_S = 60.0  # s the bridge has to start serving (rclpy, the message definitions)
_BRIDGE_URL = re.compile(r"open (ws://\S+) in Foxglove")


def watched_run(run: LiveRun, port: int) -> RunSummary:
    """The live run with a foxglove_bridge serving its topics on ``port`` of 127.0.0.1,
    started first and stopped last; prints the URL to open in Foxglove. With ``--isolated``
    the private domain is reserved here, so that the bridge runs on it too."""
    from csam_ros.run.live import ros_params, run_live
    from csam_ros.run.ros_env import isolate_this_process, reserve_domain_id, with_dds_profile

    with ExitStack() as stack:
        if run.isolated:
            domain_id = stack.enter_context(reserve_domain_id()).domain_id
            isolate_this_process(domain_id)  # run_live runs in this environment as it is
            print(f"  isolated on ROS_DOMAIN_ID {domain_id}, this host only")
            run = replace(run, isolated=False)
        group = stack.enter_context(
            ProcessGroup(run.out_dir / "logs", with_dds_profile(os.environ))
        )
        params = {"use_sim_time": True, "port": port, "robots": run.robots}
        group.start(BRIDGE, [executable(BRIDGE), "--ros-args", *ros_params(params)])
        print(f"  Foxglove: open {bridge_url(group)} (Open connection, Foxglove WebSocket)")
        return run_live(run)


def bridge_url(group: ProcessGroup) -> str:
    """The URL the bridge of ``group`` logs once it serves; RunError with its log when it
    exits or does not serve within BRIDGE_START_S."""
    log = group.log_dir / f"{BRIDGE}.log"
    deadline = time.monotonic() + BRIDGE_START_S
    while time.monotonic() < deadline:
        found = _BRIDGE_URL.search(log.read_text(errors="replace")) if log.exists() else None
        if found is not None:
            return found.group(1)
        if BRIDGE in group.dead():
            raise RunError(f"--foxglove: the bridge exited: {group.log_tail(BRIDGE, 3)}")
        time.sleep(0.1)
    raise RunError(f"--foxglove: the bridge did not serve within {BRIDGE_START_S:.0f} s")
