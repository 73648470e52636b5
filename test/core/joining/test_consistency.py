"""The local-map check before joining: a folded map stays pending, a feature whose
observations disagree is not associated, healthy maps pass untouched."""

from __future__ import annotations

import copy

import numpy as np
import pytest

from csam_ros.core.joining.config import CsamConfig
from csam_ros.core.joining.join import join_maps
from csam_ros.core.joining.pipeline import build_robot_maps
from csam_ros.core.model.log import MultiRobotLog
from csam_ros.core.smoothing.local_map_config import LocalMapConfig
from csam_ros.core.truth.evaluation import evaluate
from csam_ros.datasets.scenario import load_scenario
from csam_ros.datasets.simulation import simulate

WRONG_LOOP = 5  # features taken for others


@pytest.fixture(scope="module")
def chain() -> MultiRobotLog:
    return simulate(load_scenario("chain"), 1)


def wrong_loop(log: MultiRobotLog, robot: str, k: int) -> tuple[MultiRobotLog, list[int]]:
    """``robot`` takes the last ``k`` features it meets for the first ``k`` (a wrong loop
    closure); returns the log and the labels given twice."""
    bad = copy.deepcopy(log)
    features = bad.robots[robot].features
    first_seen = {
        int(label): features.stamps[features.labels == label].min()
        for label in np.unique(features.labels)
    }
    order = sorted(first_seen, key=first_seen.__getitem__)
    labels = features.labels.copy()
    for early, late in zip(order[:k], order[-k:], strict=True):
        labels[features.labels == late] = early
    features.labels = labels
    return bad, sorted(order[:k])


def test_healthy_maps_pass_and_join_as_without_the_check(chain) -> None:
    built = build_robot_maps(chain)
    checked = join_maps(built.maps, built.rendezvous_logs, CsamConfig())
    unchecked = join_maps(built.maps, built.rendezvous_logs, CsamConfig(check_local_maps=False))
    for name, robot in checked.robots.items():
        check = robot.local_check
        assert check is not None and check.passed, name
        assert check.trajectory_outliers == 0 and check.inconsistent_features == []
        assert check.observation_outliers <= 0.01 * check.observation_factors
        assert unchecked.robots[name].local_check is None
        np.testing.assert_array_equal(robot.poses_joined, unchecked.robots[name].poses_joined)
    assert len(checked.associations) == len(unchecked.associations)


def test_a_folded_map_stays_pending_and_the_others_join_as_without_it(chain) -> None:
    bad, _ = wrong_loop(chain, "robot4", WRONG_LOOP)
    # without a robust kernel the wrong loop folds the whole map
    built = build_robot_maps(bad, local_map=LocalMapConfig(robust_kernel=""))
    assert [m.name for m in built.maps][-1] == "robot4"
    unchecked = join_maps(built.maps, built.rendezvous_logs, CsamConfig(check_local_maps=False))
    assert unchecked.robots["robot4"].alignment == "aligned"  # joined, folded

    result = join_maps(built.maps, built.rendezvous_logs, CsamConfig())
    check = result.robots["robot4"].local_check
    assert check is not None and not check.passed
    assert check.trajectory_outliers > 0.5 * check.trajectory_factors
    assert result.robots["robot4"].alignment == f"pending: {check.reason}"
    assert any(n.text.startswith("robot4: inconsistent local map") for n in result.notes)

    others = join_maps(built.maps[:3], built.rendezvous_logs, CsamConfig())
    assert result.joined_robots() == others.joined_robots() == {"robot1", "robot2", "robot3"}
    for name in others.robots:
        np.testing.assert_allclose(
            result.robots[name].poses_joined, others.robots[name].poses_joined, atol=1e-9
        )
    assert [f.members for f in result.features] == [f.members for f in others.features]
    np.testing.assert_allclose(
        [f.xy for f in result.features], [f.xy for f in others.features], atol=1e-9
    )


def test_features_whose_observations_disagree_are_not_associated(chain) -> None:
    bad, given_twice = wrong_loop(chain, "robot4", WRONG_LOOP)
    # with the Cauchy kernel the trajectory holds and each doubled label splits
    built = build_robot_maps(bad, local_map=LocalMapConfig(robust_kernel="cauchy"))
    result = join_maps(built.maps, built.rendezvous_logs, CsamConfig())
    robot4 = result.robots["robot4"]
    assert robot4.alignment == "aligned" and robot4.local_check is not None
    assert robot4.local_check.passed
    assert robot4.local_check.inconsistent_features == given_twice
    members = {m for f in result.features if len(f.members) > 1 for m in f.members}
    assert not members & {f"robot4/{k}" for k in given_twice}
    assert evaluate(result, bad.truth)["association"]["precision"] == 1.0
