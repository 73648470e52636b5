"""Benchmark of C-SAM map joining: ``python -m csam_ros.bench.joining``.

Two robots map feature strips (1 m feature spacing, 4 m laser, 240 degrees) driving in
opposite directions on lanes 3 m apart; the strips overlap over 20 m, where the robots pass
each other (about 20 rendezvous measurements), like the paper's figure 5 at a larger scale.
For maps of
about 250, 1,000 and 4,000 features each, the local maps are built first (with their feature
covariances, as a smoother publishes them; timed apart), then C-SAM joins them. The table
gives the time of each step of the merge and the growth exponent of the merge time between
sizes (1 = linear, 2 = quadratic). "summary covariances" is the extra cost of the per-pose
heading sigmas and per-feature covariances of the local and joined maps that ``summary.json``
reports (a selected inverse of
each factor).

Target: joining two maps of 1,000 features each in under 1 s (the merge without the summary
covariances).
"""

from __future__ import annotations

import os

# The dense blocks here are tiny; a multi-threaded BLAS spends more on waking its threads than
# it saves (measured: up to 100x on a 3 x 3 triangular solve on a loaded 2-core machine).
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

from csam_ros.core.joining.config import CsamConfig  # noqa: E402
from csam_ros.core.joining.join import join_maps  # noqa: E402
from csam_ros.core.joining.pipeline import robot_map_from_local_map  # noqa: E402
from csam_ros.core.model.rendezvous import required_stamps  # noqa: E402
from csam_ros.core.smoothing.local_map_build import build_local_map  # noqa: E402
from csam_ros.core.truth.evaluation import evaluate  # noqa: E402
from csam_ros.datasets.simulation import RobotSpec, Scenario, Segment, feature_grid, simulate

LANE_GAP = 3.0  # m between the two lanes
SPACING = 1.0  # m between features
OVERLAP = 20.0  # m of strip mapped by both robots, around the meeting point


def strip_scenario(features_per_map: int, seed: int = 0) -> Scenario:
    """Two robots mapping two strips that overlap by ``OVERLAP`` metres, where they meet.

    robot1 drives +x over ``[0, L]`` on lane y = 0, robot2 drives -x over
    ``[2L - OVERLAP, L - OVERLAP]`` on lane y = 3 m at the same speed: they pass each other in
    the middle of the overlap; each maps about ``features_per_map`` features.
    """
    strip_width = 8.0  # a 4 m sensor sees 4 m to each side
    length = max(OVERLAP, features_per_map * SPACING**2 / strip_width - 8.0)
    rng = np.random.default_rng(seed)
    far_end = 2.0 * length - OVERLAP
    features = feature_grid(
        (far_end / 2, LANE_GAP / 2),
        (far_end + 8.0, 8.0 + LANE_GAP),
        SPACING,
        0.25,
        rng,
    )
    duration = 2.0 * round(length)  # 0.5 m/s, sample time 0.5 s
    sigma = (0.02, 0.01, float(np.deg2rad(0.6)))
    robots = (
        RobotSpec("robot1", (0.0, 0.0, 0.0), (Segment(duration, 0.5, 0.0),), sigma),
        RobotSpec("robot2", (far_end, LANE_GAP, np.pi), (Segment(duration, 0.5, 0.0),), sigma),
    )
    return Scenario("strips", 0.5, features, robots, seed)


def run(features_per_map: int, seed: int = 0) -> dict[str, float]:
    """Build the two local maps, join them and return timings and counts."""
    log = simulate(strip_scenario(features_per_map, seed), seed)
    stamps = required_stamps({n: r.rendezvous for n, r in log.robots.items()})
    start = time.perf_counter()
    locals_ = [build_local_map(r, stamps[n]) for n, r in log.robots.items()]
    built = time.perf_counter()
    maps = [robot_map_from_local_map(m, with_covariances=True) for m in locals_]
    covariances = time.perf_counter()
    result = join_maps(maps, {n: r.rendezvous for n, r in log.robots.items()}, CsamConfig())
    t = result.timing_s
    summary = t.get("local_marginals", 0.0) + t.get("joint_marginals", 0.0)
    association = evaluate(result, log.truth)["association"]
    return {
        "features": float(np.mean([len(m.feature_ids) for m in maps])),
        "poses": float(np.mean([len(m.stamps) for m in maps])),
        "rendezvous": float(result.statistics["rendezvous_measurements"]),
        "local_map_s": (built - start) / 2,
        "local_covariances_s": (covariances - built) / 2,
        "alignment_s": t["local_rendezvous_parts"] + t["alignment"],
        "association_s": t.get("association", 0.0),
        "joint_solve_s": t["joint_solve"] + t["joint_base_node_covariance"],
        "merge_s": t["total"] - summary,
        "summary_covariances_s": summary,
        "associations": float(len(result.associations)),
        "precision": association["precision"] or 0.0,
        "recall": association["recall"] or 0.0,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[250, 1000, 4000])
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    run(min(args.sizes), args.seed)  # warm-up, not shown: first calls load libraries
    rows = [run(n, args.seed) for n in args.sizes]
    header = (
        f"{'features/map':>12} {'poses/map':>9} {'rdv':>4} {'local map':>9} {'local cov':>9} "
        f"{'align':>7} {'assoc':>7} {'joint':>7} {'MERGE':>7} {'growth':>6} "
        f"{'summ.cov':>8} {'assoc':>6} {'prec':>5} {'recall':>6}"
    )
    print(header)
    print("-" * len(header))
    previous = None
    for row in rows:
        growth = ""
        if previous is not None:
            ratio = np.log(row["merge_s"] / previous["merge_s"])
            growth = f"{ratio / np.log(row['features'] / previous['features']):.2f}"
        print(
            f"{row['features']:12.0f} {row['poses']:9.0f} {row['rendezvous']:4.0f} "
            f"{row['local_map_s']:8.3f}s {row['local_covariances_s']:8.3f}s "
            f"{row['alignment_s']:6.3f}s {row['association_s']:6.3f}s {row['joint_solve_s']:6.3f}s "
            f"{row['merge_s']:6.3f}s {growth:>6} {row['summary_covariances_s']:7.3f}s "
            f"{row['associations']:6.0f} {row['precision']:5.2f} {row['recall']:6.2f}"
        )
        previous = row
    print(
        "local map / local cov: per robot, before joining (the smoothers' work). MERGE = align "
        "(rendezvous parts + Algorithm 1) + assoc (Algorithm 2) + joint (solve + base-node "
        "covariance); growth = d log(MERGE) / d log(features). summ.cov: per-pose heading "
        "sigmas and per-feature covariances of the local and joined maps for summary.json."
    )


if __name__ == "__main__":
    main()
