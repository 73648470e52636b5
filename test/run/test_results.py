"""What a run leaves: a new or empty output directory, summary.json and its figures, and the
lag lines of a live run's bag."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from csam_ros.run import results
from csam_ros.run.errors import RunError
from csam_ros.run.results import fresh_dir, latency_lines, write_results

BAG = Path(__file__).resolve().parents[2] / "bags" / "map_joining"


def test_a_run_gets_a_new_directory_under_runs(tmp_path: Path, monkeypatch) -> None:
    monkeypatch.setattr(results, "RUNS_DIR", tmp_path / "runs")
    first = fresh_dir(None, "demo")
    second = fresh_dir(None, "demo")
    assert first.is_dir() and second.is_dir() and first != second
    assert first.parent == second.parent == tmp_path / "runs"
    assert first.name.startswith("demo-") and second.name.startswith(first.name)


def test_an_output_directory_must_be_new_or_empty(tmp_path: Path) -> None:
    assert fresh_dir(tmp_path / "a" / "b", "x") == tmp_path / "a" / "b"
    assert fresh_dir(tmp_path / "a" / "b", "x").is_dir()  # empty: taken again
    (tmp_path / "a" / "b" / "keep.txt").write_text("mine")
    with pytest.raises(RunError, match="b exists and is not empty: choose a new --out"):
        fresh_dir(tmp_path / "a" / "b", "x")
    (tmp_path / "file").write_text("mine")
    with pytest.raises(RunError, match="file exists and is not a directory"):
        fresh_dir(tmp_path / "file", "x")
    assert (tmp_path / "a" / "b" / "keep.txt").read_text() == "mine"


def test_results_are_the_summary_and_every_figure(tmp_path: Path) -> None:
    from csam_ros.run.offline import offline_summary

    summary, _ = offline_summary(BAG)
    figures = write_results(tmp_path, summary)
    assert json.loads((tmp_path / "summary.json").read_text())["reference_frame"] == "robot1/map"
    assert [p.name for p in figures] == ["local_maps.png", "heading_sigma.png", "joined_map.png"]
    assert all(p.parent == tmp_path and p.stat().st_size > 0 for p in figures)


def test_no_lag_lines_from_a_bag_that_cannot_be_read(tmp_path: Path, capsys) -> None:
    from csam_ros.core.joining.result import RunSummary
    from csam_ros.run.offline import offline_summary

    summary, _ = offline_summary(BAG)
    assert latency_lines(tmp_path / "no_bag", summary) == []
    assert capsys.readouterr().err.startswith("warning: no lag figures: ")
    recorded = latency_lines(BAG, RunSummary(summary.result))
    assert recorded[0].startswith("lag from a local map to the joined map that uses it: mean ")
    assert "solves" in recorded[-1]
