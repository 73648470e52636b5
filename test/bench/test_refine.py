"""The refine benchmark as a command, on a live demo's bag: every map the merger built from
updates refined from the robot's last refine and from the held estimate, both within a
standard deviation of the converged optimum on this Gaussian scenario."""

from __future__ import annotations

from pathlib import Path

from module_runs import module_output


def test_refine_compares_both_starts_for_every_robot(demo_run: Path) -> None:
    printed = module_output("csam_ros.bench.refine", demo_run / "bag")
    lines = printed.splitlines()
    assert lines[1].split() == ["robot", "maps", "mean", "above", "max", "mean", "above", "max"]
    rows = [line.split() for line in lines[2:]]
    assert [row[0] for row in rows] == ["robot1", "robot2"], printed
    for row in rows:
        assert int(row[1]) >= 1, printed  # maps refined from the robot's last refine
        above = [float(row[i]) for i in (4, 5, 8, 9)]
        assert all(-1e-6 < x < 0.5 for x in above), printed
