"""The live replay as built before any node starts: the player of a bag's sensor topics, its
timeout from the bag's duration and the rate, and the options it refuses."""

from __future__ import annotations

from pathlib import Path

import pytest

from csam_ros.run.errors import RunError
from csam_ros.run.offline import bag_contents
from csam_ros.run.replay import check_replay, replay_live_run

BAG = Path(__file__).resolve().parents[2] / "bags" / "map_joining"


def test_a_missing_bag_or_state_options_of_a_live_replay_are_run_errors(tmp_path: Path) -> None:
    check_replay(BAG, offline=True, save_state=tmp_path / "s.npz", resume=None)
    check_replay(BAG, offline=False, save_state=None, resume=None)
    with pytest.raises(RunError, match="no_bag: no such bag"):
        check_replay(tmp_path / "no_bag", offline=True, save_state=None, resume=None)
    with pytest.raises(RunError, match="^--save-state and --resume go with --offline"):
        check_replay(BAG, offline=False, save_state=None, resume=tmp_path / "s.npz")


def test_the_player_plays_the_bags_sensor_topics_at_the_rate(tmp_path: Path) -> None:
    _, duration, _ = bag_contents(BAG)
    run = replay_live_run(BAG, tmp_path, 4.0, {"solve_period": 0.5}, {"a": 1}, isolated=True)
    argv = run.source_argv
    assert run.robots == ["robot1", "robot2"] and run.source_name == "player"
    assert argv[1:4] == [str(BAG), "--rate", "4.0"]
    played = argv[argv.index("--topics") + 1 : argv.index("--delay")]
    waited = argv[argv.index("--wait-for-subscribers") + 1 : argv.index("--min-subscribers")]
    assert waited == [t for t in played if t != "/sim/features_truth"]
    assert "/robot1/odom" in waited and "/sim/features_truth" in played
    assert (run.merger_params, run.smoother_params) == ({"solve_period": 0.5}, {"a": 1})
    assert run.timeout_s == pytest.approx(600.0 + 1.2 * duration / 4.0)
    unpaced = replay_live_run(BAG, tmp_path, 0.0, {}, {})
    assert unpaced.timeout_s == pytest.approx(600.0 + duration) and not unpaced.isolated


def test_state_options_naming_a_fifo_are_run_errors_before_any_work(tmp_path: Path) -> None:
    """--resume naming a FIFO would block its read, --save-state naming one (or a device)
    would be replaced by the state written: each refused by name at once."""
    import os
    import stat

    from waiting import no_hang

    fifo = tmp_path / "state.npz"
    os.mkfifo(fifo)
    with no_hang(10.0):
        with pytest.raises(RunError, match="^--resume: .*state.npz: a FIFO, not a regular"):
            check_replay(BAG, offline=True, save_state=None, resume=fifo)
        with pytest.raises(RunError, match="^--save-state: .*state.npz: a FIFO, not a regular"):
            check_replay(BAG, offline=True, save_state=fifo, resume=None)
    with pytest.raises(RunError, match="^--resume: .*none.npz: No such file"):
        check_replay(BAG, offline=True, save_state=None, resume=tmp_path / "none.npz")
    assert stat.S_ISFIFO(os.lstat(fifo).st_mode)
