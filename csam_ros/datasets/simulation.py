"""Simulated world and robots producing a :class:`~csam_ros.core.model.log.MultiRobotLog`.

The world is a set of point features; each robot follows a program of constant
``(v, omega)`` segments sampled every ``sample_time`` seconds on a clock shared by all robots.
The true motion is the commanded one; the logged odometry is the commanded input plus white
noise of the robot's ``odometry_sigma`` (so the logged input ``u_i`` satisfies
``x_i = x_{i-1} (+) U(u_i - w_i, T)`` with ``w_i ~ N(0, diag(sigma^2))``, docs/METHOD.md section 2).
Because the true paths do not depend on the noise seed, rendezvous happen at the same samples
for every seed.

At every pose (the first one included) a robot scans once with its feature sensor (range and
field of view, docs/METHOD.md section 3: the paper's URG-04LX has 4 m, 240 degrees,
``s_r = 0.01 m``, ``s_beta = 0.012 rad``) and with its rendezvous sensor observes every other
robot it may observe that is in range and field of view. Each robot labels features with its
own numbering (a seeded permutation plus a per-robot offset), so labels mean nothing across
robots; the label -> feature map stays in :class:`~csam_ros.core.model.log.GroundTruth`, for
scoring only.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from csam_ros.core.model import log, motion, se2
from csam_ros.core.model.sensor import cartesian_to_polar
from csam_ros.datasets.odometry_stress import OdometryStress, stress_odometry

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class Segment:
    """Constant commanded input held for ``duration`` seconds (a multiple of the sample time)."""

    duration: float
    v: float  # m/s, forward
    omega: float  # rad/s


@dataclass(frozen=True)
class RangeBearingSensor:
    """A range-bearing sensor at the robot centre looking forward."""

    max_range: float = 4.0
    field_of_view: float = np.deg2rad(240.0)  # full opening angle, rad
    sigma_range: float = 0.01
    sigma_bearing: float = 0.012
    min_range: float = 0.1  # closer targets are not seen (keeps measured ranges positive)

    def visible(self, ranges: FloatArray, bearings: FloatArray) -> NDArray[np.bool_]:
        """Which of the given true ranges and bearings the sensor sees."""
        return (
            (ranges <= self.max_range)
            & (ranges >= self.min_range)
            & (np.abs(bearings) <= 0.5 * self.field_of_view)
        )


@dataclass(frozen=True)
class RobotSpec:
    """One simulated robot: start pose in the world, program, noise and sensors."""

    name: str
    start_pose: tuple[float, float, float]  # world frame, (x, y, phi)
    program: tuple[Segment, ...]
    odometry_sigma: tuple[float, float, float] = (0.02, 0.01, 0.005)  # s_v, s_vlat, s_omega
    feature_sensor: RangeBearingSensor = RangeBearingSensor()
    rendezvous_sensor: RangeBearingSensor | None = RangeBearingSensor()
    observes: tuple[str, ...] | None = None  # robots it may observe; None: every other robot
    rendezvous_every: int = 1  # observe other robots at every n-th sample
    odometry_stress: OdometryStress | None = None  # reported odometry miscalibrated


@dataclass(frozen=True)
class Scenario:
    """A world of point features and the robots moving in it."""

    name: str
    sample_time: float
    features: FloatArray  # (F, 2) world positions
    robots: tuple[RobotSpec, ...]
    seed: int = 0
    description: str = ""


def feature_grid(
    center: tuple[float, float],
    size: tuple[float, float],
    spacing: float,
    jitter: float,
    rng: np.random.Generator,
) -> FloatArray:
    """Features on a jittered grid covering a rectangle.

    ``jitter`` is the fraction of ``spacing`` by which each point moves at most along each
    axis, so two features are never closer than ``spacing * (1 - 2 * jitter)``.
    """
    if spacing <= 0:
        raise ValueError(f"feature area spacing must be positive, got {spacing}")
    if not 0 <= jitter < 0.5:
        raise ValueError(f"feature area jitter must be in [0, 0.5), got {jitter}")
    nx = max(1, int(np.floor(size[0] / spacing)) + 1)
    ny = max(1, int(np.floor(size[1] / spacing)) + 1)
    gx = center[0] + (np.arange(nx) - (nx - 1) / 2) * spacing
    gy = center[1] + (np.arange(ny) - (ny - 1) / 2) * spacing
    points = np.stack(np.meshgrid(gx, gy, indexing="ij"), -1).reshape(-1, 2)
    return points + rng.uniform(-jitter, jitter, points.shape) * spacing


def program_inputs(robot: RobotSpec, sample_time: float) -> FloatArray:
    """Commanded ``(v, omega)`` per sample (N-1, 2), from the robot's program."""
    rows = []
    for k, seg in enumerate(robot.program):
        steps = seg.duration / sample_time
        n = int(round(steps))
        if n < 1 or abs(steps - n) > 1e-6:
            raise ValueError(
                f"robot {robot.name!r} segment {k}: duration {seg.duration} s is not a positive "
                f"multiple of the sample time {sample_time} s"
            )
        rows.append(np.tile([seg.v, seg.omega], (n, 1)))
    if not rows:
        raise ValueError(f"robot {robot.name!r} has an empty program")
    return np.concatenate(rows)


def true_trajectory(robot: RobotSpec, sample_time: float) -> FloatArray:
    """World poses (N, 3) of the robot at every sample, the start included."""
    cmd = program_inputs(robot, sample_time)
    inputs = np.column_stack([cmd[:, 0], np.zeros(len(cmd)), cmd[:, 1]])
    steps = motion.increment(inputs, sample_time)
    poses = np.empty((len(cmd) + 1, 3))
    poses[0] = robot.start_pose
    for i, step in enumerate(steps):  # sequential by nature; a few hundred steps
        poses[i + 1] = se2.compose(poses[i], step)
    return poses


def _scan(
    poses: FloatArray,
    targets: FloatArray,
    sensor: RangeBearingSensor,
    rng: np.random.Generator,
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Noisy observations of ``targets`` (M, 2) from every pose (N, 3) that sees them.

    Returns pose index, target index, measured range and measured bearing of each hit.
    Targets closer than the sensor's ``min_range`` are never observed.
    """
    rel = se2.inverse_transform_point(poses[:, None, :], targets[None, :, :])  # (N, M, 2)
    ranges = np.hypot(rel[..., 0], rel[..., 1])
    bearings = np.arctan2(rel[..., 1], rel[..., 0])
    seen = sensor.visible(ranges, bearings)
    pose_idx, target_idx = np.nonzero(seen)
    k = len(pose_idx)
    r = ranges[seen] + sensor.sigma_range * rng.standard_normal(k)
    b = se2.wrap_angle(bearings[seen] + sensor.sigma_bearing * rng.standard_normal(k))
    return pose_idx, target_idx, r, b


def simulate(scenario: Scenario, seed: int | None = None) -> log.MultiRobotLog:
    """Run the scenario once: odometry, feature scans and rendezvous measurements per robot.

    ``seed`` (default: the scenario's) seeds every random draw; the same seed gives the same
    log. Robots are kept in the scenario's order (the first one is C-SAM's reference).
    """
    names = [r.name for r in scenario.robots]
    if len(set(names)) != len(names):
        raise ValueError(f"scenario {scenario.name!r}: robot names must be unique, got {names}")
    if scenario.sample_time <= 0:
        raise ValueError(f"scenario {scenario.name!r}: sample_time must be positive")
    features = np.asarray(scenario.features, dtype=float).reshape(-1, 2)
    rng = np.random.default_rng(seed if seed is not None else scenario.seed)
    n_features = len(features)
    label_base = 10 ** max(2, len(str(n_features)))

    t = scenario.sample_time
    trajectories = {r.name: true_trajectory(r, t) for r in scenario.robots}
    stamps = {name: np.arange(len(p)) * t for name, p in trajectories.items()}

    robots: dict[str, log.RobotLog] = {}
    label_to_feature: dict[str, dict[int, int]] = {}
    for index, spec in enumerate(scenario.robots):
        poses = trajectories[spec.name]
        n = len(poses)
        sigma = np.asarray(spec.odometry_sigma, dtype=float)
        if sigma.shape != (3,) or np.any(sigma <= 0):
            raise ValueError(f"robot {spec.name!r}: odometry_sigma must be 3 positive numbers")
        cmd = program_inputs(spec, t)
        inputs = np.zeros((n, 3))
        inputs[1:, 0] = cmd[:, 0]
        inputs[1:, 2] = cmd[:, 1]
        inputs[1:] += sigma * rng.standard_normal((n - 1, 3))
        odometry = log.OdometryLog(stamps[spec.name].copy(), inputs, np.tile(sigma, (n, 1)))
        if spec.odometry_stress is not None:
            odometry = stress_odometry(odometry, spec.odometry_stress)

        labels = label_base * (index + 1) + rng.permutation(n_features)
        label_to_feature[spec.name] = {int(lab): int(f) for f, lab in enumerate(labels)}
        pi, fi, r, b = _scan(poses, features, spec.feature_sensor, rng)
        fs = spec.feature_sensor
        feature_log = log.FeatureLog(
            stamps=stamps[spec.name][pi],
            labels=labels[fi].astype(np.int64),
            ranges=r,
            bearings=b,
            sigma_range=np.full(len(r), fs.sigma_range),
            sigma_bearing=np.full(len(r), fs.sigma_bearing),
        )
        robots[spec.name] = log.RobotLog(
            spec.name, odometry, feature_log, _rendezvous(spec, scenario, trajectories, rng)
        )

    truth = log.GroundTruth(
        feature_ids=np.arange(n_features, dtype=np.int64),
        feature_positions=features.copy(),
        label_to_feature=label_to_feature,
        trajectory_stamps={k: v.copy() for k, v in stamps.items()},
        trajectories={k: v.copy() for k, v in trajectories.items()},
    )
    return log.MultiRobotLog(robots=robots, truth=truth)


def _rendezvous(
    spec: RobotSpec,
    scenario: Scenario,
    trajectories: dict[str, FloatArray],
    rng: np.random.Generator,
) -> log.RendezvousLog:
    """Observations of other robots by ``spec`` at the samples both robots exist."""
    sensor = spec.rendezvous_sensor
    known = {r.name for r in scenario.robots}
    targets = [n for n in (spec.observes or known) if n != spec.name]
    unknown = sorted(set(targets) - known)
    if unknown:
        raise ValueError(f"robot {spec.name!r} observes unknown robots {unknown}")
    if spec.rendezvous_every < 1:
        raise ValueError(f"robot {spec.name!r}: rendezvous_every must be >= 1")
    stamp_list, observed, ranges, bearings = [], [], [], []
    own = trajectories[spec.name]
    if sensor is not None:
        for other in (r.name for r in scenario.robots if r.name in targets):
            theirs = trajectories[other]
            n = min(len(own), len(theirs))
            samples = np.arange(0, n, spec.rendezvous_every)
            rel = se2.inverse_transform_point(own[samples], theirs[samples, :2])
            true_r = np.hypot(rel[:, 0], rel[:, 1])
            true_b = np.arctan2(rel[:, 1], rel[:, 0])
            seen = sensor.visible(true_r, true_b)
            k = int(seen.sum())
            stamp_list.append(samples[seen] * scenario.sample_time)
            observed += [other] * k
            ranges.append(true_r[seen] + sensor.sigma_range * rng.standard_normal(k))
            bearings.append(
                se2.wrap_angle(true_b[seen] + sensor.sigma_bearing * rng.standard_normal(k))
            )
    if not stamp_list:
        return log.empty_rendezvous()
    st = np.concatenate(stamp_list)
    order = np.argsort(st, kind="stable")
    r = np.concatenate(ranges)[order]
    return log.RendezvousLog(
        stamps=st[order],
        observed=[observed[i] for i in order],
        ranges=r,
        bearings=np.concatenate(bearings)[order],
        sigma_range=np.full(len(r), sensor.sigma_range if sensor else 0.0),
        sigma_bearing=np.full(len(r), sensor.sigma_bearing if sensor else 0.0),
    )


def simulate_robot_log(
    duration: float = 40.0,
    rate: float = 67.0,
    seed: int = 0,
    landmarks: int = 12,
    scan_rate: float = 2.0,
) -> tuple[log.RobotLog, FloatArray, FloatArray, FloatArray]:
    """A robot log at MR.CLAM-like rates: odometry at ``rate`` Hz (jittered stamps), feature
    scans at their own stamps (``scan_rate`` per second, between odometry samples), a
    stretch of exactly zero turn rate, two rendezvous stamps.

    Returns ``(log, true poses at the odometry stamps, odometry stamps, landmarks)``.
    """
    rng = np.random.default_rng(seed)
    stamps = 100.0 + np.cumsum(rng.uniform(0.9, 1.1, int(duration * rate)) / rate)
    n = len(stamps)
    true_u = np.column_stack(
        [0.3 + 0.1 * np.sin(stamps / 5), np.zeros(n), 0.25 * np.sin(stamps / 3)]
    )
    true_u[n // 3 : n // 3 + 80, 2] = 0.0
    truth = motion.dead_reckoning(motion.increment(true_u[1:], np.diff(stamps)))
    sig = np.tile([0.03, 0.01, 0.04], (n, 1))
    meas_u = true_u + rng.normal(size=(n, 3)) * sig
    lm = rng.uniform(-3, 8, (landmarks, 2))
    scan_t = np.sort(rng.uniform(stamps[0] + 0.05, stamps[-1] - 0.05, int(duration * scan_rate)))
    i = np.searchsorted(stamps, scan_t)
    at_scan = se2.compose(truth[i - 1], motion.increment(true_u[i], scan_t - stamps[i - 1]))
    r, b = cartesian_to_polar(se2.inverse_transform_point(at_scan[:, None], lm[None]))
    seen_scan, seen_lm = np.nonzero(r < 6.0)
    k = len(seen_scan)
    features = log.FeatureLog(
        stamps=scan_t[seen_scan],
        labels=(seen_lm + 10).astype(np.int64),
        ranges=r[seen_scan, seen_lm] + rng.normal(0, 0.02, k),
        bearings=b[seen_scan, seen_lm] + rng.normal(0, 0.01, k),
        sigma_range=np.full(k, 0.02),
        sigma_bearing=np.full(k, 0.01),
    )
    rdv_t = np.array([stamps[0] + 7.31, stamps[0] + 21.005])
    rendezvous = log.RendezvousLog(
        rdv_t, ["other", "other"], np.ones(2), np.zeros(2), np.full(2, 0.1), np.full(2, 0.1)
    )
    robot = log.RobotLog("robot1", log.OdometryLog(stamps, meas_u, sig), features, rendezvous)
    return robot, truth, stamps, lm


def arcs_scenario(stress: OdometryStress) -> Scenario:
    """Two robots on arcs, straight legs and turns on the spot among a grid of features."""
    rng = np.random.default_rng(3)
    features = feature_grid((0.0, 0.0), (16.0, 16.0), 1.5, 0.3, rng)
    program = (
        Segment(20.0, 0.4, 0.25),
        Segment(4.0, 0.0, 0.6),
        Segment(15.0, 0.4, 0.0),
        Segment(20.0, 0.3, -0.3),
        Segment(4.0, 0.0, -0.6),
        Segment(20.0, 0.4, 0.2),
    )
    robots = tuple(
        RobotSpec(name, pose, program, odometry_stress=stress)
        for name, pose in (("robot1", (-3.0, -3.0, 0.0)), ("robot2", (3.0, 2.0, np.pi)))
    )
    return Scenario("odometry_calibration", 0.05, features, robots, seed=5)
