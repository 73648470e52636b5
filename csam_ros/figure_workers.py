"""A run's figures drawn by worker processes started before its result exists.

``csam replay --offline`` computes on one core. Each worker, forked at the start, imports
matplotlib meanwhile; once ``summary.json`` is written, every worker draws its figure from it
at the same time (:func:`csam_ros.figures.draw_figure`, as ``python -m csam_ros.figures``
would). A worker's error is raised in the caller, naming the figure. Workers are forked
only from a process without other threads (:func:`figure_workers`): a fork copies no thread,
and a lock another thread held would stay locked in the worker.
"""

from __future__ import annotations

import multiprocessing
import signal
import threading
from collections.abc import Sequence
from multiprocessing.connection import Connection
from multiprocessing.process import BaseProcess
from pathlib import Path
from types import TracebackType

# a run's figures, in this order (csam_ros.figures draws them; it imports matplotlib, this
# module does not)
FIGURES = ("local_maps.png", "heading_sigma.png", "joined_map.png")
Job = tuple[Path, Path]  # summary.json, the directory to draw into


def _work(connection: Connection, name: str, callers: list[Connection]) -> None:
    # the caller's ends of the pipes, inherited by the fork: closed, so that this worker's
    # recv ends when the caller closes its end or dies; Ctrl-C is the caller's to handle
    for end in callers:
        end.close()
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    from csam_ros import figures  # matplotlib, imported while the caller computes
    from csam_ros.core.result import RunSummary

    try:
        job: Job = connection.recv()
    except EOFError:  # the caller is gone
        return
    summary_path, out_dir = job
    try:
        summary = RunSummary.read(summary_path)
        path = figures.draw_figure(name, summary.result, out_dir, scenario=summary.scenario)
        connection.send((True, str(path)))
    except Exception as err:  # noqa: BLE001  (any failure goes back to the caller)
        connection.send((False, f"{type(err).__name__}: {err}"))


def figure_workers() -> FigureWorkers | None:
    """Workers for every figure, or None (draw in-process) where this process has other
    threads or cannot fork."""
    if threading.active_count() > 1 or "fork" not in multiprocessing.get_all_start_methods():
        return None
    return FigureWorkers()


class FigureWorkers:
    """One forked process per figure of ``names``, waiting for a summary to draw from."""

    def __init__(self, names: Sequence[str] = FIGURES) -> None:
        context = multiprocessing.get_context("fork")
        self._workers: list[tuple[str, BaseProcess, Connection]] = []
        for name in names:
            ours, theirs = context.Pipe()
            callers = [*(w[2] for w in self._workers), ours]
            process = context.Process(target=_work, args=(theirs, name, callers), daemon=True)
            process.start()
            theirs.close()
            self._workers.append((name, process, ours))

    def draw(self, summary_path: Path, out_dir: Path) -> list[Path]:
        """Every figure of the summary at ``summary_path``, drawn into ``out_dir`` at once."""
        for _, _, connection in self._workers:
            connection.send((summary_path, out_dir))
        paths = []
        for name, process, connection in self._workers:
            try:
                ok, text = connection.recv()
            except EOFError:
                ok, text = False, f"its process ended with exit code {process.exitcode}"
            process.join()
            if not ok:
                raise RuntimeError(f"{name}: drawing failed: {text}")
            paths.append(Path(text))
        self._workers = []
        return paths

    def close(self) -> None:
        """Stop the workers that have not drawn (the run failed)."""
        for _, process, connection in self._workers:
            connection.close()
            process.terminate()
            process.join()
        self._workers = []

    def __enter__(self) -> FigureWorkers:
        return self

    def __exit__(
        self,
        kind: type[BaseException] | None,
        value: BaseException | None,
        traceback: TracebackType | None,
    ) -> None:
        self.close()
