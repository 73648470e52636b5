"""The demo's live run as built before any node starts: links between hosts from the options,
and the simulator, smoothers and merger configured from the scenario."""

from __future__ import annotations

from pathlib import Path

import pytest

from csam_ros.run.demo import demo_links, demo_live_run, link_cut
from csam_ros.run.errors import RunError


def test_a_link_cut_reads_robot_start_and_end() -> None:
    assert link_cut(None) is None
    assert link_cut("robot2:10-25.5") == ("robot2", 10.0, 25.5)
    with pytest.raises(ValueError, match="--cut: expected ROBOT:START-END"):
        link_cut("robot2:ten-20")


def test_link_options_need_hosts_and_valid_values() -> None:
    assert demo_links(False, 0.0, 0.0, 0.0, None) is None
    for options in ((0.1, 0.0, 0.0, None), (0.0, 0.0, 0.0, "robot1:1-2"), (0, 0, 64.0, None)):
        with pytest.raises(RunError, match="need --hosts"):
            demo_links(False, *options)
    with pytest.raises(RunError, match=r"^--hosts: loss must be in \[0, 1\)"):
        demo_links(True, 1.5, 0.0, 0.0, None)
    with pytest.raises(RunError, match="^--hosts: --cut: expected ROBOT:START-END"):
        demo_links(True, 0.0, 0.0, 0.0, "robot1")
    with pytest.raises(RunError, match="^--hosts: a link cut needs 0 <= start < end"):
        demo_links(True, 0.0, 0.0, 0.0, "robot1:5-2")


def test_the_demo_run_configures_the_nodes_from_the_scenario(tmp_path: Path) -> None:
    from csam_ros.datasets.scenario import load_document, load_scenario
    from csam_ros.run.params import merger_params

    run = demo_live_run("map_joining", tmp_path, seed=3, rate=0.0, isolated=True)
    assert run.robots == [r.name for r in load_scenario("map_joining").robots]
    assert run.out_dir == tmp_path and run.isolated and run.source_name == "simulator"
    assert run.source_ros_args[2:6] == ["-p", "seed:=3", "-p", "rate:=0.0"]
    assert run.merger_params == merger_params(load_document("map_joining"))
    assert run.smoother_params["field_of_view_deg"] > 0
