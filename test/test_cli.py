"""The `csam` command end to end: demo, its bag read by rosbags, replay and evaluate."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from rosbags.highlevel import AnyReader

from csam_ros.bag import MessageTypes
from csam_ros.core.result import RunSummary
from csam_ros.datasets.mrclam import default_dataset_dir

MRCLAM = default_dataset_dir()
REPO = Path(__file__).resolve().parents[1]
CSAM = [sys.executable, "-m", "csam_ros.cli"]


def csam(*args: str | Path, timeout: float = 240) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [*CSAM, *map(str, args)], capture_output=True, text=True, timeout=timeout, cwd=REPO
    )


def _last_joined_map(bag: Path):
    """The final /csam/joined_map recorded in a bag, read with rosbags."""
    store = MessageTypes().register_custom_types()
    with AnyReader([bag], default_typestore=store) as reader:
        connections = [c for c in reader.connections if c.topic == "/csam/joined_map"]
        last = None
        for connection, _, raw in reader.messages(connections=connections):
            last = reader.deserialize(raw, connection.msgtype)
    return last


@pytest.fixture(scope="module")
def demo_run(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("demo") / "run"
    result = csam("demo", "--scenario", "map_joining", "--rate", "0", "--out", out)
    assert result.returncode == 0, result.stdout + result.stderr
    return out


def test_demo_writes_bag_summary_and_figures(demo_run: Path) -> None:
    summary = RunSummary.read(demo_run / "summary.json")
    assert summary.scenario == "map_joining"
    assert summary.merger is not None and summary.merger.solves >= 1
    result = summary.result
    assert result.reference_frame == "robot1/map"
    assert result.robots["robot1"].alignment == "reference"
    assert result.robots["robot2"].alignment == "aligned"
    for name in ("local_maps.png", "heading_sigma.png", "joined_map.png"):
        assert (demo_run / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # the bag, read by rosbags alone
    store = MessageTypes().register_custom_types()
    with AnyReader([demo_run / "bag"], default_typestore=store) as reader:
        topics = {c.topic: c.msgcount for c in reader.connections}
    for topic in (
        "/robot1/odom",
        "/robot1/features",
        "/robot2/rendezvous",
        "/robot1/local_map",
        "/robot2/rendezvous_poses",
        "/csam/joined_map",
        "/csam/markers",
        "/sim/features_truth",
    ):
        assert topics.get(topic, 0) > 0, topic
    joined = _last_joined_map(demo_run / "bag")
    assert len(joined.features) == len(result.features)


def test_offline_replay_reproduces_the_live_run(demo_run: Path, tmp_path: Path) -> None:
    live = RunSummary.read(demo_run / "summary.json").result
    first, second = tmp_path / "a", tmp_path / "b"
    for out in (first, second):
        result = csam("replay", demo_run / "bag", "--offline", "--out", out)
        assert result.returncode == 0, result.stderr
    a = json.loads((first / "summary.json").read_text())
    b = json.loads((second / "summary.json").read_text())
    a.pop("timing_s"), b.pop("timing_s")
    a.pop("source"), b.pop("source")
    assert a == b  # offline replay is deterministic
    offline = RunSummary.read(first / "summary.json")
    assert offline.merger is None and offline.dropped == {"robot1": {}, "robot2": {}}
    for name, robot in live.robots.items():
        np.testing.assert_allclose(
            offline.result.robots[name].poses_joined, robot.poses_joined, atol=1e-6
        )
    assert {(x.a, x.b) for x in offline.result.associations} == {
        (x.a, x.b) for x in live.associations
    }


def test_evaluate_scores_the_demo(demo_run: Path) -> None:
    result = csam("evaluate", demo_run)
    assert result.returncode == 0, result.stderr
    metrics = json.loads((demo_run / "metrics.json").read_text())
    assert metrics["association"]["precision"] == 1.0
    assert metrics["association"]["recall"] >= 0.9
    assert metrics["landmark_error"]["rmse_m"] < 0.1


def test_evaluate_names_what_is_wrong_in_a_summary(tmp_path: Path) -> None:
    (tmp_path / "summary.json").write_text(json.dumps({"reference_frame": "robot1/map"}))
    bad = csam("evaluate", tmp_path)
    assert bad.returncode == 2 and "Traceback" not in bad.stderr
    assert "summary.json: summary: no 'robots' entry" in bad.stderr
    assert not (tmp_path / "metrics.json").exists()


@pytest.mark.parametrize("scenario", ["map_joining", "sensor_extension"])
def test_recorded_bags_replay_to_their_recorded_joined_map(scenario: str, tmp_path: Path) -> None:
    bag = REPO / "bags" / scenario
    result = csam("replay", bag, "--offline", "--out", tmp_path / "out")
    assert result.returncode == 0, result.stderr
    summary = RunSummary.read(tmp_path / "out" / "summary.json")
    assert (summary.source, summary.scenario) == (str(bag), scenario)
    recorded = _last_joined_map(bag)
    for trajectory in recorded.trajectories:
        poses = np.array([[p.x, p.y, p.theta] for p in trajectory.poses])
        np.testing.assert_allclose(
            summary.result.robots[trajectory.robot].poses_joined, poses, atol=1e-6
        )
    assert len(summary.result.associations) == len(recorded.associations)


def test_bad_arguments_give_one_line_errors(tmp_path: Path) -> None:
    missing = csam("replay", tmp_path / "no_such_bag", "--offline")
    assert missing.returncode == 2
    assert "no such bag" in missing.stderr and "Traceback" not in missing.stderr
    occupied = tmp_path / "occupied"
    occupied.mkdir()
    (occupied / "keep.txt").write_text("mine")
    taken = csam("demo", "--out", occupied)
    assert taken.returncode == 2 and "not empty" in taken.stderr
    assert (occupied / "keep.txt").read_text() == "mine"
    exists = csam("import", "mrclam", tmp_path, "--out", occupied)
    assert exists.returncode == 2 and "never overwrites" in exists.stderr
    bad_config = tmp_path / "bad.yaml"
    bad_config.write_text("local_map:\n  robust_kernel: tukey\n")
    bag = REPO / "bags" / "map_joining"
    for config in (bad_config, tmp_path / "missing.yaml"):
        for mode in (["--offline"], []):
            bad = csam("replay", bag, *mode, "--config", config, "--out", tmp_path / "never")
            assert bad.returncode == 2, bad.stderr
            assert len(bad.stderr.strip().splitlines()) == 1 and "Traceback" not in bad.stderr
            assert not (tmp_path / "never").exists()


def test_live_replay_matches_offline_replay(tmp_path: Path) -> None:
    bag = REPO / "bags" / "map_joining"
    live = csam("replay", bag, "--rate", "4", "--out", tmp_path / "live")
    assert live.returncode == 0, live.stdout + live.stderr
    offline = csam("replay", bag, "--offline", "--out", tmp_path / "offline")
    assert offline.returncode == 0, offline.stderr
    a = RunSummary.read(tmp_path / "live" / "summary.json").result
    b = RunSummary.read(tmp_path / "offline" / "summary.json").result
    for name, robot in b.robots.items():
        assert a.robots[name].alignment == robot.alignment
        np.testing.assert_allclose(a.robots[name].poses_joined, robot.poses_joined, atol=1e-6)
    assert len(a.associations) == len(b.associations)


@pytest.mark.skipif(MRCLAM is None or not MRCLAM.is_dir(), reason="MR.CLAM Dataset 1 not present")
def test_mrclam_window_imports_replays_and_evaluates(tmp_path: Path) -> None:
    """Real data end to end with the real-data settings: five robots, the first 120 s."""
    bag = tmp_path / "mrclam"
    imported = csam("import", "mrclam", MRCLAM, "--duration", "120", "--out", bag)
    assert imported.returncode == 0, imported.stderr
    run = tmp_path / "run"
    config = REPO / "config" / "mrclam.yaml"
    replay = csam("replay", bag, "--offline", "--config", config, "--out", run)
    assert replay.returncode == 0, replay.stderr
    evaluated = csam("evaluate", run)
    assert evaluated.returncode == 0, evaluated.stderr
    metrics = json.loads((run / "metrics.json").read_text())
    assert all(robot["joined"] for robot in metrics["robots"].values())
    assert metrics["association"]["precision"] == 1.0
    assert metrics["landmark_error"]["rmse_m"] < 0.15
    summary = RunSummary.read(run / "summary.json")
    assert "consistency" in summary.result.rendezvous_filter
    assert (run / "joined_map.png").stat().st_size > 0


def test_calibrate_gives_one_line_errors(tmp_path: Path) -> None:
    missing = csam("calibrate", "mrclam", tmp_path / "nowhere", "--out", tmp_path / "c.yaml")
    assert missing.returncode == 2 and "no such data set directory" in missing.stderr
    assert len(missing.stderr.strip().splitlines()) == 1
    taken = tmp_path / "taken.yaml"
    taken.write_text("mine")
    exists = csam("calibrate", "mrclam", tmp_path, "--out", taken)
    assert exists.returncode == 2 and "never overwrites" in exists.stderr
    assert taken.read_text() == "mine"


@pytest.mark.skipif(MRCLAM is None or not MRCLAM.is_dir(), reason="MR.CLAM Dataset 1 not present")
def test_calibrate_writes_a_config_the_importer_and_replay_read(tmp_path: Path) -> None:
    """The first 200 s of Dataset 1, two EM rounds: a config file in config/mrclam.yaml's form."""
    from csam_ros.cli import _csam_params, _smoother_params
    from csam_ros.core.config_file import load_document
    from csam_ros.datasets.mrclam import import_mrclam, load_config

    out = tmp_path / "calibrated" / "mrclam.yaml"
    base = REPO / "config" / "mrclam.yaml"
    args = ["--duration", "200", "--rounds", "2", "--config", base, "--out", out]
    done = csam("calibrate", "mrclam", MRCLAM, *args)
    assert done.returncode == 0, done.stderr
    assert "EM round 2" in done.stdout and f"wrote {out}" in done.stdout
    config = load_config(out)
    reference = load_config(base)
    assert config["landmark_swaps"] == reference["landmark_swaps"]
    assert 0.02 < config["noise"].sigma_range_per_m < 0.06
    assert 1.0 < config["noise"].rendezvous_bearing_factor < 3.0
    assert sorted(config["range_scale"]) == [1, 2, 3, 4, 5]
    assert all(0.97 < v < 1.03 for v in config["range_scale"].values())
    document, base_document = load_document(out), load_document(base)
    for section in ("local_map", "merger", "csam"):
        assert document[section] == base_document[section]
    assert _csam_params(document) == _csam_params(base_document)
    assert _smoother_params(document) == _smoother_params(base_document)
    log, report = import_mrclam(
        MRCLAM, duration=10.0, noise=config["noise"], range_scale=config["range_scale"]
    )
    assert report.range_scale == {f"robot{k}": v for k, v in config["range_scale"].items()}
    imported = csam(
        "import", "mrclam", MRCLAM, "--duration", "10", "--config", out, "--out", tmp_path / "bag"
    )
    assert imported.returncode == 0, imported.stderr
    scales = " ".join(f"{config['range_scale'][r]:>8.4f}" for r in range(1, 6))
    assert f"{scales}  range scale" in imported.stdout
    bad = csam(
        "import", "mrclam", MRCLAM, "--config", tmp_path / "no.yaml", "--out", tmp_path / "b"
    )
    assert bad.returncode == 2 and bad.stderr.startswith("csam import: --config:"), bad.stderr
    again = csam("calibrate", "mrclam", MRCLAM, *args)
    assert again.returncode == 2 and "never overwrites" in again.stderr
