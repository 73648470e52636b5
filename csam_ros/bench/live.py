"""A bag replayed live at real time, its figures beside the machine's speed that hour:
``python -m csam_ros.bench.live BAG [--config FILE] [--out DIR]`` (not in ``make bench``: as
long as the bag, about 25 minutes for MR.CLAM Dataset 1 with ``--config config/mrclam.yaml``).

``csam replay BAG --isolated`` runs the bag through the recorder, the smoothers and the merger
(its output in ``DIR/replay.log``), then the run is scored as ``csam evaluate`` scores it when
its bag holds ground truth. Printed: the merger's solves, the lags of the local maps to the
solved joined map and to the first provisional or solved one (:mod:`csam_ros.run.lag`), both
also over tenths of the run (a join that grows with the data shows as lags that grow), the
final joined map's time after the end of the sensor data, the landmark metrics, and GTSAM's
batch Levenberg-Marquardt on Victoria Park from dead reckoning (as
``python -m csam_ros.bench.smoothing`` runs it) timed just before and just after the run: how
fast the machine was that hour, so that a slow hour can be told from a regression. The lags and
solves over the run are drawn to ``DIR/run/latency.png`` (:mod:`csam_ros.run.latency_figure`).
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path


def final_after_data(bag: Path) -> float:
    """Seconds from the last sensor message of a run's bag to its last solved joined map."""
    from csam_ros.bag import inspect_bag, read_bag
    from csam_ros.ros.topics import JOINED_MAP, parse

    parsed = {name: parse(name) for name in inspect_bag(bag).topics}
    sensors = {name for name, p in parsed.items() if p is not None and p[0].sensor}
    data_end = joined = None
    for message in read_bag(bag, [*sensors, JOINED_MAP.name]):
        if message.topic == JOINED_MAP.name:
            joined = message.log_time_ns
        else:
            data_end = message.log_time_ns
    if data_end is None or joined is None:
        raise ValueError(f"{bag}: no sensor data or no joined map recorded")
    return (joined - data_end) / 1e9


def live_lines(run_dir: Path) -> list[str]:
    """What a live run's directory (``summary.json``, ``bag``) says of its speed, also over
    tenths of the run (drawn to ``latency.png`` there), then of its map when its bag holds
    ground truth (``metrics.json`` written, as ``csam evaluate``)."""
    from csam_ros.core.joining.result import RunSummary
    from csam_ros.run.errors import RunError
    from csam_ros.run.evaluation import evaluate_run, evaluation_lines
    from csam_ros.run.lag import RUN_PARTS
    from csam_ros.run.latency_figure import draw_latency
    from csam_ros.run.results import run_timeline, timeline_lines

    bag = run_dir / "bag"
    lines = []
    timeline = run_timeline(bag)  # read once: a long run's bag takes a minute or more
    if timeline is not None:
        summary = RunSummary.read(run_dir / "summary.json")
        lines += timeline_lines(timeline, summary, parts=RUN_PARTS)
        figure = draw_latency(timeline, run_dir / "latency.png")
        lines.append(f"the lags and solves over the run: {figure}")
    lines.append(f"the final joined map {final_after_data(bag):.2f} s after the data")
    try:
        return lines + evaluation_lines(evaluate_run(run_dir))
    except RunError as err:
        return [*lines, f"not scored: {err}"]


def main(argv: list[str] | None = None) -> None:
    from csam_ros.bench.smoothing import victoria_park_lm_seconds
    from csam_ros.run.results import fresh_dir

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("bag", type=Path)
    parser.add_argument("--config", default=None, help="as csam replay's --config")
    parser.add_argument("--out", type=Path, default=None, help="the run's directory")
    args = parser.parse_args(argv)
    out = fresh_dir(args.out, "live")
    before = victoria_park_lm_seconds()
    command = [sys.executable, "-m", "csam_ros.cli", "replay", str(args.bag), "--isolated"]
    command += ["--out", str(out / "run")] + (["--config", args.config] if args.config else [])
    print(f"live replay of {args.bag} into {out / 'run'} (its output: {out / 'replay.log'})")
    with open(out / "replay.log", "w") as log:
        done = subprocess.run(command, stdout=log, stderr=subprocess.STDOUT, check=False)
    if done.returncode != 0:
        raise SystemExit(f"csam replay failed (exit {done.returncode}): see {out / 'replay.log'}")
    after = victoria_park_lm_seconds()
    for line in live_lines(out / "run"):
        print(f"  {line.strip()}")
    speed = "n/a (GTSAM or its Victoria Park file missing)"
    if before is not None and after is not None:
        speed = f"{before:.2f} s before the run, {after:.2f} s after"
    print(f"  GTSAM's Victoria Park batch LM (the machine's speed): {speed}")


if __name__ == "__main__":
    main()
