"""The many-robots benchmark: its generated scenarios (every neighbour pair meets, no other
pair does, the scenario file loads back the same, rendezvous at every sample on request), the
growth exponents, and the command on two robots live and on a few offline."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from module_runs import module_output

from csam_ros.bench.many_robots import (
    HEADER,
    JOIN_STAGE,
    OfflineRow,
    growth_exponents,
    joined_difference,
    meetings,
    robot_counts,
    stage_table,
    write_scenario,
)
from csam_ros.core.joining.result import RunSummary
from csam_ros.datasets.formations import CSAM_SECTION, many_robot_scenario, neighbours
from csam_ros.datasets.scenario import load_scenario
from csam_ros.datasets.simulation import simulate


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
    printed = module_output(
        "csam_ros.bench.many_robots", "--robots", "2", "--seconds", "20", "--rate", "4",
        "--out", out,
    )  # fmt: skip
    lines = printed.splitlines()
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


@pytest.mark.parametrize("layout", ["ring", "chain"])
def test_rendezvous_at_every_sample_observe_what_every_fourth_sample_does_and_more(
    layout: str, tmp_path: Path
) -> None:
    """The geometry decides what is seen: every 4th sample's observations are among those
    of every sample, which add the samples between them."""
    every = many_robot_scenario(6, layout, duration=20.0, rendezvous_every=1)
    fourth = many_robot_scenario(6, layout, duration=20.0)
    assert {r.rendezvous_every for r in every.robots} == {1}
    assert set(meetings(every)) == set(meetings(fourth))
    for name, robot in simulate(every).robots.items():
        seen = set(zip(robot.rendezvous.stamps.tolist(), robot.rendezvous.observed, strict=True))
        sparse = simulate(fourth).robots[name].rendezvous
        stamps = sparse.stamps.tolist()
        assert set(zip(stamps, sparse.observed, strict=True)) < seen
        assert {round(t / every.sample_time) % 4 for t, _ in seen} == {0, 1, 2, 3}
    back = load_scenario(write_scenario(every, tmp_path / "s.yaml", CSAM_SECTION))
    assert {r.rendezvous_every for r in back.robots} == {1}
    assert meetings(back) == meetings(every)
    with pytest.raises(ValueError, match="rendezvous_every must be >= 1"):
        many_robot_scenario(4, layout, rendezvous_every=0)


def test_growth_exponents_are_log_log_slopes() -> None:
    successive, overall = growth_exponents([4, 8, 16, 32], [0.5, 2.0, 8.0, 64.0])
    np.testing.assert_allclose(successive, [2.0, 2.0, 3.0])
    assert overall == pytest.approx(
        np.polyfit(np.log([4, 8, 16, 32]), np.log([0.5, 2, 8, 64]), 1)[0]
    )
    successive, overall = growth_exponents([4, 8, 16], [1.0, 0.0, 4.0])
    assert np.isnan(successive).all() and overall == pytest.approx(1.0)
    assert np.isnan(growth_exponents([4, 8], [0.0, 1.0])[1])


def test_the_stage_table_holds_each_stage_the_join_alone_and_their_exponents() -> None:
    def row(n: int, scale: float) -> OfflineRow:
        timing = {"alignment": scale, "association": 2 * scale}
        timing |= {"total": 4 * scale, "local_maps": scale}
        return OfflineRow(n, n, n, 4 * n, 100 * n, n, 10, 20, timing, 0.1, 0.2)

    lines = stage_table([row(4, 1.0), row(8, 4.0), row(16, 32.0)])
    assert lines[0].split() == ["stage", "[s]", "N=4", "N=8", "N=16", "4->8", "8->16", "overall"]
    by_stage = {line[:26].strip(): line[26:].split() for line in lines[2:]}
    assert list(by_stage) == ["local_maps", "alignment", "association", JOIN_STAGE, "total"]
    assert by_stage[JOIN_STAGE][:3] == ["3.000", "12.000", "96.000"]
    assert by_stage[JOIN_STAGE][3:5] == ["2.00", "3.00"]
    assert robot_counts([4, 8, 16, 32, 64], 16) == [4, 8, 16]
    assert robot_counts([4, 8], None) == [4, 8]


def test_the_offline_command_on_a_few_robots(tmp_path: Path) -> None:
    out = tmp_path / "out"
    printed = module_output(
        "csam_ros.bench.many_robots", "--offline", "--robots", "2", "3", "4", "--max-robots",
        "3", "--seconds", "10", "--layout", "chain", "--out", out,
    )  # fmt: skip
    assert "rendezvous every 1 sample(s)" in printed
    lines = printed.splitlines()
    assert any(line.startswith("  3 robots: 3/3 aligned, pairs met 2/2") for line in lines)
    header = next(line for line in lines if line.startswith("stage [s]"))
    assert header.split()[2:] == ["N=2", "N=3", "2->3", "overall"]
    join = next(line for line in lines if line.startswith(JOIN_STAGE))
    assert len(join[26:].split()) == 4
    assert not (out / "chain4").exists()
    for n in (2, 3):
        summary = RunSummary.read(out / f"chain{n}" / "summary.json")
        assert {"total", "local_maps"} <= set(summary.result.timing_s)
        assert summary.result.joined_robots() == set(summary.result.robots)
        scenario = load_scenario(out / f"chain{n}" / "scenario.yaml")
        assert {r.rendezvous_every for r in scenario.robots} == {1}
        assert (out / f"chain{n}" / "bag" / "metadata.yaml").exists()


def test_the_scenario_files_are_written_alone_on_request(tmp_path: Path) -> None:
    from csam_ros.bench.many_robots import main

    out = tmp_path / "out"
    assert (
        main(
            ["--scenarios-only", "--robots", "5", "--layout", "ring", "chain"]
            + ["--every", "1", "--out", str(out)]
        )
        == 0
    )
    for layout in ("ring", "chain"):
        written = load_scenario(out / f"{layout}5" / "scenario.yaml")
        generated = many_robot_scenario(5, layout, rendezvous_every=1)
        assert written.name == generated.name == f"{layout}5"
        np.testing.assert_array_equal(written.features, generated.features)
        assert [(r.name, r.observes, r.rendezvous_every) for r in written.robots] == [
            (r.name, r.observes, 1) for r in generated.robots
        ]
    assert sorted(p.name for p in (out / "ring5").iterdir()) == ["scenario.yaml"]
