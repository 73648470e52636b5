"""Joins of a simulated run at moments of it, for tests of what a merger does as maps grow.

test/conftest.py puts this folder on ``sys.path``, so a test imports it as ``growing_joins``.
"""

from __future__ import annotations

import numpy as np
from log_slices import robot_log_between

from csam_ros.core.joining.pipeline import robot_map_from_local_map
from csam_ros.core.joining.result import CsamResult
from csam_ros.core.model import se2
from csam_ros.core.model.log import MultiRobotLog, RendezvousLog
from csam_ros.core.model.rendezvous import required_stamps
from csam_ros.core.smoothing.local_map_build import build_local_map
from csam_ros.core.smoothing.robot_map import RobotMap


def maps_until(log: MultiRobotLog, t: float) -> tuple[list[RobotMap], dict[str, RendezvousLog]]:
    """The robots' local maps and rendezvous logs of the run up to ``t``."""
    robots = {n: robot_log_between(r, end=t) for n, r in log.robots.items()}
    logs = {n: r.rendezvous for n, r in robots.items()}
    stamps = required_stamps(logs)
    maps = [robot_map_from_local_map(build_local_map(r, stamps[n])) for n, r in robots.items()]
    return maps, logs


def largest_difference(a: CsamResult, b: CsamResult) -> float:
    """The largest difference of two joins' poses, base nodes and features (their robots
    and associations must be the same)."""
    assert a.joined_robots() == b.joined_robots()
    assert [f.members for f in a.features] == [f.members for f in b.features]
    worst = 0.0
    for name in a.joined_robots():
        d = a.robots[name].poses_joined - b.robots[name].poses_joined
        d[:, 2] = se2.wrap_angle(d[:, 2])
        worst = max(worst, float(np.abs(d).max()))
        worst = max(worst, float(np.abs(a.robots[name].base_node - b.robots[name].base_node).max()))
    for fa, fb in zip(a.features, b.features, strict=True):
        worst = max(worst, float(np.abs(fa.xy - fb.xy).max()), float(np.abs(fa.cov - fb.cov).max()))
    return worst
