"""Benchmark of single-robot square-root smoothing against GTSAM (run as a module).

``python -m csam_ros.bench.smoothing [--poses 7000 --landmarks 150 --observations 3600]``

Simulates a landmark SLAM problem with a fixed seed (dead-reckoning initial values), solves it
with this project's solver and with GTSAM (imported here only), and prints side by side:
problem size, iterations, seconds per iteration, total seconds, final cost and peak memory.

GTSAM is run twice: with its native factors (``BetweenFactorPose2``, ``BearingRangeFactor2D``),
the fair speed reference, whose objective is the same model to first order but not the
same function; and, for the cost comparison, on exactly this project's objective through
``CustomFactor`` (slower, since it calls Python per factor). The problem builders are also
used by the tests (GTSAM as an oracle).
"""

from __future__ import annotations

import argparse
import resource
import time
import tracemalloc
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from csam_ros.core import motion, se2, sensor
from csam_ros.core.factors import POINT, POSE, PointObservation, PosePrior, RelativePose
from csam_ros.core.solver import GAUGE_SIGMA, Problem, SolverOptions

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


def build_problem(sim: LandmarkProblem) -> Problem:
    """This project's problem: gauge prior, odometry and Cartesian landmark observations."""
    problem = Problem()
    n = len(sim.initial_poses)
    pose_ids = problem.add_variables(POSE, [("x", i) for i in range(n)], sim.initial_poses)
    lm_ids = problem.add_variables(
        POINT, [("l", j) for j in range(len(sim.initial_landmarks))], sim.initial_landmarks
    )
    problem.add_factor(
        PosePrior(pose_ids[:1], sim.initial_poses[:1], np.eye(3) / GAUGE_SIGMA, name="gauge")
    )
    problem.add_factor(
        RelativePose(pose_ids[:-1], pose_ids[1:], sim.odometry, covariance=sim.odometry_covariance)
    )
    problem.add_factor(
        PointObservation(
            pose_ids[sim.obs_pose],
            lm_ids[sim.obs_landmark],
            sim.obs_xy,
            covariance=sim.obs_covariance,
        )
    )
    return problem


def _local_to_global(phi: float) -> Array:
    """``d(global pose)/d(GTSAM tangent)`` at a pose with heading ``phi``: blkdiag(R, 1)."""
    m = np.eye(3)
    m[:2, :2] = se2.rotation(phi)
    return m


def build_gtsam(sim: LandmarkProblem, identical: bool) -> tuple[Any, Any]:
    """GTSAM graph and initial values.

    ``identical=True`` writes exactly this project's errors as ``CustomFactor`` (Jacobians
    chained to GTSAM's tangent space); ``False`` uses GTSAM's native Pose2 between and
    bearing-range factors with the same covariances (same model to first order).
    """
    import gtsam

    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    n = len(sim.initial_poses)

    def pose_key(i: int) -> int:
        return gtsam.symbol("x", i)

    def lm_key(j: int) -> int:
        return gtsam.symbol("l", j)

    for i, p in enumerate(sim.initial_poses):
        values.insert(pose_key(i), gtsam.Pose2(*p))
    for j, p in enumerate(sim.initial_landmarks):
        values.insert(lm_key(j), np.asarray(p, dtype=float))
    graph.add(
        gtsam.PriorFactorPose2(
            pose_key(0),
            gtsam.Pose2(*sim.initial_poses[0]),
            gtsam.noiseModel.Isotropic.Sigma(3, GAUGE_SIGMA),
        )
    )
    if not identical:
        for i in range(n - 1):
            graph.add(
                gtsam.BetweenFactorPose2(
                    pose_key(i),
                    pose_key(i + 1),
                    gtsam.Pose2(*sim.odometry[i]),
                    gtsam.noiseModel.Gaussian.Covariance(sim.odometry_covariance[i]),
                )
            )
        noise = gtsam.noiseModel.Diagonal.Sigmas(np.array([sim.sigma_bearing, sim.sigma_range]))
        for k in range(len(sim.obs_pose)):
            graph.add(
                gtsam.BearingRangeFactor2D(
                    pose_key(int(sim.obs_pose[k])),
                    lm_key(int(sim.obs_landmark[k])),
                    gtsam.Rot2(float(sim.obs_bearing[k])),
                    float(sim.obs_range[k]),
                    noise,
                )
            )
        return graph, values

    def between_error(z: Array):
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

    def observation_error(z: Array):
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

    for i in range(n - 1):
        graph.add(
            gtsam.CustomFactor(
                gtsam.noiseModel.Gaussian.Covariance(sim.odometry_covariance[i]),
                [pose_key(i), pose_key(i + 1)],
                between_error(sim.odometry[i]),
            )
        )
    z_all, cov_all = sim.obs_xy, sim.obs_covariance
    for k in range(len(sim.obs_pose)):
        graph.add(
            gtsam.CustomFactor(
                gtsam.noiseModel.Gaussian.Covariance(cov_all[k]),
                [pose_key(int(sim.obs_pose[k])), lm_key(int(sim.obs_landmark[k]))],
                observation_error(z_all[k]),
            )
        )
    return graph, values


def gtsam_estimate(sim: LandmarkProblem, result: Any) -> tuple[Array, Array]:
    """Poses ``(N, 3)`` and landmarks ``(L, 2)`` from GTSAM values."""
    import gtsam

    poses = np.array(
        [
            [p.x(), p.y(), p.theta()]
            for p in (result.atPose2(gtsam.symbol("x", i)) for i in range(len(sim.initial_poses)))
        ]
    )
    lms = np.array(
        [result.atPoint2(gtsam.symbol("l", j)) for j in range(len(sim.initial_landmarks))]
    )
    return poses, lms


def gtsam_marginal_covariance(sim: LandmarkProblem, graph: Any, result: Any, keys: list) -> Array:
    """GTSAM's joint marginal of ``keys`` (("x", i) or ("l", j)) in global parametrisation."""
    import gtsam

    marginals = gtsam.Marginals(graph, result)
    gkeys = [gtsam.symbol(kind, idx) for kind, idx in keys]
    joint = marginals.jointMarginalCovariance(gkeys)
    blocks = []
    transforms = []
    for (kind, _), gk in zip(keys, gkeys, strict=True):
        if kind == "x":
            transforms.append(_local_to_global(result.atPose2(gk).theta()))
        else:
            transforms.append(np.eye(2))
        blocks.append(joint.at(gk, gk).shape[0])
    dim = sum(blocks)
    m = np.zeros((dim, dim))
    edges = np.cumsum([0, *blocks])
    full = np.zeros((dim, dim))
    for a, ka in enumerate(gkeys):
        m[edges[a] : edges[a + 1], edges[a] : edges[a + 1]] = transforms[a]
        for b, kb in enumerate(gkeys):
            full[edges[a] : edges[a + 1], edges[b] : edges[b + 1]] = joint.at(ka, kb)
    return m @ full @ m.T


# ---------------------------------------------------------------------------------------------
# benchmark


def _peak_mb(function: Any) -> tuple[Any, float]:
    tracemalloc.start()
    tracemalloc.reset_peak()
    out = function()
    peak = tracemalloc.get_traced_memory()[1] / 1e6
    tracemalloc.stop()
    return out, peak


def run_ours(sim: LandmarkProblem, backend: str = "qdldl") -> dict[str, Any]:
    start = time.perf_counter()
    problem = build_problem(sim)
    build = time.perf_counter() - start
    report = problem.solve(SolverOptions(backend=backend))
    system = problem.normal_equations(backend)
    reps = 5
    t0 = time.perf_counter()
    for _ in range(reps):
        system.linearize(problem.values)
        system.factorize(0.0)
        system.solve(-system.gradient)
    per_iteration = (time.perf_counter() - t0) / reps
    return {
        "problem": problem,
        "iterations": report.iterations,
        "per_iteration": per_iteration,
        "total": report.seconds,
        "build": build,
        "cost": report.final_cost,
        "converged": report.converged,
    }


def run_gtsam(sim: LandmarkProblem, identical: bool, max_iterations: int = 100) -> dict[str, Any]:
    import gtsam

    start = time.perf_counter()
    graph, values = build_gtsam(sim, identical)
    build = time.perf_counter() - start
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(1e-10)
    params.setAbsoluteErrorTol(0.0)
    params.setMaxIterations(max_iterations)
    t0 = time.perf_counter()
    optimizer = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
    result = optimizer.optimize()
    total = time.perf_counter() - t0
    iterations = optimizer.iterations()
    # One Gauss-Newton iteration: linearise + eliminate (sequential Cholesky, COLAMD) + retract.
    reps = 3
    t0 = time.perf_counter()
    for _ in range(reps):
        linear = graph.linearize(result)
        delta = linear.optimize()
        result.retract(delta)
    per_iteration = (time.perf_counter() - t0) / reps
    return {
        "graph": graph,
        "result": result,
        "iterations": iterations,
        "per_iteration": per_iteration,
        "total": total,
        "build": build,
        "cost": graph.error(result),
    }


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--poses", type=int, default=7000)
    parser.add_argument("--landmarks", type=int, default=150)
    parser.add_argument("--observations", type=int, default=3600)
    parser.add_argument("--seed", type=int, default=7)
    parser.add_argument("--no-identical", action="store_true", help="skip GTSAM CustomFactor run")
    args = parser.parse_args(argv)
    sim = simulate_landmark_problem(args.poses, args.landmarks, args.observations, args.seed)
    n, l_count, k = len(sim.initial_poses), len(sim.initial_landmarks), len(sim.obs_pose)
    print(f"simulated problem: {n} poses, {l_count} landmarks, {k} observations, seed {args.seed}")
    print(f"unknowns: {3 * n + 2 * l_count}; factors: {1 + (n - 1) + k}")

    ours, ours_mem = _peak_mb(lambda: run_ours(sim))
    rows = [("this project (qdldl)", ours, ours_mem)]
    try:
        import gtsam  # noqa: F401
    except ImportError:
        print("GTSAM not installed: only this project's numbers")
        gt = None
    else:
        gt, gt_mem = _peak_mb(lambda: run_gtsam(sim, identical=False))
        rows.append(("GTSAM LM, native factors", gt, gt_mem))
        if not args.no_identical:
            gti, gti_mem = _peak_mb(lambda: run_gtsam(sim, identical=True))
            rows.append(("GTSAM LM, identical objective", gti, gti_mem))
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print()
    header = (
        f"{'solver':32s} {'iter':>5s} {'s/iter':>9s} {'total s':>9s} {'final cost':>14s} "
        f"{'peak MB':>8s}"
    )
    print(header)
    for name, r, mem in rows:
        print(
            f"{name:32s} {r['iterations']:5d} {r['per_iteration']:9.4f} {r['total']:9.3f} "
            f"{r['cost']:14.6f} {mem:8.1f}"
        )
    print(f"(peak MB: tracemalloc of Python allocations; process max RSS {rss:.0f} MB)")
    if gt is not None:
        print(
            f"ratios vs GTSAM native: time per iteration {ours['per_iteration'] / gt['per_iteration']:.3f}"
            f", time to optimum {ours['total'] / gt['total']:.3f}"
        )
        problem = ours["problem"]
        poses, lms = gtsam_estimate(sim, gt["result"])
        values = np.concatenate([poses.reshape(-1), lms.reshape(-1)])
        print(
            f"this project's objective at GTSAM-native optimum: {problem.cost(values):.6f} "
            f"(ours {ours['cost']:.6f})"
        )
        if len(rows) == 3:
            poses, lms = gtsam_estimate(sim, rows[2][1]["result"])
            values = np.concatenate([poses.reshape(-1), lms.reshape(-1)])
            dx = np.abs(values - problem.values)
            dx[2 : 3 * n : 3] = np.abs(se2.wrap_angle(dx[2 : 3 * n : 3]))
            print(
                f"max |difference| of the two estimates on the identical objective: {dx.max():.2e}"
            )


if __name__ == "__main__":
    main()
