"""A run scored against its ground truth: metrics.json, what it says, the joined map over the
true features, and the run directories it cannot score."""

from __future__ import annotations

import json
import os
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


def _summary_changed(summary, tmp_path: Path, change) -> Path:
    """A run directory whose summary.json (of the replay of BAG) has ``change`` applied."""
    replace(summary, source=str(BAG)).write(tmp_path / "summary.json")
    document = json.loads((tmp_path / "summary.json").read_text())
    change(document)
    (tmp_path / "summary.json").write_text(json.dumps(document))
    return tmp_path


def _feature(key: str, value) -> object:
    def change(document: dict) -> None:
        document["features"][0][key] = value

    return change


@pytest.mark.parametrize(
    ("change", "expected"),
    [
        (_feature("members", ["robot1x100"]), "features[0]: member 'robot1x100' is not"),
        (_feature("members", ["robot1/x"]), "features[0]: member 'robot1/x' is not"),
        (_feature("xy", [float("nan"), 1.0]), "features[0].xy: a value that is not a finite"),
        (_feature("xy", [1e308, -1e308]), "features[0].xy: a value that is not a finite"),
        (
            lambda d: d["robots"]["robot2"]["poses_joined"][3].__setitem__(0, 1e308),
            "robots.robot2.poses_joined: a value",
        ),
    ],
    ids=["no-slash", "label-not-integer", "nan", "beyond-float", "pose-beyond"],
)
def test_a_summary_whose_map_cannot_be_scored_is_a_run_error_naming_it(
    summary, tmp_path, change, expected: str
) -> None:
    """Features and poses no run writes (a traceback in the scoring, or a figure that
    overflows) are refused with the file and the entry."""
    run = _summary_changed(summary, tmp_path, change)
    with pytest.raises(RunError) as caught:
        evaluate_run(run)
    assert str(run / "summary.json") in str(caught.value) and expected in str(caught.value)
    assert not (run / "metrics.json").exists()


def test_a_summary_with_no_feature_is_scored_as_none(summary, tmp_path) -> None:
    """A joined map without features (a run that saw none): metrics without a score, no
    traceback in the lines that say them."""
    run = _summary_changed(summary, tmp_path, lambda d: d.__setitem__("features", []))
    lines = evaluation_lines(evaluate_run(run))
    assert lines[1] == "  landmarks: no feature of the joined map could be scored"
    assert lines[2].startswith("  associations: precision n/a, recall n/a"), lines[2]


def test_a_summary_that_is_not_utf8_or_not_a_file_is_refused_by_name(tmp_path) -> None:
    from waiting import no_hang

    from csam_ros.core.joining.result import SummaryError

    (tmp_path / "summary.json").write_bytes(b'{"features": \xff}')
    with pytest.raises(SummaryError, match=r"summary.json: not UTF-8 text \(byte 13\)"):
        evaluate_run(tmp_path)
    (tmp_path / "summary.json").unlink()
    os.mkfifo(tmp_path / "summary.json")
    with no_hang(10.0), pytest.raises(OSError, match="a FIFO, not a regular file"):
        evaluate_run(tmp_path)


@pytest.mark.parametrize("section", ["files", "topics_with_message_count"])
def test_a_run_bag_whose_metadata_section_is_not_a_list_is_a_run_error(
    summary, tmp_path, section: str
) -> None:
    import shutil

    import yaml

    shutil.copytree(BAG, tmp_path / "bag")
    metadata = yaml.safe_load((tmp_path / "bag" / "metadata.yaml").read_text())
    metadata["rosbag2_bagfile_information"][section] = 5
    (tmp_path / "bag" / "metadata.yaml").write_text(yaml.safe_dump(metadata))
    summary.write(tmp_path / "summary.json")
    with pytest.raises(RunError, match=f"metadata.yaml: {section} is 5, not a list"):
        evaluate_run(tmp_path)
