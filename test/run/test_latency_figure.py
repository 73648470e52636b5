"""The latency figure: each robot's lags at their arrivals, the p95 of each tenth of the run and
the solve times, checked on the matplotlib Figure it saves; its command on a recorded run."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from matplotlib.figure import Figure
from matplotlib.image import imread

from csam_ros.figures.draw import DPI, FIGURE_WIDTH_IN
from csam_ros.run import latency_figure as latency
from csam_ros.run.lag import NOT_USED, RUN_PARTS, Timeline

REPO = Path(__file__).resolve().parents[2]


def _timeline() -> Timeline:
    """Two robots' maps at 0..9 s, each joined 0.5 s later by a solve of 0.4 s; robot b's last
    map never."""
    arrivals = np.arange(10.0)
    joined = arrivals + 0.5
    used_b = arrivals.copy()
    used_b[-1] = NOT_USED
    return Timeline(
        map_arrivals={"a": arrivals, "b": arrivals + 0.1},
        map_stamps={"a": arrivals, "b": arrivals + 0.1},
        joined_times=joined,
        used_stamps={"a": arrivals, "b": np.where(used_b == NOT_USED, NOT_USED, used_b + 0.1)},
        solves=10,
        solve_seconds=np.full(10, 0.4),
        solve_times=joined,
        provisional_times=np.zeros(0),
        provisional_used={"a": np.zeros(0), "b": np.zeros(0)},
    )


@pytest.fixture
def saved(monkeypatch: pytest.MonkeyPatch) -> list[Figure]:
    figures: list[Figure] = []
    save = latency.save_figure

    def keep(figure: Figure, path: str | Path) -> Path:
        figures.append(figure)
        return save(figure, path)

    monkeypatch.setattr(latency, "save_figure", keep)
    return figures


def test_lags_p95_and_solves_are_drawn(tmp_path: Path, saved: list[Figure]) -> None:
    path = latency.draw_latency(_timeline(), tmp_path / "latency.png", "a run")
    (figure,) = saved
    lags_axes, solves_axes = figure.axes
    assert lags_axes.get_title() == "a run"
    points = {line.get_label(): line.get_xydata() for line in lags_axes.lines}
    np.testing.assert_allclose(points["a"], np.c_[np.arange(10.0), np.full(10, 0.5)])
    assert len(points["b"]) == 9  # the map never joined is not drawn
    np.testing.assert_allclose(points["b"][:, 1], 0.4)
    (stairs,) = [p for p in lags_axes.patches if p.get_label() == "p95 of each tenth"]
    p95, edges, _ = stairs.get_data()
    assert len(p95) == RUN_PARTS and edges[0] == 0.0 and edges[-1] == pytest.approx(9.1)
    assert np.all((p95 >= 0.4) & (p95 <= 0.5))
    (solves,) = solves_axes.lines
    np.testing.assert_allclose(solves.get_xydata(), np.c_[np.arange(10.0) + 0.5, np.full(10, 0.4)])
    image = imread(path)
    assert image.shape[1] == round(FIGURE_WIDTH_IN * DPI)


def test_a_run_without_joined_maps_or_solves_says_so(tmp_path: Path, saved: list[Figure]) -> None:
    empty = Timeline(
        map_arrivals={"a": np.array([1.0])},
        map_stamps={"a": np.array([1.0])},
        joined_times=np.zeros(0),
        used_stamps={"a": np.zeros(0)},
        solves=0,
        solve_seconds=np.zeros(0),
        solve_times=np.zeros(0),
        provisional_times=np.zeros(0),
        provisional_used={"a": np.zeros(0)},
    )
    latency.draw_latency(empty, tmp_path / "latency.png")
    texts = [t.get_text() for axes in saved[0].axes for t in axes.texts]
    assert "no local map reached a solved joined map" in texts
    assert "no solve time in /csam/status" in texts


def test_command_draws_a_recorded_run(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    out = tmp_path / "figure.png"
    assert latency.main([str(REPO / "bags" / "map_joining"), "--out", str(out)]) == 0
    assert capsys.readouterr().out.strip() == str(out)
    assert imread(out).shape[1] == round(FIGURE_WIDTH_IN * DPI)
