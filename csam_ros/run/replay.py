"""The live replay (``csam replay`` without ``--offline``): the player of a recorded bag feeding
its sensor topics to smoothers and a merger, recorded to a new bag."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

from csam_ros.core.model.regular_files import check_replaceable, open_regular
from csam_ros.run.errors import RunError
from csam_ros.run.launch import executable
from csam_ros.run.offline import bag_contents

if TYPE_CHECKING:
    from csam_ros.run.live import LiveRun


def check_replay(bag: Path, offline: bool, save_state: Path | None, resume: Path | None) -> None:
    """That the bag exists, the state options go with an offline replay and name regular
    files (a FIFO would block the read, a device be replaced by the write), before any
    work."""
    if not bag.exists():
        raise RunError(f"{bag}: no such bag")
    if (save_state or resume) and not offline:
        raise RunError(
            "--save-state and --resume go with --offline (a live merger saves its state "
            "through its state_path parameter)"
        )
    for option, path, check in (
        ("--save-state", save_state, check_replaceable),
        ("--resume", resume, lambda p: open_regular(p).close()),
    ):
        try:
            if path is not None:
                check(path)
        except OSError as err:
            raise RunError(f"{option}: {path}: {err.strerror or err}") from None


def replay_live_run(
    bag: Path,
    out: Path,
    rate: float,
    merger_params: dict,
    smoother_params: dict,
    isolated: bool = False,
) -> LiveRun:
    """The live run of ``csam replay``: the player of ``bag`` at ``rate`` times real time (0:
    as fast as it goes) into smoothers and a merger with these parameters, recorded to
    ``out/bag``."""
    from csam_ros.ros.topics import FEATURES_TRUTH, sensor_topics
    from csam_ros.run.live import LiveRun

    robots, duration, in_bag = bag_contents(bag)
    # the sensor topics a bag has (a 2D SLAM file's has feature points, no features)
    sensors = [t for t in sensor_topics(robots) if t in in_bag]
    topics = [t for t in [*sensors, FEATURES_TRUTH.name] if t in in_bag]
    return LiveRun(
        out_dir=out,
        robots=robots,
        source_name="player",
        source_argv=[
            executable("player"),
            str(bag),
            "--rate",
            str(rate),
            "--topics",
            *topics,
            "--delay",  # let discovery settle both ways: odometry is best effort
            "2.0",
            "--wait-for-subscribers",
            *sensors,
            "--min-subscribers",  # the recorder and at least the robot's smoother
            "2",
        ],
        smoother_params=smoother_params,
        merger_params=merger_params,
        # the playback itself plus a margin (a replay at --rate 0 is not paced)
        timeout_s=600.0 + (1.2 * duration / rate if rate > 0 else duration),
        isolated=isolated,
    )
