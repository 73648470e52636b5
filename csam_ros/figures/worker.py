"""A run's figures drawn by a worker process started before the run's result exists.

``csam replay --offline`` computes on one core, and a live run (``csam demo``, ``csam
replay``) waits for its nodes. The worker, forked at the start, imports matplotlib meanwhile;
once ``summary.json`` is written it reads it and draws every figure at the same time, each in
a process forked from it (:func:`csam_ros.figures.draw_figure`, as ``python -m
csam_ros.figures`` would). A figure's
error is raised in the caller, naming the figure. The worker is forked only from a process
without other threads (:func:`figure_worker`): a fork copies no thread, and a lock another
thread held would stay locked in the worker.
"""

from __future__ import annotations

import multiprocessing
import signal
from collections.abc import Sequence
from multiprocessing.connection import Connection
from pathlib import Path
from typing import TYPE_CHECKING

from csam_ros.closing import Closing
from csam_ros.figures import FIGURES
from csam_ros.forked import Forked, can_fork

if TYPE_CHECKING:
    from csam_ros.core.joining.result import RunSummary

Outcome = tuple[bool, str]  # drawn, and its path; or not, and why


def _draw(name: str, summary: RunSummary, out_dir: Path) -> Outcome:
    from csam_ros.figures import draw  # matplotlib: only in the worker

    try:
        return True, str(draw.draw_figure(name, summary.result, out_dir, scenario=summary.scenario))
    except Exception as err:  # noqa: BLE001  (any failure goes back to the caller)
        return False, f"{type(err).__name__}: {err}"


def _draw_at_once(names: Sequence[str], summary: RunSummary, out_dir: Path) -> list[Outcome]:
    """Each figure in a process forked from this one (it has no threads)."""
    children = [Forked(_draw, name, summary, out_dir) for name in names]
    outcomes: list[Outcome] = []
    for child in children:
        try:
            outcomes.append(child.result())
        except RuntimeError as err:  # the child died before it could send its outcome
            outcomes.append((False, str(err)))
    return outcomes


def _work(connection: Connection, names: Sequence[str], caller: Connection) -> None:
    # the caller's end of the pipe, inherited by the fork, is closed so that recv ends when
    # the caller closes it or dies; Ctrl-C is the caller's to handle
    caller.close()
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    from csam_ros.core.joining.result import RunSummary
    from csam_ros.figures import draw  # noqa: F401  (matplotlib, imported while the caller computes)

    try:
        summary_path, out_dir = connection.recv()
    except EOFError:  # the caller is gone
        return
    try:
        summary = RunSummary.read(summary_path)
    except Exception as err:  # noqa: BLE001
        connection.send([(False, f"{type(err).__name__}: {err}")] * len(names))
        return
    connection.send(_draw_at_once(names, summary, out_dir))


def figure_worker() -> FigureWorker | None:
    """A worker for every figure, or None (draw in-process) where this process has other
    threads or cannot fork."""
    if not can_fork() or "fork" not in multiprocessing.get_all_start_methods():
        return None
    return FigureWorker()


class FigureWorker(Closing):
    """A forked process that imports matplotlib and waits for a summary to draw from."""

    def __init__(self, names: Sequence[str] = FIGURES) -> None:
        self.names = list(names)
        context = multiprocessing.get_context("fork")
        self._connection, theirs = context.Pipe()
        self._process = context.Process(
            target=_work, args=(theirs, self.names, self._connection), daemon=True
        )
        self._process.start()
        theirs.close()

    def draw(self, summary_path: Path, out_dir: Path) -> list[Path]:
        """Every figure of the summary at ``summary_path``, drawn into ``out_dir`` at once."""
        self._connection.send((summary_path, out_dir))
        try:
            outcomes: list[Outcome] = self._connection.recv()
        except EOFError:
            outcomes = [(False, "the worker ended without a word")] * len(self.names)
        self._process.join()
        self.close()
        failed = [
            f"{n}: {text}" for n, (ok, text) in zip(self.names, outcomes, strict=True) if not ok
        ]
        if failed:
            raise RuntimeError("drawing failed: " + "; ".join(failed))
        return [Path(text) for _, text in outcomes]

    def close(self) -> None:
        """Stop the worker (at once if it has not drawn: the run failed)."""
        self._connection.close()
        if self._process.is_alive():
            self._process.terminate()
        self._process.join()
