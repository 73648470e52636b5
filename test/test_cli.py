"""The `csam` command end to end: demo, its bag read by rosbags, replay and evaluate."""

from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from rosbags.highlevel import AnyReader
from straight_logs import straight_log_bag

from csam_ros.bag import MessageTypes
from csam_ros.core.joining.result import RunSummary
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
        "/robot1/local_map_updates",
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


def test_a_simulated_bag_replays_offline_to_the_cores_join_of_the_simulated_log(
    tmp_path: Path,
) -> None:
    """``csam simulate`` then ``csam replay --offline``: the joined map of the core on the
    scenario's simulated log (run_csam), to 1e-9."""
    from csam_ros.bench.many_robots import joined_difference
    from csam_ros.core.joining.config import CsamConfig
    from csam_ros.core.joining.pipeline import run_csam
    from csam_ros.datasets.scenario import load_document, load_scenario
    from csam_ros.datasets.simulation import simulate

    bag, out, scenario = tmp_path / "bag", tmp_path / "out", REPO / "config" / "chain.yaml"
    simulated = csam("simulate", "--scenario", scenario, "--out", bag, "--seed", "4")
    assert simulated.returncode == 0, simulated.stderr
    assert f"messages of 4 robot(s) to {bag}" in simulated.stdout
    replayed = csam("replay", bag, "--offline", "--config", scenario, "--out", out)
    assert replayed.returncode == 0, replayed.stderr
    summary = RunSummary.read(out / "summary.json")
    assert {"total", "local_maps"} <= set(summary.result.timing_s)
    config = CsamConfig.from_dict(load_document(scenario)["csam"], "csam")
    core = run_csam(simulate(load_scenario(scenario), 4), config)
    assert summary.result.joined_robots() == core.joined_robots() == set(core.robots)
    same = joined_difference(summary.result, core)
    assert same.position_m < 1e-9 and same.heading_deg < 1e-9 and same.features_apart == 0
    assert same.poses == sum(len(r.stamps) for r in core.robots.values())
    assert same.features == len(core.features) > 0
    replayed_pairs = [(x.a, x.b) for x in summary.result.associations]
    assert replayed_pairs == [(x.a, x.b) for x in core.associations]
    np.testing.assert_allclose(
        [x.mahalanobis for x in summary.result.associations],
        [x.mahalanobis for x in core.associations],
        atol=1e-9,
    )


REST_MARKUP = re.compile(r"``|:[a-z]+:`|`[^`]+`_")  # ``literal``, :func:`x`, `link`_


def _commands(parser: argparse.ArgumentParser) -> Iterator[list[str]]:
    """The words of every command below ``parser`` (``[]``: the parser itself)."""
    yield []
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, child in action.choices.items():
                yield from ([name, *words] for words in _commands(child))


def test_every_help_says_what_each_argument_does_in_plain_text(capsys) -> None:
    """``csam [COMMAND...] --help``: a help string for every option, argument and
    subcommand, and no reST markup (double backticks, roles such as :func:)."""
    from csam_ros.cli import main, parser

    commands = list(_commands(parser()))
    assert ["replay"] in commands and ["bag", "recover"] in commands
    for words in commands:
        command = parser()
        for word in words:
            sub = next(a for a in command._actions if isinstance(a, argparse._SubParsersAction))
            command = sub.choices[word]
        for action in command._actions:
            assert action.help and action.help.strip(), (words, action.dest)
            if isinstance(action, argparse._SubParsersAction):
                for choice in action._choices_actions:
                    assert choice.help and choice.help.strip(), (words, choice.dest)
        with pytest.raises(SystemExit) as done:
            main([*words, "--help"])
        assert done.value.code == 0
        text = capsys.readouterr().out
        assert text.startswith(f"usage: csam {' '.join(words)}".rstrip()), text
        assert REST_MARKUP.search(text) is None, (words, REST_MARKUP.search(text))


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


def _planar(t) -> np.ndarray:
    """(x, y, yaw) of a geometry_msgs Transform about z."""
    r = t.rotation
    return np.array([t.translation.x, t.translation.y, 2 * np.arctan2(r.z, r.w)])


def _odometry_at(received: dict[int, np.ndarray], bag: Path, topic: str, stamp) -> np.ndarray:
    """``odom -> base_link`` at ``stamp``: as received on /tf, else (the last transforms of a
    run that ends at once may not reach a watcher) the pose of the odometry message the run
    recorded at that stamp, which the transform is made of."""
    from csam_ros.ros.conversions import time_to_ns

    stamp_ns = time_to_ns(stamp)
    if stamp_ns in received:
        return received[stamp_ns]
    store = MessageTypes().register_custom_types()
    with AnyReader([bag], default_typestore=store) as reader:
        connections = [c for c in reader.connections if c.topic == topic]
        for connection, _, raw in reader.messages(connections=connections):
            msg = reader.deserialize(raw, connection.msgtype)
            if msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec == stamp_ns:
                p, q = msg.pose.pose.position, msg.pose.pose.orientation
                return np.array([p.x, p.y, 2 * np.arctan2(q.z, q.w)])
    raise AssertionError(f"no odometry of {topic} at {stamp_ns} ns")


def test_a_demo_is_seen_by_other_ros_processes_unless_isolated(
    tmp_path: Path, ros_context, ros_domain: int, spin
) -> None:
    """A process on the caller's domain (this session's) receives the demo's joined map and
    frames; robot2's latest pose composed from /tf (merger, smoother's map -> odom, the
    simulator's odom -> base_link at that pose's stamp) is the joined map's. An --isolated
    demo runs on another domain."""
    import rclpy
    from rclpy.qos import QoSProfile

    from csam_ros.core.model import se2
    from csam_ros.ros.conversions import time_to_ns
    from csam_ros.ros.topics import JOINED_MAP, TF

    node = rclpy.create_node("watcher", context=ros_context)
    received: list = []
    frames: dict[tuple[str, str], np.ndarray] = {}
    odometry: dict[int, np.ndarray] = {}  # robot2/odom -> robot2/base_link by stamp

    def on_tf(msg) -> None:
        for t in msg.transforms:
            frames[(t.header.frame_id, t.child_frame_id)] = _planar(t.transform)
            if (t.header.frame_id, t.child_frame_id) == ("robot2/odom", "robot2/base_link"):
                odometry[time_to_ns(t.header.stamp)] = _planar(t.transform)

    node.create_subscription(JOINED_MAP.msgtype, JOINED_MAP.of(), received.append, JOINED_MAP.qos)
    # a deep history: at --rate 0 the run's /tf comes in bursts, and the last odometry
    # transform is needed
    node.create_subscription(TF.msgtype, TF.of(), on_tf, QoSProfile(depth=100_000))
    executor = rclpy.executors.SingleThreadedExecutor(context=ros_context)
    executor.add_node(node)
    try:
        for flag, seen in (([], True), (["--isolated"], False)):
            out = tmp_path / ("isolated" if flag else "visible")
            received.clear()
            frames.clear()
            demo = subprocess.Popen(
                [*CSAM, "demo", "--rate", "0", *flag, "--out", str(out)],
                stdout=subprocess.PIPE,
                stderr=subprocess.STDOUT,
                text=True,
                cwd=REPO,
            )
            spin(executor, lambda d=demo: d.poll() is not None, 240)
            output = demo.communicate(timeout=60)[0]
            assert demo.returncode == 0, output
            assert bool(received) == seen, output
            assert bool(frames) == seen, output
            domain = f"ROS_DOMAIN_ID {ros_domain}" in output
            assert domain == seen, output
            if seen:
                trajectory = {t.robot: t for t in received[-1].trajectories}["robot2"]
                joined = trajectory.poses[-1]
                composed = se2.compose(
                    se2.compose(
                        frames[("robot1/map", "robot2/map")], frames[("robot2/map", "robot2/odom")]
                    ),
                    _odometry_at(odometry, out / "bag", "/robot2/odom", trajectory.stamps[-1]),
                )
                assert ("robot2/map", "robot2/base_link") not in frames  # one parent: odom
                # the merger refines each map to its smoother's optimum (to the solver's
                # tolerance), the smoother's map -> odom is of its own estimate
                np.testing.assert_allclose(
                    se2.between([joined.x, joined.y, joined.theta], composed), 0.0, atol=1e-6
                )
    finally:
        node.destroy_node()
        executor.shutdown()


def test_live_replay_matches_offline_replay_and_prints_the_lag(tmp_path: Path) -> None:
    from csam_ros.run.lag import read_timeline

    bag = REPO / "bags" / "map_joining"
    live = csam("replay", bag, "--rate", "4", "--isolated", "--out", tmp_path / "live")
    assert live.returncode == 0, live.stdout + live.stderr
    stats = read_timeline(tmp_path / "live" / "bag").lag_stats()
    assert f"  {stats}\n" in live.stdout
    assert "lag from a local map to the joined map that uses it: mean " in live.stdout
    assert "  merger: " in live.stdout and " solves" in live.stdout
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
    from csam_ros.core.model.config_file import load_document
    from csam_ros.datasets.mrclam import import_mrclam, load_config
    from csam_ros.run.params import merger_params, smoother_params

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
    assert merger_params(document) == merger_params(base_document)
    assert smoother_params(document) == smoother_params(base_document)
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


def _summary_without(tmp: Path, key: str) -> Path:
    """A run directory whose summary.json (of a real offline run) lacks ``key``."""
    run = tmp / "run"
    done = csam("replay", straight_log_bag(tmp / "bag", {"robot1": 4}), "--offline", "--out", run)
    assert done.returncode == 0, done.stderr
    document = json.loads((run / "summary.json").read_text())
    del document[key]
    (run / "summary.json").write_text(json.dumps(document))
    return run


def _dataset(tmp: Path, name: str | None = None, content: bytes | None = b"") -> list[str]:
    """``import mrclam`` arguments for a small data set whose file ``name`` holds ``content``
    (None: the file is missing)."""
    from mrclam_files import PLAIN_CONFIG, small_dataset

    directory = small_dataset(tmp / "dataset")
    if name is not None:
        (directory / name).unlink()
        if content is not None:
            (directory / name).write_bytes(content)
    config = tmp / "plain.yaml"
    config.write_text(PLAIN_CONFIG)
    return ["import", "mrclam", str(directory), "--config", str(config)]


def _write(path: Path, content: str | bytes) -> Path:
    if isinstance(content, bytes):
        path.write_bytes(content)
    else:
        path.write_text(content)
    return path


BINARY = bytes(range(255, -1, -1)) * 4  # not UTF-8 from its first byte
BAG = REPO / "bags" / "map_joining"
BAD_INPUT = {
    # name: (arguments of csam given a tmp directory, what the one stderr line must name)
    "mrclam_empty_odometry": (
        lambda t: _dataset(t, "Robot1_Odometry.dat"),
        "Robot1_Odometry.dat: no valid odometry row",
    ),
    "mrclam_binary_odometry": (
        lambda t: _dataset(t, "Robot1_Odometry.dat", BINARY),
        "Robot1_Odometry.dat: no valid odometry row",
    ),
    "mrclam_empty_barcodes": (
        lambda t: _dataset(t, "Barcodes.dat"),
        "Barcodes.dat: no valid (subject, barcode) row",
    ),
    "mrclam_empty_landmarks": (
        lambda t: _dataset(t, "Landmark_Groundtruth.dat", b"# only a comment\n"),
        "Landmark_Groundtruth.dat: no valid landmark ground truth row",
    ),
    "mrclam_missing_landmarks": (
        lambda t: _dataset(t, "Landmark_Groundtruth.dat", None),
        "Landmark_Groundtruth.dat: missing",
    ),
    "mrclam_robots_not_numbers": (
        lambda t: [*_dataset(t), "--robots", "abc"],
        "--robots: expected robot numbers such as 1,2,3, got 'abc'",
    ),
    "mrclam_config_not_yaml": (
        lambda t: [*_dataset(t), "--config", str(_write(t / "c.yaml", "mrclam: [\n"))],
        "c.yaml: not valid YAML",
    ),
    "mrclam_config_noise_not_a_mapping": (
        lambda t: [*_dataset(t), "--config", str(_write(t / "c.yaml", "mrclam:\n  noise: 3\n"))],
        "c.yaml: mrclam.noise: expected a mapping of numbers",
    ),
    "mrclam_config_unknown_key": (
        lambda t: [
            *_dataset(t),
            "--config",
            str(_write(t / "c.yaml", "mrclam:\n  lable_seed: 1\n")),
        ],
        "c.yaml: mrclam: unknown key(s) ['lable_seed']",
    ),
    "slam2d_binary": (
        lambda t: ["import", "slam2d", str(_write(t / "f.g2o", BINARY))],
        "f.g2o:1: not UTF-8 text",
    ),
    "slam2d_only_landmark_edges": (
        lambda t: ["import", "slam2d", str(_write(t / "f.g2o", "EDGE_SE2_XY 0 1 1 0 1 0 1\n"))],
        "f.g2o: no odometry record (ODOMETRY or EDGE_SE2)",
    ),
    "slam2d_odometry_beyond_float_range": (
        lambda t: [
            "import",
            "slam2d",
            str(_write(t / "f.g2o", "EDGE_SE2 0 1 1e308 0 0 1 0 0 1 0 1\n")),
        ],
        "f.g2o:1: the record converts to a non-finite value",
    ),
    "replay_one_odometry_sample": (
        lambda t: ["replay", str(straight_log_bag(t / "bag", {"robot1": 1})), "--offline"],
        "robot1: no local map: ",
    ),
    "replay_speed_beyond_float_range": (  # dropped at the boundary, or its solve fails
        lambda t: ["replay", str(straight_log_bag(t / "bag", {"robot1": 4}, v=1e305)), "--offline"],
        "no robot has a local map: robot1: no local map: ",
    ),
    "replay_binary_config": (
        lambda t: ["replay", str(BAG), "--offline", "--config", str(_write(t / "c.yaml", BINARY))],
        "c.yaml: not valid YAML",
    ),
    "replay_unknown_config_section": (
        lambda t: [
            "replay",
            str(BAG),
            "--offline",
            "--config",
            str(_write(t / "c.yaml", "local_map: {}\nlocal_maps: {}\n")),
        ],
        "c.yaml: unknown top-level section(s) ['local_maps']; known: ['csam', ",
    ),
    "replay_out_is_a_file": (
        lambda t: ["replay", str(BAG), "--offline", "--out", str(_write(t / "taken", "mine"))],
        "taken exists and is not a directory",
    ),
    "evaluate_invalid_json": (
        lambda t: ["evaluate", str(_write(t / "summary.json", "{bad").parent)],
        "summary.json: Expecting property name",
    ),
    "evaluate_json_list": (
        lambda t: ["evaluate", str(_write(t / "summary.json", "[1, 2]").parent)],
        "summary.json: summary: expected an object, got list",
    ),
    "evaluate_no_features": (
        lambda t: ["evaluate", str(_summary_without(t, "features"))],
        "summary.json: summary: no 'features' entry",
    ),
    "simulate_missing_scenario": (
        lambda t: ["simulate", "--scenario", str(t / "nowhere.yaml")],
        "nowhere.yaml: no such file",
    ),
    "simulate_negative_seed": (
        lambda t: ["simulate", "--seed", "-2"],
        "--seed: expected 0..2147483647, got -2",
    ),
    "demo_missing_scenario": (
        lambda t: ["demo", "--scenario", str(t / "nowhere.yaml")],
        "nowhere.yaml: no such file",
    ),
    "demo_invalid_scenario": (
        lambda t: ["demo", "--scenario", str(_write(t / "s.yaml", "scenario:\n  name: x\n"))],
        "s.yaml: scenario.robots: expected a non-empty list",
    ),
}


@pytest.mark.parametrize("case", sorted(BAD_INPUT))
def test_bad_input_gives_one_line_and_exit_code_2(case: str, tmp_path: Path) -> None:
    """Each kind of bad input: exit code 2 and one line ``csam <command>: ...`` naming the
    file and line or key, never a traceback."""
    make_args, expected = BAD_INPUT[case]
    args = make_args(tmp_path)
    out = [] if "--out" in args or args[0] == "evaluate" else ["--out", str(tmp_path / "out")]
    result = csam(*args, *out)
    lines = result.stderr.strip().splitlines()
    assert result.returncode == 2, result.stderr
    assert len(lines) == 1 and "Traceback" not in result.stderr, result.stderr
    assert lines[0].startswith(f"csam {args[0]}: ") and expected in lines[0], lines[0]


def _killed_counter_bag(path: Path, flushed: int, unflushed: int) -> None:
    """A bag whose writer was never closed (as after SIGKILL): ``flushed`` messages on disk."""
    from csam_ros.bag import BagWriter

    bag = BagWriter(path, flush_period_s=3600)
    bag.add_topic("/counter", "std_msgs/msg/UInt32")
    for i in range(flushed + unflushed):
        bag.write("/counter", (i + 1) * 10**9, b"\x00\x01\x00\x00" + i.to_bytes(4, "little"))
        if i + 1 == flushed:
            bag.flush()
    bag._file.flush()


def test_bag_recover_rewrites_a_killed_bag_for_rosbags(tmp_path: Path) -> None:
    """Case 8 through the command: the recovered bag opens in rosbags with every flushed
    message; the report names the topic counts and the cut file; errors are one line."""
    killed = tmp_path / "killed"
    _killed_counter_bag(killed, flushed=12, unflushed=5)
    done = csam("bag", "recover", killed)
    assert done.returncode == 0, done.stderr
    out = tmp_path / "killed-recovered"
    assert f"recovered 12 message(s) of {killed} into {out}/" in done.stdout
    assert "/counter: 12" in done.stdout and "killed_0.mcap: cut short" in done.stdout
    with AnyReader([out]) as reader:
        values = [int.from_bytes(raw[4:], "little") for _, _, raw in reader.messages()]
    assert values == list(range(12))
    for args, words in (
        (["bag", "recover", killed, "--out", out], "already exists"),
        (["bag", "recover", tmp_path / "nowhere"], "does not exist"),
        (["bag", "recover", REPO / "README.md"], "not an MCAP file"),
    ):
        bad = csam(*args)
        assert bad.returncode == 2 and words in bad.stderr, bad.stderr
        assert len(bad.stderr.strip().splitlines()) == 1 and "Traceback" not in bad.stderr


def test_offline_replay_of_a_bag_with_a_damaged_chunk_warns_and_runs(tmp_path: Path) -> None:
    """Case 9 through the command: 64 bytes flipped inside a chunk of a recorded bag made
    `csam replay --offline` end in a ZstdError traceback; now that chunk is skipped with a
    warning line naming it, and the run completes."""
    import shutil

    from mcap.reader import make_reader

    bag = tmp_path / "map_joining"
    shutil.copytree(REPO / "bags" / "map_joining", bag)
    mcap = bag / "bag_0.mcap"
    with mcap.open("rb") as stream:
        summary = make_reader(stream).get_summary()
    assert summary is not None
    chunk = sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset)[1]
    data = bytearray(mcap.read_bytes())
    middle = chunk.chunk_start_offset + chunk.chunk_length // 2
    data[middle : middle + 64] = bytes(b ^ 0x5A for b in data[middle : middle + 64])
    mcap.write_bytes(bytes(data))
    done = csam("replay", bag, "--offline", "--out", tmp_path / "out")
    assert done.returncode == 0, done.stderr
    assert "Traceback" not in done.stderr
    warnings = [line for line in done.stderr.splitlines() if line.startswith("warning:")]
    assert len(warnings) == 1, done.stderr
    assert f"{mcap}: chunk at offset {chunk.chunk_start_offset} skipped" in warnings[0]
    assert "lost" in warnings[0]


def test_evaluate_opens_only_a_bag_as_the_summary_source(tmp_path: Path) -> None:
    """Case 10: summary.json's source names a file that is no bag: one line, exit 2."""
    document = {
        "reference_frame": "robot1/map",
        "robots": {},
        "features": [],
        "associations": [],
        "timing_s": {},
        "statistics": {},
        "notes": [],
        "rendezvous_filter": {},
    }
    for source in ("/etc/passwd", str(tmp_path)):
        (tmp_path / "summary.json").write_text(json.dumps({**document, "source": source}))
        bad = csam("evaluate", tmp_path)
        assert bad.returncode == 2, bad.stderr
        assert len(bad.stderr.strip().splitlines()) == 1 and "Traceback" not in bad.stderr
        assert f"{source} (the source named in summary.json) is not a readable bag" in bad.stderr
    assert not (tmp_path / "metrics.json").exists()


@pytest.mark.parametrize("mode", ["offline", "live"])
def test_replay_of_a_bag_cut_in_half_says_what_it_recovered(mode: str, tmp_path: Path) -> None:
    """A recorded bag whose .mcap file is cut at half its bytes replays its readable part
    (live and offline) and says, in one warning line, that the file was cut, how many of the
    messages in metadata.yaml it read and up to which log time; the run ends normally."""
    import shutil

    from csam_ros.bag import inspect_bag, read_bag

    bag = tmp_path / "map_joining"
    shutil.copytree(BAG, bag)
    listed = inspect_bag(bag).message_count
    mcap = bag / "bag_0.mcap"
    data = mcap.read_bytes()
    mcap.write_bytes(data[: len(data) // 2])
    stamps = [m.log_time_ns for m in read_bag(bag, on_damage=lambda _: None)]
    last = stamps[-1]
    args = ["--offline"] if mode == "offline" else ["--rate", "4", "--isolated"]
    done = csam("replay", bag, *args, "--out", tmp_path / "out")
    assert done.returncode == 0, done.stdout + done.stderr
    assert "Traceback" not in done.stderr
    warnings = [line for line in done.stderr.splitlines() if line.startswith("warning:")]
    assert len(warnings) == 1, done.stderr
    assert f"{mcap} is cut short" in warnings[0]
    assert (
        f"read {len(stamps)} message(s) of the {listed} in metadata.yaml, up to log time "
        f"{last // 10**9}.{last % 10**9:09d} s" in warnings[0]
    ), warnings[0]
    result = RunSummary.read(tmp_path / "out" / "summary.json").result
    assert sorted(result.robots) == ["robot1", "robot2"]
    for robot in result.robots.values():  # the readable part: the whole bag gives 70 poses
        assert robot.alignment in ("reference", "aligned") and 0 < len(robot.stamps) < 70


def _bag_copy(tmp: Path, **metadata: object) -> Path:
    """A copy of bags/map_joining with ``metadata`` set in its metadata.yaml."""
    import shutil

    import yaml

    bag = Path(shutil.copytree(BAG, tmp / "bag"))
    document = yaml.safe_load((bag / "metadata.yaml").read_text())
    document["rosbag2_bagfile_information"].update(metadata)
    (bag / "metadata.yaml").write_text(yaml.safe_dump(document))
    return bag


def _fifo_bag(tmp: Path) -> Path:
    """A bag directory whose bag_0.mcap is a FIFO (no metadata.yaml)."""
    import os

    bag = tmp / "fifo_bag"
    bag.mkdir()
    os.mkfifo(bag / "bag_0.mcap")
    return bag


def _state_with_scalar(tmp: Path) -> Path:
    """An offline replay's state whose odometry stamps are a scalar, not an array."""
    from straight_logs import straight_robot

    from csam_ros.core.exchange.checkpoint import FilterState, OfflineState
    from csam_ros.core.exchange.state_files import read_npz, write_npz

    path = tmp / "state.npz"
    OfflineState({"robot1": straight_robot("robot1", 4)}, FilterState({}, {})).write(path)
    header, arrays = read_npz(path, "offline")
    arrays["logs/robot1/odometry/stamps"] = np.float64(3.0)
    write_npz(path, "offline", header, arrays)
    return path


def _fifo(path: Path) -> Path:
    import os

    os.mkfifo(path)
    return path


HOSTILE_FILES = {
    # name: (arguments of csam given a tmp directory, what the one stderr line must name)
    "bandwidth_files_not_a_list": (
        lambda t: ["bandwidth", str(_bag_copy(t, files=5))],
        "metadata.yaml: files is 5, not a list",
    ),
    "bag_recover_files_not_a_list": (
        lambda t: ["bag", "recover", str(_bag_copy(t, files=5)), "--out", str(t / "r")],
        "metadata.yaml: files is 5, not a list",
    ),
    "replay_topics_not_a_list": (
        lambda t: ["replay", str(_bag_copy(t, topics_with_message_count=5)), "--offline"],
        "metadata.yaml: topics_with_message_count is 5, not a list",
    ),
    "bandwidth_file_listed_twice": (
        lambda t: ["bandwidth", str(_bag_copy(t, relative_file_paths=["bag_0.mcap"] * 2))],
        "metadata.yaml names bag_0.mcap twice",
    ),
    "bandwidth_fifo": (
        lambda t: ["bandwidth", str(_fifo_bag(t))],
        "bag_0.mcap: a FIFO, not a regular file",
    ),
    "bag_recover_fifo": (
        lambda t: ["bag", "recover", str(_fifo_bag(t)), "--out", str(t / "r")],
        "bag_0.mcap: a FIFO, not a regular file",
    ),
    "import_slam2d_id_beyond_64_bits": (
        lambda t: [
            "import",
            "slam2d",
            str(_write(t / "f.g2o", "EDGE_SE2 0 100000000000000000000 1 0 0 1 0 0 1 0 1\n")),
            "--out",
            str(t / "out"),
        ],
        "f.g2o:1: EDGE_SE2 has an id beyond",
    ),
    "replay_resume_scalar_array": (
        lambda t: ["replay", str(BAG), "--offline", "--resume", str(_state_with_scalar(t))],
        "state.npz: array 'logs/robot1/odometry/stamps' is a scalar, not an array",
    ),
    "replay_save_state_onto_a_fifo": (
        lambda t: ["replay", str(BAG), "--offline", "--save-state", str(_fifo(t / "s.npz"))],
        "--save-state: " + "{t}/s.npz: a FIFO, not a regular file",
    ),
    "evaluate_summary_not_utf8": (
        lambda t: ["evaluate", str(_write(t / "summary.json", BINARY).parent)],
        "summary.json: not UTF-8 text (byte 0)",
    ),
}


@pytest.mark.parametrize("case", sorted(HOSTILE_FILES))
def test_hostile_files_end_in_one_line_and_exit_code_2(case: str, tmp_path: Path, capsys) -> None:
    """Files made to break the command (a metadata.yaml section of the wrong kind, a FIFO
    where a file belongs, an id beyond 64 bits, a scalar in a state file, a device or FIFO as
    the output, a summary that is not text): one line naming the file, exit code 2, never a
    traceback or a wait. Run in this process (no interpreter start per case)."""
    from waiting import no_hang

    from csam_ros.cli import main

    make_args, expected = HOSTILE_FILES[case]
    args = make_args(tmp_path)
    if args[0] == "replay":
        args += ["--out", str(tmp_path / "out")]
    with no_hang(120.0):
        code = main(args)
    lines = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(lines) == 1, lines
    assert lines[0].startswith(f"csam {args[0]}: "), lines[0]
    assert expected.format(t=tmp_path) in lines[0], lines[0]
