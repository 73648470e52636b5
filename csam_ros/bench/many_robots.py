"""Benchmark of many robots live: ``python -m csam_ros.bench.many_robots``.

N robots each drive one loop (radius 2.4 m, 0.5 m/s, about 30 s at a sample time of 0.5 s)
around a centre of their own; neighbouring centres are 3.5 m apart, so neighbours' loops and
feature areas overlap and they pass within the 4 m sensor range of each other. ``ring``: the
centres on a circle, robot i meets robots i-1 and i+1 and robot N meets robot 1 (the whole
formation turns together, every pair alike); ``chain``: the centres on a line, neighbours
turning in opposite directions (mirror images of each other), no wrap. A robot observes only
its neighbours (``observes``), at every 4th sample: the rendezvous poses are the state of
Algorithm 2's conditioning, whose cost grows with the square of their number.

For each N the generated scenario is written as a scenario file (the layout of
``config/chain.yaml``), run live through the nodes as ``csam demo --scenario FILE`` runs it,
and the recorded bag is run offline as ``csam replay BAG --offline`` runs it. Per N: robots
aligned, features and associations of the live joined map, the merger's solve times and the
lag of the local maps (``/csam/status`` and the bag, ``csam_ros.run.lag``), the wall time of
the live run, and the largest difference between the live and the offline joined maps.
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
from csam_ros.datasets.simulation import (
    RangeBearingSensor,
    RobotSpec,
    Scenario,
    Segment,
    feature_grid,
    simulate,
)
from csam_ros.run.lag import LagStats, SolveStats

LAYOUTS = ("ring", "chain")
NEIGHBOUR_DISTANCE = 3.5  # m between neighbouring loop centres
LOOP_RADIUS = 2.4  # m
SPEED = 0.5  # m/s
SAMPLE_TIME = 0.5  # s
RENDEZVOUS_EVERY = 4  # samples between observations of the neighbours
FEATURE_SPACING = 1.5  # m
SENSOR = RangeBearingSensor(max_range=4.0, field_of_view=float(np.deg2rad(240.0)))
ODOMETRY_SIGMA = (0.02, 0.01, float(np.deg2rad(0.6)))
CSAM_SECTION = {"chi2_gate": 9.21}


def robot_name(i: int, n: int) -> str:
    """``robot01`` ... (zero-padded: the names sort in the scenario's order)."""
    return f"robot{i + 1:0{len(str(n))}d}"


def neighbours(n: int, layout: str) -> list[list[int]]:
    """The robots each robot meets: i-1 and i+1, wrapping round in a ring."""
    if layout not in LAYOUTS:
        raise ValueError(f"layout must be one of {LAYOUTS}, got {layout!r}")
    ring = layout == "ring"
    return [
        sorted({j % n if ring else j for j in (i - 1, i + 1) if ring or 0 <= j < n} - {i})
        for i in range(n)
    ]


def many_robot_scenario(n: int, layout: str, duration: float = 30.0, seed: int = 1) -> Scenario:
    """``n`` robots looping around centres on a ring or a chain (module docs); ``duration``
    seconds each, a multiple of the sample time."""
    if n < 2:
        raise ValueError(f"need at least 2 robots, got {n}")
    index = np.arange(n)
    omega = SPEED / LOOP_RADIUS
    if layout == "ring":
        theta = 2 * np.pi * index / n
        radius = NEIGHBOUR_DISTANCE / (2 * np.sin(np.pi / n))
        centres = radius * np.column_stack([np.cos(theta), np.sin(theta)])
        phase, turn = theta, np.ones(n)  # the formation turns as one: every pair alike
    else:
        centres = np.column_stack([NEIGHBOUR_DISTANCE * index, np.zeros(n)])
        odd = index % 2 == 1  # the mirror image of its left neighbour
        phase, turn = np.where(odd, np.pi, 0.0), np.where(odd, -1.0, 1.0)
    starts = centres + LOOP_RADIUS * np.column_stack([np.cos(phase), np.sin(phase)])
    headings = se2.wrap_angle(phase + turn * np.pi / 2)
    low = centres.min(axis=0) - LOOP_RADIUS - SENSOR.max_range
    high = centres.max(axis=0) + LOOP_RADIUS + SENSOR.max_range
    features = feature_grid(
        tuple((low + high) / 2), tuple(high - low), FEATURE_SPACING, 0.25, np.random.default_rng(5)
    )
    met = neighbours(n, layout)
    robots = tuple(
        RobotSpec(
            name=robot_name(i, n),
            start_pose=(float(starts[i, 0]), float(starts[i, 1]), float(headings[i])),
            program=(Segment(duration, SPEED, float(turn[i] * omega)),),
            odometry_sigma=ODOMETRY_SIGMA,
            feature_sensor=SENSOR,
            rendezvous_sensor=SENSOR,
            observes=tuple(robot_name(j, n) for j in met[i]),
            rendezvous_every=RENDEZVOUS_EVERY,
        )
        for i in range(n)
    )
    description = f"{n} robots looping on a {layout}, each meeting its neighbours"
    return Scenario(f"{layout}{n}", SAMPLE_TIME, features, robots, seed, description)


def meetings(scenario: Scenario) -> dict[tuple[str, str], int]:
    """Rendezvous measurements per ordered pair (observer, observed) of a simulated run."""
    counts: dict[tuple[str, str], int] = {}
    for name, robot in simulate(scenario).robots.items():
        observed, k = np.unique(
            np.asarray(robot.rendezvous.observed, dtype=str), return_counts=True
        )
        counts.update({(name, str(o)): int(c) for o, c in zip(observed, k, strict=True)})
    return counts


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


def run(n: int, layout: str, out: Path, duration: float, rate: float, seed: int) -> Row:
    """Generate, run live, run offline and compare, for ``n`` robots under ``out``."""
    from csam_ros.core.model.config_file import load_document
    from csam_ros.run.demo import demo_live_run
    from csam_ros.run.lag import read_timeline
    from csam_ros.run.live import run_live
    from csam_ros.run.offline import offline_summary

    scenario = many_robot_scenario(n, layout, duration, seed)
    met = meetings(scenario)
    pairs = {(i, j) for i, js in enumerate(neighbours(n, layout)) for j in js if i < j}
    names = [r.name for r in scenario.robots]
    meeting = sum((names[i], names[j]) in met and (names[j], names[i]) in met for i, j in pairs)
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
        pairs=len(pairs),
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


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--robots", type=int, nargs="+", default=[2, 4, 8, 16])
    parser.add_argument("--layout", choices=LAYOUTS, default="ring")
    parser.add_argument("--seconds", type=float, default=30.0, help="each robot's program [s]")
    parser.add_argument("--rate", type=float, default=4.0, help="simulation speed (0: max)")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--out", type=Path, help="output directory (default: a new temp dir)")
    args = parser.parse_args(argv)
    if min(args.robots) < 2:
        parser.error("--robots: at least 2 robots per run")
    if args.out is not None and args.out.exists() and any(args.out.iterdir()):
        parser.error(f"--out: {args.out} is not empty")
    out = args.out or Path(tempfile.mkdtemp(prefix="csam-many-robots-"))
    print(
        f"many robots, {args.layout}: {args.seconds:g} s per robot at rate {args.rate:g}, "
        f"output {out}/",
        flush=True,
    )
    rows = []
    for n in args.robots:
        print(f"  {n} robots ...", flush=True)
        rows.append(
            run(n, args.layout, out / f"{args.layout}{n}", args.seconds, args.rate, args.seed)
        )
    print(HEADER)
    print("-" * len(HEADER))
    for row in rows:
        print(format_row(row))
    print(
        "pairs met: neighbour pairs observing each other in the simulation; solve: the "
        "merger's solve times in /csam/status; lag: from a local map's arrival to the first "
        "joined map using it or a newer one, over 'maps' local maps (+ never included); prov "
        "p95: the same to the first joined or provisional map ('-': none published); wall: "
        "the live run; offline: csam replay --offline of its bag; live - offline: largest "
        "position and heading difference of joined poses and features"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
