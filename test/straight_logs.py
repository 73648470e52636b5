"""Logs of robots driving straight on, one feature observation at each odometry sample: the
smallest real input for the offline pipeline, its command and its boundary tests.

test/conftest.py puts this folder on ``sys.path``, so a test imports it as ``straight_logs``.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np

from csam_ros.core.model.log import (
    FeatureLog,
    MultiRobotLog,
    OdometryLog,
    RobotLog,
    empty_rendezvous,
)
from csam_ros.run.bag_io import write_log_bag


def straight_robot(name: str, n: int, v: float = 0.1) -> RobotLog:
    """``n`` odometry samples 0.5 s apart at ``v`` m/s straight on, one feature seen at each."""
    t = 0.5 * np.arange(n)
    odometry = OdometryLog(t, np.tile([v, 0.0, 0.0], (n, 1)), np.full((n, 3), 0.01))
    features = FeatureLog(
        t, np.arange(n), np.full(n, 2.0), np.zeros(n), np.full(n, 0.01), np.full(n, 0.01)
    )
    return RobotLog(name, odometry, features, empty_rendezvous())


def straight_log_bag(path: Path, samples: Mapping[str, int], v: float = 0.1) -> Path:
    """A bag of sensor topics at ``path``: each robot ``samples`` straight steps at ``v``."""
    robots = {name: straight_robot(name, n, v) for name, n in samples.items()}
    write_log_bag(MultiRobotLog(robots), path)
    return path
