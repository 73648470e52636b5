"""A run scored against its ground truth (``csam evaluate``): ``metrics.json`` and the joined map
drawn over the true features."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from csam_ros.run.errors import RunError, warn

if TYPE_CHECKING:
    from csam_ros.core.joining.result import RunSummary
    from csam_ros.core.model.log import GroundTruth


@dataclass
class Evaluation:
    """A run directory's summary, its ground truth and the metrics written to it."""

    run_dir: Path
    summary: RunSummary
    truth: GroundTruth
    metrics: dict[str, Any]


def truth_of(run_dir: Path, source: str | None) -> GroundTruth | None:
    """The ground truth in the run's bag, or in the bag it replayed (``source``, the path as
    given to ``csam replay``: a relative one is relative to where replay ran, as is the
    current directory's). Only a bag is opened: RunError for anything else."""
    from csam_ros.bag import BagError, inspect_bag, read_bag_messages
    from csam_ros.ros.conversions import truth_from_message
    from csam_ros.ros.topics import FEATURES_TRUTH

    candidates = [(run_dir / "bag", "the run's bag")]
    if source:
        candidates.append((Path(source), "the source named in summary.json"))
    for bag, what in candidates:
        if not bag.exists():
            continue
        try:
            info = inspect_bag(bag)
        except BagError as err:
            raise RunError(f"{bag} ({what}) is not a readable bag: {err}") from None
        if FEATURES_TRUTH.name not in info.topics:
            continue
        for line in info.warnings:
            warn(line)
        for m in read_bag_messages(bag, [FEATURES_TRUTH.name], on_damage=warn):
            return truth_from_message(m.message)
    return None


def evaluate_run(run_dir: Path) -> Evaluation:
    """Score a run directory's ``summary.json`` against its ground truth; the metrics are
    written to ``metrics.json`` there."""
    from csam_ros.core.joining.result import RunSummary
    from csam_ros.core.truth.evaluation import evaluate

    summary_path = run_dir / "summary.json"
    if not summary_path.exists():
        raise RunError(f"{summary_path}: no such file (a run directory holds summary.json)")
    summary = RunSummary.read(summary_path)
    check_scorable(summary, summary_path)
    truth = truth_of(run_dir, summary.source)
    if truth is None:
        raise RunError(f"{run_dir}: no ground truth (/sim/features_truth) in the run's bag")
    try:
        metrics = evaluate(summary.result, truth)
    except ValueError as err:  # numpy's LinAlgError too
        raise RunError(f"{summary_path}: cannot be scored ({err})") from None
    (run_dir / "metrics.json").write_text(json.dumps(metrics, indent=1))
    return Evaluation(run_dir, summary, truth, metrics)


def check_scorable(summary: RunSummary, path: Path) -> None:
    """RunError naming ``path`` and the entry where the joined map's features cannot be scored
    or drawn: a member that is not ``<robot>/<label>``, a position that is not finite or
    beyond MAX_COORDINATE (1e9 m), as of no run; or a robot pose likewise."""
    from csam_ros.core.exchange.local_map_checks import MAX_COORDINATE

    result = summary.result
    for i, feature in enumerate(result.features):
        for member in feature.members:
            robot, slash, label = member.rpartition("/")
            if not slash or not robot or not label.removeprefix("-").isdigit():
                raise RunError(
                    f"{path}: features[{i}]: member {member!r:.60} is not <robot>/<label>"
                )
    checked = [(f"features[{i}].xy", f.xy) for i, f in enumerate(result.features)]
    for name, robot in result.robots.items():
        checked += [(f"robots.{name}.poses_joined", robot.poses_joined)]
        checked += [(f"robots.{name}.features_local", robot.features_local)]
    for where, values in checked:
        numbers = np.asarray(values if values is not None else [], dtype=float)
        if not (np.isfinite(numbers) & (np.abs(numbers) <= MAX_COORDINATE)).all():
            raise RunError(
                f"{path}: {where}: a value that is not a finite number within {MAX_COORDINATE:g} m"
            )


def _ratio(value: float | None) -> str:
    return "n/a" if value is None else f"{value:.3f}"


def evaluation_lines(evaluation: Evaluation) -> list[str]:
    """What the metrics say: the landmarks' error, the associations' precision and recall and
    each robot's alignment."""
    metrics = evaluation.metrics
    error, assoc = metrics["landmark_error"], metrics["association"]
    lines = [f"{evaluation.run_dir}/metrics.json"]
    if error["rmse_m"] is None:
        lines.append("  landmarks: no feature of the joined map could be scored")
    else:
        lines.append(
            f"  landmarks: RMSE {error['rmse_m']:.3f} m, max {error['max_m']:.3f} m over "
            f"{error['n_features']} features (after a rigid 2D alignment to the truth)"
        )
    lines.append(
        f"  associations: precision {_ratio(assoc['precision'])}, "
        f"recall {_ratio(assoc['recall'])} "
        f"({assoc['true_positives']} of {assoc['true_pairs']} true pairs)"
    )
    for name, robot in metrics["robots"].items():
        own = robot.get("local_map_error") or {}
        alone = (
            f"; its local map alone: RMSE {own['rmse_m']:.3f} m, max {own['max_m']:.3f} m"
            if own.get("rmse_m") is not None
            else ""
        )
        lines.append(f"  {name}: {robot['alignment']}{alone}")
    return lines


def draw_over_truth(evaluation: Evaluation) -> Path | None:
    """``joined_map.png`` in the run directory: the joined map over the true features, brought
    into its reference frame by the inverse of the scoring alignment (None: no alignment)."""
    transform = evaluation.metrics["landmark_error"].get("transform")
    if transform is None:
        return None
    from csam_ros.core.model import se2
    from csam_ros.figures.draw import draw_joined_map

    true_xy = se2.inverse_transform_point(np.asarray(transform), evaluation.truth.feature_positions)
    summary = evaluation.summary
    return draw_joined_map(
        summary.result,
        evaluation.run_dir / "joined_map.png",
        truth=true_xy,
        scenario=summary.scenario,
    )
