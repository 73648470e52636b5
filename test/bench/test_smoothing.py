"""The smoothing benchmark as a command, on a small problem: every solver's row, the same optimum
for both factorisations of ours, and the online local map ending at the offline one."""

from __future__ import annotations

import re

import pytest
from module_runs import module_output

ARGS = [
    "--poses", "300", "--landmarks", "12", "--observations", "400",
    "--no-identical", "--no-victoria", "--online-duration", "60",
]  # fmt: skip


@pytest.fixture(scope="module")
def printed() -> str:
    return module_output("csam_ros.bench.smoothing", *ARGS)


def solver_rows(out: str) -> dict[str, dict[str, float]]:
    """The table of the simulated problem: solver -> iterations, own and our cost."""
    rows = {}
    for line in out.splitlines():
        fields = line.split()
        if len(fields) == 9 and fields[0] in ("ours", "ours-splu", "gtsam-native"):
            rows[fields[0]] = {
                "iterations": int(fields[1]),
                "own_cost": float(fields[5]),
                "our_cost": float(fields[6]),
            }
    return rows


def have_gtsam() -> bool:
    try:
        import gtsam  # noqa: F401
    except ImportError:
        return False
    return True


def test_each_solver_reports_on_the_simulated_problem(printed: str) -> None:
    assert "== simulated: 300 poses, 12 landmarks, 299 odometry factors, 400 obs." in printed
    assert "unknowns 924; start: dead reckoning" in printed
    rows = solver_rows(printed)
    ours, splu = rows["ours"], rows["ours-splu"]
    assert 0 < ours["iterations"] < 50
    assert ours["own_cost"] == ours["our_cost"]
    assert splu["our_cost"] == pytest.approx(ours["our_cost"], rel=1e-9)
    assert re.search(r"the \d+ factorisations alone: [\d.]+ ms", printed)
    if not have_gtsam():
        assert "GTSAM is not installed" in printed
        return
    native = rows["gtsam-native"]
    # GTSAM optimises the same model to first order: on our objective, never below our optimum
    assert ours["our_cost"] <= native["our_cost"] * (1 + 1e-9)
    assert native["our_cost"] == pytest.approx(ours["our_cost"], rel=1e-2)
    assert "ratio ours / GTSAM native: time per iteration" in printed


def test_online_local_map_ends_at_the_offline_map(printed: str) -> None:
    assert "60 s of data" in printed
    found = re.search(
        r"max difference of positions (\S+) m, headings (\S+) rad, landmarks (\S+) m; "
        r"cost (\S+) vs (\S+)\n",
        printed,
    )
    assert found, printed
    positions, headings, landmarks, online, offline = map(float, found.groups())
    assert max(positions, headings, landmarks) < 1e-6
    assert online == pytest.approx(offline, abs=0.01)
    assert re.search(r"online: [1-9]\d* updates", printed)
    assert re.search(r"every pose and landmark covariance \d+ ms", printed)
