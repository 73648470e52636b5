"""The merger's refine of the maps it builds from local map updates, from the held estimate
against from the robot's last refine: ``python -m csam_ros.bench.refine BAG [--start S]
[--end S] [--robots NAME ...]``.

A live run's bag holds every ``/<robot>/local_map_updates`` message the merger received. Each
robot's updates are applied in order as the merger applies them. From ``--start`` (seconds of
log time after the robot's first update) each map built is refined as a live merger refines it:
the first from its held estimate, every later one from the robot's last refined map
(:func:`~csam_ros.core.exchange.map_arrays.refine_start`). Until ``--end`` each of those later
maps is also refined from its held estimate alone, and solved to convergence (relative cost
decrease 1e-13, steps stretched up to 64 times) as the reference.

Per robot: the maps refined, the mean time of each refine, and how far above the converged cost
each ends, in cost units (half a squared whitened residual; 0.5 is one standard deviation),
mean and largest (negative: a lower minimum than the reference's).
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from csam_ros.bag.reader import inspect_bag, read_bag_messages  # noqa: E402
from csam_ros.core.exchange.map_arrays import (  # noqa: E402
    Refined,
    held_robot_map,
    robot_map_from_arrays,
)
from csam_ros.core.exchange.map_updates import HeldMap, MissingBaseError, apply_update  # noqa: E402
from csam_ros.core.sam.solver import SolverOptions  # noqa: E402
from csam_ros.core.smoothing.robot_map import RobotMap  # noqa: E402
from csam_ros.ros.map_messages import map_update_from_message  # noqa: E402
from csam_ros.ros.topics import LOCAL_MAP_UPDATES, parse  # noqa: E402

CONVERGED = SolverOptions(
    max_iterations=300, relative_tolerance=1e-13, step_tolerance=1e-10, max_step_scale=64.0
)


def timed_refine(robot: str, held: HeldMap, last: Refined | None) -> tuple[float, RobotMap]:
    """The merger's refine of ``held`` (from ``last`` where given) and its seconds."""
    start = time.perf_counter()
    refined = held_robot_map(robot, held, last=last)
    return time.perf_counter() - start, refined


def compare(bag: Path, robot: str, start_s: float, end_s: float) -> None:
    """One robot's row of the table (module docstring)."""
    held: HeldMap | None = None
    last: Refined | None = None
    first: int | None = None
    rows: list[tuple[float, float, float, float]] = []  # seconds and excess, warm then cold
    for message in read_bag_messages(bag, [LOCAL_MAP_UPDATES.of(robot)]):
        first = message.log_time_ns if first is None else first
        t = (message.log_time_ns - first) / 1e9
        if t > end_s:
            break
        try:
            held = apply_update(held, map_update_from_message(message.message, robot))
        except MissingBaseError:
            continue  # recorded before the robot's first whole map
        if t < start_s:
            continue
        warm_s, refined = timed_refine(robot, held, last)
        first_refine, last = last is None, Refined(refined, held.map)
        if first_refine:
            continue  # refined from its held estimate: the next one starts from it
        cold_s, cold = timed_refine(robot, held, None)
        reference = robot_map_from_arrays(robot, held.map.arrays()).problem
        reference.solve(CONVERGED)
        optimum = reference.cost()
        excess = refined.problem.cost() - optimum, cold.problem.cost() - optimum
        rows.append((warm_s, excess[0], cold_s, excess[1]))
    if not rows:
        print(f"{robot:>10} no map between {start_s:.0f} and {end_s:.0f} s")
        return
    a = np.array(rows)
    print(
        f"{robot:>10} {len(a):5d} {a[:, 0].mean() * 1e3:8.0f} ms {a[:, 1].mean():+7.2f} "
        f"{a[:, 1].max():+7.2f}   {a[:, 2].mean() * 1e3:8.0f} ms {a[:, 3].mean():+7.2f} "
        f"{a[:, 3].max():+7.2f}",
        flush=True,
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("bag", type=Path)
    parser.add_argument("--start", type=float, default=0.0, help="s after the robot's first update")
    parser.add_argument(
        "--end", type=float, default=float("inf"), help="s after the robot's first update"
    )
    parser.add_argument("--robots", nargs="+", help="default: every robot in the bag")
    args = parser.parse_args()
    declared = [parse(name) for name in inspect_bag(args.bag).topics]
    robots = args.robots or sorted(
        d[1] for d in declared if d is not None and d[0] is LOCAL_MAP_UPDATES
    )
    print(f"{'':>10} {'':>5} {'from the last refine':^29}   {'from the held estimate':^29}")
    print(
        f"{'robot':>10} {'maps':>5} {'mean':>11} {'above':>7} {'max':>7}   "
        f"{'mean':>11} {'above':>7} {'max':>7}"
    )
    for robot in robots:
        compare(args.bag, robot, args.start, args.end)


if __name__ == "__main__":
    main()
