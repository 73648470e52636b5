"""What a run leaves: its own output directory, ``summary.json`` and the figures there, and
how long its local maps took to reach the joined map."""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING

from csam_ros.run.errors import RunError, warn

if TYPE_CHECKING:
    from csam_ros.core.joining.result import RunSummary
    from csam_ros.figures.worker import FigureWorker
    from csam_ros.run.lag import Timeline

RUNS_DIR = Path("runs")


def new_run_dir(name: str) -> Path:
    """``runs/<name>-<time>``, with a count appended if a run of that second has it."""
    stamp = time.strftime("%Y%m%d-%H%M%S")
    out = RUNS_DIR / f"{name}-{stamp}"
    k = 1
    while out.exists():
        k += 1
        out = RUNS_DIR / f"{name}-{stamp}-{k}"
    return out


def fresh_dir(path: Path | None, name: str) -> Path:
    """``path`` (None: a new run directory for ``name``) made, if it is new or empty."""
    out = path or new_run_dir(name)
    if out.exists() and not out.is_dir():
        raise RunError(f"{out} exists and is not a directory: choose a new --out directory")
    if out.exists() and any(out.iterdir()):
        raise RunError(f"{out} exists and is not empty: choose a new --out directory")
    out.mkdir(parents=True, exist_ok=True)
    return out


@contextmanager
def figures_drawn_aside() -> Iterator[FigureWorker | None]:
    """A worker process that imports matplotlib while the run goes on and draws its figures
    (:func:`write_results`), closed on leaving; None where this process may not fork. Forked
    now: before any node starts, while this process has no thread but the main one."""
    from csam_ros.figures.worker import figure_worker

    worker = figure_worker()
    try:
        yield worker
    finally:
        if worker is not None:
            worker.close()


def write_results(out: Path, summary: RunSummary, worker: FigureWorker | None = None) -> list[Path]:
    """Write ``summary.json`` and the figures into ``out`` (by ``worker`` if given); the
    figures' paths."""
    summary.write(out / "summary.json")
    if worker is not None:
        return worker.draw(out / "summary.json", out)
    from csam_ros.figures.draw import draw_all

    return draw_all(summary.result, out, scenario=summary.scenario)


def latency_lines(bag: Path, summary: RunSummary) -> list[str]:
    """:func:`timeline_lines` of a live run's bag; no line if the bag cannot be read (a warning
    says why)."""
    timeline = run_timeline(bag)
    return [] if timeline is None else timeline_lines(timeline, summary)


def run_timeline(bag: Path) -> Timeline | None:
    """The timeline of a live run's bag (:func:`~csam_ros.run.lag.read_timeline`), or None
    when it cannot be read (a warning says why)."""
    from csam_ros.bag import BagError
    from csam_ros.run.lag import read_timeline

    try:
        return read_timeline(bag, on_damage=warn)
    except BagError as err:
        warn(f"no lag figures: {err}")
        return None


def timeline_lines(timeline: Timeline, summary: RunSummary, parts: int = 0) -> list[str]:
    """How long a live run's local maps took to reach the joined map, and how long the
    merger's solves took (the merger's count from its summary), then (``parts`` > 0) the same
    over that many equal spans of the run."""
    lines = [str(timeline.lag_stats())]
    provisional = timeline.provisional_lag_stats()
    if provisional is not None:
        lines.append(str(provisional))
    lines.append(str(timeline.solve_stats(summary.merger.solves if summary.merger else None)))
    if parts > 0:
        lines.append("over the run (local maps by arrival, solves by their report):")
        lines += [f"  {part}" for part in timeline.lags_over_run(parts)]
    return lines
