"""The many-robots benchmark: its generated scenarios (every neighbour pair meets, no other
pair does, the scenario file loads back the same) and the command on two robots."""

from __future__ import annotations

import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from csam_ros.bench.many_robots import (
    CSAM_SECTION,
    HEADER,
    joined_difference,
    many_robot_scenario,
    meetings,
    neighbours,
    write_scenario,
)
from csam_ros.core.joining.result import RunSummary
from csam_ros.datasets.scenario import load_scenario

REPO = Path(__file__).resolve().parents[2]


def test_neighbours_of_a_ring_wrap_and_of_a_chain_do_not() -> None:
    assert neighbours(2, "ring") == [[1], [0]]
    assert neighbours(4, "ring") == [[1, 3], [0, 2], [1, 3], [0, 2]]
    assert neighbours(4, "chain") == [[1], [0, 2], [1, 3], [2]]
    with pytest.raises(ValueError):
        neighbours(3, "star")


@pytest.mark.parametrize("layout", ["ring", "chain"])
@pytest.mark.parametrize("n", [2, 3, 5, 16])
def test_every_neighbour_pair_meets_both_ways_and_no_other_pair(layout: str, n: int) -> None:
    scenario = many_robot_scenario(n, layout)
    names = [r.name for r in scenario.robots]
    expected = {(names[i], names[j]) for i, js in enumerate(neighbours(n, layout)) for j in js}
    met = meetings(scenario)
    assert set(met) == expected
    assert min(met.values()) >= 2


@pytest.mark.parametrize("layout", ["ring", "chain"])
def test_the_scenario_file_loads_back_the_same_scenario(layout: str, tmp_path: Path) -> None:
    scenario = many_robot_scenario(8, layout, duration=20.0, seed=3)
    back = load_scenario(write_scenario(scenario, tmp_path / "s.yaml", CSAM_SECTION))
    assert (back.name, back.seed, back.sample_time) == (scenario.name, 3, 0.5)
    np.testing.assert_array_equal(back.features, scenario.features)
    for a, b in zip(scenario.robots, back.robots, strict=True):
        np.testing.assert_allclose(b.start_pose, a.start_pose, rtol=1e-14, atol=1e-14)
        assert b.program[0].duration == a.program[0].duration == 20.0
        np.testing.assert_allclose(b.program[0].omega, a.program[0].omega, rtol=1e-14)
        np.testing.assert_allclose(b.odometry_sigma, a.odometry_sigma, rtol=1e-14)
        assert (
            replace(b, start_pose=a.start_pose, program=a.program, odometry_sigma=a.odometry_sigma)
            == a
        )
    assert meetings(back) == meetings(scenario)


def test_the_command_on_two_robots(tmp_path: Path) -> None:
    out = tmp_path / "out"
    done = subprocess.run(
        [sys.executable, "-m", "csam_ros.bench.many_robots", "--robots", "2"]
        + ["--seconds", "20", "--rate", "4", "--out", str(out)],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=REPO,
    )
    assert done.returncode == 0, done.stdout + done.stderr
    lines = done.stdout.splitlines()
    assert HEADER in lines
    row = lines[lines.index(HEADER) + 2].split()
    assert row[:3] == ["2", "1/1", "2/2"]  # two robots, their pair met, both joined
    assert int(row[4]) > 0  # associations
    assert "live - offline" in HEADER and float(row[15]) < 1e-6  # metres, live vs offline
    live = RunSummary.read(out / "ring2" / "live" / "summary.json").result
    offline = RunSummary.read(out / "ring2" / "offline" / "summary.json").result
    same = joined_difference(live, offline)
    assert same.poses == sum(len(r.stamps) for r in live.robots.values())
    assert same.features == len(live.features) and same.features_apart == 0
    moved = live.robots["robot2"].poses_joined.copy()
    moved[3] += [0.0, 0.5, 0.1]
    live.robots["robot2"] = replace(live.robots["robot2"], poses_joined=moved)
    apart = joined_difference(live, offline)
    assert apart.position_m == pytest.approx(0.5, abs=1e-6)
    assert apart.heading_deg == pytest.approx(np.rad2deg(0.1), abs=1e-4)
