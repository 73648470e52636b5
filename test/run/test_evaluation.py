"""A run scored against its ground truth: metrics.json, what it says, the joined map over the
true features, and the run directories it cannot score."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import pytest

from csam_ros.run.errors import RunError
from csam_ros.run.evaluation import draw_over_truth, evaluate_run, evaluation_lines, truth_of

BAG = Path(__file__).resolve().parents[2] / "bags" / "map_joining"


@pytest.fixture(scope="module")
def summary():
    from csam_ros.run.offline import offline_summary

    return offline_summary(BAG)[0]


def test_an_offline_replay_is_scored_with_the_truth_of_its_source(summary, tmp_path) -> None:
    replace(summary, source=str(BAG)).write(tmp_path / "summary.json")
    evaluation = evaluate_run(tmp_path)
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    assert metrics == json.loads(json.dumps(evaluation.metrics))
    assert metrics["association"]["precision"] == 1.0
    lines = evaluation_lines(evaluation)
    assert lines[0] == f"{tmp_path}/metrics.json"
    assert lines[1].startswith("  landmarks: RMSE ") and lines[2].startswith("  associations: ")
    robots = [line.split(";")[0] for line in lines[3:]]
    assert robots == ["  robot1: reference", "  robot2: aligned"]
    assert all("; its local map alone: RMSE " in line for line in lines[3:])
    figure = draw_over_truth(evaluation)
    assert figure == tmp_path / "joined_map.png" and figure.stat().st_size > 0


def test_a_run_without_summary_truth_or_readable_source_is_a_run_error(summary, tmp_path) -> None:
    with pytest.raises(RunError, match="summary.json: no such file"):
        evaluate_run(tmp_path)
    summary.write(tmp_path / "summary.json")  # no source, no bag in the run
    with pytest.raises(RunError, match="no ground truth"):
        evaluate_run(tmp_path)
    assert not (tmp_path / "metrics.json").exists()
    with pytest.raises(RunError, match=r"\(the source named in summary.json\) is not a readable"):
        truth_of(tmp_path, str(tmp_path / "summary.json"))
    assert truth_of(tmp_path, None) is None
    assert truth_of(tmp_path, str(BAG)) is not None
