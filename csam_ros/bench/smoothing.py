"""Benchmark of single-robot square-root smoothing against GTSAM (run as a module).

``python -m csam_ros.bench.smoothing [--poses 7000 --landmarks 150 --observations 3600]
[--victoria PATH | --no-victoria] [--no-identical] [--tolerance 1e-8] [--chunk 1000]
[--no-online | --mrclam DIR | --online-duration 1500]``

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

On Victoria Park (with GTSAM installed) the product path follows: ``csam import slam2d`` and
``csam replay --offline`` of the file, each timed as a whole command and set against GTSAM's
batch LM of the same run, and the replay's map against GTSAM's optimum of the file's model
started from it.

Printed side by side: problem size, iterations, seconds per Gauss-Newton iteration
(linearise, factor, solve, evaluate the cost), total seconds to convergence (solver call
only; problem construction listed separately), final cost on its own objective and on this
project's objective, peak memory. For this project also where the time goes (structure,
ordering with the first factorisation, and each part of an iteration) and the share of
GTSAM's time its factorisations alone take. The problem generators and builders are shared
with the tests: :mod:`csam_ros.testing.landmark_problem` (simulated problem, this project's
problem, the incremental policy) and :mod:`csam_ros.testing.gtsam_oracle` (the same in GTSAM).

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
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from csam_ros.core.model import se2
from csam_ros.core.model.log import RobotLog
from csam_ros.core.sam.factors import Cauchy
from csam_ros.core.sam.normal_equations import NormalEquations
from csam_ros.core.sam.solver import Problem, SolverOptions
from csam_ros.core.smoothing.local_map import LocalMap
from csam_ros.core.smoothing.local_map_build import build_local_map
from csam_ros.core.smoothing.local_map_config import LocalMapOptions
from csam_ros.datasets.simulation import simulate_robot_log
from csam_ros.datasets.slam2d import Slam2dData, initial_values, read_slam2d
from csam_ros.testing.gtsam_oracle import build_gtsam, gtsam_estimate
from csam_ros.testing.landmark_problem import (
    GraphData,
    build_problem,
    read_graph,
    save_graph,
    simulate_landmark_problem,
    solve_incremental,
)

Array = NDArray[np.float64]


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


# ---------------------------------------------------------------------------------------------
# benchmark: one solver per process


def victoria_park_path() -> Path | None:
    """The Victoria Park file shipped with GTSAM's wheel, if GTSAM is installed."""
    try:
        import gtsam
    except ImportError:
        return None
    path = Path(gtsam.__file__).parent / "Data" / "victoria_park.txt"
    return path if path.exists() else None


def victoria_park_lm_seconds() -> float | None:
    """Seconds of GTSAM's batch Levenberg-Marquardt on Victoria Park from dead reckoning, in a
    process of its own with this benchmark's defaults (the figure this benchmark prints on the
    ``gtsam-native`` line): the machine's speed that hour. None without GTSAM or the file."""
    path = victoria_park_path()
    if path is None:
        return None
    graph_data = graph_from_slam2d(read_slam2d(str(path)), name=path.stem)
    with tempfile.TemporaryDirectory() as tmp:
        saved = Path(tmp) / "problem.npz"
        save_graph(graph_data, saved)
        result = run_worker("gtsam-native", str(saved), [], Path(tmp) / "estimate.npy")
    return None if result is None else float(result["total"])


def load_graph(spec: str, args: argparse.Namespace) -> GraphData:
    if spec == "simulated":
        return simulate_landmark_problem(
            args.poses, args.landmarks, args.observations, args.seed
        ).graph()
    return graph_from_slam2d(read_slam2d(spec), name=Path(spec).stem)


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


def product_path(spec: str, graph_data: GraphData, tmp: Path) -> dict[str, Any]:
    """A 2D SLAM file through the product: ``csam import slam2d`` and ``csam replay
    --offline``, each timed as a whole command (a fresh process: imports, bag, figures), and
    the replay's map against GTSAM's optimum of the file's model (this project's errors with
    GTSAM's geometry) started from it: how far GTSAM's Gauss-Newton moves it."""
    from csam_ros.testing.gtsam_oracle import gauss_newton

    seconds = {}
    for name, command in (
        ("import", ["import", "slam2d", spec, "--out", str(tmp / "bag")]),
        ("replay", ["replay", str(tmp / "bag"), "--offline", "--out", str(tmp / "run")]),
    ):
        t0 = time.perf_counter()
        done = subprocess.run(
            [sys.executable, "-m", "csam_ros.cli", *command], capture_output=True, text=True
        )
        seconds[name] = time.perf_counter() - t0
        if done.returncode != 0:
            raise RuntimeError(f"csam {name} failed: {done.stderr.strip()}")
    summary = json.loads((tmp / "run" / "summary.json").read_text())
    poses = np.array(summary["robots"]["robot1"]["poses_joined"])
    xy = {f["members"][0].split("/")[1]: f["xy"] for f in summary["features"]}
    ids = read_slam2d(spec).landmark_ids
    landmarks = np.array([xy[str(int(i))] for i in ids]).reshape(-1, 2)
    start = replace(graph_data, initial_poses=poses, initial_landmarks=landmarks)
    graph, values = build_gtsam(start, identical=True)
    result, iterations = gauss_newton(graph, values)
    theirs, their_landmarks = gtsam_estimate(start, result)
    return seconds | {
        "cost": graph.error(values),
        "gtsam_cost": graph.error(result),
        "gtsam_iterations": iterations,
        "poses": float(np.hypot(*(poses[:, :2] - theirs[:, :2]).T).max()),
        "headings": float(np.abs(se2.wrap_angle(poses[:, 2] - theirs[:, 2])).max()),
        "landmarks": float(np.hypot(*(landmarks - their_landmarks).T).max()),
    }


def print_product_path(product: dict[str, Any], native: dict[str, Any] | None) -> None:
    print(
        f"   product path, whole commands: csam import slam2d {product['import']:.2f} s, "
        f"csam replay --offline {product['replay']:.2f} s"
        + (
            f" = {product['replay'] / native['total']:.2f} of GTSAM's batch LM "
            f"({native['total']:.2f} s, cost {native['cost']:.1f} on its own model)"
            if native is not None
            else ""
        )
    )
    print(
        f"   replay vs GTSAM's optimum of the file's model from there "
        f"({product['gtsam_iterations']} Gauss-Newton iterations, cost "
        f"{product['cost']:.4f} -> {product['gtsam_cost']:.4f}): "
        f"max difference of positions {product['poses']:.1e} m, headings "
        f"{product['headings']:.1e} rad, landmarks {product['landmarks']:.1e} m"
    )


def compare(
    spec: str,
    args: argparse.Namespace,
    argv: list[str],
    solvers: list[str],
    product: bool = False,
) -> None:
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
        product_row = product_path(spec, graph_data, Path(tmp)) if product else None
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
    for solver in ("ours", "ours-incremental"):
        if solver in by_name and "gtsam-native" in by_name:
            print(ratio_line(solver, by_name[solver][0], by_name["gtsam-native"][0]))
    if product_row is not None:
        print_product_path(product_row, by_name.get("gtsam-native", (None,))[0])
    if "ours" in by_name and "gtsam-identical" in by_name:
        a, b = by_name["ours"][1], by_name["gtsam-identical"][1]
        diff = np.abs(a - b)
        diff[2 : 3 * n : 3] = np.abs(se2.wrap_angle(a[2 : 3 * n : 3] - b[2 : 3 * n : 3]))
        print(f"   identical objective: max |ours - GTSAM| over all unknowns {diff.max():.2e}")


def ratio_line(solver: str, ours: dict[str, Any], native: dict[str, Any]) -> str:
    """One of our solvers against GTSAM's batch LM: the time per iteration (batch only: the
    incremental policy's iterations are on growing problems), the time to convergence and,
    for the incremental policy, the optimum each reached on our objective."""
    line = f"   ratio {solver} / GTSAM native: "
    if solver == "ours":
        line += f"time per iteration {ours['per_iteration'] / native['per_iteration']:.3f}, "
    line += f"time to convergence {ours['total'] / native['total']:.3f}"
    if solver != "ours":
        line += f" (our cost {ours['our_cost']:.1f} vs {native['our_cost']:.1f})"
    return line


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
        local.add_log_part(log, slice(oi, oj), order[fi:fj])
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
        f"{1e3 * r['publish_covariances']:.0f} ms"
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
    parser.add_argument(
        "--online-duration", type=float, default=1500.0, help="s of the simulated online log"
    )
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
        compare(str(path), args, argv, [*solvers, "ours-incremental"], product=have_gtsam)
    if args.no_online:
        return
    print("\n== online local map, one update per second of data")
    options = LocalMapOptions(robust=Cauchy())
    if args.mrclam:
        # as `csam replay --config config/mrclam.yaml` runs the smoothers: calibrated import,
        # thinned rendezvous, the local_map section, one update per publish period
        from csam_ros.bench.mrclam import CONFIG, RunOptions
        from csam_ros.core.joining.rendezvous_filters import thin_rendezvous
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
        log = simulate_robot_log(duration=args.online_duration, landmarks=40, scan_rate=5.0)[0]
        print_online("simulated MR.CLAM-rate robot (Cauchy kernel)", online_rate(log, options))
        print("   (give --mrclam DIR for the real data set)")


if __name__ == "__main__":
    main()
