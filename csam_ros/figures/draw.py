"""The figures of the paper's section V, drawn from a C-SAM result.

Andersson & Nygards, figures 5 and 6: (a, b) each robot's local map before joining,
(c) heading standard deviation per sample before and after C-SAM with the rendezvous
interval marked, (d) the joined map in the reference robot's frame.

- :func:`draw_local_maps`: one panel per robot, its trajectory and features in its own
  frame ``G_r`` (``poses_local``, ``features_local``).
- :func:`draw_heading_sigma`: ``sigma_phi_local`` (dashed) and ``sigma_phi_joined`` (solid)
  per robot over time, rendezvous intervals shaded.
- :func:`draw_joined_map`: aligned trajectories (``poses_joined``), merged features, base
  nodes and, optionally, true feature positions in the reference frame.
- :func:`draw_all`: the three into a directory.

Every function takes a :class:`~csam_ros.core.joining.result.CsamResult` (``python -m
csam_ros.figures SUMMARY.json`` reads one from a run's ``summary.json``) and, for the titles,
the scenario's name. What a result lacks (a pending robot's joined fields, features, rendezvous)
is left out of the figure (and said so in it); a covariance that is not positive semi-definite
raises :class:`~csam_ros.core.joining.result.SummaryError` naming it. Covariance ellipses are drawn
at 95 % (chi-square, 2 dof: 5.991) and magnified by a stated factor when they would be invisible
at map scale. Rendering goes through the Agg canvas directly (no pyplot, no display).
"""

from __future__ import annotations

import math
import textwrap
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import EllipseCollection
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Patch
from numpy.typing import ArrayLike, NDArray

from csam_ros.core.joining.result import CsamResult, RobotResult, RunSummary, SummaryError
from csam_ros.core.model.chi_square import chi2_quantile
from csam_ros.core.model.stamps import matching_stamp
from csam_ros.figures import FIGURES

FloatArray = NDArray[np.float64]

CONFIDENCE = 0.95
FIGURE_WIDTH_IN = 10.0
DPI = 120  # 10 in x 120 dpi = 1200 px wide
VISIBLE_SEMI_AXIS_PX = 6.0  # a typical ellipse is magnified until its semi-major axis is this
MAGNIFICATIONS = (1, 2, 5, 10, 20, 50, 100, 200, 500, 1000)
ROBOT_MARKERS = ("o", "s", "^", "D", "v", "P", "X", "*")
ROBOT_PALETTE = (
    "#1f77b4",
    "#d62728",
    "#2ca02c",
    "#9467bd",
    "#ff7f0e",
    "#8c564b",
    "#e377c2",
    "#17becf",
    "#bcbd22",
    "#7f7f7f",
)
MULTI_ROBOT_COLOUR = "black"
UNKNOWN_COLOUR = "0.5"


def ellipse_axes(
    covariances: ArrayLike, confidence: float = CONFIDENCE
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Full axis lengths and orientation of the confidence ellipses of 2x2 covariances.

    For ``Sigma = V diag(l_major, l_minor) V^T`` the ellipse ``x^T Sigma^-1 x = k`` with
    ``k = chi2_2(confidence)`` has semi-axes ``sqrt(k l)``. Returns ``(widths, heights,
    angles_deg)``: full major and minor axis lengths (twice the semi-axes) and the
    anticlockwise angle of the major axis from x in degrees, each of shape ``(N,)``.
    """
    cov = np.asarray(covariances, dtype=float)
    if cov.ndim == 2:
        cov = cov[None]
    if cov.ndim != 3 or cov.shape[1:] != (2, 2):
        raise ValueError(f"covariances: expected shape (N, 2, 2), got {cov.shape}")
    scale = np.maximum(np.abs(cov).max(axis=(1, 2)), np.finfo(float).tiny)
    asymmetric = np.abs(cov[:, 0, 1] - cov[:, 1, 0]) > 1e-6 * scale
    eigenvalues, eigenvectors = np.linalg.eigh(0.5 * (cov + np.swapaxes(cov, 1, 2)))
    indefinite = eigenvalues[:, 0] < -1e-9 * scale
    bad = np.flatnonzero(asymmetric | indefinite | ~np.isfinite(cov).all(axis=(1, 2)))
    if bad.size:
        raise ValueError(
            f"covariances {bad[:5].tolist()} are not finite symmetric positive semi-definite: "
            f"{cov[bad[0]].tolist()}"
        )
    k = chi2_quantile(confidence, 2)
    semi = np.sqrt(k * np.clip(eigenvalues, 0.0, None))
    major = eigenvectors[:, :, 1]
    angles = np.degrees(np.arctan2(major[:, 1], major[:, 0]))
    return 2.0 * semi[:, 1], 2.0 * semi[:, 0], angles


def group_stamps(stamps: ArrayLike, max_gap: float) -> FloatArray:
    """Group stamps into intervals ``(K, 2)`` of ``[first, last]``, split at gaps > max_gap."""
    if not max_gap >= 0.0:
        raise ValueError(f"max_gap must be >= 0, got {max_gap}")
    values = np.asarray(stamps, dtype=float).ravel()
    if not np.isfinite(values).all():
        raise ValueError("stamps must be finite")
    if values.size == 0:
        return np.empty((0, 2))
    values = np.unique(values)
    breaks = np.flatnonzero(np.diff(values) > max_gap)
    starts = np.concatenate(([values[0]], values[breaks + 1]))
    ends = np.concatenate((values[breaks], [values[-1]]))
    return np.column_stack((starts, ends))


def ellipse_magnification(
    semi_major: ArrayLike, extent: float, min_fraction: float = 0.006, max_fraction: float = 0.08
) -> int:
    """Factor from :data:`MAGNIFICATIONS` that makes ellipses visible at map scale.

    The smallest factor bringing the median semi-major axis to ``min_fraction`` of the map
    extent, reduced while the 90th percentile would exceed ``max_fraction`` of it.
    """
    values = np.asarray(semi_major, dtype=float).ravel()
    values = values[np.isfinite(values) & (values > 0.0)]
    if values.size == 0 or not extent > 0.0:
        return 1
    typical = float(np.median(values))
    large = float(np.quantile(values, 0.9))
    index = next(
        (i for i, m in enumerate(MAGNIFICATIONS) if typical * m >= min_fraction * extent),
        len(MAGNIFICATIONS) - 1,
    )
    while index > 0 and large * MAGNIFICATIONS[index] > max_fraction * extent:
        index -= 1
    return MAGNIFICATIONS[index]


def value_axis_scale(values: ArrayLike) -> tuple[str, tuple[float, float] | None]:
    """``("log", limits)`` when the positive values span more than two decades, else linear.

    The span is taken from the 2nd percentile up, so that one anchored pose with a near-zero
    standard deviation does not force a log axis on its own.
    """
    array = np.asarray(values, dtype=float).ravel()
    positive = array[np.isfinite(array) & (array > 0.0)]
    if positive.size == 0:
        return "linear", None
    low, high = float(np.quantile(positive, 0.02)), float(positive.max())
    if high > 100.0 * low:
        return "log", (low / 2.0, high * 1.5)
    return "linear", (0.0, high * 1.08)


def robot_colours(robot_names: Sequence[str]) -> dict[str, str]:
    """One colour per robot, by its position in the summary (the same in every figure)."""
    return {name: ROBOT_PALETTE[i % len(ROBOT_PALETTE)] for i, name in enumerate(robot_names)}


def robot_of_label(label: str) -> str:
    """The robot part of a feature label ``<robot>/<local label>``."""
    return label.rsplit("/", 1)[0]


# --------------------------------------------------------------------------- drawing views


def _checked_ellipses(
    cov: FloatArray, names: Sequence[str], where: str
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """:func:`ellipse_axes` of ``cov`` (N, 2, 2); a bad covariance is named."""
    if len(cov) == 0:
        return np.empty(0), np.empty(0), np.empty(0)
    try:
        return ellipse_axes(cov)
    except ValueError:
        first = _first_bad_covariance(cov)
        raise SummaryError(
            f"{where}: covariance of {names[first]!r} is not a finite symmetric "
            f"positive semi-definite 2x2 matrix: {cov[first].tolist()}"
        ) from None


def _first_bad_covariance(cov: FloatArray) -> int:
    """Index of the first covariance :func:`ellipse_axes` rejects (error path only)."""
    for i in range(len(cov)):
        try:
            ellipse_axes(cov[i])
        except ValueError:
            return i
    return 0


@dataclass
class _Features:
    labels: list[str]
    xy: FloatArray  # (F, 2)
    widths: FloatArray  # (F,) full 95 % axes
    heights: FloatArray
    angles: FloatArray  # degrees

    @property
    def semi_major(self) -> FloatArray:
        return 0.5 * self.widths


def _features(labels: list[str], xy: ArrayLike, cov: ArrayLike, where: str) -> _Features:
    widths, heights, angles = _checked_ellipses(
        np.asarray(cov, dtype=float).reshape(-1, 2, 2), labels, where
    )
    return _Features(labels, np.asarray(xy, dtype=float).reshape(-1, 2), widths, heights, angles)


@dataclass
class _Robot:
    name: str
    colour: str
    alignment: str
    aligned: bool  # in the joined map (RobotResult.joined)
    stamps: FloatArray
    poses_local: FloatArray
    poses_joined: FloatArray | None
    sigma_local: FloatArray  # rad
    sigma_joined: FloatArray | None
    features_local: _Features
    rendezvous_stamps: FloatArray
    base_node: FloatArray | None
    base_node_cov: FloatArray | None

    @property
    def pending_reason(self) -> str:
        text = self.alignment
        return text.split(":", 1)[1].strip() if ":" in text else text


def _robot(robot: RobotResult, colour: str) -> _Robot:
    labels = [f"{robot.name}/{int(k)}" for k in robot.feature_labels_local]
    return _Robot(
        name=robot.name,
        colour=colour,
        alignment=robot.alignment,
        aligned=robot.joined,
        stamps=robot.stamps,
        poses_local=robot.poses_local,
        poses_joined=robot.poses_joined,
        sigma_local=robot.sigma_phi_local,
        sigma_joined=robot.sigma_phi_joined,
        features_local=_features(
            labels,
            robot.features_local,
            robot.feature_covariances_local,
            f"robots.{robot.name}.features_local",
        ),
        rendezvous_stamps=robot.rendezvous_stamps,
        base_node=robot.base_node,
        base_node_cov=robot.base_node_cov,
    )


@dataclass
class _Summary:
    scenario: str | None
    reference_frame: str
    robots: list[_Robot]
    features: _Features
    feature_members: list[list[str]]


def _view(result: CsamResult, scenario: str | None) -> _Summary:
    """What the figures draw of ``result``, with a colour per robot."""
    colours = robot_colours(list(result.robots))
    members = [list(f.members) for f in result.features]
    return _Summary(
        scenario=scenario,
        reference_frame=result.reference_frame,
        robots=[_robot(r, colours[name]) for name, r in result.robots.items()],
        features=_features(
            ["+".join(m) for m in members],
            [f.xy for f in result.features],
            [f.cov for f in result.features],
            "features",
        ),
        feature_members=members,
    )


# --------------------------------------------------------------------------- drawing helpers


def new_figure(height_in: float) -> Figure:
    """A figure of the common width and resolution, ``height_in`` inches high."""
    figure = Figure(figsize=(FIGURE_WIDTH_IN, height_in), dpi=DPI, layout="constrained")
    FigureCanvasAgg(figure)
    return figure


def save_figure(figure: Figure, path: str | Path) -> Path:
    """Write ``figure`` to ``path`` as PNG (its folder made); the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path, dpi=DPI, format="png")
    return path


def _title(summary: _Summary, what: str) -> str:
    return f"{summary.scenario}: {what}" if summary.scenario else what


def _ellipse_label(magnification: int) -> str:
    text = f"{CONFIDENCE:.0%} ellipses (χ²₂ = {chi2_quantile(CONFIDENCE, 2):.3f})"
    return text.replace("%", " %") + (f", drawn ×{magnification}" if magnification > 1 else "")


def _spans(points: Sequence[FloatArray | None]) -> tuple[float, float]:
    """Width and height of the bounding box of the finite (x, y) of all point sets."""
    stacked = [p[:, :2] for p in points if p is not None and p.size]
    xy = np.concatenate(stacked) if stacked else np.empty((0, 2))
    xy = xy[np.isfinite(xy).all(axis=1)]
    if xy.size == 0:
        return 0.0, 0.0
    width, height = xy.max(axis=0) - xy.min(axis=0)
    return float(width), float(height)


def _extent(points: Sequence[FloatArray | None]) -> float:
    return max(_spans(points))


def _map_height(spans: Sequence[tuple[float, float]], axes_width_in: float) -> float:
    """Height of a map axes of the given width that fits the widest data aspect, clamped."""
    ratios = [(h + 0.1 * max(w, h)) / (w + 0.1 * max(w, h)) for w, h in spans if max(w, h) > 0]
    ratio = max(ratios, default=0.6)
    return axes_width_in * min(max(ratio, 0.4), 1.25)


def _add_ellipses(
    axes: Axes,
    centres: FloatArray,
    widths: FloatArray,
    heights: FloatArray,
    angles: FloatArray,
    colours: Sequence[Any] | str,
    magnification: float,
    linestyle: str = "solid",
    linewidth: float = 0.8,
) -> None:
    """Outline ellipses in data units (one collection) and grow the data limits to hold them."""
    keep = np.isfinite(widths) & np.isfinite(heights) & np.isfinite(centres).all(axis=1)
    if not keep.any():
        return
    if not isinstance(colours, str):
        colours = [c for c, k in zip(colours, keep, strict=True) if k]
    widths, heights = widths[keep] * magnification, heights[keep] * magnification
    centres, angles = centres[keep], angles[keep]
    collection = EllipseCollection(
        widths,
        heights,
        angles,
        units="xy",
        offsets=centres,
        offset_transform=axes.transData,
        facecolors="none",
        edgecolors=colours,
        linewidths=linewidth,
        linestyles=linestyle,
        zorder=2,
    )
    axes.add_collection(collection, autolim=False)
    theta = np.radians(angles)
    half_x = 0.5 * np.hypot(widths * np.cos(theta), heights * np.sin(theta))
    half_y = 0.5 * np.hypot(widths * np.sin(theta), heights * np.cos(theta))
    half = np.column_stack((half_x, half_y))
    axes.update_datalim(np.concatenate((centres - half, centres + half)))
    axes.autoscale_view()


def _feature_ellipses(
    axes: Axes, features: _Features, colours: Sequence[Any] | str, magnification: float
) -> bool:
    """The features' 95 % ellipses (those with finite axes); whether any has a finite width."""
    _add_ellipses(
        axes,
        features.xy,
        features.widths,
        features.heights,
        features.angles,
        colours,
        magnification,
    )
    return bool(np.isfinite(features.widths).any())


def _rendezvous_poses(robot: _Robot, poses: FloatArray, tolerance: float) -> FloatArray:
    """Poses whose stamps are within ``tolerance`` of one of the robot's rendezvous stamps."""
    if robot.rendezvous_stamps.size == 0 or poses.shape[0] == 0:
        return np.empty((0, 3))
    order = np.argsort(robot.stamps)
    stamps = robot.stamps[order]
    matched = matching_stamp(stamps, robot.rendezvous_stamps, tolerance)
    return poses[order[np.unique(matched[matched >= 0])]]


def _sample_period(robots: Sequence[_Robot]) -> float:
    gaps = [np.diff(np.sort(r.stamps)) for r in robots if r.stamps.size]
    positive = np.concatenate(gaps) if gaps else np.empty(0)
    positive = positive[positive > 0]
    return float(np.median(positive)) if positive.size else 0.0


def _wrap(text: str, width: int = 34) -> str:
    return "\n".join(textwrap.wrap(text, width)) or text


def _key(label: str, **style: Any) -> Line2D:
    """A legend entry: a marker without a line unless ``style`` gives one."""
    return Line2D([], [], **{"ls": "none", **style}, label=label)


def axes_note(axes: Axes, text: str) -> None:
    """``text`` in the middle of ``axes``: why they show nothing."""
    axes.text(0.5, 0.5, text, transform=axes.transAxes, ha="center", va="center", color="0.4")


def _map_axes(axes: Axes, frame: str | None) -> None:
    axes.set_aspect("equal", adjustable="datalim")
    axes.set_xlabel(f"x in {frame} [m]" if frame else "x [m]")
    axes.set_ylabel(f"y in {frame} [m]" if frame else "y [m]")
    axes.grid(True, color="0.9", linewidth=0.6)
    axes.set_axisbelow(True)


def _start_marker(axes: Axes, poses: FloatArray, colour: str) -> None:
    axes.plot(
        poses[0, 0], poses[0, 1], marker="o", markersize=6, color=colour, mec="black", zorder=4
    )


def _draw_trajectory(axes: Axes, robot: _Robot, poses: FloatArray, tolerance: float) -> bool:
    """A robot's path with its first pose and its rendezvous poses (stamps within
    ``tolerance``) circled; whether any rendezvous pose was drawn."""
    axes.plot(poses[:, 0], poses[:, 1], color=robot.colour, linewidth=1.4, zorder=3)
    _start_marker(axes, poses, robot.colour)
    meeting = _rendezvous_poses(robot, poses, tolerance)
    if meeting.shape[0]:
        axes.plot(*meeting[:, :2].T, "o", ms=5, mfc="none", mec="black", mew=0.8, zorder=4)
    return bool(meeting.shape[0])


# --------------------------------------------------------------------------- figures


def draw_local_maps(result: CsamResult, path: str | Path, scenario: str | None = None) -> Path:
    """Paper fig. 5/6 (a, b): each robot's trajectory and features in its own frame ``G_r``."""
    parsed = _view(result, scenario)
    robots = parsed.robots
    columns = max(1, min(len(robots), 3))
    rows = max(1, math.ceil(len(robots) / columns))
    spans = [_spans([r.poses_local, r.features_local.xy]) for r in robots]
    panel_height = _map_height(spans, 0.85 * FIGURE_WIDTH_IN / columns) + 0.9
    figure = new_figure(1.3 + rows * panel_height)
    figure.suptitle(_title(parsed, "local maps before joining, each robot in its own frame"))
    grid = figure.subplots(rows, columns, squeeze=False)
    for axes in grid.ravel()[len(robots) :]:
        axes.set_visible(False)
    if not robots:
        axes_note(grid[0, 0], "no robots in the result")
        return save_figure(figure, path)

    # one magnification for every panel, so that panels compare
    extent = max(max(span) for span in spans)
    semi_major = np.concatenate([r.features_local.semi_major for r in robots])
    visible = VISIBLE_SEMI_AXIS_PX / (0.85 * FIGURE_WIDTH_IN * DPI / columns)
    magnification = ellipse_magnification(semi_major, extent, min_fraction=visible)
    tolerance = 0.5 * _sample_period(robots) or 1e-6
    drawn_ellipses = drawn_rendezvous = False
    for axes, robot in zip(grid.ravel(), robots, strict=False):
        _map_axes(axes, f"{robot.name}/map")
        axes.set_title(f"{robot.name} ({robot.alignment})", color=robot.colour, fontsize=10)
        poses = robot.poses_local
        features = robot.features_local
        if poses.shape[0] == 0 and features.xy.shape[0] == 0:
            axes_note(axes, "empty local map")
            continue
        if poses.shape[0]:
            drawn_rendezvous |= _draw_trajectory(axes, robot, poses, tolerance)
        if features.xy.shape[0]:
            axes.plot(*features.xy.T, ".", color="0.1", markersize=3, zorder=3)
            drawn_ellipses |= _feature_ellipses(axes, features, robot.colour, magnification)
        axes.autoscale_view()

    handles: list[Any] = [
        Line2D([], [], color=r.colour, linewidth=1.4, label=f"{r.name} trajectory") for r in robots
    ]
    handles.append(_key("first pose", marker="o", ms=6, color="0.7", mec="black"))
    if any(r.features_local.xy.shape[0] for r in robots):
        handles.append(_key("feature", marker=".", color="0.1", ms=5))
    if drawn_ellipses:
        handles.append(_key(_ellipse_label(magnification), marker="o", ms=9, mfc="none", mec="0.3"))
    if drawn_rendezvous:
        handles.append(_key("pose with a rendezvous", marker="o", ms=5, mfc="none", mec="black"))
    figure.legend(handles=handles, loc="outside lower center", ncols=min(len(handles), 4))
    return save_figure(figure, path)


def draw_heading_sigma(result: CsamResult, path: str | Path, scenario: str | None = None) -> Path:
    """Paper fig. 5/6 (c): heading standard deviation per sample before and after C-SAM."""
    parsed = _view(result, scenario)
    robots = parsed.robots
    figure = new_figure(5.2)
    axes = figure.subplots()
    axes.set_title(_title(parsed, "heading standard deviation before and after C-SAM"))
    axes.set_ylabel("heading std-dev σ_φ [deg]")
    axes.grid(True, color="0.9", linewidth=0.6)
    axes.set_axisbelow(True)
    if not robots:
        axes.set_xlabel("time [s]")
        axes_note(axes, "no robots in the result")
        return save_figure(figure, path)

    use_time = all(r.stamps.size for r in robots)
    t0 = min(float(np.min(r.stamps)) for r in robots) if use_time else 0.0
    if use_time:
        axes.set_xlabel("time [s]" if t0 == 0.0 else f"time since {t0:.3f} s [s]")
    else:
        axes.set_xlabel("sample")

    plotted: list[FloatArray] = []
    handles: list[Any] = []
    for robot in robots:
        label = (
            robot.name if robot.aligned else _wrap(f"{robot.name} pending: {robot.pending_reason}")
        )
        marker = ROBOT_MARKERS[parsed.robots.index(robot) % len(ROBOT_MARKERS)]
        handles.append(Line2D([], [], color=robot.colour, marker=marker, ms=5, label=label))
        for sigma, style in ((robot.sigma_local, "--"), (robot.sigma_joined, "-")):
            if sigma is None or sigma.size == 0:
                continue
            x = robot.stamps - t0 if use_time else np.arange(sigma.size, dtype=float)
            degrees = np.degrees(sigma)
            # markers every ~1/12 of the run, shifted per robot, tell overlapping curves apart
            step = max(1, sigma.size // 12)
            offset = (robots.index(robot) * step) // len(robots)
            axes.plot(
                x,
                degrees,
                style,
                color=robot.colour,
                linewidth=1.3,
                marker=marker,
                ms=4.5,
                markevery=(offset, step),
                zorder=3,
            )
            plotted.append(degrees)
    handles.append(Line2D([], [], color="0.2", ls="--", label="before C-SAM (local)"))
    handles.append(Line2D([], [], color="0.2", ls="-", label="after C-SAM (joined)"))

    stamps = [r.rendezvous_stamps for r in parsed.robots if r.rendezvous_stamps.size]
    if stamps and use_time:
        period = _sample_period(parsed.robots)
        intervals = group_stamps(np.concatenate(stamps), max_gap=2.5 * period)
        pad = 0.5 * period
        for start, end in intervals - t0:
            axes.axvspan(start - pad, end + pad, color="0.5", alpha=0.18, lw=0, zorder=1)
            for edge in (start - pad, end + pad):
                axes.axvline(edge, color="0.35", lw=0.7, ls=":", zorder=1)
        handles.append(Patch(color="0.5", alpha=0.3, label=f"rendezvous ({len(intervals)}×)"))
    else:
        reason = "poses have no stamps" if stamps else "no rendezvous in the result"
        handles.append(_key(f"rendezvous not marked:\n{reason}"))

    scale, limits = value_axis_scale(np.concatenate(plotted) if plotted else np.empty(0))
    axes.set_yscale(scale)
    if limits is not None:
        axes.set_ylim(*limits)
    if scale == "log":
        axes.set_ylabel("heading std-dev σ_φ [deg] (log scale)")
    axes.legend(handles=handles, loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=9)
    return save_figure(figure, path)


def draw_joined_map(
    result: CsamResult,
    path: str | Path,
    truth: ArrayLike | None = None,
    scenario: str | None = None,
) -> Path:
    """Paper fig. 5/6 (d): the joined map in the reference frame.

    ``truth``: true feature positions ``(F, 2)`` already in the reference frame, drawn as
    grey crosses underneath.
    """
    truth_xy = None if truth is None else np.asarray(truth, dtype=float)
    if truth_xy is not None and (truth_xy.ndim != 2 or truth_xy.shape[1] != 2):
        raise ValueError(f"truth: expected shape (N, 2), got {truth_xy.shape}")
    parsed = _view(result, scenario)
    frame = parsed.reference_frame
    aligned = [r for r in parsed.robots if r.aligned]
    bases = [r.base_node[None] for r in aligned if r.base_node is not None]
    drawn = [*(r.poses_joined for r in aligned), parsed.features.xy, truth_xy, *bases]
    figure = new_figure(max(4.5, _map_height([_spans(drawn)], 0.68 * FIGURE_WIDTH_IN) + 1.0))
    axes = figure.subplots()
    axes.set_title(_title(parsed, f"joined map in {frame}" if frame else "joined map"))
    _map_axes(axes, frame)
    colours = {r.name: r.colour for r in parsed.robots}
    aligned = [r for r in parsed.robots if r.aligned]
    pending = [r for r in parsed.robots if not r.aligned]
    features = parsed.features
    member_robots = [{robot_of_label(m) for m in members} for members in parsed.feature_members]
    multi = np.array([len(s) > 1 for s in member_robots], dtype=bool)
    feature_colours = [
        MULTI_ROBOT_COLOUR if len(s) > 1 else colours.get(next(iter(s), ""), UNKNOWN_COLOUR)
        for s in member_robots
    ]

    trajectories = [r.poses_joined for r in aligned if r.poses_joined is not None]
    extent = _extent([*trajectories, features.xy])
    visible = VISIBLE_SEMI_AXIS_PX / (0.68 * FIGURE_WIDTH_IN * DPI)
    magnification = ellipse_magnification(features.semi_major, extent, min_fraction=visible)
    arrow = 0.06 * extent if extent > 0 else 1.0
    tolerance = 0.5 * _sample_period(parsed.robots) or 1e-6
    handles: list[Any] = []

    if truth_xy is not None and truth_xy.shape[0]:
        axes.plot(*truth_xy.T, "x", color="0.6", ms=5, mew=0.9, zorder=1)
        handles.append(_key("true feature", marker="x", color="0.6"))

    drawn_rendezvous = False
    for robot in aligned:
        poses = robot.poses_joined
        label = f"{robot.name} ({robot.alignment})"
        if poses is None or poses.shape[0] == 0:
            label += ", no joined trajectory"
        else:
            drawn_rendezvous |= _draw_trajectory(axes, robot, poses, tolerance)
        handles.append(Line2D([], [], color=robot.colour, linewidth=1.4, label=label))
        if robot.base_node is not None:
            _draw_base_node(axes, robot, arrow, magnification)

    if features.xy.shape[0]:
        single = ~multi
        if single.any():
            axes.scatter(
                *features.xy[single].T,
                s=9,
                marker="o",
                c=[c for c, s in zip(feature_colours, single, strict=True) if s],
                linewidths=0,
                zorder=3,
            )
            handles.append(
                _key("feature of one robot (its colour)", marker="o", ms=4, color="0.45")
            )
        if multi.any():
            axes.scatter(
                *features.xy[multi].T,
                s=14,
                marker="D",
                color=MULTI_ROBOT_COLOUR,
                linewidths=0,
                zorder=5,
            )
            label = f"feature seen by several robots ({int(multi.sum())})"
            handles.append(_key(label, marker="D", ms=4, color=MULTI_ROBOT_COLOUR))
        if _feature_ellipses(axes, features, feature_colours, magnification):
            handles.append(
                _key(_ellipse_label(magnification), marker="o", ms=9, mfc="none", mec="0.3")
            )
    if any(r.base_node is not None for r in aligned):
        label = "base node G_r (x axis; y axis pale)"
        handles.append(_key(label, color="0.2", marker=">", ms=5, ls="-", lw=1.5))
    if any(r.poses_joined is not None and r.poses_joined.shape[0] for r in aligned):
        handles.append(_key("first pose", marker="o", ms=6, color="0.7", mec="black"))
    if drawn_rendezvous:
        handles.append(_key("pose with a rendezvous", marker="o", ms=5, mfc="none", mec="black"))
    for robot in pending:
        label = _wrap(f"{robot.name} pending: {robot.pending_reason}")
        handles.append(_key(label, color=robot.colour, ls=":", lw=1.4))
    if not aligned and features.xy.shape[0] == 0:
        axes_note(axes, "nothing joined yet")
    axes.autoscale_view()
    axes.legend(handles=handles, loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8)
    return save_figure(figure, path)


def _draw_base_node(axes: Axes, robot: _Robot, length: float, magnification: float) -> None:
    """Base node ``G_r`` as its frame axes (x solid, y pale) and its 95 % position ellipse."""
    assert robot.base_node is not None
    x, y, phi = robot.base_node
    for angle, alpha in ((phi, 1.0), (phi + 0.5 * np.pi, 0.45)):
        axes.annotate(
            "",
            xy=(x + length * np.cos(angle), y + length * np.sin(angle)),
            xytext=(x, y),
            arrowprops={"arrowstyle": "-|>", "color": robot.colour, "lw": 1.6, "alpha": alpha},
            zorder=6,
        )
    axes.annotate(
        f"G_{robot.name}",
        xy=(x, y),
        xytext=(-9 * np.cos(phi), -9 * np.sin(phi)),
        textcoords="offset points",
        ha="right" if np.cos(phi) > 0.3 else "left" if np.cos(phi) < -0.3 else "center",
        va="top" if np.sin(phi) > 0.3 else "bottom" if np.sin(phi) < -0.3 else "center",
        fontsize=8,
        color=robot.colour,
    )
    axes.update_datalim([(x - length, y - length), (x + length, y + length)])
    if robot.base_node_cov is not None:
        try:
            width, height, angle = ellipse_axes(robot.base_node_cov[:2, :2])
        except ValueError:
            raise SummaryError(
                f"robots.{robot.name}.base_node_cov: position block is not a finite symmetric "
                f"positive semi-definite matrix: {robot.base_node_cov.tolist()}"
            ) from None
        _add_ellipses(
            axes,
            robot.base_node[None, :2],
            width,
            height,
            angle,
            robot.colour,
            magnification,
            linestyle="dashed",
            linewidth=1.0,
        )


def draw_figure(
    name: str,
    result: CsamResult,
    out_dir: str | Path,
    truth: ArrayLike | None = None,
    scenario: str | None = None,
) -> Path:
    """Write the figure ``name`` (one of ``FIGURES``) into ``out_dir``."""
    path = Path(out_dir) / name
    if name == "local_maps.png":
        return draw_local_maps(result, path, scenario)
    if name == "heading_sigma.png":
        return draw_heading_sigma(result, path, scenario)
    if name == "joined_map.png":
        return draw_joined_map(result, path, truth=truth, scenario=scenario)
    raise ValueError(f"no figure {name!r}; the figures are {FIGURES}")


def draw_all(
    result: CsamResult,
    out_dir: str | Path,
    truth: ArrayLike | None = None,
    scenario: str | None = None,
) -> list[Path]:
    """Write every figure of ``FIGURES`` into ``out_dir``."""
    return [draw_figure(name, result, out_dir, truth, scenario) for name in FIGURES]


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m csam_ros.figures SUMMARY.json [OUT_DIR]``: draw every figure."""
    import argparse

    parser = argparse.ArgumentParser(description=main.__doc__)
    parser.add_argument("summary", type=Path)
    parser.add_argument("out_dir", type=Path, nargs="?")
    args = parser.parse_args(argv)
    summary = RunSummary.read(args.summary)
    out = args.out_dir or args.summary.parent
    for path in draw_all(summary.result, out, scenario=summary.scenario):
        print(path)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
