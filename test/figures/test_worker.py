"""Figures drawn by the forked worker equal those drawn in-process; a figure's failure is
raised in the caller, naming it."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from csam_ros.core.joining.pipeline import run_csam
from csam_ros.core.joining.result import RunSummary
from csam_ros.datasets.scenario import load_scenario
from csam_ros.datasets.simulation import simulate
from csam_ros.figures import FIGURES, draw

# run in a fresh process: the test process may hold threads (in-process nodes), and the
# worker is forked only from a process without them
DRAW = """
import sys
from pathlib import Path
from csam_ros.figures.worker import FigureWorker, figure_worker

summary, out = Path(sys.argv[1]), Path(sys.argv[2])
worker = figure_worker()
assert worker is not None, "no worker"
print(" ".join(str(p) for p in worker.draw(summary, out)))
with FigureWorker(["local_maps.png", "no_such_figure.png"]) as failing:
    try:
        failing.draw(summary, out / "failing")
    except RuntimeError as err:
        print(err)
with FigureWorker():  # closed unused: the worker ends
    pass
"""


def test_the_worker_draws_what_the_caller_would_and_reports_a_failure(tmp_path: Path) -> None:
    result = run_csam(simulate(load_scenario("map_joining"), 1))
    summary_path = tmp_path / "summary.json"
    RunSummary(result, scenario="map_joining").write(summary_path)
    done = subprocess.run(
        [sys.executable, "-c", DRAW, str(summary_path), str(tmp_path / "workers")],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0, done.stderr
    drawn, failure = done.stdout.strip().splitlines()
    here = draw.draw_all(
        RunSummary.read(summary_path).result, tmp_path / "here", scenario="map_joining"
    )
    assert [Path(p).name for p in drawn.split()] == [p.name for p in here] == list(FIGURES)
    for path in here:
        assert (tmp_path / "workers" / path.name).read_bytes() == path.read_bytes()
    assert failure.startswith("drawing failed: no_such_figure.png: ValueError: no figure")
    assert (tmp_path / "workers" / "failing" / "local_maps.png").is_file()
