"""Figures of a C-SAM result: geometry helpers, and drawing synthetic and real results.

What a figure draws is checked on the matplotlib Figure each draw function saves (caught at
``draw.save_figure``): one trajectory line per robot at its poses, feature markers and ellipses at
the result's positions, titles and legends naming the robots; and in the PNG read back, the
robots' colours at their trajectories and the features' at theirs."""

from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from matplotlib.axes import Axes
from matplotlib.collections import EllipseCollection, PathCollection
from matplotlib.colors import to_rgba
from matplotlib.figure import Figure
from matplotlib.image import imread
from matplotlib.lines import Line2D

from csam_ros.core.joining.result import (
    AssociationRecord,
    CsamResult,
    FeatureResult,
    RobotResult,
    RunSummary,
    SummaryError,
)
from csam_ros.core.model import se2
from csam_ros.core.model.chi_square import chi2_quantile
from csam_ros.figures import FIGURES, draw

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def synthetic_summary(
    poses_per_robot: int = 80, feature_spacing: float = 1.0, seed: int = 0
) -> CsamResult:
    """A map-joining-like result: robot1 (reference) and robot2 (aligned) cross between two
    feature areas, robot3 is pending. Local quantities are in each robot's first-pose frame."""
    rng = np.random.default_rng(seed)
    sample_time = 0.5
    stamps = sample_time * np.arange(poses_per_robot)
    travel = 0.5 * stamps
    starts = {"robot1": np.array([-10.5, -1.0, 0.0]), "robot2": np.array([10.5, 1.0, np.pi])}
    true_poses = {
        name: se2.compose(start, np.column_stack((travel, 0 * travel, 0 * travel)))
        for name, start in starts.items()
    }
    grid = np.arange(-2.5, 2.5 + 1e-9, feature_spacing)
    gx, gy = np.meshgrid(grid, grid)
    area = np.column_stack((gx.ravel(), gy.ravel()))
    world = np.concatenate((area + [-9.0, 0.0], area + [9.0, 0.0]))
    world += rng.uniform(-0.2, 0.2, world.shape)

    distance = np.linalg.norm(true_poses["robot1"][:, :2] - true_poses["robot2"][:, :2], axis=1)
    rendezvous = stamps[distance < 4.0]
    robots: dict[str, RobotResult] = {}
    seen_by: dict[int, list[str]] = {}
    for name, poses in true_poses.items():
        base = starts[name]
        near = np.linalg.norm(world[None] - poses[::10, None, :2], axis=2).min(axis=0) < 4.0
        ids = np.flatnonzero(near)
        steps = np.cumsum(
            rng.uniform(0.0, 0.01, poses_per_robot) + (np.arange(poses_per_robot) > 40) * 0.02
        )
        sigma_local = np.radians(0.05) + steps * np.radians(1.0)
        sigma_local[0] = 0.0 if name == "robot1" else sigma_local[0]
        for index, feature in enumerate(ids):
            seen_by.setdefault(int(feature), []).append(f"{name}/{index}")
        robots[name] = RobotResult(
            name=name,
            alignment="reference" if name == "robot1" else "aligned",
            stamps=stamps,
            poses_local=se2.between(base, poses),
            sigma_phi_local=sigma_local,
            base_node=se2.between(starts["robot1"], base),
            base_node_cov=np.diag([0.01, 0.02, 1e-4]) if name == "robot2" else np.zeros((3, 3)),
            poses_joined=se2.between(starts["robot1"], poses),
            sigma_phi_joined=0.6 * sigma_local,
            rendezvous_stamps=rendezvous,
            feature_labels_local=np.arange(len(ids)),
            features_local=se2.inverse_transform_point(base, world[ids]),
            feature_covariances_local=np.array([_feature_cov(rng, 1e-4) for _ in ids]),
        )
    robots["robot3"] = RobotResult(
        name="robot3",
        alignment="pending: no rendezvous yet",
        stamps=stamps[:20],
        poses_local=np.column_stack((0.3 * stamps[:20], 0 * stamps[:20], 0 * stamps[:20])),
        sigma_phi_local=np.radians(0.1 * np.arange(20)),
    )
    reference = starts["robot1"]
    features = [
        FeatureResult(
            members,
            se2.inverse_transform_point(reference, world[feature]),
            _feature_cov(rng, 4e-4 if len(members) == 1 else 2e-4),
        )
        for feature, members in sorted(seen_by.items())
    ]
    associations = [
        AssociationRecord(m[0], m[1], float(rng.uniform(0, 5)))
        for m in seen_by.values()
        if len(m) > 1
    ]
    return CsamResult(
        reference_frame="robot1/map",
        robots=robots,
        features=features,
        associations=associations,
        timing_s={"joint_solve": 0.1},
    )


def _feature_cov(rng: np.random.Generator, variance: float) -> np.ndarray:
    root = rng.normal(0.0, math.sqrt(variance), (2, 2))
    return root @ root.T + 1e-6 * np.eye(2)


def assert_png(path: Path, min_bytes: int = 15_000) -> None:
    data = path.read_bytes()
    assert data[:8] == PNG_SIGNATURE, path
    assert len(data) > min_bytes, (path, len(data))


# --------------------------------------------------------------------------- geometry


def test_ellipse_axes_of_rotated_covariance() -> None:
    sigma_major, sigma_minor, angle = 0.3, 0.1, np.radians(30.0)
    rotation = se2.rotation(angle)
    cov = rotation @ np.diag([sigma_major**2, sigma_minor**2]) @ rotation.T
    widths, heights, angles = draw.ellipse_axes(np.stack([cov, np.diag([0.04, 0.09])]))
    k = math.sqrt(5.991464547107979)
    np.testing.assert_allclose(widths, [2 * k * 0.3, 2 * k * 0.3])
    np.testing.assert_allclose(heights, [2 * k * 0.1, 2 * k * 0.2])
    # an axis has no sign: compare the direction modulo 180 degrees
    np.testing.assert_allclose(np.mod(angles, 180.0), [30.0, 90.0], atol=1e-9)


def test_ellipse_axes_boundary_point_is_on_the_chi2_contour() -> None:
    cov = np.array([[0.5, 0.2], [0.2, 0.3]])
    width, height, angle = draw.ellipse_axes(cov, confidence=0.9)
    theta = np.radians(angle[0])
    ends = np.array(
        [
            0.5 * width[0] * np.array([np.cos(theta), np.sin(theta)]),
            0.5 * height[0] * np.array([-np.sin(theta), np.cos(theta)]),
        ]
    )
    distances = np.einsum("ni,ij,nj->n", ends, np.linalg.inv(cov), ends)
    np.testing.assert_allclose(distances, chi2_quantile(0.9, 2))


def test_ellipse_axes_rejects_indefinite_and_asymmetric() -> None:
    with pytest.raises(ValueError, match="positive semi-definite"):
        draw.ellipse_axes(np.array([[1.0, 0.0], [0.0, -1.0]]))
    with pytest.raises(ValueError, match="positive semi-definite"):
        draw.ellipse_axes(np.array([[1.0, 0.5], [0.0, 1.0]]))
    with pytest.raises(ValueError, match="shape"):
        draw.ellipse_axes(np.eye(3))


def test_group_stamps_splits_at_gaps() -> None:
    stamps = [10.5, 10.0, 11.0, 11.5, 30.0, 30.5, 50.0, 10.0]
    intervals = draw.group_stamps(stamps, max_gap=1.0)
    np.testing.assert_array_equal(intervals, [[10.0, 11.5], [30.0, 30.5], [50.0, 50.0]])
    assert draw.group_stamps([], max_gap=1.0).shape == (0, 2)
    np.testing.assert_array_equal(draw.group_stamps(stamps, max_gap=100.0), [[10.0, 50.0]])
    with pytest.raises(ValueError, match="max_gap"):
        draw.group_stamps(stamps, max_gap=-1.0)


def test_magnification_makes_small_ellipses_visible_but_not_huge() -> None:
    assert draw.ellipse_magnification([1.0, 1.0], extent=20.0) == 1
    factor = draw.ellipse_magnification([0.01, 0.012], extent=20.0)
    assert factor > 1 and 0.012 * factor <= 0.08 * 20.0 and 0.01 * factor >= 0.006 * 20.0
    assert draw.ellipse_magnification([], extent=20.0) == 1


def test_value_axis_scale_goes_log_beyond_two_decades() -> None:
    assert draw.value_axis_scale([0.1, 0.5, 2.0]) == ("linear", (0.0, 2.0 * 1.08))
    scale, limits = draw.value_axis_scale(np.geomspace(0.01, 5.0, 50))
    assert scale == "log" and limits is not None and limits[0] < 0.02 and limits[1] > 5.0
    # one anchored pose at zero or near zero does not force a log axis
    assert draw.value_axis_scale([0.0, 1e-9, *np.linspace(0.1, 2.0, 200)])[0] == "linear"
    assert draw.value_axis_scale([np.nan, 0.0]) == ("linear", None)


def test_robot_colours_are_stable_and_distinct() -> None:
    colours = draw.robot_colours(["robot1", "robot2", "robot3"])
    assert len(set(colours.values())) == 3
    assert draw.robot_colours(["robot1", "robot2"])["robot2"] == colours["robot2"]


# --------------------------------------------------------------------------- drawing


@pytest.fixture
def drawn(monkeypatch: pytest.MonkeyPatch) -> dict[str, Figure]:
    """Every figure the draw functions save, by file name (still saved as before)."""
    figures: dict[str, Figure] = {}
    save = draw.save_figure

    def keep(figure: Figure, path: str | Path) -> Path:
        figures[Path(path).name] = figure
        return save(figure, path)

    monkeypatch.setattr(draw, "save_figure", keep)
    return figures


def _same_colour(a: Any, b: Any) -> bool:
    return to_rgba(a) == to_rgba(b)


def _lines_through(
    axes: Axes, xy: np.ndarray, colour: Any, linestyle: str | None = None
) -> list[Line2D]:
    """The lines of ``axes`` whose points are exactly ``xy``, in ``colour``."""
    found = []
    for line in axes.get_lines():
        data = np.column_stack([np.asarray(v, dtype=float) for v in line.get_data()])
        if (
            data.shape == xy.shape
            and np.allclose(data, xy, rtol=0, atol=1e-12, equal_nan=True)
            and _same_colour(line.get_color(), colour)
            and (linestyle is None or line.get_linestyle() == linestyle)
        ):
            found.append(line)
    return found


def _sorted_rows(xy: np.ndarray) -> np.ndarray:
    xy = np.asarray(xy, dtype=float).reshape(-1, 2)
    return xy[np.lexsort(xy.T[::-1])]


def _offsets(axes: Axes, kind: type) -> list[np.ndarray]:
    return [np.asarray(c.get_offsets()) for c in axes.collections if type(c) is kind]


def _notes(axes: Axes) -> list[str]:
    return [t.get_text() for t in axes.texts]


def _legend_labels(legend: Any) -> list[str]:
    assert legend is not None
    return [t.get_text() for t in legend.get_texts()]


def _shown(png: np.ndarray, axes: Axes, xy: np.ndarray, colour: Any) -> float:
    """The share of the points ``xy`` (data of ``axes``) that the saved PNG shows in
    ``colour``: a pixel of that colour within 2 px of the point."""
    rgb = np.array(to_rgba(colour)[:3])
    height = png.shape[0]
    hits = 0
    for x, y in axes.transData.transform(np.asarray(xy, dtype=float)):
        col, row = int(x), int(height - y)
        window = png[max(row - 2, 0) : row + 3, max(col - 2, 0) : col + 3, :3]
        hits += bool(window.size and (np.abs(window - rgb).max(axis=-1) < 0.12).any())
    return hits / len(xy)


def _colour_pixels(png: np.ndarray, axes: Axes, colour: Any) -> int:
    """How many pixels inside ``axes`` the saved PNG shows in ``colour``."""
    box = axes.get_window_extent()
    height = png.shape[0]
    inside = png[int(height - box.y1) : int(height - box.y0), int(box.x0) : int(box.x1), :3]
    return int((np.abs(inside - np.array(to_rgba(colour)[:3])).max(axis=-1) < 0.12).sum())


def _png(figure: Figure, path: Path) -> np.ndarray:
    """The saved PNG as RGB(A) floats, checked to be the figure's size."""
    assert_png(path, min_bytes=5_000)
    image = imread(path)
    width, height = figure.canvas.get_width_height()
    assert image.shape[:2] == (height, width)
    return image


def check_local_maps(figure: Figure, path: Path, result: CsamResult) -> None:
    """A panel per robot titled with its name and alignment: its trajectory in its colour,
    its features and their ellipses at its local feature positions; all visible in the PNG."""
    png = _png(figure, path)
    panels = [a for a in figure.axes if a.get_visible()]
    colours = draw.robot_colours(list(result.robots))
    if not result.robots:  # (the note's panel is hidden: see the xfail test below)
        assert _notes(figure.axes[0]) == ["no robots in the result"]
        return
    assert len(panels) == len(result.robots)
    for axes, (name, robot) in zip(panels, result.robots.items(), strict=True):
        assert axes.get_title() == f"{name} ({robot.alignment})"
        assert _same_colour(axes.title.get_color(), colours[name])
        poses, features = robot.poses_local[:, :2], robot.features_local.reshape(-1, 2)
        if poses.shape[0]:
            assert len(_lines_through(axes, poses, colours[name], "-")) == 1, name
            assert _shown(png, axes, poses[::5], colours[name]) > 0.9, name
        if features.shape[0]:
            assert len(_lines_through(axes, features, "0.1")) == 1, name
            (ellipses,) = _offsets(axes, EllipseCollection)
            np.testing.assert_array_equal(ellipses, features)
            assert _shown(png, axes, features, "0.1") > 0.9, name
        else:
            assert not _offsets(axes, EllipseCollection)
        if not poses.shape[0] and not features.shape[0]:
            assert _notes(axes) == ["empty local map"]
    labels = _legend_labels(figure.legends[0])
    assert [f"{name} trajectory" for name in result.robots] == labels[: len(result.robots)]


def check_heading_sigma(
    figure: Figure, path: Path, result: CsamResult, scenario: str | None
) -> None:
    """Per robot its local heading sigma dashed and its joined one solid, in degrees over
    time, in its colour; the legend names each robot; rendezvous shaded when there are any."""
    png = _png(figure, path)
    (axes,) = figure.axes
    title = "heading standard deviation before and after C-SAM"
    assert axes.get_title() == (f"{scenario}: {title}" if scenario else title)
    if not result.robots:
        assert _notes(axes) == ["no robots in the result"]
        return
    colours = draw.robot_colours(list(result.robots))
    t0 = min(float(np.min(r.stamps)) for r in result.robots.values())
    curves = 0
    for name, robot in result.robots.items():
        for sigma, style in ((robot.sigma_phi_local, "--"), (robot.sigma_phi_joined, "-")):
            if sigma is None or sigma.size == 0:
                continue
            xy = np.column_stack((robot.stamps - t0, np.degrees(sigma)))
            assert len(_lines_through(axes, xy, colours[name], style)) == 1, (name, style)
            curves += 1
        # curves of similar robots overlap: the robot's colour shows somewhere on the axes
        if robot.sigma_phi_local.size:
            assert _colour_pixels(png, axes, colours[name]) > 50, name
    in_robot_colours = [
        line
        for line in axes.get_lines()
        if any(_same_colour(line.get_color(), c) for c in colours.values())
    ]
    assert curves == len(in_robot_colours) and curves >= len(result.robots)
    labels = _legend_labels(axes.get_legend())
    for label, (name, robot) in zip(labels, result.robots.items(), strict=False):
        assert label == name if robot.joined else label.startswith(f"{name} pending:")
    spans = [p for p in axes.patches if p.get_alpha() == pytest.approx(0.18)]
    if any(r.rendezvous_stamps.size for r in result.robots.values()):
        assert spans and f"rendezvous ({len(spans)}×)" in labels
    else:
        assert not spans


def check_joined_map(
    figure: Figure,
    path: Path,
    result: CsamResult,
    truth: np.ndarray | None = None,
    scenario: str | None = None,
) -> None:
    """The aligned robots' joined trajectories in their colours (pending robots none), every
    feature of the result at its position with its ellipse (those of several robots as black
    diamonds), the truth as crosses; the legend names each robot; all visible in the PNG."""
    png = _png(figure, path)
    (axes,) = figure.axes
    frame = result.reference_frame
    title = f"joined map in {frame}" if frame else "joined map"
    assert axes.get_title() == (f"{scenario}: {title}" if scenario else title)
    colours = draw.robot_colours(list(result.robots))
    labels = _legend_labels(axes.get_legend())
    trajectories = 0
    for name, robot in result.robots.items():
        if robot.joined:
            assert any(label.startswith(f"{name} ({robot.alignment})") for label in labels)
        else:
            assert any(label.startswith(f"{name} pending:") for label in labels), labels
        poses = robot.poses_joined
        if robot.joined and poses is not None and poses.shape[0]:
            assert len(_lines_through(axes, poses[:, :2], colours[name], "-")) == 1, name
            assert _shown(png, axes, poses[::5, :2], colours[name]) > 0.9, name
            trajectories += 1
    paths = [
        line
        for line in axes.get_lines()
        if line.get_linestyle() == "-" and len(line.get_xdata()) > 1
    ]
    assert trajectories == len(paths)
    xy = np.array([f.xy for f in result.features]).reshape(-1, 2)
    scattered = _offsets(axes, PathCollection)
    if xy.shape[0]:
        np.testing.assert_array_equal(_sorted_rows(np.concatenate(scattered)), _sorted_rows(xy))
        # one collection of the features' ellipses (the base nodes' are others)
        ellipses = _offsets(axes, EllipseCollection)
        assert sum(np.array_equal(e, xy) for e in ellipses) == 1
        robots_of = [{draw.robot_of_label(m) for m in f.members} for f in result.features]
        several = [len(robots) > 1 for robots in robots_of]
        if any(several):
            assert _shown(png, axes, xy[several], "black") > 0.9
            assert f"feature seen by several robots ({sum(several)})" in labels
        for name in result.robots:  # a feature of one robot in its colour
            own = [robots == {name} for robots in robots_of]
            if any(own):
                assert _shown(png, axes, xy[own], colours[name]) > 0.9, name
    else:
        assert not scattered
    if truth is not None and len(truth):
        assert len(_lines_through(axes, np.asarray(truth), "0.6")) == 1
        assert "true feature" in labels
    if not any(r.joined for r in result.robots.values()) and not xy.shape[0]:
        assert _notes(axes) == ["nothing joined yet"]


def check_figures(
    figures: dict[str, Figure],
    paths: list[Path],
    result: CsamResult,
    truth: np.ndarray | None = None,
    scenario: str | None = None,
) -> None:
    assert [p.name for p in paths] == list(FIGURES) and set(figures) == set(FIGURES)
    by_name = {p.name: p for p in paths}
    check_local_maps(figures["local_maps.png"], by_name["local_maps.png"], result)
    check_heading_sigma(
        figures["heading_sigma.png"], by_name["heading_sigma.png"], result, scenario
    )
    check_joined_map(figures["joined_map.png"], by_name["joined_map.png"], result, truth, scenario)


def test_draw_all_draws_each_robot_and_feature(tmp_path: Path, drawn) -> None:
    result = synthetic_summary()
    truth = np.array([f.xy for f in result.features])
    paths = draw.draw_all(result, tmp_path / "out", truth=truth, scenario="map_joining")
    for path in paths:
        assert_png(path)
    check_figures(drawn, paths, result, truth, "map_joining")


def test_main_draws_a_summary_json(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], drawn
) -> None:
    path = tmp_path / "summary.json"
    RunSummary(synthetic_summary(poses_per_robot=30), scenario="map_joining").write(path)
    assert draw.main([str(path)]) == 0
    printed = [Path(p) for p in capsys.readouterr().out.split()]
    assert [p.parent for p in printed] == [tmp_path] * 3
    check_figures(drawn, printed, RunSummary.read(path).result, scenario="map_joining")


def _without_features(result: CsamResult) -> CsamResult:
    return replace(result, features=[], associations=[])


def _without_local_features_or_rendezvous(result: CsamResult) -> CsamResult:
    robots = {
        name: replace(
            r,
            rendezvous_stamps=np.zeros(0),
            feature_labels_local=np.zeros(0, dtype=np.int64),
            features_local=np.zeros((0, 2)),
            feature_covariances_local=np.zeros((0, 2, 2)),
        )
        for name, r in result.robots.items()
    }
    return replace(result, robots=robots)


def _all_pending(result: CsamResult) -> CsamResult:
    robots = {
        name: RobotResult(name, "pending: lost", r.stamps, r.poses_local, r.sigma_phi_local)
        for name, r in result.robots.items()
    }
    return replace(result, robots=robots, features=[], associations=[])


def _only_the_pending_robot(result: CsamResult) -> CsamResult:
    return replace(result, robots={"robot3": result.robots["robot3"]}, features=[])


def _no_robots(result: CsamResult) -> CsamResult:
    return replace(result, robots={}, features=[], associations=[])


@pytest.mark.parametrize(
    "change",
    [
        _without_features,
        _without_local_features_or_rendezvous,
        _all_pending,
        _only_the_pending_robot,
        _no_robots,
    ],
)
def test_what_a_result_lacks_is_left_out(tmp_path: Path, drawn, change) -> None:
    result = change(synthetic_summary(poses_per_robot=30))
    check_figures(drawn, draw.draw_all(result, tmp_path), result)


def test_bad_covariance_and_truth_are_named(tmp_path: Path) -> None:
    result = synthetic_summary(poses_per_robot=30)
    bad = result.features[3]
    result.features[3] = replace(bad, cov=np.array([[1.0, 0.0], [0.0, -2.0]]))
    label = "+".join(bad.members)
    with pytest.raises(SummaryError, match=rf"features: covariance of '{label}'"):
        draw.draw_joined_map(result, tmp_path / "c.png")

    result = synthetic_summary(poses_per_robot=30)
    result.robots["robot2"].feature_covariances_local[1] = [[1.0, 0.5], [0.0, 1.0]]
    with pytest.raises(SummaryError, match=r"robots\.robot2\.features_local: .*'robot2/1'"):
        draw.draw_local_maps(result, tmp_path / "a.png")

    with pytest.raises(ValueError, match="truth"):
        draw.draw_joined_map(synthetic_summary(30), tmp_path / "d.png", truth=np.zeros(4))


def test_large_summary_draws(tmp_path: Path, drawn) -> None:
    """A few thousand poses and features go through the collections (speed is printed)."""
    import time

    result = synthetic_summary(poses_per_robot=2000, feature_spacing=0.12)
    count = len(result.features)
    start = time.perf_counter()
    path = draw.draw_joined_map(result, tmp_path / "joined_map.png")
    elapsed = time.perf_counter() - start
    print(f"joined map with {count} features and 2 x 2000 poses: {elapsed:.2f} s")
    assert count > 2000
    assert_png(path)
    check_joined_map(drawn["joined_map.png"], path, result)


@pytest.mark.parametrize("scenario", ["map_joining", "sensor_extension"])
def test_draw_from_a_real_csam_run(tmp_path: Path, drawn, scenario: str) -> None:
    """The result C-SAM writes to summary.json and reads back draws, truth included."""
    from csam_ros.core.joining.pipeline import run_csam
    from csam_ros.datasets.scenario import load_scenario
    from csam_ros.datasets.simulation import simulate

    log = simulate(load_scenario(scenario), seed=1)
    result = CsamResult.from_dict(json.loads(json.dumps(run_csam(log).to_dict())))
    reference = result.reference
    truth = se2.inverse_transform_point(
        log.truth.trajectories[reference][0], log.truth.feature_positions
    )
    paths = draw.draw_all(result, tmp_path, truth=truth, scenario=scenario)
    for png in paths:
        assert_png(png)
    check_figures(drawn, paths, result, truth, scenario)


@pytest.mark.xfail(
    strict=True,
    reason="draw_local_maps hides every panel past the robots' count, the one panel holding "
    "its 'no robots in the result' note included, so the note is never drawn",
)
def test_local_maps_without_robots_show_their_note(tmp_path: Path, drawn) -> None:
    path = draw.draw_local_maps(
        _no_robots(synthetic_summary(poses_per_robot=30)), tmp_path / "a.png"
    )
    figure = drawn["a.png"]
    (note,) = figure.axes[0].texts
    png = _png(figure, path)
    box = note.get_window_extent()  # where the note's text is drawn, in pixels
    rows = slice(int(png.shape[0] - box.y1), int(png.shape[0] - box.y0) + 1)
    assert (png[rows, int(box.x0) : int(box.x1) + 1, :3] < 0.8).any()
