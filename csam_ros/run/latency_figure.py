"""The figure of a live run's latency over the run: :func:`draw_latency` (it imports
matplotlib), and ``python -m csam_ros.run.latency_figure BAG [--out PNG] [--title TEXT]`` on a
recorded live run's bag (``csam demo``, ``csam replay`` live, ``python -m csam_ros.bench.live``).

Top: each local map's lag to the solved joined map that uses it, at its arrival, one colour per
robot, with the p95 of each tenth of the run; bottom: the merger's solve times where its status
reported them. A join that grows with the data shows as both rising with the run; a slow start
as a few early points.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from csam_ros.figures.draw import axes_note, new_figure, robot_colours, save_figure
from csam_ros.run.lag import Timeline, read_timeline


def draw_latency(timeline: Timeline, path: str | Path, title: str = "") -> Path:
    """Draw ``timeline`` (:func:`~csam_ros.run.lag.read_timeline`) to ``path`` (PNG)."""
    figure = new_figure(6.0)
    lags_axes, solves_axes = figure.subplots(2, 1, sharex=True, height_ratios=(2, 1))
    lags_axes.set_title(title or "lag from a local map to the solved joined map that uses it")
    lags_axes.set_ylabel("lag [s]")
    solves_axes.set_ylabel("solve [s]")
    solves_axes.set_xlabel("time into the run [s] (since its first map, joined map or status)")
    for axes in (lags_axes, solves_axes):
        axes.grid(True, color="0.9", linewidth=0.6)
        axes.set_axisbelow(True)
    colours = robot_colours(sorted(timeline.map_arrivals))
    lags_by_robot = timeline.robot_lags()
    for robot, lags in lags_by_robot.items():
        arrivals = timeline.map_arrivals[robot]
        shown = np.isfinite(lags)
        lags_axes.plot(
            arrivals[shown], lags[shown], ".", ms=3, color=colours[robot], label=robot, alpha=0.7
        )
    parts = [p for p in timeline.lags_over_run() if p.lags.count]
    if parts:
        edges = [p.start for p in parts] + [parts[-1].end]
        p95 = [p.lags.p95 for p in parts]
        lags_axes.stairs(p95, edges, color="0.15", linewidth=1.5, label="p95 of each tenth")
        lags_axes.legend(loc="upper left", fontsize=8, ncols=min(len(lags_by_robot) + 1, 6))
    else:
        axes_note(lags_axes, "no local map reached a solved joined map")
    if len(timeline.solve_times):
        solves_axes.plot(timeline.solve_times, timeline.solve_seconds, ".-", ms=3, color="0.3")
    else:
        axes_note(solves_axes, "no solve time in /csam/status")
    for axes in (lags_axes, solves_axes):
        axes.set_ylim(bottom=0.0)
    return save_figure(figure, path)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("bag", type=Path, help="a live run's bag (DIR/bag)")
    parser.add_argument("--out", type=Path, default=None, help="default: latency.png beside it")
    parser.add_argument("--title", default="", help="the figure's title")
    args = parser.parse_args(argv)
    out = args.out or args.bag.resolve().parent / "latency.png"
    print(draw_latency(read_timeline(args.bag), out, args.title))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
