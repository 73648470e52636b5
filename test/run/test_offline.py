"""The offline replay: a bag's sensor data through the core in stamp order, read here or in a
forked process, and what it cannot use named as one RunError."""

from __future__ import annotations

from pathlib import Path

import pytest
from straight_logs import straight_log_bag

from csam_ros.run.errors import RunError
from csam_ros.run.offline import bag_contents, offline_summary, read_offline_log, reading_ahead

BAG = Path(__file__).resolve().parents[2] / "bags" / "map_joining"


def test_a_bag_names_its_robots_duration_and_topics() -> None:
    robots, duration, topics = bag_contents(BAG)
    assert robots == ["robot1", "robot2"]
    assert duration > 0 and "/robot1/odom" in topics and "/sim/features_truth" in topics


def test_a_bag_without_sensor_topics_is_a_run_error(tmp_path: Path) -> None:
    from csam_ros.bag import BagWriter

    with BagWriter(tmp_path / "chatter") as bag:
        bag.add_topic("/chatter", "std_msgs/msg/UInt32")
        bag.write("/chatter", 1, b"\x00\x01\x00\x00\x07\x00\x00\x00")
    with pytest.raises(RunError, match="chatter: no sensor topics"):
        bag_contents(tmp_path / "chatter")


def test_reading_ahead_gives_the_replay_read_here() -> None:
    """The log read in a forked process and the one read here give the same summary."""
    here, truth = offline_summary(BAG)
    with reading_ahead(BAG, {}) as reading:
        ahead, _ = offline_summary(BAG, {}, reading=reading)
    assert truth is not None and len(truth.feature_positions) > 0
    assert ahead.dropped == here.dropped == {"robot1": {}, "robot2": {}}
    assert ahead.result.to_dict() | {"timing_s": {}} == here.result.to_dict() | {"timing_s": {}}


def test_what_the_replay_cannot_use_is_one_run_error(tmp_path: Path) -> None:
    with pytest.raises(RunError, match="robot1: no local map: "):
        offline_summary(straight_log_bag(tmp_path / "one", {"robot1": 1}))
    with pytest.raises(RunError, match="^csam"):
        offline_summary(BAG, {"csam": {"no_such_key": 1}})
    with pytest.raises(RunError, match="^input"):
        read_offline_log(BAG, {"input": {"no_such_key": 1}})
    (tmp_path / "bad.npz").write_text("not a state")
    with pytest.raises(RunError, match="^--resume: "):
        read_offline_log(BAG, resume=tmp_path / "bad.npz")


def test_a_saved_state_is_said_to_progress(tmp_path: Path) -> None:
    said: list[str] = []
    state = tmp_path / "state.npz"
    offline_summary(BAG, save_state=state, progress=said.append)
    size = state.stat().st_size / 1e6
    assert said == [f"  state saved to {state} ({size:.2f} MB)"]
