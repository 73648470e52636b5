"""summary.json: to_dict and from_dict are inverses; a malformed summary names its key."""

from __future__ import annotations

import copy
import json
from dataclasses import fields, is_dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from csam_ros.core.joining.csam import CsamConfig, run_csam
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
