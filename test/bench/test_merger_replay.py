"""The merger-replay benchmark as a command, on a live demo's bag: every solve joined cold
and warm, the two equal on this Gaussian scenario."""

from __future__ import annotations

from pathlib import Path

from module_runs import module_output


def test_merger_replay_joins_a_live_run_cold_and_warm_alike(demo_run: Path) -> None:
    # the demo ran at rate 8: its maps arrive over about 5 s of log time
    printed = module_output("csam_ros.bench.merger_replay", demo_run / "bag", "--every", "0.5")
    lines = printed.splitlines()
    assert lines[0].split() == [
        "t", "poses", "cold", "it1", "itJ", "warm", "it1", "itJ", "reused", "warm-cold",
    ]  # fmt: skip
    rows = [line.split() for line in lines[1:] if not line.startswith(("cold", "warm"))]
    assert len(rows) >= 3
    assert all(float(row[-1]) < 1e-6 for row in rows), printed
    solves = [line for line in lines if line.startswith(("cold:", "warm:"))]
    assert [s.split()[1] for s in solves] == [str(len(rows))] * 2, printed


def test_merger_replay_compares_warm_joins_with_and_without_the_solve_ahead(
    demo_run: Path,
) -> None:
    printed = module_output(
        "csam_ros.bench.merger_replay", demo_run / "bag", "--every", "0.5", "--ahead"
    )
    lines = printed.splitlines()
    assert lines[0].split() == ["t", "without", "ahead", "taken"]
    rows = [line.split() for line in lines[1:-1]]
    assert len(rows) >= 3 and all(row[3] in ("0", "1") for row in rows), printed
    assert rows[0][3] == "0"  # the first join has no previous one
    taken = sum(int(row[3]) for row in rows[1:])
    assert lines[-1].endswith(f"taken in {taken} of {len(rows) - 1}"), printed
