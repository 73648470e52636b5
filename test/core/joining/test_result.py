"""summary.json: to_dict and from_dict are inverses; a malformed summary names its key; notes
are written as their texts and read back typed."""

from __future__ import annotations

import copy
import json
from dataclasses import fields, is_dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from csam_ros.core.joining.config import CsamConfig
from csam_ros.core.joining.notes import Note, NoteKind
from csam_ros.core.joining.pipeline import run_csam
from csam_ros.core.joining.result import CsamResult, MergerStats, RunSummary, SummaryError
from csam_ros.core.model.log import RendezvousLog
from csam_ros.datasets.scenario import load_scenario
from csam_ros.datasets.simulation import simulate


def assert_same(a: Any, b: Any, where: str = "result") -> None:
    """Equal types and values, arrays with their shapes and dtypes, exactly."""
    if isinstance(a, np.ndarray):
        assert isinstance(b, np.ndarray), where
        assert a.dtype == b.dtype, (where, a.dtype, b.dtype)
        np.testing.assert_array_equal(a, b, strict=True, err_msg=where)
    elif is_dataclass(a):
        assert type(a) is type(b), where
        for f in fields(a):
            assert_same(getattr(a, f.name), getattr(b, f.name), f"{where}.{f.name}")
    elif isinstance(a, dict):
        assert isinstance(b, dict) and list(a) == list(b), (where, list(a), list(b))
        for key in a:
            assert_same(a[key], b[key], f"{where}.{key}")
    elif isinstance(a, list | tuple):
        assert type(a) is type(b) and len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            assert_same(x, y, f"{where}[{i}]")
    else:
        assert a == b, (where, a, b)


@pytest.fixture(scope="module")
def joined() -> CsamResult:
    """Map joining with the rendezvous filters on, so that every part of a result is filled."""
    log = simulate(load_scenario("map_joining"), seed=3)
    config = CsamConfig(rendezvous_consistency=True, rendezvous_min_interval=0.5)
    result = run_csam(log, config)
    assert set(result.rendezvous_filter) == {"consistency", "thinning"}
    return result


@pytest.fixture(scope="module")
def pending() -> CsamResult:
    """A robot that never met the others: a pending robot's None fields."""
    log = simulate(load_scenario("map_joining"), seed=3)
    for robot in log.robots.values():
        robot.rendezvous = RendezvousLog(np.zeros(0), [], *(np.zeros(0) for _ in range(4)))
    result = run_csam(log)
    assert result.robots["robot2"].alignment.startswith("pending")
    assert result.robots["robot2"].poses_joined is None
    return result


def round_trip(result: CsamResult) -> CsamResult:
    return CsamResult.from_dict(json.loads(json.dumps(result.to_dict())))


def test_csam_result_survives_json(joined: CsamResult, pending: CsamResult) -> None:
    for result in (joined, pending):
        back = round_trip(result)
        statistics = {k: float(v) for k, v in result.statistics.items()}  # JSON numbers
        assert_same(back.statistics, statistics)
        back.statistics = result.statistics
        assert_same(back, result)
        assert back.to_dict() == result.to_dict()
    robot = joined.robots["robot2"]
    assert robot.alignment == "aligned" and len(robot.feature_labels_local) > 10


def test_run_summary_survives_its_file(joined: CsamResult, tmp_path: Path) -> None:
    summary = RunSummary(
        joined,
        merger=MergerStats(dropped={"failed_solve": 1}, solves=7),
        dropped={"robot1": {}, "robot2": {"stamp_backwards": 2}},
        source="bags/map_joining",
        scenario="map_joining",
    )
    path = tmp_path / "summary.json"
    summary.write(path)
    document = json.loads(path.read_text())
    assert list(document)[-4:] == ["merger", "dropped", "source", "scenario"]
    back = RunSummary.read(path)
    assert back.to_dict() == summary.to_dict()
    assert back.merger == summary.merger and back.dropped == summary.dropped
    bare = RunSummary.from_dict(joined.to_dict())
    assert (bare.merger, bare.dropped, bare.source, bare.scenario) == (None, None, None, None)
    assert bare.to_dict() == joined.to_dict()


def _broken(document: dict, path: str, value: Any) -> dict:
    """``document`` with the entry at the dotted ``path`` set to ``value`` (``...``: deleted)."""
    document = copy.deepcopy(document)
    *parents, last = path.split(".")
    node: Any = document
    for key in parents:
        node = node[int(key)] if isinstance(node, list) else node[key]
    if value is Ellipsis:
        del node[last]
    elif isinstance(node, list):
        node[int(last)] = value
    else:
        node[last] = value
    return document


@pytest.mark.parametrize(
    ("path", "value", "message"),
    [
        ("features", ..., r"summary: no 'features' entry"),
        ("robots.robot2.stamps", ..., r"robots\.robot2: no 'stamps' entry"),
        (
            "robots.robot2.poses_local",
            [[0.0, 1.0]],
            r"robots\.robot2\.poses_local: expected shape \(N, 3\), got \(1, 2\)",
        ),
        (
            "robots.robot1.sigma_phi_local",
            [0.1, 0.2],
            r"robots\.robot1\.sigma_phi_local: 2 entries but \d+ stamps",
        ),
        (
            "robots.robot2.base_node",
            [1.0, "x", 2.0],
            r"robots\.robot2\.base_node: expected numbers",
        ),
        ("robots.robot2.stamps.3", None, r"robots\.robot2\.stamps: null among the numbers"),
        (
            "robots.robot2.base_node_cov",
            [1.0, 2.0, 3.0],
            r"robots\.robot2\.base_node_cov: expected shape \(3, 3\)",
        ),
        (
            "robots.robot2.features_local.0.label",
            "robot1/3",
            r"features_local\[0\]\.label: expected 'robot2/<integer>'",
        ),
        ("robots.robot1.alignment", None, r"robots\.robot1\.alignment: expected a string"),
        ("features.2.members", [], r"features\[2\]\.members: a feature needs at least one member"),
        ("features.2.cov", [[1.0, 0.0]], r"features\[2\]\.cov: expected shape \(2, 2\)"),
        (
            "associations.0.mahalanobis",
            "small",
            r"associations\[0\]\.mahalanobis: expected a number",
        ),
        ("timing_s.total", True, r"timing_s\.total: expected a number"),
        (
            "rendezvous_filter.thinning.kept",
            [],
            r"rendezvous_filter\.thinning\.kept: expected an object",
        ),
        ("notes", "none", r"notes: expected a list"),
        ("extra", 1, r"summary: unknown key\(s\) \['extra'\]"),
        ("merger", {"solves": 2}, r"merger: no 'dropped' entry"),
        (
            "dropped.robot1.stamp_backwards",
            -1,
            r"dropped\.robot1\.stamp_backwards: expected a count",
        ),
        ("scenario", 5, r"scenario: expected a string"),
        (
            "robots.robot2.local_check.trajectory_outliers",
            -2,
            r"robots\.robot2\.local_check\.trajectory_outliers: expected a count",
        ),
        (
            "robots.robot2.local_check.inconsistent_features",
            ["a"],
            r"robots\.robot2\.local_check\.inconsistent_features: expected integer labels",
        ),
    ],
)
def test_malformed_summary_names_the_key(
    joined: CsamResult, path: str, value: Any, message: str
) -> None:
    document = RunSummary(joined, dropped={"robot1": {}}).to_dict()
    with pytest.raises(SummaryError, match=message):
        RunSummary.from_dict(_broken(document, path, value))


def test_unreadable_summary_file_names_the_file(tmp_path: Path) -> None:
    path = tmp_path / "summary.json"
    path.write_text("{not json")
    with pytest.raises(SummaryError, match="summary.json"):
        RunSummary.read(path)
    path.write_text("[]")
    with pytest.raises(SummaryError, match=r"summary\.json: summary: expected an object"):
        RunSummary.read(path)


def test_summaries_from_before_the_local_map_check_still_read(joined: CsamResult) -> None:
    assert all(r.local_check is not None for r in joined.robots.values())
    document = joined.to_dict()
    for entry in document["robots"].values():
        del entry["local_check"]
    back = CsamResult.from_dict(document)
    assert all(r.local_check is None for r in back.robots.values())
    assert back.robots["robot2"].alignment == joined.robots["robot2"].alignment


def test_notes_are_written_as_their_texts_and_read_back_typed(joined: CsamResult) -> None:
    result = copy.copy(joined)
    left_out = [Note.no_local_map("robot3", "its solve failed"), Note.no_local_map("r4", "none")]
    result.notes = [
        left_out[0],
        Note.features_not_associated("robot2", [3, 8]),
        left_out[1],
        Note.not_converged_joint("maximum iterations reached", 1, 1903.1),
        Note(NoteKind.OTHER, "a note of another version"),
    ]
    document = json.loads(json.dumps(result.to_dict()))
    assert document["notes"] == [n.text for n in result.notes] == result.note_texts
    back = CsamResult.from_dict(document)
    assert back.notes == result.notes
    assert back.notes_of(NoteKind.NO_LOCAL_MAP) == left_out
    assert back.to_dict() == result.to_dict()


def test_notes_of_summaries_written_before_notes_were_typed_still_read(
    joined: CsamResult,
) -> None:
    document = joined.to_dict()
    document["notes"] = [
        "robot2: no local map: 1 usable odometry sample(s), a map needs two",
        "9 rendezvous measurement(s) of 'robot3' by 'robot2' ignored: no map of 'robot3'",
        "Algorithm 1 not converged: maximum iterations reached after 1 iterations (cost 14.483)",
        "joint solve not converged: maximum iterations reached after 1 iterations (cost 1903.1)",
    ]
    back = CsamResult.from_dict(document)
    assert [n.kind for n in back.notes] == [
        NoteKind.NO_LOCAL_MAP,
        NoteKind.RENDEZVOUS_LEFT_OUT,
        NoteKind.NOT_CONVERGED_ALIGNMENT,
        NoteKind.NOT_CONVERGED_JOINT,
    ]
    assert back.to_dict()["notes"] == document["notes"]


def test_odometry_calibration_is_an_optional_key(joined: CsamResult) -> None:
    joined = copy.deepcopy(joined)
    name = next(iter(joined.robots))
    assert "odometry_calibration" not in joined.to_dict()["robots"][name]  # off: as before
    joined.robots[name].odometry_calibration = np.array([[1.1, 0.66, 1.0], [0.01, 0.02, 0.5]])
    document = json.loads(json.dumps(joined.to_dict()))
    assert document["robots"][name]["odometry_calibration"]["scale"] == [1.1, 0.66, 1.0]
    back = CsamResult.from_dict(document)
    np.testing.assert_array_equal(
        back.robots[name].odometry_calibration, joined.robots[name].odometry_calibration
    )
    document["robots"][name]["odometry_calibration"]["sigma"] = [0.1]
    with pytest.raises(SummaryError, match="odometry_calibration.sigma"):
        CsamResult.from_dict(document)
