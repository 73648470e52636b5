"""What the smoothers' local map updates carry, and what their tolerance does to the joined map:
``python -m csam_ros.bench.map_updates BAG [--config FILE] [--tolerances 0.001,0.01,0.02]
[--every S]``.

Each robot's sensor log in the bag is fed to a local map as its smoother does (an update every
``publish_period`` s of data, the config's ``local_map:`` section; poses at the stamps of the
kept rendezvous that involve it), and after every update each tolerance's
:class:`~csam_ros.core.exchange.map_updates.UpdateSender` makes the update it would publish.
Printed: the serialized ``LocalMapUpdate`` bytes per second of data, per robot by tenth of the run
(what the robot sends the base station, without DDS and IP headers), and the poses per update.

Every ``--every`` s of data (and at the end, before the final exact update) the maps as the
merger holds them at each tolerance, refined as it refines them
(:func:`~csam_ros.ros.map_messages.checked_robot_map`), are joined
(:func:`~csam_ros.core.joining.join.join_maps`) and compared with the join of the smoothers' own
maps at that time: the largest difference of a joined feature and of a joined pose, and whether the
same robots are aligned and the same features associated.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import time  # noqa: E402
from dataclasses import dataclass, field, replace  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from csam_ros.core.exchange.local_map_checks import LocalMapArrays  # noqa: E402
from csam_ros.core.exchange.map_arrays import checked_robot_map, robot_map_arrays  # noqa: E402
from csam_ros.core.exchange.map_updates import UpdateSender, UpdateTolerance  # noqa: E402
from csam_ros.core.joining.config import CsamConfig
from csam_ros.core.joining.join import join_maps
from csam_ros.core.joining.pipeline import robot_map_from_local_map, thinned_rendezvous
from csam_ros.core.joining.rendezvous_filters import select_rendezvous  # noqa: E402
from csam_ros.core.joining.result import CsamResult  # noqa: E402
from csam_ros.core.model.log import MultiRobotLog, RendezvousLog  # noqa: E402
from csam_ros.core.model.rendezvous import required_stamps  # noqa: E402
from csam_ros.core.smoothing.local_map import LocalMap  # noqa: E402
from csam_ros.core.smoothing.local_map_config import LocalMapConfig  # noqa: E402

PARTS = 10


@dataclass
class RobotUpdates:
    """One robot fed online: bytes of each update at each tolerance, the maps held at the
    snapshot times."""

    seconds: float = 0.0  # of data
    update_bytes: dict[float, list[tuple[float, int, int]]] = field(default_factory=dict)
    snapshots: list[dict[float | None, LocalMapArrays]] = field(default_factory=list)


def read_log(bag: Path) -> MultiRobotLog:
    """The sensor logs of every robot in ``bag``, checked as the smoothers check them."""
    from csam_ros.bag import inspect_bag, read_bag_messages
    from csam_ros.ros.conversions import LogBuilder
    from csam_ros.ros.topics import parse, sensor_topics

    declared = [parse(name) for name in inspect_bag(bag).topics]
    robots = sorted({d[1] for d in declared if d is not None and d[1] and d[0].sensor})
    builder = LogBuilder(robots)
    for m in read_bag_messages(bag, sensor_topics(robots)):
        builder.add(m.topic, m.message)
    return builder.build()


def feed(
    name: str,
    log: MultiRobotLog,
    pose_stamps: np.ndarray,
    local_map: LocalMapConfig,
    tolerances: list[float],
    key: float,
    snapshot_times: np.ndarray,
) -> RobotUpdates:
    """``name``'s log fed as its smoother takes it (one update per ``publish_period``)."""
    from rclpy.serialization import serialize_message

    from csam_ros.ros.map_messages import local_map_update_message

    robot = log.robots[name]
    local = LocalMap(name, local_map.options())
    senders = {t: UpdateSender(1, UpdateTolerance(t, t, min(t, key))) for t in tolerances}
    out = RobotUpdates(update_bytes={t: [] for t in tolerances})
    o, f = robot.odometry, robot.features
    order = np.argsort(f.stamps, kind="stable")
    ft = f.stamps[order]
    period = local_map.publish_period
    start = o.stamps[0]
    oi = fi = 0
    taken = 0
    for end in np.arange(start + period, o.stamps[-1] + period, period):
        oj = int(np.searchsorted(o.stamps, end, side="right"))
        fj = int(np.searchsorted(ft, end, side="right"))
        local.add_log_part(robot, slice(oi, oj), order[fi:fj])
        local.request_poses(pose_stamps[(pose_stamps > end - period) & (pose_stamps <= end)])
        oi, fi = oj, fj
        local.update()
        if len(local.stamps) < 2:
            continue
        arrays = robot_map_arrays(robot_map_from_local_map(local))
        keys = np.unique(local.pose_index(pose_stamps[pose_stamps <= local.stamps[-1]]))
        for t, sender in senders.items():
            update = sender.update(arrays, key_poses=keys)
            size = len(serialize_message(local_map_update_message(update, name, 0)))
            out.update_bytes[t].append((end - start, size, len(update.changes.pose_stamps)))
        held = {None: arrays, **{t: s.held.map.arrays() for t, s in senders.items() if s.held}}
        while taken < len(snapshot_times) and end - start >= snapshot_times[taken]:
            out.snapshots.append(held)
            taken += 1
    out.seconds = float(o.stamps[-1] - start)
    out.snapshots += [held] * (len(snapshot_times) + 1 - len(out.snapshots))
    return out


def _difference(a: CsamResult, b: CsamResult) -> tuple[float, float, bool]:
    """Largest feature and pose difference (m) between two joins, and whether they aligned
    the same robots and associated the same features."""
    same = a.joined_robots() == b.joined_robots() and {tuple(f.members) for f in a.features} == {
        tuple(f.members) for f in b.features
    }
    xy = {tuple(f.members): np.asarray(f.xy) for f in b.features}
    features = max(
        (
            float(np.abs(np.asarray(f.xy) - xy[tuple(f.members)]).max())
            for f in a.features
            if tuple(f.members) in xy
        ),
        default=0.0,
    )
    poses = 0.0
    for r in set(a.joined_robots()) & set(b.joined_robots()):
        pa = np.asarray(a.robots[r].poses_joined)[:, :2]
        pb = np.asarray(b.robots[r].poses_joined)[:, :2]
        if pa.shape == pb.shape:
            poses = max(poses, float(np.abs(pa - pb).max()))
    return features, poses, same


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("bag", type=Path)
    parser.add_argument("--config", help="YAML file with local_map: and csam: sections")
    parser.add_argument(
        "--tolerances",
        default="0.001,0.01,0.02,0.05",
        help="m (and rad) a pose moves before it is sent (features and rendezvous poses: the "
        "config's update_key_tolerance, or the tolerance where smaller)",
    )
    parser.add_argument("--every", type=float, default=300.0, help="s of data between joins")
    args = parser.parse_args()
    from csam_ros.core.model.config_file import load_document

    document = load_document(args.config) if args.config else {}
    local_map = LocalMapConfig.from_dict(document.get("local_map"), "local_map")
    config = replace(CsamConfig.from_dict(document.get("csam"), "csam"), skip_missing_poses=True)
    tolerances = [float(t) for t in args.tolerances.split(",")]
    t0 = time.perf_counter()
    log = read_log(args.bag)
    names = list(log.robots)
    kept, _ = thinned_rendezvous(log, config)
    stamps = required_stamps(kept)
    duration = max(float(r.odometry.stamps[-1] - r.odometry.stamps[0]) for r in log.robots.values())
    times = np.arange(args.every, duration, args.every)
    read_s = time.perf_counter() - t0
    print(f"{args.bag}: {len(names)} robots, {duration:.0f} s of data ({read_s:.0f} s to read)")
    fed = {}
    for name in names:
        t1 = time.perf_counter()
        fed[name] = feed(
            name, log, stamps[name], local_map, tolerances, local_map.update_key_tolerance, times
        )
        print(f"  {name} fed in {time.perf_counter() - t1:.0f} s", flush=True)
    print(
        "\nkbit/s a robot sends (LocalMapUpdate, serialized), by tenth of the run; poses per update"
    )
    header = " ".join(f"{f'{10 * i}-{10 * i + 10}%':>8}" for i in range(PARTS))
    print(f"  {'tolerance':>9} {'robot':>7} {header} {'mean':>7} {'poses':>7}")
    for t in tolerances:
        for name in names:
            rows = np.array(fed[name].update_bytes[t], dtype=float)
            edges = np.linspace(0, fed[name].seconds, PARTS + 1)
            part = np.clip(np.searchsorted(edges, rows[:, 0], side="right") - 1, 0, PARTS - 1)
            rates = [
                rows[part == i, 1].sum() * 8e-3 / (edges[i + 1] - edges[i]) for i in range(PARTS)
            ]
            mean = rows[:, 1].sum() * 8e-3 / fed[name].seconds
            cells = " ".join(f"{r:8.1f}" for r in rates)
            print(f"  {t:9g} {name:>7} {cells} {mean:7.1f} {rows[:, 2].mean():7.0f}")
    print("\njoined map from the maps as sent against the join of the smoothers' own maps")
    print(f"  {'t [s]':>7} {'tolerance':>9} {'features [m]':>12} {'poses [m]':>10} {'same':>5}")
    for k in range(len(times) + 1):
        at = f"{times[k]:.0f}" if k < len(times) else "end"

        def join(tolerance: float | None, k: int = k) -> CsamResult:
            maps = [  # the held maps as the merger takes them (refined)
                checked_robot_map(n, fed[n].snapshots[k][tolerance], refine=tolerance is not None)
                for n in names
            ]
            last = max(m.stamps[-1] for m in maps)
            logs: dict[str, RendezvousLog] = {
                n: select_rendezvous(kept[n], kept[n].stamps <= last) for n in names
            }
            return join_maps(maps, logs, config)

        exact = join(None)
        for t in tolerances:
            features, poses, same = _difference(join(t), exact)
            print(f"  {at:>7} {t:9g} {features:12.4f} {poses:10.4f} {same!s:>5}", flush=True)
    print(f"\n{time.perf_counter() - t0:.0f} s in all")


if __name__ == "__main__":
    main()
