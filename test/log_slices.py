"""Parts of a simulated run in time, for tests that need what a robot had measured by then.

test/conftest.py puts this folder on ``sys.path``, so a test imports it as ``log_slices``.
"""

from __future__ import annotations

from dataclasses import fields, replace
from typing import Any

import numpy as np

from csam_ros.core.model.log import RobotLog


def _select(data: Any, keep: np.ndarray) -> Any:
    """A stamped log (a dataclass of equal-length fields) with the rows ``keep``."""
    return replace(
        data,
        **{
            f.name: (
                [v for v, k in zip(getattr(data, f.name), keep, strict=True) if k]
                if isinstance(getattr(data, f.name), list)
                else np.asarray(getattr(data, f.name))[keep]
            )
            for f in fields(data)
            if getattr(data, f.name) is not None  # an optional field left out stays None
        },
    )


def robot_log_between(log: RobotLog, start: float = -np.inf, end: float = np.inf) -> RobotLog:
    """``log`` with only what was measured from ``start`` to ``end`` (both included)."""

    def part(data: Any) -> Any:
        stamps = np.asarray(data.stamps)
        return _select(data, (stamps >= start) & (stamps <= end))

    return replace(
        log,
        odometry=part(log.odometry),
        features=part(log.features),
        rendezvous=part(log.rendezvous),
    )
