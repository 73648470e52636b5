"""Benchmark of single-robot square-root smoothing against GTSAM (run as a module).

``python -m csam_ros.bench.smoothing [--poses 7000 --landmarks 150 --observations 3600]
[--victoria PATH | --no-victoria] [--no-identical] [--tolerance 1e-8] [--chunk 1000]``

Problems: (1) a simulated landmark SLAM problem generated with a fixed seed; (2) the public
Victoria Park data set in the ``ODOMETRY``/``LANDMARK`` text format (the copy shipped in
GTSAM's Python wheel under ``gtsam/Data/victoria_park.txt`` is found automatically). Both
start from dead reckoning (landmarks from their first observation).

Solvers, each in its own process (so that peak memory is the process's maximum resident set
size): this project's Gauss-Newton/LM; GTSAM's batch Levenberg-Marquardt with its native
factors (``BetweenFactorPose2``, ``BearingRangeFactor2D`` with the same covariances mapped to
its parametrisation: the same model to first order, not the same function), the fair speed
reference; and GTSAM's LM on exactly this project's objective through ``CustomFactor`` (slow,
Python per factor; used to compare the optimum reached, not the speed). Both LMs stop on the
same relative cost decrease ``--tolerance``.

On Victoria Park the batch solvers from dead reckoning end in poor local minima; the
incremental policy (``ours-incremental``: ``--chunk`` poses at a time, warm-started, inner
solves to ``--chunk-tolerance``, the last to ``--tolerance``) reaches a far lower cost and its
time is compared with GTSAM's batch LM. Chunk size measured (same optimum, cost 3,092, every
time; seconds on one loaded run): 200 poses 2.2 s, 500 1.0 s, 700 1.0 s, 1000 0.9 s, 1200
1.5 s; the default 1000 is that measurement, not a property of the method.

Printed side by side: problem size, iterations, seconds per Gauss-Newton iteration
(linearise, factor, solve, evaluate the cost), total seconds to convergence (solver call
only; problem construction listed separately), final cost on its own objective and on this
project's objective, peak memory. For this project also where the time goes (structure,
ordering with the first factorisation, and each part of an iteration) and the share of
GTSAM's time its factorisations alone take. The problem builders are also used by the tests
(GTSAM as an oracle).

Online (``--no-online`` skips it): a robot log fed to a local map one second at a time, a
simulated one or, with ``--mrclam DIR``, each MR.CLAM robot as ``csam replay --config
config/mrclam.yaml`` runs the smoothers. Printed: the real-time factor, the converged online
map against the offline build, and what the smoother computes for its messages at the end.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from csam_ros.core import motion, se2, sensor
from csam_ros.core.factors import POINT, POSE, Cauchy, PointObservation, PosePrior, RelativePose
from csam_ros.core.local_map import LocalMap, LocalMapOptions, build_local_map
from csam_ros.core.log import FeatureLog, OdometryLog, RendezvousLog, RobotLog
from csam_ros.core.solver import GAUGE_SIGMA, NormalEquations, Problem, SolverOptions
from csam_ros.datasets.slam2d import Slam2dData, initial_values, read_slam2d

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


def graph_from_slam2d(data: Slam2dData, name: str = "file") -> GraphData:
    """Index arrays of a 2D SLAM file (ids renumbered in sorted order)."""
    poses, landmarks = initial_values(data)
    pose_ids, lm_ids = data.pose_ids, data.landmark_ids
    return GraphData(
        name=name,
        initial_poses=np.array([poses[int(i)] for i in pose_ids]),
        initial_landmarks=np.array([landmarks[int(i)] for i in lm_ids]).reshape(-1, 2),
        odometry_first=np.searchsorted(pose_ids, data.odometry_first),
        odometry_second=np.searchsorted(pose_ids, data.odometry_second),
        odometry=data.odometry,
        odometry_covariance=data.odometry_covariance,
        obs_pose=np.searchsorted(pose_ids, data.observation_pose),
        obs_landmark=np.searchsorted(lm_ids, data.observation_landmark),
        obs_xy=data.observations,
        obs_covariance=data.observation_covariance,
    )


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


def simulate_robot_log(
    duration: float = 40.0,
    rate: float = 67.0,
    seed: int = 0,
    landmarks: int = 12,
    scan_rate: float = 2.0,
) -> tuple[RobotLog, Array, Array, Array]:
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
    r, b = sensor.cartesian_to_polar(se2.inverse_transform_point(at_scan[:, None], lm[None]))
    seen_scan, seen_lm = np.nonzero(r < 6.0)
    k = len(seen_scan)
    features = FeatureLog(
        stamps=scan_t[seen_scan],
        labels=(seen_lm + 10).astype(np.int64),
        ranges=r[seen_scan, seen_lm] + rng.normal(0, 0.02, k),
        bearings=b[seen_scan, seen_lm] + rng.normal(0, 0.01, k),
        sigma_range=np.full(k, 0.02),
        sigma_bearing=np.full(k, 0.01),
    )
    rdv_t = np.array([stamps[0] + 7.31, stamps[0] + 21.005])
    rendezvous = RendezvousLog(
        rdv_t, ["other", "other"], np.ones(2), np.zeros(2), np.full(2, 0.1), np.full(2, 0.1)
    )
    log = RobotLog("robot1", OdometryLog(stamps, meas_u, sig), features, rendezvous)
    return log, truth, stamps, lm


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


def _local_to_global(phi: float) -> Array:
    """``d(global pose)/d(GTSAM tangent)`` at a pose with heading ``phi``: blkdiag(R, 1)."""
    m = np.eye(3)
    m[:2, :2] = se2.rotation(phi)
    return m


def polar_sigmas(xy: Array, covariance: Array) -> tuple[Array, Array, Array, Array]:
    """Range, bearing and their sigmas of Cartesian observations (first-order projection)."""
    r, b = sensor.cartesian_to_polar(xy)
    radial = np.stack([np.cos(b), np.sin(b)], axis=1)
    tangential = np.stack([-np.sin(b), np.cos(b)], axis=1)
    s_r = np.sqrt(np.einsum("ki,kij,kj->k", radial, covariance, radial))
    s_b = np.sqrt(np.einsum("ki,kij,kj->k", tangential, covariance, tangential)) / r
    return r, b, s_r, s_b


def build_gtsam(source: LandmarkProblem | GraphData, identical: bool) -> tuple[Any, Any]:
    """GTSAM graph and initial values.

    ``identical=True`` writes exactly this project's errors as ``CustomFactor`` (Jacobians
    chained to GTSAM's tangent space); ``False`` uses GTSAM's native Pose2 between and
    bearing-range factors with the covariances mapped to their errors at first order
    (between: ``blkdiag(R(z_phi)^T, 1)``; Cartesian to polar at the measurement).
    """
    import gtsam

    g = as_graph(source)
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()

    def pose_key(i: int) -> int:
        return gtsam.symbol("x", i)

    def lm_key(j: int) -> int:
        return gtsam.symbol("l", j)

    for i, p in enumerate(g.initial_poses):
        values.insert(pose_key(i), gtsam.Pose2(*p))
    for j, p in enumerate(g.initial_landmarks):
        values.insert(lm_key(j), np.asarray(p, dtype=float))
    graph.add(
        gtsam.PriorFactorPose2(
            pose_key(0),
            gtsam.Pose2(*g.initial_poses[0]),
            gtsam.noiseModel.Isotropic.Sigma(3, GAUGE_SIGMA),
        )
    )
    edges = zip(g.odometry_first, g.odometry_second, g.odometry, g.odometry_covariance, strict=True)
    if not identical:
        for a, b, z, cov in edges:
            m = np.eye(3)
            m[:2, :2] = se2.rotation(z[2]).T
            graph.add(
                gtsam.BetweenFactorPose2(
                    pose_key(int(a)),
                    pose_key(int(b)),
                    gtsam.Pose2(*z),
                    gtsam.noiseModel.Gaussian.Covariance(m @ cov @ m.T),
                )
            )
        r, bearing, s_r, s_b = polar_sigmas(g.obs_xy, g.obs_covariance)
        for k in range(len(g.obs_pose)):
            graph.add(
                gtsam.BearingRangeFactor2D(
                    pose_key(int(g.obs_pose[k])),
                    lm_key(int(g.obs_landmark[k])),
                    gtsam.Rot2(float(bearing[k])),
                    float(r[k]),
                    gtsam.noiseModel.Diagonal.Sigmas(np.array([s_b[k], s_r[k]])),
                )
            )
        return graph, values

    def between_error(z: Array) -> Any:
        def error(this: Any, v: Any, H: Any) -> Array:
            a = v.atPose2(this.keys()[0])
            b = v.atPose2(this.keys()[1])
            xa = np.array([a.x(), a.y(), a.theta()])
            xb = np.array([b.x(), b.y(), b.theta()])
            f = RelativePose([0], [1], z[None], np.eye(3)[None])
            e, jac = f.evaluate([xa[None], xb[None]])
            if H is not None:
                H[0] = jac[0][0] @ _local_to_global(xa[2])
                H[1] = jac[1][0] @ _local_to_global(xb[2])
            return e[0]

        return error

    def observation_error(z: Array) -> Any:
        def error(this: Any, v: Any, H: Any) -> Array:
            a = v.atPose2(this.keys()[0])
            xa = np.array([a.x(), a.y(), a.theta()])
            lm = np.asarray(v.atPoint2(this.keys()[1]), dtype=float)
            f = PointObservation([0], [1], z[None], np.eye(2)[None])
            e, jac = f.evaluate([xa[None], lm[None]])
            if H is not None:
                H[0] = jac[0][0] @ _local_to_global(xa[2])
                H[1] = jac[1][0]
            return e[0]

        return error

    for a, b, z, cov in edges:
        graph.add(
            gtsam.CustomFactor(
                gtsam.noiseModel.Gaussian.Covariance(cov),
                [pose_key(int(a)), pose_key(int(b))],
                between_error(z),
            )
        )
    for k in range(len(g.obs_pose)):
        graph.add(
            gtsam.CustomFactor(
                gtsam.noiseModel.Gaussian.Covariance(g.obs_covariance[k]),
                [pose_key(int(g.obs_pose[k])), lm_key(int(g.obs_landmark[k]))],
                observation_error(g.obs_xy[k]),
            )
        )
    return graph, values


def gtsam_estimate(source: LandmarkProblem | GraphData, result: Any) -> tuple[Array, Array]:
    """Poses ``(N, 3)`` and landmarks ``(L, 2)`` from GTSAM values."""
    import gtsam

    g = as_graph(source)
    poses = np.array(
        [
            [p.x(), p.y(), p.theta()]
            for p in (result.atPose2(gtsam.symbol("x", i)) for i in range(len(g.initial_poses)))
        ]
    )
    lms = np.array(
        [result.atPoint2(gtsam.symbol("l", j)) for j in range(len(g.initial_landmarks))]
    ).reshape(-1, 2)
    return poses, lms


def gtsam_marginal_covariance(
    source: LandmarkProblem | GraphData, graph: Any, result: Any, keys: list
) -> Array:
    """GTSAM's joint marginal of ``keys`` (("x", i) or ("l", j)) in global parametrisation."""
    import gtsam

    marginals = gtsam.Marginals(graph, result)
    gkeys = [gtsam.symbol(kind, idx) for kind, idx in keys]
    joint = marginals.jointMarginalCovariance(gkeys)
    transforms = []
    dims = []
    for (kind, _), gk in zip(keys, gkeys, strict=True):
        if kind == "x":
            transforms.append(_local_to_global(result.atPose2(gk).theta()))
        else:
            transforms.append(np.eye(2))
        dims.append(joint.at(gk, gk).shape[0])
    edges = np.cumsum([0, *dims])
    m = np.zeros((edges[-1], edges[-1]))
    full = np.zeros((edges[-1], edges[-1]))
    for a, ka in enumerate(gkeys):
        m[edges[a] : edges[a + 1], edges[a] : edges[a + 1]] = transforms[a]
        for b, kb in enumerate(gkeys):
            full[edges[a] : edges[a + 1], edges[b] : edges[b + 1]] = joint.at(ka, kb)
    return m @ full @ m.T


# ---------------------------------------------------------------------------------------------
# benchmark: one solver per process


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


def victoria_park_path() -> Path | None:
    """The Victoria Park file shipped with GTSAM's wheel, if GTSAM is installed."""
    try:
        import gtsam
    except ImportError:
        return None
    path = Path(gtsam.__file__).parent / "Data" / "victoria_park.txt"
    return path if path.exists() else None


def load_graph(spec: str, args: argparse.Namespace) -> GraphData:
    if spec == "simulated":
        return simulate_landmark_problem(
            args.poses, args.landmarks, args.observations, args.seed
        ).graph()
    return graph_from_slam2d(read_slam2d(spec), name=Path(spec).stem)


def save_graph(g: GraphData, path: Path) -> None:
    np.savez(path, **{k: v for k, v in vars(g).items() if k != "name"}, name=np.array(g.name))


def read_graph(path: Path) -> GraphData:
    with np.load(path) as data:
        fields = {k: data[k] for k in data.files}
    fields["name"] = str(fields["name"])
    return GraphData(**fields)


def peak_rss_mb() -> float:
    """This process's peak resident set (``VmHWM``; ``ru_maxrss`` survives exec on Linux)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return float(line.split()[1]) / 1024
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def iteration_parts(problem: Problem, backend: str = "qdldl", reps: int = 5) -> dict[str, float]:
    """Seconds of each part of a Gauss-Newton solve at the current values, on a fresh
    structure: ``structure`` (sparsity pattern and index maps), ``first_factorisation``
    (fill-reducing ordering, symbolic analysis and the numeric factorisation), then per
    iteration ``linearise`` (evaluate and assemble), ``refactorise`` (numeric only),
    ``solve`` and ``cost`` (mean of ``reps``)."""
    t0 = time.perf_counter()
    system = NormalEquations(problem, backend)
    structure = time.perf_counter() - t0
    system.linearize(problem.values)
    t0 = time.perf_counter()
    system.factorize(0.0)
    first = time.perf_counter() - t0
    laps = np.zeros(4)
    for _ in range(reps):
        t = [time.perf_counter()]
        system.linearize(problem.values)
        t.append(time.perf_counter())
        system.factorize(0.0)
        t.append(time.perf_counter())
        step = system.solve(-system.gradient)
        t.append(time.perf_counter())
        system.cost(problem.values + step)
        t.append(time.perf_counter())
        laps += np.diff(t)
    laps /= reps
    names = ("linearise", "refactorise", "solve", "cost")
    return {"structure": structure, "first_factorisation": first} | dict(
        zip(names, laps.tolist(), strict=True)
    )


def _values_of(poses: Array, lms: Array) -> Array:
    return np.concatenate([poses.reshape(-1), lms.reshape(-1)])


def worker(solver: str, spec: str, args: argparse.Namespace, out: Path) -> dict[str, Any]:
    """Solve one saved problem with one solver in this process; save the estimate to ``out``."""
    graph_data = read_graph(Path(spec))
    if solver.startswith("gtsam"):
        import gtsam  # noqa: F401  (imported before the baseline is taken)
    baseline_mb = peak_rss_mb()
    result: dict[str, Any] = {}
    if solver == "ours-incremental":
        problem, iterations, seconds = solve_incremental(
            graph_data, args.chunk, args.tolerance, args.max_iterations, args.chunk_tolerance
        )
        result.update(
            build=0.0,
            iterations=iterations,
            per_iteration=seconds / max(iterations, 1),
            total=seconds,
            cost=problem.cost(),
            converged=True,
        )
        np.save(out, problem.values)
    elif solver in ("ours", "ours-splu"):
        backend = "splu" if solver == "ours-splu" else "qdldl"
        t0 = time.perf_counter()
        problem = build_problem(graph_data)
        result["build"] = time.perf_counter() - t0
        report = problem.solve(
            SolverOptions(
                relative_tolerance=args.tolerance,
                max_iterations=args.max_iterations,
                backend=backend,
            )
        )
        result["peak_mb"] = peak_rss_mb()  # before the timing below builds a second system
        parts = iteration_parts(problem, backend)
        result.update(
            parts=parts,
            iterations=report.iterations,
            per_iteration=sum(parts[k] for k in ("linearise", "refactorise", "solve", "cost")),
            total=report.seconds,
            cost=report.final_cost,
            converged=report.converged,
        )
        np.save(out, problem.values)
    else:
        import gtsam

        identical = solver == "gtsam-identical"
        t0 = time.perf_counter()
        graph, values = build_gtsam(graph_data, identical)
        result["build"] = time.perf_counter() - t0
        params = gtsam.LevenbergMarquardtParams()
        params.setRelativeErrorTol(args.tolerance)
        params.setAbsoluteErrorTol(0.0)
        params.setMaxIterations(args.max_iterations)
        t0 = time.perf_counter()
        optimizer = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
        estimate = optimizer.optimize()
        total = time.perf_counter() - t0
        # One iteration as inside LM: linearise, eliminate with the (fixed) COLAMD ordering,
        # retract, evaluate the error.
        ordering = gtsam.Ordering.ColamdNonlinearFactorGraph(graph)
        reps = 3 if not identical else 1
        t0 = time.perf_counter()
        for _ in range(reps):
            linear = graph.linearize(estimate)
            delta = linear.optimize(ordering)
            graph.error(estimate.retract(delta))
        poses, lms = gtsam_estimate(graph_data, estimate)
        result.update(
            iterations=optimizer.iterations(),
            per_iteration=(time.perf_counter() - t0) / reps,
            total=total,
            cost=graph.error(estimate),
            converged=optimizer.iterations() < args.max_iterations,
        )
        np.save(out, _values_of(poses, lms))
    result.setdefault("peak_mb", peak_rss_mb())
    result["baseline_mb"] = baseline_mb
    return result


def run_worker(solver: str, spec: str, argv: list[str], out: Path) -> dict[str, Any] | None:
    cmd = [sys.executable, "-m", "csam_ros.bench.smoothing", *argv]
    cmd += ["--worker", solver, "--problem", spec, "--out", str(out)]
    done = subprocess.run(cmd, capture_output=True, text=True, check=False)
    if done.returncode != 0:
        print(f"  {solver} failed: {done.stderr.strip().splitlines()[-1:]}")
        return None
    return json.loads(done.stdout.strip().splitlines()[-1])


def compare(spec: str, args: argparse.Namespace, argv: list[str], solvers: list[str]) -> None:
    graph_data = load_graph(spec, args)
    n, nl = len(graph_data.initial_poses), len(graph_data.initial_landmarks)
    k, e = len(graph_data.obs_pose), len(graph_data.odometry)
    print(f"\n== {graph_data.name}: {n} poses, {nl} landmarks, {e} odometry factors, {k} obs.")
    print(f"   unknowns {3 * n + 2 * nl}; start: dead reckoning; tolerance {args.tolerance:g}")
    reference = build_problem(graph_data)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        saved = Path(tmp) / "problem.npz"
        save_graph(graph_data, saved)
        for solver in solvers:
            out = Path(tmp) / f"{solver}.npy"
            res = run_worker(solver, str(saved), argv, out)
            if res is None:
                continue
            estimate = np.load(out)
            res["our_cost"] = reference.cost(estimate)
            rows.append((solver, res, estimate))
    header = (
        f"   {'solver':18s} {'iter':>5s} {'s/iter':>8s} {'total s':>8s} {'build s':>8s} "
        f"{'own cost':>13s} {'our cost':>13s} {'peak MB':>8s} {'(imports)':>9s}"
    )
    print(header)
    for solver, r, _ in rows:
        print(
            f"   {solver:18s} {r['iterations']:5d} {r['per_iteration']:8.4f} {r['total']:8.3f} "
            f"{r['build']:8.3f} {r['cost']:13.4f} {r['our_cost']:13.4f} {r['peak_mb']:8.0f} "
            f"{r['baseline_mb']:9.0f}"
        )
    by_name = {name: (r, est) for name, r, est in rows}
    if "ours" in by_name:
        print_parts(by_name["ours"][0], by_name.get("gtsam-native", (None,))[0])
    if "ours" in by_name and "gtsam-native" in by_name:
        ours, native = by_name["ours"][0], by_name["gtsam-native"][0]
        print(
            f"   ratio ours / GTSAM native: time per iteration "
            f"{ours['per_iteration'] / native['per_iteration']:.3f}, time to convergence "
            f"{ours['total'] / native['total']:.3f}"
        )
    if "ours-incremental" in by_name and "gtsam-native" in by_name:
        inc, native = by_name["ours-incremental"][0], by_name["gtsam-native"][0]
        print(
            f"   ratio ours-incremental / GTSAM native: time to convergence "
            f"{inc['total'] / native['total']:.3f} (our cost {inc['our_cost']:.1f} vs "
            f"{native['our_cost']:.1f})"
        )
    if "ours" in by_name and "gtsam-identical" in by_name:
        a, b = by_name["ours"][1], by_name["gtsam-identical"][1]
        diff = np.abs(a - b)
        diff[2 : 3 * n : 3] = np.abs(se2.wrap_angle(a[2 : 3 * n : 3] - b[2 : 3 * n : 3]))
        print(f"   identical objective: max |ours - GTSAM| over all unknowns {diff.max():.2e}")


def print_parts(ours: dict[str, Any], gtsam: dict[str, Any] | None) -> None:
    """Where this project's time to convergence goes, and the share of it the sparse
    factorisations alone take (the floor of any solver built on the same factorisation)."""
    p = {k: 1e3 * v for k, v in ours["parts"].items()}
    print(
        f"   ours, set-up: structure {p['structure']:.1f} ms, ordering + first factorisation "
        f"{p['first_factorisation']:.1f} ms; per iteration: linearise {p['linearise']:.1f}, "
        f"refactorise {p['refactorise']:.1f}, solve {p['solve']:.1f}, cost {p['cost']:.1f} ms"
    )
    floor = p["first_factorisation"] + (ours["iterations"] - 1) * p["refactorise"]
    line = f"   the {ours['iterations']} factorisations alone: {floor:.1f} ms"
    if gtsam is not None:
        line += f" = {floor / (1e3 * gtsam['total']):.3f} of GTSAM's time to convergence"
    print(line)


def online_rate(
    log: RobotLog, options: LocalMapOptions, window: float | None = 60.0
) -> dict[str, float]:
    """Feed a log to a local map one second of data at a time (``maybe_update`` after each
    second); compare the final converged map with the offline build (``window``: its
    ``build_local_map`` window)."""
    local = LocalMap(log.name, options)
    o, f, rv = log.odometry, log.features, log.rendezvous
    order = np.argsort(f.stamps, kind="stable")
    ft = f.stamps[order]
    edges = np.arange(o.stamps[0] + 1.0, o.stamps[-1] + 1.0, 1.0)
    oi = fi = 0
    worst = 0.0
    updates = 0
    start = time.perf_counter()
    for end in edges:
        t0 = time.perf_counter()
        oj = int(np.searchsorted(o.stamps, end, side="right"))
        fj = int(np.searchsorted(ft, end, side="right"))
        local.add_odometry(o.stamps[oi:oj], o.inputs[oi:oj], o.sigmas[oi:oj])
        sel = order[fi:fj]
        local.add_features(
            f.stamps[sel],
            f.labels[sel],
            f.ranges[sel],
            f.bearings[sel],
            f.sigma_range[sel],
            f.sigma_bearing[sel],
        )
        local.request_poses(rv.stamps[(rv.stamps > end - 1.0) & (rv.stamps <= end)])
        oi, fi = oj, fj
        updates += local.maybe_update() is not None
        worst = max(worst, time.perf_counter() - t0)
    compute = time.perf_counter() - start
    local.update(converge=True)
    # what a smoother computes for its messages after an update (its map's size at the end)
    t0 = time.perf_counter()
    local.pose_covariances()
    local.landmark_covariances()
    covariances = time.perf_counter() - t0
    t0 = time.perf_counter()
    rendezvous = rv.stamps[rv.stamps <= local.stamps[-1]]
    if len(rendezvous):
        local.sqrt_information(rendezvous)
    sqrt_information = time.perf_counter() - t0
    t0 = time.perf_counter()
    offline = build_local_map(log, options=options, window=window)
    offline_seconds = time.perf_counter() - t0
    duration = float(o.stamps[-1] - o.stamps[0])
    same = local.poses.shape == offline.poses.shape
    difference = local.poses - offline.poses if same else np.full((1, 3), np.inf)
    same_landmarks = np.array_equal(local.landmark_labels, offline.landmark_labels)
    return {
        "duration": duration,
        "odometry": len(o.stamps),
        "features": len(f.stamps),
        "poses": len(local.stamps),
        "updates": updates,
        "compute": compute,
        "real_time_factor": duration / compute,
        "worst_update": worst,
        "offline_seconds": offline_seconds,
        "max_position_difference": float(np.abs(difference[:, :2]).max()),
        "max_heading_difference": float(np.abs(se2.wrap_angle(difference[:, 2])).max()),
        "max_landmark_difference": float(np.abs(local.landmarks - offline.landmarks).max())
        if same_landmarks
        else np.inf,
        "online_cost": local.problem.cost(),
        "offline_cost": offline.problem.cost(),
        "publish_covariances": covariances,
        "rendezvous_poses": len(np.unique(local.pose_index(rendezvous))) if len(rendezvous) else 0,
        "publish_sqrt_information": sqrt_information,
    }


def print_online(name: str, r: dict[str, float]) -> None:
    print(
        f"   {name}: {r['duration']:.0f} s of data, {r['odometry']} odometry samples, "
        f"{r['features']} feature observations -> {r['poses']} poses"
    )
    print(
        f"   online: {r['updates']} updates in {r['compute']:.1f} s = "
        f"{r['real_time_factor']:.0f}x real time (worst second {r['worst_update']:.3f} s); "
        f"offline build {r['offline_seconds']:.1f} s"
    )
    print(
        f"   online (converged at the end) vs offline: max difference of positions "
        f"{r['max_position_difference']:.1e} m, headings {r['max_heading_difference']:.1e} rad, "
        f"landmarks {r['max_landmark_difference']:.1e} m; cost {r['online_cost']:.2f} vs "
        f"{r['offline_cost']:.2f}"
    )
    print(
        f"   for the smoother's messages at the end: every pose and landmark covariance "
        f"{1e3 * r['publish_covariances']:.0f} ms, square-root information of "
        f"{r['rendezvous_poses']} rendezvous poses {1e3 * r['publish_sqrt_information']:.0f} ms"
    )


def main(argv: list[str] | None = None) -> None:
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--poses", type=int, default=7000)
    parser.add_argument("--landmarks", type=int, default=150)
    parser.add_argument("--observations", type=int, default=3600)
    parser.add_argument("--seed", type=int, default=7)
    parser.add_argument("--tolerance", type=float, default=1e-8)
    parser.add_argument("--max-iterations", type=int, default=200)
    parser.add_argument("--chunk", type=int, default=1000, help="poses per incremental step")
    parser.add_argument(
        "--chunk-tolerance", type=float, default=1e-6, help="relative tolerance of inner solves"
    )
    parser.add_argument("--victoria", default=None, help="path of victoria_park.txt")
    parser.add_argument("--no-victoria", action="store_true")
    parser.add_argument("--no-identical", action="store_true", help="skip GTSAM CustomFactor")
    parser.add_argument("--mrclam", default=None, help="MR.CLAM data set directory (online test)")
    parser.add_argument("--no-online", action="store_true", help="skip the online local map test")
    parser.add_argument("--worker", default=None, help=argparse.SUPPRESS)
    parser.add_argument("--problem", default=None, help=argparse.SUPPRESS)
    parser.add_argument("--out", default=None, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.worker:
        print(json.dumps(worker(args.worker, args.problem, args, Path(args.out))))
        return
    try:
        import gtsam  # noqa: F401

        have_gtsam = True
    except ImportError:
        have_gtsam = False
        print("GTSAM is not installed: only this project's numbers")
    solvers = ["ours"] + (["gtsam-native"] if have_gtsam else [])
    identical = [] if args.no_identical or not have_gtsam else ["gtsam-identical"]
    print(f"machine: {os.cpu_count()} cores; peak MB = max resident set of the solver's process")
    compare("simulated", args, argv, [*solvers, "ours-splu", *identical])
    path = None if args.no_victoria else (args.victoria or victoria_park_path())
    if path is None:
        if not args.no_victoria:
            print("\nVictoria Park data set not found (give --victoria PATH)")
    else:
        # CustomFactor LM on Victoria Park from dead reckoning takes many minutes: skipped.
        # Batch solves from dead reckoning end in local minima there; the incremental policy
        # of the local map (poses added in chunks, warm-started) is listed for its optimum.
        compare(str(path), args, argv, [*solvers, "ours-incremental"])
    if args.no_online:
        return
    print("\n== online local map, one update per second of data")
    options = LocalMapOptions(robust=Cauchy())
    if args.mrclam:
        # as `csam replay --config config/mrclam.yaml` runs the smoothers: calibrated import,
        # thinned rendezvous, the local_map section, one update per publish period
        from csam_ros.bench.mrclam import CONFIG, RunOptions
        from csam_ros.core.robust import thin_rendezvous
        from csam_ros.datasets.mrclam import import_mrclam, load_config

        section = load_config(CONFIG)
        run = RunOptions.from_config(CONFIG)
        multi, _ = import_mrclam(
            args.mrclam,
            noise=section["noise"],
            landmark_swaps=section.get("landmark_swaps") or [],
            range_scale=section.get("range_scale"),
        )
        thinned, _ = thin_rendezvous(
            {n: r.rendezvous for n, r in multi.robots.items()},
            run.csam.rendezvous_min_interval,
            run.csam.rendezvous_max_per_pair or None,
        )
        options = replace(run.local_map.options(), update_period=run.local_map.publish_period)
        for name, log in multi.robots.items():
            log = replace(log, rendezvous=thinned[name])
            rate = online_rate(log, options, run.local_map.window)
            print_online(f"MR.CLAM {name} ({CONFIG.name})", rate)
    else:
        log = simulate_robot_log(duration=1500.0, landmarks=40, scan_rate=5.0)[0]
        print_online("simulated MR.CLAM-rate robot (Cauchy kernel)", online_rate(log, options))
        print("   (give --mrclam DIR for the real data set)")


if __name__ == "__main__":
    main()
