"""Score a C-SAM result (:class:`~csam_ros.core.joining.result.CsamResult`) against ground truth.

Metrics (all JSON-ready):

- ``landmark_error``: the estimated features of the joined map (every feature with a member
  from the reference robot or an aligned robot) are fitted onto the true feature positions by
  a rigid 2D alignment (rotation and translation, no scale; Kabsch), and the residual
  distances give RMSE and maximum. A feature's true id is the subject its members' labels
  name (the majority when an association mixed subjects; such features count as impure).
  Features of robots that are not aligned are in their own frames: ``pending_frames`` scores
  each such robot's features alone, with its own rigid alignment.
- ``association``: every pair of members of one feature is a predicted "same feature" pair;
  it is a true positive when both labels name the same subject. Recall is over all
  cross-robot pairs of labels that name the same subject and are both in the maps
  (``recall_aligned`` counts only pairs whose two robots are both in the joined map).
- ``robots``: per robot alignment status as reported by the run.
- ``trajectory_error`` (when the truth has trajectories): joined poses, mapped through the
  same rigid alignment, against the true poses interpolated at the pose stamps.
- ``timing_s``: passed through from the result.
"""

from __future__ import annotations

from collections import Counter
from itertools import combinations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from csam_ros.core.joining.result import CsamResult, FeatureResult, RobotResult
from csam_ros.core.model.log import GroundTruth
from csam_ros.core.model.se2 import wrap_angle

FloatArray = NDArray[np.float64]

ALIGNMENT_METHOD = (
    "rigid 2D alignment (rotation + translation, no scale; Kabsch) of the estimated features "
    "onto the ground truth, fitted over all scored features of the frame"
)


def kabsch_2d(source: ArrayLike, target: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Rotation ``R`` (2, 2) and translation ``t`` (2,) minimising ``sum |R s_i + t - t_i|^2``.

    One point gives the identity rotation (the heading is not determined); no point is an
    error.
    """
    source = np.asarray(source, dtype=float).reshape(-1, 2)
    target = np.asarray(target, dtype=float).reshape(-1, 2)
    if source.shape != target.shape:
        raise ValueError(f"kabsch_2d: source {source.shape} and target {target.shape} differ")
    if source.shape[0] == 0:
        raise ValueError("kabsch_2d: no point to align")
    source_mean, target_mean = source.mean(axis=0), target.mean(axis=0)
    if source.shape[0] == 1:
        return np.eye(2), target_mean - source_mean
    cross = (source - source_mean).T @ (target - target_mean)
    u, _, vt = np.linalg.svd(cross)
    reflection = np.sign(np.linalg.det(vt.T @ u.T)) or 1.0
    rotation = vt.T @ np.diag([1.0, reflection]) @ u.T
    return rotation, target_mean - rotation @ source_mean


def _split_member(member: str) -> tuple[str, int]:
    robot, sep, label = str(member).rpartition("/")
    if not sep or not robot:
        raise ValueError(f"feature member {member!r} is not '<robot>/<label>'")
    try:
        return robot, int(label)
    except ValueError as error:
        raise ValueError(f"feature member {member!r}: label {label!r} is not an integer") from error


def _subject(truth: GroundTruth, member: str) -> int | None:
    robot, label = _split_member(member)
    return truth.label_to_feature.get(robot, {}).get(label)


def _landmark_error(
    features: list[FeatureResult], truth: GroundTruth, positions: dict[int, FloatArray]
) -> dict:
    """Rigid-align the features onto the truth; RMSE, maximum and per-feature errors."""
    rows = []
    unscored = 0
    impure = 0
    for feature in features:
        subjects = [_subject(truth, m) for m in feature.members]
        known = [s for s in subjects if s is not None and s in positions]
        if not known:
            unscored += 1
            continue
        counts = Counter(known).most_common()
        best = max(n for _, n in counts)
        subject = min(s for s, n in counts if n == best)
        impure += len(counts) > 1
        xy = np.asarray(feature.xy, dtype=float).reshape(2)
        if not np.isfinite(xy).all():
            raise ValueError(f"feature {feature.members}: xy {xy.tolist()} is not finite")
        rows.append((list(feature.members), subject, xy))
    result: dict = {"method": ALIGNMENT_METHOD, "n_features": len(rows)}
    result["unscored_features"] = unscored
    result["impure_features"] = impure
    if not rows:
        result.update(rmse_m=None, max_m=None, transform=None, per_feature=[])
        return result
    estimated = np.array([r[2] for r in rows])
    true_xy = np.array([positions[r[1]] for r in rows])
    rotation, translation = kabsch_2d(estimated, true_xy)
    errors = np.linalg.norm(estimated @ rotation.T + translation - true_xy, axis=1)
    result.update(
        rmse_m=float(np.sqrt(np.mean(errors**2))),
        max_m=float(errors.max()),
        heading_determined=len(rows) >= 2,
        transform=[
            float(translation[0]),
            float(translation[1]),
            float(np.arctan2(rotation[1, 0], rotation[0, 0])),
        ],
        per_feature=[
            {"members": r[0], "subject": int(r[1]), "error_m": float(e)}
            for r, e in zip(rows, errors, strict=True)
        ],
    )
    return result


def _association(features: list[FeatureResult], truth: GroundTruth, joined: set[str]) -> dict:
    """Pairwise precision and recall of the members of features against the truth."""
    true_positives = false_positives = unscored = 0
    for feature in features:
        for a, b in combinations(feature.members, 2):
            sa, sb = _subject(truth, a), _subject(truth, b)
            if sa is None or sb is None:
                unscored += 1
            elif sa == sb:
                true_positives += 1
            else:
                false_positives += 1
    # Every label of the maps, grouped by the subject it names.
    by_subject: dict[int, list[str]] = {}
    for feature in features:
        for member in feature.members:
            subject = _subject(truth, member)
            if subject is not None:
                by_subject.setdefault(subject, []).append(member)
    predicted = {
        frozenset(pair) for feature in features for pair in combinations(feature.members, 2)
    }
    true_pairs = found = true_pairs_joined = found_joined = 0
    for members in by_subject.values():
        for a, b in combinations(sorted(set(members)), 2):
            robot_a, robot_b = _split_member(a)[0], _split_member(b)[0]
            if robot_a == robot_b:
                continue
            hit = frozenset((a, b)) in predicted
            true_pairs += 1
            found += hit
            if robot_a in joined and robot_b in joined:
                true_pairs_joined += 1
                found_joined += hit
    predicted_scored = true_positives + false_positives
    return {
        "predicted_pairs": predicted_scored,
        "true_positives": true_positives,
        "false_positives": false_positives,
        "false_negatives": true_pairs - found,
        "true_pairs": true_pairs,
        "unscored_pairs": unscored,
        "precision": true_positives / predicted_scored if predicted_scored else None,
        "recall": found / true_pairs if true_pairs else None,
        "recall_aligned": found_joined / true_pairs_joined if true_pairs_joined else None,
    }


def _trajectory_error(
    robots: dict[str, RobotResult],
    truth: GroundTruth,
    joined: set[str],
    transform: list[float] | None,
) -> dict | None:
    """Joined poses mapped by the landmark alignment vs the true poses at the same stamps."""
    if transform is None or not truth.trajectories:
        return None
    c, s = np.cos(transform[2]), np.sin(transform[2])
    rotation = np.array([[c, -s], [s, c]])
    result = {}
    for name in sorted(joined):
        robot = robots[name]
        if name not in truth.trajectories or robot.poses_joined is None:
            continue
        stamps = np.asarray(robot.stamps, dtype=float)
        poses = np.asarray(robot.poses_joined, dtype=float).reshape(-1, 3)
        true_stamps = np.asarray(truth.trajectory_stamps[name], dtype=float)
        true_poses = np.asarray(truth.trajectories[name], dtype=float)
        inside = (stamps >= true_stamps[0]) & (stamps <= true_stamps[-1])
        if not inside.any():
            continue
        stamps, poses = stamps[inside], poses[inside]
        true_xy = np.stack([np.interp(stamps, true_stamps, true_poses[:, k]) for k in (0, 1)], -1)
        true_phi = np.interp(stamps, true_stamps, np.unwrap(true_poses[:, 2]))
        xy = poses[:, :2] @ rotation.T + np.array(transform[:2])
        position = np.linalg.norm(xy - true_xy, axis=1)
        heading = np.abs(wrap_angle(poses[:, 2] + transform[2] - true_phi))
        result[name] = {
            "n_poses": int(stamps.size),
            "position_rmse_m": float(np.sqrt(np.mean(position**2))),
            "position_max_m": float(position.max()),
            "heading_rmse_rad": float(np.sqrt(np.mean(heading**2))),
        }
    return result


def _local_map_error(
    name: str, robot: RobotResult, truth: GroundTruth, positions: dict[int, FloatArray]
) -> dict:
    """RMSE, maximum and count of a robot's own local map (its features in its frame ``G_r``,
    before any joining) after a rigid alignment to the truth."""
    own = [
        FeatureResult([f"{name}/{int(label)}"], xy, np.zeros((2, 2)))
        for label, xy in zip(robot.feature_labels_local, robot.features_local, strict=True)
    ]
    error = _landmark_error(own, truth, positions)
    return {key: error[key] for key in ("rmse_m", "max_m", "n_features")}


def evaluate(result: CsamResult, truth: GroundTruth) -> dict:
    """Metrics of a C-SAM ``result`` against ``truth`` (JSON-ready)."""
    features = result.features
    for i, feature in enumerate(features):
        if not feature.members:
            raise ValueError(f"features[{i}] has no member")
    status = {name: robot.alignment for name, robot in result.robots.items()}
    joined = result.joined_robots()
    positions = {
        int(i): np.asarray(p, dtype=float)
        for i, p in zip(truth.feature_ids, truth.feature_positions, strict=True)
    }

    def robots_of(feature: FeatureResult) -> set[str]:
        return {_split_member(m)[0] for m in feature.members}

    joined_features = [f for f in features if robots_of(f) & joined]
    landmark = _landmark_error(joined_features, truth, positions)
    landmark["frame"] = result.reference_frame
    pending = {}
    for name in sorted(set(status) - joined):
        own = [f for f in features if robots_of(f) == {name}]
        if own:
            pending[name] = _landmark_error(own, truth, positions)
            pending[name]["frame"] = f"{name}/map"
    robots = {}
    for name in sorted(status):
        robots[name] = {"alignment": status[name], "joined": name in joined}
        own_map = result.robots[name]
        if len(own_map.features_local):
            robots[name]["local_map_error"] = _local_map_error(name, own_map, truth, positions)
    return {
        "landmark_error": landmark,
        "pending_frames": pending,
        "association": _association(features, truth, joined),
        "robots": robots,
        "n_joined": len(joined),
        "trajectory_error": _trajectory_error(
            result.robots, truth, joined, landmark.get("transform")
        ),
        "timing_s": dict(result.timing_s),
    }
