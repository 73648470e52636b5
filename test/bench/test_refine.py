"""The refine benchmark as a command, on a live demo's bag: every map the merger built from
updates refined from the robot's last refine and from the held estimate, both within a
standard deviation of the converged optimum on this Gaussian scenario."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def test_refine_compares_both_starts_for_every_robot(demo_run: Path) -> None:
    done = subprocess.run(
        [sys.executable, "-m", "csam_ros.bench.refine", str(demo_run / "bag")],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=REPO,
    )
    assert done.returncode == 0, done.stdout + done.stderr
    lines = done.stdout.splitlines()
    assert lines[1].split() == ["robot", "maps", "mean", "above", "max", "mean", "above", "max"]
    rows = [line.split() for line in lines[2:]]
    assert [row[0] for row in rows] == ["robot1", "robot2"], done.stdout
    for row in rows:
        assert int(row[1]) >= 1, done.stdout  # maps refined from the robot's last refine
        above = [float(row[i]) for i in (4, 5, 8, 9)]
        assert all(-1e-6 < x < 0.5 for x in above), done.stdout
