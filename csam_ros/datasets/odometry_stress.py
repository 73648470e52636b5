"""Odometry that lies: a robot's reported odometry miscalibrated as real robots' is
(MR.CLAM-like: the logged turn while driving ~1.5x the real one), the truth unchanged.

``turn_driving`` scales the reported turn rate where ``|v| > driving_speed``, ``turn_spot``
where not, ``distance`` the reported speeds; ``resample_hz`` (0: off) then holds the reported
input piecewise constant over windows of ``1/resample_hz`` s (the mean input of the window,
reported at its last sample's stamp, so that the composed motion is kept; sigmas scaled by
``sqrt(sample period / window)``: the same noise density). A local map with
``odometry_calibration`` should estimate ``(1/distance, 1/turn_driving, 1/turn_spot)``.
``slip_turn`` (rad, 0: none) is a turn the odometry reports and the robot never makes (a
wheel slip or a bump), in the sample ``slip_at`` s after the first: no calibration explains
it, ``fold_recovery`` must (docs/METHOD.md, a fold cannot persist).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from csam_ros.core.model.log import MultiRobotLog, OdometryLog


@dataclass(frozen=True)
class OdometryStress:
    """How a robot's reported odometry is miscalibrated (see the module docstring)."""

    turn_driving: float = 1.0
    turn_spot: float = 1.0
    distance: float = 1.0
    resample_hz: float = 0.0
    driving_speed: float = 0.02
    slip_at: float = 0.0
    slip_turn: float = 0.0

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            negative = value < 0 and f.name != "slip_turn"
            if not np.isfinite(value) or negative or (value == 0 and f.name in SCALES):
                kind = "finite" if f.name == "slip_turn" else "positive"
                raise ValueError(f"odometry stress: {f.name} must be a {kind} number, not {value}")

    @property
    def applied(self) -> np.ndarray:
        """The calibration ``(s, k_d, k_s)`` that undoes this stress."""
        return 1.0 / np.array([self.distance, self.turn_driving, self.turn_spot])


SCALES = ("turn_driving", "turn_spot", "distance")


def parse_odometry_stress(text: str) -> OdometryStress:
    """``turn_driving=1.54,distance=0.9,resample_hz=8`` as an :class:`OdometryStress`."""
    names = {f.name for f in dataclasses.fields(OdometryStress)}
    values: dict[str, float] = {}
    for item in filter(None, (part.strip() for part in text.split(","))):
        key, sep, value = item.partition("=")
        if not sep or key.strip() not in names:
            raise ValueError(f"expected NAME=NUMBER with NAME one of {sorted(names)}, got {item!r}")
        try:
            values[key.strip()] = float(value)
        except ValueError:
            raise ValueError(f"{key.strip()}: {value!r} is not a number") from None
    return OdometryStress(**values)


def stress_odometry(odometry: OdometryLog, stress: OdometryStress) -> OdometryLog:
    """The odometry as a robot miscalibrated by ``stress`` would report it."""
    t = np.asarray(odometry.stamps, dtype=float)
    u = np.array(odometry.inputs, dtype=float)
    u[:, :2] *= stress.distance
    driving = np.abs(u[:, 0]) > stress.driving_speed  # as reported, as the calibration sees it
    u[:, 2] *= np.where(driving, stress.turn_driving, stress.turn_spot)
    if stress.slip_turn and len(t) > 1:
        i = min(max(int(np.searchsorted(t, t[0] + stress.slip_at)), 1), len(t) - 1)
        u[i, 2] += stress.slip_turn / (t[i] - t[i - 1])  # sample i holds (t[i-1], t[i]]
    if not stress.resample_hz or len(t) < 2:
        return OdometryLog(t.copy(), u, np.array(odometry.sigmas), odometry.correlations)
    window = np.floor((t - t[0]) * stress.resample_hz - 1e-9).astype(np.int64)
    window[0] = -1  # the first sample only marks the start
    last = np.flatnonzero(np.diff(np.append(window, window[-1] + 1)))
    dt = np.diff(t, prepend=t[0])
    first = np.concatenate([[0], last[:-1] + 1])
    span = np.add.reduceat(dt, first)
    mean = np.add.reduceat(u * dt[:, None], first, axis=0) / np.where(span > 0, span, 1.0)[:, None]
    mean[0] = u[0]
    count = np.diff(np.append(first, len(t)))  # samples per window: sigma^2 T kept
    sigmas = np.asarray(odometry.sigmas, dtype=float)[last] / np.sqrt(count)[:, None]
    sigmas[0] = odometry.sigmas[0]
    rho = None if odometry.correlations is None else np.asarray(odometry.correlations)[last]
    return OdometryLog(t[last], mean, sigmas, rho)


def stress_log(log: MultiRobotLog, stress: OdometryStress) -> MultiRobotLog:
    """Every robot's odometry stressed; features, rendezvous and truth unchanged."""
    robots = {
        name: dataclasses.replace(robot, odometry=stress_odometry(robot.odometry, stress))
        for name, robot in log.robots.items()
    }
    return MultiRobotLog(robots, log.truth)
