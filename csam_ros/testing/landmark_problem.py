"""Single-robot landmark SLAM problems as index arrays, and this project's problem built from
them: a simulated one (fixed seed, dead-reckoning start), a problem solved whole or the local
map's incremental way, and their files.

Poses and landmarks are numbered from 0; odometry joins two poses, an observation a pose and a
landmark (Cartesian, in the pose frame). The benchmark (``csam_ros.bench.smoothing``) and the
tests (GTSAM as an oracle, :mod:`csam_ros.testing.gtsam_oracle`) share these generators.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from csam_ros.core.model import motion, se2, sensor
from csam_ros.core.sam.factors import POINT, POSE, PointObservation, PosePrior, RelativePose
from csam_ros.core.sam.solver import GAUGE_SIGMA, Problem, SolverOptions

Array = NDArray[np.float64]


@dataclass
class LandmarkProblem:
    """A simulated single-robot landmark SLAM problem."""

    truth_poses: Array  # (N, 3)
    truth_landmarks: Array  # (L, 2)
    odometry: Array  # (N-1, 3) measured relative poses
    odometry_covariance: Array  # (N-1, 3, 3)
    obs_pose: NDArray[np.int64]  # (K,)
    obs_landmark: NDArray[np.int64]  # (K,)
    obs_range: Array  # (K,)
    obs_bearing: Array  # (K,)
    sigma_range: float
    sigma_bearing: float
    initial_poses: Array  # (N, 3) dead reckoning
    initial_landmarks: Array  # (L, 2) from the first observation

    @property
    def obs_xy(self) -> Array:
        return sensor.polar_to_cartesian(
            self.obs_range, self.obs_bearing, self.sigma_range, self.sigma_bearing
        )[0]

    @property
    def obs_covariance(self) -> Array:
        return sensor.polar_to_cartesian(
            self.obs_range, self.obs_bearing, self.sigma_range, self.sigma_bearing
        )[1]

    def graph(self) -> GraphData:
        n = len(self.initial_poses)
        z, cov = sensor.polar_to_cartesian(
            self.obs_range, self.obs_bearing, self.sigma_range, self.sigma_bearing
        )
        return GraphData(
            name="simulated",
            initial_poses=self.initial_poses,
            initial_landmarks=self.initial_landmarks,
            odometry_first=np.arange(n - 1),
            odometry_second=np.arange(1, n),
            odometry=self.odometry,
            odometry_covariance=self.odometry_covariance,
            obs_pose=self.obs_pose,
            obs_landmark=self.obs_landmark,
            obs_xy=z,
            obs_covariance=cov,
        )


@dataclass
class GraphData:
    """A landmark SLAM problem as index arrays (poses and landmarks numbered from 0)."""

    name: str
    initial_poses: Array  # (N, 3)
    initial_landmarks: Array  # (L, 2)
    odometry_first: NDArray[np.int64]  # (E,)
    odometry_second: NDArray[np.int64]  # (E,)
    odometry: Array  # (E, 3) pose of second in the frame of first
    odometry_covariance: Array  # (E, 3, 3)
    obs_pose: NDArray[np.int64]  # (K,)
    obs_landmark: NDArray[np.int64]  # (K,)
    obs_xy: Array  # (K, 2) in the pose frame
    obs_covariance: Array  # (K, 2, 2)


def as_graph(problem: LandmarkProblem | GraphData) -> GraphData:
    return problem.graph() if isinstance(problem, LandmarkProblem) else problem


def simulate_landmark_problem(
    num_poses: int = 7000,
    num_landmarks: int = 150,
    num_observations: int = 3600,
    seed: int = 7,
    area: float = 30.0,
    sample_time: float = 0.25,
    speed: float = 0.8,
    sigma_input: tuple[float, float, float] = (0.05, 0.02, 0.03),
    sensor_range: float = 5.0,
    sigma_range: float = 0.05,
    sigma_bearing: float = 0.02,
) -> LandmarkProblem:
    """Robot wandering in a square ``area`` among random landmarks, range-bearing sensor.

    Observations are drawn uniformly (fixed seed) among all pose-landmark pairs within
    ``sensor_range`` and +-120 degrees, so that exactly ``num_observations`` remain.
    """
    rng = np.random.default_rng(seed)
    landmarks = rng.uniform(0.0, area, (num_landmarks, 2))
    poses = np.zeros((num_poses, 3))
    poses[0] = [area / 2, area / 2, 0.0]
    inputs = np.zeros((num_poses - 1, 3))
    turn = 0.0
    for i in range(1, num_poses):
        x = poses[i - 1]
        to_centre = np.arctan2(area / 2 - x[1], area / 2 - x[0])
        dist = np.hypot(area / 2 - x[0], area / 2 - x[1])
        turn = 0.9 * turn + rng.normal(0.0, 0.15)
        if dist > 0.4 * area:
            turn = 1.5 * se2.wrap_angle(to_centre - x[2])
        inputs[i - 1] = [speed, 0.0, np.clip(turn, -1.2, 1.2)]
        poses[i] = se2.compose(x, motion.increment(inputs[i - 1], sample_time))
    dt = np.full(num_poses - 1, sample_time)
    sig = np.tile(sigma_input, (num_poses - 1, 1))
    measured_inputs = inputs + rng.normal(size=inputs.shape) * sig
    odometry, odometry_cov = motion.step_covariance(measured_inputs, dt, sig)

    def visibility(lms: Array) -> tuple[Array, Array, NDArray[np.bool_]]:
        local = se2.inverse_transform_point(poses[:, None, :], lms[None, :, :])
        r, b = sensor.cartesian_to_polar(local)
        return r, b, (r < sensor_range) & (np.abs(b) < np.radians(120)) & (r > 0.1)

    rng_all, bearing_all, visible = visibility(landmarks)
    unseen = np.flatnonzero(~visible.any(axis=0))
    if unseen.size:  # move never-visible landmarks in front of random poses
        hosts = poses[rng.integers(0, num_poses, unseen.size)]
        dist = rng.uniform(0.5, 0.8 * sensor_range, unseen.size)
        ang = rng.uniform(-1.0, 1.0, unseen.size)
        local_xy = np.stack([dist * np.cos(ang), dist * np.sin(ang)], axis=1)
        landmarks[unseen] = se2.transform_point(hosts, local_xy)
        rng_all, bearing_all, visible = visibility(landmarks)
    pi, li = np.nonzero(visible)
    if len(pi) < num_observations:
        raise ValueError(f"only {len(pi)} visible pairs for {num_observations} observations")
    # one observation of every landmark, the rest drawn uniformly among visible pairs
    first_of_each = np.unique(li, return_index=True)[1]
    if num_observations < len(first_of_each):
        raise ValueError(f"{num_observations} observations cannot see {num_landmarks} landmarks")
    others = np.setdiff1d(np.arange(len(pi)), first_of_each)
    extra = rng.choice(others, num_observations - len(first_of_each), replace=False)
    keep = np.sort(np.concatenate([first_of_each, extra]))
    pi, li = pi[keep], li[keep]
    obs_r = rng_all[pi, li] + rng.normal(0.0, sigma_range, len(pi))
    obs_b = se2.wrap_angle(bearing_all[pi, li] + rng.normal(0.0, sigma_bearing, len(pi)))

    initial = motion.dead_reckoning(odometry, poses[0])
    first = np.unique(li, return_index=True)[1]
    z, _ = sensor.polar_to_cartesian(obs_r, obs_b, sigma_range, sigma_bearing)
    initial_landmarks = se2.transform_point(initial[pi[first]], z[first])
    return LandmarkProblem(
        truth_poses=poses,
        truth_landmarks=landmarks,
        odometry=odometry,
        odometry_covariance=odometry_cov,
        obs_pose=pi.astype(np.int64),
        obs_landmark=li.astype(np.int64),
        obs_range=obs_r,
        obs_bearing=obs_b,
        sigma_range=sigma_range,
        sigma_bearing=sigma_bearing,
        initial_poses=initial,
        initial_landmarks=initial_landmarks,
    )


def build_problem(source: LandmarkProblem | GraphData) -> Problem:
    """This project's problem: gauge prior, odometry and Cartesian landmark observations."""
    g = as_graph(source)
    problem = Problem()
    n = len(g.initial_poses)
    pose_ids = problem.add_variables(POSE, [("x", i) for i in range(n)], g.initial_poses)
    lm_ids = problem.add_variables(
        POINT, [("l", j) for j in range(len(g.initial_landmarks))], g.initial_landmarks
    )
    problem.add_factor(
        PosePrior(pose_ids[:1], g.initial_poses[:1], np.eye(3) / GAUGE_SIGMA, name="gauge")
    )
    problem.add_factor(
        RelativePose(
            pose_ids[g.odometry_first],
            pose_ids[g.odometry_second],
            g.odometry,
            covariance=g.odometry_covariance,
        )
    )
    problem.add_factor(
        PointObservation(
            pose_ids[g.obs_pose], lm_ids[g.obs_landmark], g.obs_xy, covariance=g.obs_covariance
        )
    )
    return problem


def solve_incremental(
    g: GraphData,
    chunk: int,
    tolerance: float,
    max_iterations: int,
    chunk_tolerance: float = 1e-6,
) -> tuple[Problem, int, float]:
    """The local map's policy on a whole problem: add ``chunk`` poses at a time (in index
    order) with the observations they make, initialise them by composing odometry from the
    current estimate, and solve warm-started to ``chunk_tolerance`` (or ``tolerance`` if
    tighter); the last solve to ``tolerance``.

    Returns the final problem, the total number of iterations and seconds.
    """
    start = time.perf_counter()
    n = len(g.initial_poses)
    poses = g.initial_poses.copy()
    lms = np.full(g.initial_landmarks.shape, np.nan)
    first_obs = np.unique(g.obs_landmark, return_index=True)[1]
    iterations = 0
    done = 1
    problem = Problem()
    while done < n:
        k = min(n, done + chunk)
        rel = se2.between(g.initial_poses[done - 1], g.initial_poses[done:k])
        poses[done:k] = se2.compose(poses[done - 1], rel)
        obs = g.obs_pose < k
        new = first_obs[(g.obs_pose[first_obs] < k) & np.isnan(lms[g.obs_landmark[first_obs], 0])]
        lms[g.obs_landmark[new]] = se2.transform_point(poses[g.obs_pose[new]], g.obs_xy[new])
        seen = np.flatnonzero(~np.isnan(lms[:, 0]))
        edges = (g.odometry_first < k) & (g.odometry_second < k)
        sub = GraphData(
            g.name,
            poses[:k],
            lms[seen],
            g.odometry_first[edges],
            g.odometry_second[edges],
            g.odometry[edges],
            g.odometry_covariance[edges],
            g.obs_pose[obs],
            np.searchsorted(seen, g.obs_landmark[obs]),
            g.obs_xy[obs],
            g.obs_covariance[obs],
        )
        problem = build_problem(sub)
        last = k == n
        report = problem.solve(
            SolverOptions(
                relative_tolerance=tolerance if last else max(tolerance, chunk_tolerance),
                max_iterations=max_iterations,
            )
        )
        iterations += report.iterations
        poses[:k] = problem.values[: 3 * k].reshape(-1, 3)
        lms[seen] = problem.values[3 * k :].reshape(-1, 2)
        done = k
    return problem, iterations, time.perf_counter() - start


def save_graph(g: GraphData, path: Path) -> None:
    np.savez(path, **{k: v for k, v in vars(g).items() if k != "name"}, name=np.array(g.name))


def read_graph(path: Path) -> GraphData:
    with np.load(path) as data:
        fields = {k: data[k] for k in data.files}
    fields["name"] = str(fields["name"])
    return GraphData(**fields)
