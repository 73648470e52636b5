"""Closed-form cases of the evaluation of a C-SAM result against ground truth."""

from __future__ import annotations

import json

import numpy as np
import pytest

from csam_ros.core.joining.result import CsamResult, FeatureResult, RobotResult
from csam_ros.core.model.log import GroundTruth
from csam_ros.core.model.se2 import rotation
from csam_ros.core.truth.evaluation import evaluate, kabsch_2d

IDS = np.array([10, 11, 12, 13, 14])
POSITIONS = np.array([[0.0, 0.0], [4.0, 0.0], [4.0, 3.0], [0.0, 3.0], [2.0, 5.0]])
# robot1 labels subject s as s - 9 (1..5), robot2 as 15 - s (5..1): equal labels mean nothing
LABELS = {
    "robot1": {int(s) - 9: int(s) for s in IDS},
    "robot2": {15 - int(s): int(s) for s in IDS},
}


def truth(trajectories: bool = False) -> GroundTruth:
    gt = GroundTruth(IDS, POSITIONS, LABELS)
    if trajectories:
        stamps = np.linspace(0.0, 10.0, 11)
        gt.trajectory_stamps = {"robot1": stamps}
        gt.trajectories = {"robot1": np.stack([stamps, 0.5 * stamps, 0.1 * stamps], -1)}
    return gt


def rigid(points: np.ndarray, phi: float, t: tuple[float, float]) -> np.ndarray:
    return points @ rotation(phi).T + np.array(t)


def robot(name: str, alignment: str, stamps: np.ndarray | None = None, poses=None) -> RobotResult:
    """A robot of ``len(stamps)`` poses (none by default), joined ``poses`` when given."""
    stamps = np.zeros(0) if stamps is None else stamps
    n = len(stamps)
    return RobotResult(name, alignment, stamps, np.zeros((n, 3)), np.zeros(n), poses_joined=poses)


def summary(features: list[FeatureResult], status: dict[str, str] | None = None) -> CsamResult:
    status = status or {"robot1": "reference", "robot2": "aligned"}
    return CsamResult(
        reference_frame="robot1/map",
        robots={name: robot(name, s) for name, s in status.items()},
        features=features,
        associations=[],
        timing_s={"total": 1.5},
    )


def feature(members: list[str], xy) -> FeatureResult:
    return FeatureResult(members, np.asarray(xy, dtype=float), np.eye(2))


def joined_features(xy: np.ndarray) -> list[FeatureResult]:
    """Each subject one feature with both robots' labels."""
    return [
        feature([f"robot1/{s - 9}", f"robot2/{15 - s}"], p) for s, p in zip(IDS, xy, strict=True)
    ]


def test_kabsch_recovers_a_rigid_motion() -> None:
    rng = np.random.default_rng(0)
    source = rng.normal(size=(20, 2))
    target = rigid(source, 2.5, (3.0, -1.0))
    r, t = kabsch_2d(source, target)
    np.testing.assert_allclose(r, rotation(2.5), atol=1e-12)
    np.testing.assert_allclose(t, [3.0, -1.0], atol=1e-12)
    # a mirror image is not a rotation: the best proper rotation leaves residuals
    r, _ = kabsch_2d(source, source * np.array([1.0, -1.0]))
    assert np.linalg.det(r) == pytest.approx(1.0)
    with pytest.raises(ValueError, match="no point"):
        kabsch_2d(np.zeros((0, 2)), np.zeros((0, 2)))


def test_rotated_translated_copy_has_zero_error() -> None:
    estimate = rigid(POSITIONS, -0.7, (10.0, 5.0))
    metrics = evaluate(summary(joined_features(estimate)), truth())
    landmark = metrics["landmark_error"]
    assert landmark["rmse_m"] == pytest.approx(0.0, abs=1e-12)
    assert landmark["max_m"] == pytest.approx(0.0, abs=1e-12)
    assert landmark["n_features"] == 5
    assert "Kabsch" in landmark["method"] and "no scale" in landmark["method"]
    assert landmark["transform"][2] == pytest.approx(0.7)
    association = metrics["association"]
    assert association["precision"] == 1.0 and association["recall"] == 1.0
    assert association["true_pairs"] == 5
    assert metrics["timing_s"] == {"total": 1.5}
    json.dumps(metrics)


def test_known_offsets_give_known_rmse() -> None:
    # Offsets with zero mean and zero "torque" about the centroid leave the alignment at
    # identity: +d and -d along x on two features symmetric about the centroid's y.
    offsets = np.zeros((5, 2))
    offsets[1] = [0.0, 0.3]  # (4, 0)
    offsets[3] = [0.0, 0.3]  # (0, 3)
    offsets[0] = [0.0, -0.3]  # (0, 0)
    offsets[2] = [0.0, -0.3]  # (4, 3)
    estimate = POSITIONS + offsets
    # check that the optimal alignment is the identity for these offsets
    r, t = kabsch_2d(estimate, POSITIONS)
    np.testing.assert_allclose(r, np.eye(2), atol=1e-12)
    np.testing.assert_allclose(t, [0.0, 0.0], atol=1e-12)
    metrics = evaluate(summary(joined_features(rigid(estimate, 1.0, (2.0, 2.0)))), truth())
    assert metrics["landmark_error"]["rmse_m"] == pytest.approx(np.sqrt(4 * 0.09 / 5))
    assert metrics["landmark_error"]["max_m"] == pytest.approx(0.3)


def test_precision_recall_hand_made() -> None:
    xy = POSITIONS
    features = [
        # 10 correct pair
        feature(["robot1/1", "robot2/5"], xy[0]),
        # wrong: robot1's 11 with robot2's 12
        feature(["robot1/2", "robot2/3"], xy[1]),
        # 12 and 11 left unassociated on their other side
        feature(["robot1/3"], xy[2]),
        feature(["robot2/4"], xy[1]),
        # 13 correct pair
        feature(["robot1/4", "robot2/2"], xy[3]),
        # 14 only seen by robot1
        feature(["robot1/5"], xy[4]),
    ]
    association = evaluate(summary(features), truth())["association"]
    # predicted pairs: 3, true positives 2; true pairs: subjects 10, 11, 12, 13 = 4
    assert association["predicted_pairs"] == 3
    assert association["true_positives"] == 2
    assert association["false_positives"] == 1
    assert association["true_pairs"] == 4
    assert association["false_negatives"] == 2
    assert association["precision"] == pytest.approx(2 / 3)
    assert association["recall"] == pytest.approx(2 / 4)


def test_three_member_feature_counts_all_pairs() -> None:
    gt = truth()
    gt.label_to_feature["robot3"] = {7: 10}
    features = [feature(["robot1/1", "robot2/5", "robot3/7"], [0.0, 0.0])]
    status = {"robot1": "reference", "robot2": "aligned", "robot3": "aligned"}
    association = evaluate(summary(features, status), gt)["association"]
    assert association["true_positives"] == 3
    assert association["true_pairs"] == 3
    assert association["recall"] == 1.0


def test_pending_robot_scored_in_its_own_frame() -> None:
    features = [
        feature([f"robot1/{s - 9}"], p)
        for s, p in zip(IDS, rigid(POSITIONS, 0.3, (1.0, 0.0)), strict=True)
    ]
    # robot2's map is in its own frame, far away and rotated: it must not spoil robot1's score
    features += [
        feature([f"robot2/{15 - s}"], p)
        for s, p in zip(IDS[:3], rigid(POSITIONS[:3], 2.0, (50.0, 50.0)), strict=True)
    ]
    status = {"robot1": "reference", "robot2": "pending: one rendezvous measurement"}
    metrics = evaluate(summary(features, status), truth())
    assert metrics["landmark_error"]["n_features"] == 5
    assert metrics["landmark_error"]["rmse_m"] == pytest.approx(0.0, abs=1e-12)
    assert metrics["pending_frames"]["robot2"]["rmse_m"] == pytest.approx(0.0, abs=1e-12)
    assert metrics["robots"]["robot2"] == {
        "alignment": "pending: one rendezvous measurement",
        "joined": False,
    }
    assert metrics["n_joined"] == 1
    association = metrics["association"]
    assert association["true_pairs"] == 3 and association["recall"] == 0.0
    assert association["recall_aligned"] is None
    assert association["precision"] is None


def test_impure_and_unknown_features() -> None:
    features = joined_features(POSITIONS)
    features[0].members.append("robot1/2")  # robot1's subject 11 wrongly merged into 10
    features.append(feature(["robot1/99"], [0.0, 0.0]))  # no truth for label 99
    landmark = evaluate(summary(features), truth())["landmark_error"]
    assert landmark["impure_features"] == 1
    assert landmark["unscored_features"] == 1
    assert landmark["per_feature"][0]["subject"] == 10


def test_trajectory_error_uses_the_landmark_alignment() -> None:
    phi, t = 0.4, (3.0, -2.0)
    # estimate = truth expressed in a frame G with G (+) estimate = truth
    features = joined_features(rigid(POSITIONS - np.array(t), 0.0, (0.0, 0.0)) @ rotation(phi))
    gt = truth(trajectories=True)
    stamps = np.array([0.5, 2.0, 7.25])
    true_poses = np.stack([stamps, 0.5 * stamps, 0.1 * stamps], -1)
    local_xy = (true_poses[:, :2] - np.array(t)) @ rotation(phi)
    poses = np.column_stack([local_xy, true_poses[:, 2] - phi]) + np.array([0.1, 0.0, 0.0])
    s = summary(features)
    s.robots["robot1"] = robot("robot1", "reference", stamps, poses)
    error = evaluate(s, gt)["trajectory_error"]["robot1"]
    assert error["n_poses"] == 3
    assert error["position_rmse_m"] == pytest.approx(0.1)
    assert error["heading_rmse_rad"] == pytest.approx(0.0, abs=1e-12)


def test_bad_results_give_clear_errors() -> None:
    with pytest.raises(ValueError, match="not '<robot>/<label>'"):
        evaluate(summary([feature(["seven"], [0, 0])]), truth())
    with pytest.raises(ValueError, match="label 'x' is not an integer"):
        evaluate(summary([feature(["robot1/x"], [0, 0])]), truth())
    with pytest.raises(ValueError, match=r"features\[0\] has no member"):
        evaluate(summary([feature([], [0, 0])]), truth())
    with pytest.raises(ValueError, match="not finite"):
        evaluate(summary([feature(["robot1/1"], [np.nan, 0])]), truth())


def test_each_robot_local_map_is_scored_alone_in_its_own_frame() -> None:
    """A robot's local map (its features in its frame, before joining) gets its own rigid
    alignment: a rotated, shifted copy of the truth scores zero; with one feature 0.3 m off,
    the errors of the best rigid fit."""
    result = summary(joined_features(POSITIONS))
    r2 = result.robots["robot2"]
    r2.feature_labels_local = np.array([15 - int(s) for s in IDS])
    r2.features_local = rigid(POSITIONS, 1.1, (-7.0, 2.0))
    exact = evaluate(result, truth())["robots"]["robot2"]["local_map_error"]
    assert exact["n_features"] == 5
    assert exact["rmse_m"] == pytest.approx(0.0, abs=1e-12)
    assert exact["max_m"] == pytest.approx(0.0, abs=1e-12)

    r2.features_local[2] += rotation(1.1) @ np.array([0.3, 0.0])
    metrics = evaluate(result, truth())
    off = metrics["robots"]["robot2"]["local_map_error"]
    rot, shift = kabsch_2d(r2.features_local, POSITIONS)
    errors = np.linalg.norm(r2.features_local @ rot.T + shift - POSITIONS, axis=1)
    assert off["rmse_m"] == pytest.approx(np.sqrt(np.mean(errors**2)), abs=1e-12)
    assert off["max_m"] == pytest.approx(errors.max(), abs=1e-12)
    assert 0.1 < off["max_m"] < 0.3
    assert "local_map_error" not in metrics["robots"]["robot1"]  # no local features given
