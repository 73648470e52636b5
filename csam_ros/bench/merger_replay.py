"""The merger's solves replayed from a recorded live run, cold against warm:
``python -m csam_ros.bench.merger_replay BAG [--config FILE] [--every S] [--ahead]``.

A live run's bag holds every local map update and rendezvous poses message the merger
received (``/<robot>/local_map_updates``, ``/<robot>/rendezvous_poses``). Read in log-time
order, the inputs are taken every ``--every`` seconds of log time (and at the end), and each
is joined twice by the core: cold (:func:`~csam_ros.core.joining.join.join_maps` from scratch) and
warm (from the previous warm result, with the local views kept between solves, as the merger
does). The table gives each solve's time and iterations and the largest difference between
the warm and the cold joined map (poses and features); the last line the distribution of the
solve times. ``--ahead`` compares instead two chains of warm joins, with the joint solve ahead
of Algorithm 2 (:class:`~csam_ros.core.joining.join.JointSolveAhead`) and without it.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import time  # noqa: E402
from dataclasses import replace  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from csam_ros.bag.reader import inspect_bag, read_bag_messages  # noqa: E402
from csam_ros.core.exchange.map_arrays import Refined, held_robot_map  # noqa: E402
from csam_ros.core.exchange.map_updates import HeldMap, MissingBaseError, apply_update  # noqa: E402
from csam_ros.core.joining.config import CsamConfig  # noqa: E402
from csam_ros.core.joining.join import join_maps  # noqa: E402
from csam_ros.core.joining.local_views import LocalViewCache  # noqa: E402
from csam_ros.core.joining.result import CsamResult  # noqa: E402
from csam_ros.core.smoothing.robot_map import RobotMap  # noqa: E402
from csam_ros.ros.map_messages import (  # noqa: E402
    map_update_from_message,
    rendezvous_log_from_message,
)
from csam_ros.ros.topics import LOCAL_MAP_UPDATES, RENDEZVOUS_POSES, parse  # noqa: E402


def difference(a: CsamResult, b: CsamResult) -> float:
    """Largest difference (m or rad) between two results' joined poses and features; inf
    when they join different robots or features."""
    if a.joined_robots() != b.joined_robots() or len(a.features) != len(b.features):
        return float("inf")
    worst = 0.0
    for name in a.joined_robots():
        pa, pb = a.robots[name].poses_joined, b.robots[name].poses_joined
        d = np.abs(np.asarray(pa) - np.asarray(pb))
        d[:, 2] = np.abs((d[:, 2] + np.pi) % (2 * np.pi) - np.pi)
        worst = max(worst, float(d.max(initial=0.0)))
    xy_b = {tuple(f.members): f.xy for f in b.features}
    for f in a.features:
        other = xy_b.get(tuple(f.members))
        if other is None:
            return float("inf")
        worst = max(worst, float(np.abs(np.asarray(f.xy) - np.asarray(other)).max()))
    return worst


def snapshots(bag: Path, every: float):
    """(s since the first message, the maps in first-heard order, the rendezvous messages,
    the robots) every ``every`` s of log time; each map refined from the robot's last, as the
    merger refines it."""
    declared = [parse(name) for name in inspect_bag(bag).topics]
    robots = sorted(d[1] for d in declared if d is not None and d[0] is LOCAL_MAP_UPDATES)
    topics = [t.of(r) for r in robots for t in (LOCAL_MAP_UPDATES, RENDEZVOUS_POSES)]
    held: dict[str, HeldMap] = {}
    refined: dict[str, Refined] = {}
    maps: dict[str, RobotMap] = {}
    rendezvous: dict[str, object] = {}
    first = next_t = None
    t = 0.0
    pending = False  # inputs changed since the last snapshot
    for message in read_bag_messages(bag, topics):
        first = message.log_time_ns if first is None else first
        t = (message.log_time_ns - first) / 1e9
        robot, kind = message.topic.split("/")[1:3]
        if kind == LOCAL_MAP_UPDATES.name:
            try:
                update = map_update_from_message(message.message, robot)
                held[robot] = apply_update(held.get(robot), update)
            except MissingBaseError:
                continue  # recorded before the robot's first whole map
            maps[robot] = held_robot_map(robot, held[robot], last=refined.get(robot))
            refined[robot] = Refined(maps[robot], held[robot].map)
        else:
            rendezvous[robot] = message.message
        pending = True
        if next_t is None:
            next_t = t + every
        if t >= next_t:
            yield t, dict(maps), dict(rendezvous), robots
            next_t, pending = t + every, False
    if pending:
        yield t, dict(maps), dict(rendezvous), robots


def ordered_inputs(
    maps: dict[str, RobotMap], messages: dict, robots: list[str], reference: str, config: CsamConfig
) -> tuple[list[RobotMap], dict]:
    """The maps in join order (``reference`` first) and the rendezvous logs of a snapshot."""
    order = [reference] + [r for r in maps if r != reference]
    logs = {
        r: rendezvous_log_from_message(m, r, robots, maps[r].stamps, config.stamp_tolerance)
        for r, m in messages.items()
        if r in maps
    }
    return [maps[r] for r in order], logs


def compare_ahead(
    bag: Path, every: float, start_s: float, reference: str, config: CsamConfig
) -> None:
    """Two chains of warm joins, one with the joint solve ahead of Algorithm 2 and one
    without (in turns first, each with its maps prepared as the merger does): each solve's
    time, whether the solve ahead was taken, and the means after the first solve."""
    chains: dict[bool, tuple[LocalViewCache, list[CsamResult]]] = {
        on: (LocalViewCache(), []) for on in (False, True)
    }
    seconds: dict[bool, list[float]] = {False: [], True: []}
    print(f"{'t':>7} {'without':>8} {'ahead':>7} {'taken':>5}")
    for n, (t, maps, messages, robots) in enumerate(snapshots(bag, every)):
        first = reference or robots[0]
        if first not in maps or t < start_s:
            continue
        ordered, logs = ordered_inputs(maps, messages, robots, first, config)
        for on in (n % 2 == 1, n % 2 == 0):
            cache, results = chains[on]
            cache.prepare(ordered)
            start = time.perf_counter()
            previous = results[-1] if results else None
            results.append(
                join_maps(ordered, logs, config, previous=previous, cache=cache, overlap=on)
            )
            seconds[on].append(time.perf_counter() - start)
        taken = chains[True][1][-1].statistics["joint_solve_ahead"]
        print(f"{t:7.1f} {seconds[False][-1]:7.2f}s {seconds[True][-1]:6.2f}s {taken:5.0f}")
    taken = [r.statistics["joint_solve_ahead"] for r in chains[True][1][1:]]
    print(
        f"after the first: without {np.mean(seconds[False][1:]):.3f} s, ahead "
        f"{np.mean(seconds[True][1:]):.3f} s, taken in {sum(taken):.0f} of {len(taken)}"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("bag", type=Path)
    parser.add_argument("--config", help="YAML file with a csam: section (config/mrclam.yaml)")
    parser.add_argument("--every", type=float, default=60.0, help="s of log time between solves")
    parser.add_argument("--reference", default="", help="reference robot (default: the first)")
    parser.add_argument(
        "--start", type=float, default=0.0, help="s of log time before the first solve"
    )
    parser.add_argument(
        "--ahead",
        action="store_true",
        help="warm joins with the joint solve ahead of Algorithm 2 against without it, "
        "instead of cold against warm",
    )
    args = parser.parse_args()
    config = CsamConfig.from_file(args.config) if args.config else CsamConfig()
    config = replace(config, skip_missing_poses=True)  # as the merger
    if args.ahead:
        compare_ahead(args.bag, args.every, args.start, args.reference, config)
        return
    cache = LocalViewCache()
    warm: CsamResult | None = None
    print(
        f"{'t':>7} {'poses':>6} {'cold':>7} {'it1':>4} {'itJ':>4} "
        f"{'warm':>7} {'it1':>4} {'itJ':>4} {'reused':>6} {'warm-cold':>9}"
    )
    cold_s, warm_s = [], []
    for t, maps, messages, robots in snapshots(args.bag, args.every):
        reference = args.reference or robots[0]
        if reference not in maps or t < args.start:
            continue
        ordered, logs = ordered_inputs(maps, messages, robots, reference, config)
        start = time.perf_counter()
        cold = join_maps(ordered, logs, config)
        cold_s.append(time.perf_counter() - start)
        reused = cache.reused
        start = time.perf_counter()
        warm = join_maps(ordered, logs, config, previous=warm, cache=cache)
        warm_s.append(time.perf_counter() - start)
        st_c, st_w = cold.statistics, warm.statistics
        print(
            f"{t:7.1f} {sum(len(m.stamps) for m in ordered):6d} "
            f"{cold_s[-1]:6.2f}s {st_c['algorithm1_iterations']:4.0f} "
            f"{st_c['joint_iterations']:4.0f} {warm_s[-1]:6.2f}s "
            f"{st_w['algorithm1_iterations']:4.0f} {st_w['joint_iterations']:4.0f} "
            f"{cache.reused - reused:6d} {difference(cold, warm):9.1e}",
            flush=True,
        )
    for name, s in (("cold", cold_s), ("warm", warm_s)):
        print(
            f"{name}: {len(s)} solves, mean {np.mean(s):.2f} s, p95 "
            f"{np.percentile(s, 95):.2f} s, max {np.max(s):.2f} s"
        )


if __name__ == "__main__":
    main()
