"""Benchmark of many robots, live or offline: ``python -m csam_ros.bench.many_robots``.

N robots each drive one loop (radius 2.4 m, 0.5 m/s, about 30 s at a sample time of 0.5 s)
around a centre of their own; neighbouring centres are 3.5 m apart, so neighbours' loops and
feature areas overlap and they pass within the 4 m sensor range of each other. ``ring``: the
centres on a circle, robot i meets robots i-1 and i+1 and robot N meets robot 1 (the whole
formation turns together, every pair alike); ``chain``: the centres on a line, neighbours
turning in opposite directions (mirror images of each other), no wrap. A robot observes only
its neighbours (``observes``), at every 4th sample (``--every``): the rendezvous poses are the
state of Algorithm 2's conditioning, whose cost grows with the square of their number.

For each N the generated scenario is written as a scenario file (the layout of
``config/chain.yaml``), run live through the nodes as ``csam demo --scenario FILE`` runs it,
and the recorded bag is run offline as ``csam replay BAG --offline`` runs it. Per N: robots
aligned, features and associations of the live joined map, the merger's solve times and the
lag of the local maps (``/csam/status`` and the bag, ``csam_ros.run.lag``), the wall time of
the live run, and the largest difference between the live and the offline joined maps.

``--offline``: the join alone, to 64 robots, each observing its neighbours at every sample
(``--every 1``); up to 16 robots each bag is joined again by the dense path (``csam:
alignment_method: dense-newton``) and the largest difference of the joined maps printed. Each
N's scenario is written to a bag as ``csam simulate`` writes it (no DDS, no nodes) and the bag
joined as ``csam replay BAG --offline`` joins it; per N the time of each stage of the join
(summary.json ``timing_s``), the join alone (``total - local_maps``), and the growth exponent
of each in N: the log-log slope between successive N and, fitted to them all, overall.
``--scenarios-only`` writes the scenario files and stops.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from csam_ros.core.joining.result import CsamResult, RunSummary
from csam_ros.core.model import se2
from csam_ros.datasets.formations import (
    CSAM_SECTION,
    LAYOUTS,
    RENDEZVOUS_EVERY,
    many_robot_scenario,
    neighbours,
)
from csam_ros.datasets.simulation import (
    RangeBearingSensor,
    Scenario,
    simulate,
)
from csam_ros.run.lag import LagStats, SolveStats


def meetings(scenario: Scenario) -> dict[tuple[str, str], int]:
    """Rendezvous measurements per ordered pair (observer, observed) of a simulated run."""
    counts: dict[tuple[str, str], int] = {}
    for name, robot in simulate(scenario).robots.items():
        observed, k = np.unique(
            np.asarray(robot.rendezvous.observed, dtype=str), return_counts=True
        )
        counts.update({(name, str(o)): int(c) for o, c in zip(observed, k, strict=True)})
    return counts


def neighbour_pairs_meeting(scenario: Scenario, layout: str) -> tuple[int, int, int]:
    """Neighbour pairs observing each other both ways, neighbour pairs, and rendezvous
    measurements, in a simulation of ``scenario`` (one of :func:`many_robot_scenario`)."""
    n = len(scenario.robots)
    met = meetings(scenario)
    pairs = {(i, j) for i, js in enumerate(neighbours(n, layout)) for j in js if i < j}
    names = [r.name for r in scenario.robots]
    meeting = sum((names[i], names[j]) in met and (names[j], names[i]) in met for i, j in pairs)
    return meeting, len(pairs), sum(met.values())


def _sensor_dict(sensor: RangeBearingSensor | None) -> dict[str, float] | None:
    if sensor is None:
        return None
    return {
        "max_range": float(sensor.max_range),
        "min_range": float(sensor.min_range),
        "field_of_view_deg": float(np.rad2deg(sensor.field_of_view)),
        "sigma_range": float(sensor.sigma_range),
        "sigma_bearing": float(sensor.sigma_bearing),
    }


def scenario_document(scenario: Scenario, csam: dict[str, Any] | None = None) -> dict[str, Any]:
    """A scenario as a scenario file's document (``csam_ros.datasets.scenario``), the
    features as explicit points; ``csam`` is its ``csam:`` section."""
    robots = []
    for r in scenario.robots:
        v, v_lat, omega = r.odometry_sigma
        entry: dict[str, Any] = {
            "name": r.name,
            "start": {
                "x": float(r.start_pose[0]),
                "y": float(r.start_pose[1]),
                "phi_deg": float(np.rad2deg(r.start_pose[2])),
            },
            "program": [
                {
                    "duration": float(s.duration),
                    "v": float(s.v),
                    "omega_deg": float(np.rad2deg(s.omega)),
                }
                for s in r.program
            ],
            "odometry_sigma": {
                "v": float(v),
                "v_lat": float(v_lat),
                "omega_deg": float(np.rad2deg(omega)),
            },
            "feature_sensor": _sensor_dict(r.feature_sensor),
            "rendezvous_sensor": _sensor_dict(r.rendezvous_sensor),
            "rendezvous_every": int(r.rendezvous_every),
        }
        if r.observes is not None:
            entry["observes"] = list(r.observes)
        robots.append(entry)
    document: dict[str, Any] = {
        "scenario": {
            "name": scenario.name,
            "description": scenario.description,
            "seed": int(scenario.seed),
            "sample_time": float(scenario.sample_time),
            "world": {"points": np.asarray(scenario.features, dtype=float).tolist()},
            "robots": robots,
        }
    }
    if csam:
        document["csam"] = dict(csam)
    return document


def write_scenario(scenario: Scenario, path: Path, csam: dict[str, Any] | None = None) -> Path:
    """Write ``scenario`` as a scenario file at ``path`` (a new file)."""
    text = yaml.safe_dump(
        scenario_document(scenario, csam), sort_keys=False, default_flow_style=None
    )
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "x") as stream:
        stream.write(f"# generated by csam_ros.bench.many_robots\n{text}")
    return path


@dataclass(frozen=True)
class Difference:
    """The largest differences between two joined maps of the same robots (same frame)."""

    position_m: float  # of a joined pose at a stamp both hold, or of a feature both hold
    heading_deg: float  # of a joined pose
    poses: int  # poses compared
    features: int  # features compared (the same members in both)
    features_apart: int  # features whose members are in one map only
    alignment_apart: tuple[str, ...]  # robots joined in one map only

    def __str__(self) -> str:
        apart = f", {self.features_apart} features apart" if self.features_apart else ""
        robots = (
            f", robots joined in one only: {list(self.alignment_apart)}"
            if self.alignment_apart
            else ""
        )
        return f"{self.position_m:.1e} m, {self.heading_deg:.1e} deg{apart}{robots}"


def joined_difference(a: CsamResult, b: CsamResult) -> Difference:
    """How far apart two joined maps are (poses and features matched by stamp and members)."""
    position, heading, poses = [0.0], [0.0], 0
    for name in sorted(a.joined_robots() & b.joined_robots()):
        ra, rb = a.robots[name], b.robots[name]
        _, ia, ib = np.intersect1d(ra.stamps, rb.stamps, return_indices=True)
        pa, pb = ra.poses_joined[ia], rb.poses_joined[ib]
        position.append(float(np.max(np.hypot(*(pa[:, :2] - pb[:, :2]).T), initial=0.0)))
        heading.append(float(np.max(np.abs(se2.wrap_angle(pa[:, 2] - pb[:, 2])), initial=0.0)))
        poses += len(ia)
    fa = {frozenset(f.members): f.xy for f in a.features}
    fb = {frozenset(f.members): f.xy for f in b.features}
    both = sorted(fa.keys() & fb.keys(), key=sorted)
    if both:
        xy = np.array([[fa[k], fb[k]] for k in both])
        position.append(float(np.max(np.hypot(*(xy[:, 0] - xy[:, 1]).T))))
    return Difference(
        position_m=max(position),
        heading_deg=float(np.rad2deg(max(heading))),
        poses=poses,
        features=len(both),
        features_apart=len(fa.keys() ^ fb.keys()),
        alignment_apart=tuple(sorted(a.joined_robots() ^ b.joined_robots())),
    )


@dataclass(frozen=True)
class Row:
    """One N of the benchmark."""

    robots: int
    pairs_meeting: int  # neighbour pairs with rendezvous (both ways) in the simulation
    pairs: int  # neighbour pairs
    aligned: int  # robots in the live joined map (the reference included)
    features: int
    associations: int
    solves: SolveStats
    lag: LagStats
    provisional_lag: LagStats | None  # to the first joined or provisional map (None: none)
    wall_s: float  # the live run, from starting the nodes to the last one stopped
    offline_s: float
    difference: Difference


def run(
    n: int,
    layout: str,
    out: Path,
    duration: float,
    rate: float,
    seed: int,
    rendezvous_every: int = RENDEZVOUS_EVERY,
) -> Row:
    """Generate, run live, run offline and compare, for ``n`` robots under ``out``."""
    from csam_ros.core.model.config_file import load_document
    from csam_ros.run.demo import demo_live_run
    from csam_ros.run.lag import read_timeline
    from csam_ros.run.live import run_live
    from csam_ros.run.offline import offline_summary

    scenario = many_robot_scenario(n, layout, duration, seed, rendezvous_every)
    meeting, pairs, _ = neighbour_pairs_meeting(scenario, layout)
    path = write_scenario(scenario, out / "scenario.yaml", CSAM_SECTION)
    start = time.perf_counter()
    run = demo_live_run(path, out / "live", seed, rate, isolated=True)
    live = run_live(run, progress=lambda _: None)
    wall = time.perf_counter() - start
    start = time.perf_counter()
    offline, _ = offline_summary(out / "live" / "bag", load_document(path))
    offline_s = time.perf_counter() - start
    offline.write(out / "offline" / "summary.json")
    a = RunSummary.read(out / "live" / "summary.json").result
    b = RunSummary.read(out / "offline" / "summary.json").result
    timeline = read_timeline(out / "live" / "bag")
    return Row(
        robots=n,
        pairs_meeting=meeting,
        pairs=pairs,
        aligned=len(a.joined_robots()),
        features=len(a.features),
        associations=len(a.associations),
        solves=timeline.solve_stats(live.merger.solves if live.merger else None),
        lag=timeline.lag_stats(),
        provisional_lag=timeline.provisional_lag_stats(),
        wall_s=wall,
        offline_s=offline_s,
        difference=joined_difference(a, b),
    )


HEADER = (
    f"{'robots':>6} {'pairs met':>9} {'aligned':>8} {'features':>8} {'assoc':>5} "
    f"{'solves':>6} {'solve mean':>10} {'solve max':>9} {'lag mean':>8} {'lag p95':>7} "
    f"{'lag max':>7} {'prov p95':>8} {'maps':>5} {'wall':>6} {'offline':>7}  "
    "live - offline (largest)"
)


def format_row(row: Row) -> str:
    """One line of the table."""
    s, lag = row.solves, row.lag
    never = f"+{lag.never_included}" if lag.never_included else ""
    provisional = f"{row.provisional_lag.p95:7.2f}s" if row.provisional_lag else f"{'-':>8}"
    return (
        f"{row.robots:6d} {f'{row.pairs_meeting}/{row.pairs}':>9} "
        f"{f'{row.aligned}/{row.robots}':>8} {row.features:8d} {row.associations:5d} "
        f"{s.solves:6d} {s.mean:9.2f}s {s.max:8.2f}s {lag.mean:7.2f}s {lag.p95:6.2f}s "
        f"{lag.max:6.2f}s {provisional} {f'{lag.count}{never}':>5} {row.wall_s:5.0f}s "
        f"{row.offline_s:6.1f}s  {row.difference}"
    )


@dataclass(frozen=True)
class OfflineRow:
    """One N of the offline benchmark: a simulated bag joined offline."""

    robots: int
    pairs_meeting: int  # neighbour pairs with rendezvous (both ways) in the simulation
    pairs: int  # neighbour pairs
    rendezvous: int  # rendezvous measurements of every robot
    messages: int  # in the bag
    aligned: int  # robots in the joined map (the reference included)
    features: int
    associations: int
    timing_s: dict[str, float]  # summary.json's: each stage of the join, local_maps and total
    simulate_s: float  # the scenario to a bag, as csam simulate writes it
    replay_s: float  # the bag read and joined, as csam replay --offline (without figures)
    dense: Difference | None = None  # the joined map against the dense path's (small N only)

    @property
    def join_s(self) -> float:
        """The join alone: every stage but the local maps."""
        return self.timing_s["total"] - self.timing_s["local_maps"]


# robot counts up to which the offline benchmark also joins each bag by the dense path
# (Algorithm 1 and the association's conditioning dense: csam alignment_method) to compare
DENSE_ROBOTS = 16


def run_offline(
    n: int, layout: str, out: Path, duration: float, seed: int, rendezvous_every: int
) -> OfflineRow:
    """``n`` robots' scenario written under ``out`` (``scenario.yaml``), simulated to a bag
    (``bag``) and joined offline (``summary.json``)."""
    from csam_ros.core.model.config_file import load_document
    from csam_ros.datasets.scenario import load_scenario
    from csam_ros.run.offline import offline_summary
    from csam_ros.run.simulate import simulated_bag_messages, write_simulated_bag

    scenario = many_robot_scenario(n, layout, duration, seed, rendezvous_every)
    meeting, pairs, rendezvous = neighbour_pairs_meeting(scenario, layout)
    path = write_scenario(scenario, out / "scenario.yaml", CSAM_SECTION)
    start = time.perf_counter()
    messages = write_simulated_bag(simulated_bag_messages(load_scenario(path)), out / "bag")
    simulate_s = time.perf_counter() - start
    start = time.perf_counter()
    summary, _ = offline_summary(out / "bag", load_document(path), progress=lambda _: None)
    replay_s = time.perf_counter() - start
    summary.write(out / "summary.json")
    result = summary.result
    dense = None
    if n <= DENSE_ROBOTS:
        document = load_document(path)
        document["csam"] = {**document.get("csam", {}), "alignment_method": "dense-newton"}
        oracle, _ = offline_summary(out / "bag", document, progress=lambda _: None)
        dense = joined_difference(result, oracle.result)
    return OfflineRow(
        robots=n,
        pairs_meeting=meeting,
        pairs=pairs,
        rendezvous=rendezvous,
        messages=messages,
        aligned=len(result.joined_robots()),
        features=len(result.features),
        associations=len(result.associations),
        timing_s=dict(result.timing_s),
        simulate_s=simulate_s,
        replay_s=replay_s,
        dense=dense,
    )


def format_offline_row(row: OfflineRow) -> str:
    """What one N gave, on one line."""
    return (
        f"  {row.robots} robots: {row.aligned}/{row.robots} aligned, pairs met "
        f"{row.pairs_meeting}/{row.pairs}, {row.rendezvous} rendezvous, {row.features} "
        f"features, {row.associations} associations; bag of {row.messages} messages in "
        f"{row.simulate_s:.1f} s, replay {row.replay_s:.1f} s, join {row.join_s:.2f} s"
        + ("" if row.dense is None else f"; against the dense path {row.dense}")
    )


def growth_exponents(robots: list[int], seconds: list[float]) -> tuple[list[float], float]:
    """How ``seconds`` grow with the number of ``robots``: the log-log slope between each
    two successive counts, and the slope of the least-squares line through them all (NaN
    where a time is not positive)."""
    n, t = np.asarray(robots, dtype=float), np.asarray(seconds, dtype=float)
    with np.errstate(divide="ignore", invalid="ignore"):
        log_t = np.where(t > 0, np.log(np.where(t > 0, t, 1.0)), np.nan)
        successive = (np.diff(log_t) / np.diff(np.log(n))).tolist()
    usable = np.isfinite(log_t)
    overall = float("nan")
    if usable.sum() >= 2:
        overall = float(np.polyfit(np.log(n[usable]), log_t[usable], 1)[0])
    return successive, overall


JOIN_STAGE = "join (total - local_maps)"


def stage_table(rows: list[OfflineRow]) -> list[str]:
    """Seconds of each stage by N (``timing_s``: the local maps, each step of the join, the
    join alone, the total) with their growth exponents in N."""
    keys = list(dict.fromkeys(k for row in rows for k in row.timing_s))
    steps = [k for k in keys if k not in ("local_maps", "total")]
    stages = ["local_maps", *steps, JOIN_STAGE, "total"]
    robots = [row.robots for row in rows]
    slopes = [f"{a}->{b}" for a, b in zip(robots, robots[1:], strict=False)]
    header = (
        f"{'stage [s]':<26}"
        + "".join(f"{f'N={n}':>9}" for n in robots)
        + "".join(f"{s:>8}" for s in slopes)
        + f"{'overall':>8}"
    )
    lines = [header, "-" * len(header)]
    for stage in stages:
        if stage == JOIN_STAGE:
            seconds = [row.join_s for row in rows]
        else:
            seconds = [row.timing_s.get(stage, float("nan")) for row in rows]
        successive, overall = growth_exponents(robots, seconds)
        lines.append(
            f"{stage:<26}"
            + "".join(f"{t:9.3f}" for t in seconds)
            + "".join(f"{e:8.2f}" for e in successive)
            + f"{overall:8.2f}"
        )
    return lines


def robot_counts(robots: list[int], max_robots: int | None) -> list[int]:
    """The counts to run: ``robots`` up to ``max_robots`` (None: all)."""
    return [n for n in robots if max_robots is None or n <= max_robots]


LIVE_NOTES = (
    "pairs met: neighbour pairs observing each other in the simulation; solve: the "
    "merger's solve times in /csam/status; lag: from a local map's arrival to the first "
    "joined map using it or a newer one, over 'maps' local maps (+ never included); prov "
    "p95: the same to the first joined or provisional map ('-': none published); wall: "
    "the live run; offline: csam replay --offline of its bag; live - offline: largest "
    "position and heading difference of joined poses and features"
)
OFFLINE_NOTES = (
    "stage: summary.json timing_s (local_maps: every robot's local map; the steps of the "
    "join; the join alone; total); a->b: the growth exponent in N between those robot "
    "counts (log-log slope); overall: the slope of the least-squares line through every N"
)


def arguments(argv: list[str] | None) -> argparse.Namespace:
    """The benchmark's options, checked."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument(
        "--offline",
        action="store_true",
        help="the join alone, of bags written as csam simulate writes them (no nodes)",
    )
    parser.add_argument(
        "--robots",
        type=int,
        nargs="+",
        help="robot counts (default: 2 4 8 16 live, 4 8 16 32 64 offline)",
    )
    parser.add_argument("--max-robots", type=int, help="leave out the robot counts above this")
    parser.add_argument(
        "--layout", choices=LAYOUTS, nargs="+", default=["ring"], help="ring, chain or both"
    )
    parser.add_argument(
        "--every",
        type=int,
        help="samples between a robot's observations of its neighbours (default: "
        f"{RENDEZVOUS_EVERY} live, 1 offline)",
    )
    parser.add_argument("--seconds", type=float, default=30.0, help="each robot's program [s]")
    parser.add_argument("--rate", type=float, default=4.0, help="live: simulation speed (0: max)")
    parser.add_argument("--seed", type=int, default=1, help="the scenarios' noise seed")
    parser.add_argument("--out", type=Path, help="output directory (default: a new temp dir)")
    parser.add_argument(
        "--scenarios-only",
        action="store_true",
        help="write each scenario file (OUT/<layout><N>/scenario.yaml) and stop",
    )
    args = parser.parse_args(argv)
    if args.robots is None:
        args.robots = [4, 8, 16, 32, 64] if args.offline else [2, 4, 8, 16]
    if args.every is None:
        args.every = 1 if args.offline else RENDEZVOUS_EVERY
    args.robots = robot_counts(args.robots, args.max_robots)
    if not args.robots:
        parser.error(f"--max-robots: no robot count left of {args.max_robots} or fewer")
    if min(args.robots) < 2:
        parser.error("--robots: at least 2 robots per run")
    if args.every < 1:
        parser.error("--every: at least 1 (every sample)")
    if args.out is not None and args.out.exists() and any(args.out.iterdir()):
        parser.error(f"--out: {args.out} is not empty")
    return args


def write_scenarios(args: argparse.Namespace, out: Path) -> None:
    """``--scenarios-only``: each layout's and robot count's scenario file under ``out``."""
    for layout in args.layout:
        for n in args.robots:
            scenario = many_robot_scenario(n, layout, args.seconds, args.seed, args.every)
            path = out / f"{layout}{n}" / "scenario.yaml"
            write_scenario(scenario, path, CSAM_SECTION)
            print(f"  {path} ({path.stat().st_size / 1e3:.0f} kB)")


def main_offline(args: argparse.Namespace, out: Path) -> None:
    """``--offline``: each layout's joins by robot count, then its stage table."""
    for layout in args.layout:
        print(f"{layout}:", flush=True)
        rows = []
        for n in args.robots:
            folder = out / f"{layout}{n}"
            rows.append(run_offline(n, layout, folder, args.seconds, args.seed, args.every))
            print(format_offline_row(rows[-1]), flush=True)
        print("\n".join(stage_table(rows)), flush=True)
    print(OFFLINE_NOTES)


def main_live(args: argparse.Namespace, out: Path) -> None:
    """Live: each layout's runs by robot count, then its table."""
    for layout in args.layout:
        rows = []
        for n in args.robots:
            print(f"  {layout}, {n} robots ...", flush=True)
            folder = out / f"{layout}{n}"
            rows.append(run(n, layout, folder, args.seconds, args.rate, args.seed, args.every))
        print(HEADER)
        print("-" * len(HEADER))
        for row in rows:
            print(format_row(row))
    print(LIVE_NOTES)


def main(argv: list[str] | None = None) -> int:
    args = arguments(argv)
    out = args.out or Path(tempfile.mkdtemp(prefix="csam-many-robots-"))
    layouts = ", ".join(args.layout)
    every = f"rendezvous every {args.every} sample(s)"
    if args.scenarios_only:
        print(f"many robots, {layouts}: scenario files ({every}) in {out}/")
        write_scenarios(args, out)
    elif args.offline:
        print(
            f"many robots offline, {layouts}: {args.seconds:g} s per robot, {every}, output {out}/",
            flush=True,
        )
        main_offline(args, out)
    else:
        print(
            f"many robots, {layouts}: {args.seconds:g} s per robot at rate {args.rate:g}, "
            f"{every}, output {out}/",
            flush=True,
        )
        main_live(args, out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
