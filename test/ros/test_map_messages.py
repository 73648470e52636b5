"""Local maps survive the trip through their messages: the merger sees what the smoother had."""

from __future__ import annotations

import numpy as np
import pytest

from csam_ros.core.csam import join_maps, robot_map_from_local_map
from csam_ros.core.factors import Cauchy, Huber
from csam_ros.core.local_map import LocalMapOptions, build_local_map
from csam_ros.core.rendezvous import required_stamps
from csam_ros.core.simulation import simulate
from csam_ros.datasets.scenario import load_scenario
from csam_ros.ros.map_messages import (
    rendezvous_log_from_message,
    rendezvous_poses_message,
    robot_map_from_message,
    robot_map_to_message,
)


@pytest.fixture(scope="module")
def maps_and_logs():
    log = simulate(load_scenario("map_joining"), seed=2)
    logs = {n: r.rendezvous for n, r in log.robots.items()}
    stamps = required_stamps(logs)
    maps = [robot_map_from_local_map(build_local_map(r, stamps[n])) for n, r in log.robots.items()]
    return maps, logs


def test_local_map_round_trip_gives_the_same_problem(maps_and_logs) -> None:
    maps, _ = maps_and_logs
    for m in maps:
        back = robot_map_from_message(robot_map_to_message(m, 123))
        np.testing.assert_array_equal(back.poses, m.poses)
        np.testing.assert_array_equal(back.stamps, np.round(m.stamps * 1e9) / 1e9)
        np.testing.assert_array_equal(back.feature_labels, m.feature_labels)
        np.testing.assert_array_equal(back.feature_positions, m.feature_positions)
        assert back.problem.cost() == pytest.approx(m.problem.cost(), rel=1e-12)


@pytest.mark.parametrize("kernel", [Huber(2.0), Cauchy(), Cauchy(1.5)])
def test_robust_kernels_survive_the_message(kernel) -> None:
    log = simulate(load_scenario("map_joining"), seed=2).robots["robot1"]
    m = robot_map_from_local_map(build_local_map(log, options=LocalMapOptions(robust=kernel)))
    back = robot_map_from_message(robot_map_to_message(m, 1))
    kernels = [f.robust for f in back.problem.factors if f.robust is not None]
    assert kernels and all(k == kernel for k in kernels)
    assert back.problem.cost() == pytest.approx(m.problem.cost(), rel=1e-12)


def test_join_from_messages_equals_join_in_process(maps_and_logs) -> None:
    maps, logs = maps_and_logs
    direct = join_maps(maps, logs).to_dict()
    rebuilt = [robot_map_from_message(robot_map_to_message(m, 1)) for m in maps]
    logs_back = {}
    for m in maps:
        msg = rendezvous_poses_message(m, 1, np.arange(2), logs[m.name])
        logs_back[m.name] = rendezvous_log_from_message(msg)
        assert logs_back[m.name].observed == list(logs[m.name].observed)
    via = join_maps(rebuilt, logs_back).to_dict()
    for name, robot in direct["robots"].items():
        assert via["robots"][name]["alignment"] == robot["alignment"]
        if robot["poses_joined"]:
            np.testing.assert_allclose(
                via["robots"][name]["poses_joined"], robot["poses_joined"], atol=1e-9
            )
    assert [a["a"] for a in via["associations"]] == [a["a"] for a in direct["associations"]]
