"""The local views: each local map's rendezvous part and feature cross covariance against the
dense inverse, the views and checks kept while a map stays the same, work in threads."""

from __future__ import annotations

import copy

import numpy as np
import pytest
from sam_problems import dense_inverse_at_estimate

from csam_ros.core.joining.config import CsamConfig
from csam_ros.core.joining.local_views import (
    LocalViewCache,
    in_threads,
    local_view,
    map_features,
)
from csam_ros.core.joining.pipeline import robot_map_from_local_map
from csam_ros.core.smoothing.local_map_build import build_local_map
from csam_ros.core.smoothing.robot_map import RobotMap
from csam_ros.datasets.scenario import load_scenario
from csam_ros.datasets.simulation import simulate


@pytest.fixture(scope="module")
def robot1() -> RobotMap:
    log = simulate(load_scenario("map_joining"), seed=1)
    return robot_map_from_local_map(build_local_map(log.robots["robot1"]))


def _dense_covariance(m: RobotMap) -> np.ndarray:
    return dense_inverse_at_estimate(m.problem)[1]


@pytest.mark.parametrize("kept", [4, 8])
def test_a_local_view_is_the_dense_covariance_of_its_rendezvous_poses_and_features(
    robot1: RobotMap, kept: int
) -> None:
    """The rendezvous part (``R^T R`` = the poses' marginal information) and ``P_l,rho``
    against the dense inverse: with three poses of four rendezvous poses (the others
    eliminated along the trajectory) and with one of eight (more feature than pose scalars:
    the covariance columns)."""
    m = robot1
    index = np.arange(len(m.pose_ids))
    poses = index[index % 4 != 0] if kept == 4 else index[index % 8 == 1]
    view = local_view(m, poses)
    dense = _dense_covariance(m)
    pose_columns = m.problem.scalar_indices(m.pose_ids[poses])
    feature_columns = m.problem.scalar_indices(m.feature_ids)
    assert (len(feature_columns) <= len(pose_columns)) == (kept == 4)  # which way
    root = view.part.sqrt_information
    block = dense[np.ix_(pose_columns, pose_columns)]
    np.testing.assert_allclose(np.linalg.inv(root.T @ root), block, rtol=1e-6, atol=1e-9)
    cross = dense[np.ix_(feature_columns, pose_columns)].reshape(len(m.feature_ids), 2, -1)
    np.testing.assert_allclose(view.cross, cross, rtol=1e-6, atol=1e-10)


def test_the_local_marginals_are_those_of_the_dense_inverse(robot1: RobotMap) -> None:
    view = local_view(robot1, np.array([3, 9]))
    view.factor.with_marginals()
    dense = _dense_covariance(robot1)
    headings = robot1.problem.scalar_indices(robot1.pose_ids)[2::3]
    np.testing.assert_allclose(view.factor.sigma_phi, np.sqrt(dense[headings, headings]), rtol=1e-6)
    xy = robot1.problem.scalar_indices(robot1.feature_ids).reshape(-1, 2)
    expected = dense[xy[:, :, None], xy[:, None, :]]
    np.testing.assert_allclose(view.factor.feature_covariances, expected, rtol=1e-6, atol=1e-12)


def test_a_map_without_rendezvous_poses_has_no_part_and_no_features_to_associate(
    robot1: RobotMap,
) -> None:
    view = local_view(robot1, np.zeros(0, dtype=np.int64))
    assert view.part is None and view.cross is None
    assert map_features(robot1, view) is None


def test_map_features_leave_out_the_labels_given(robot1: RobotMap) -> None:
    view = local_view(robot1, np.array([2, 5, 11]))
    every = map_features(robot1, view)
    left_out = [int(k) for k in robot1.feature_labels[:3]]
    fewer = map_features(robot1, view, left_out)
    assert every is not None and fewer is not None
    assert list(every.labels) == list(robot1.feature_labels)
    assert list(fewer.labels) == list(robot1.feature_labels[3:])
    np.testing.assert_array_equal(fewer.positions, every.positions[3:])
    np.testing.assert_array_equal(fewer.covariances, every.covariances[3:])


def test_a_view_and_a_check_are_kept_while_the_map_is_the_same_object(robot1: RobotMap) -> None:
    cache = LocalViewCache()
    poses = np.array([1, 4])
    first = cache.view(robot1, poses)
    assert cache.view(robot1, poses.copy()) is first
    assert (cache.built, cache.reused) == (1, 1)
    assert cache.view(robot1, np.array([1, 5])) is not first  # other rendezvous poses
    assert cache.view(copy.copy(robot1), np.array([1, 5])) is not first  # another map object
    assert (cache.built, cache.reused) == (3, 1)

    options = CsamConfig().consistency_options()
    check = cache.check(robot1, options)
    assert cache.check(robot1, options) is check
    assert cache.check(copy.copy(robot1), options) is not check
    assert (
        cache.check(robot1, CsamConfig(max_feature_outliers=0.1).consistency_options()) is not check
    )


def test_in_threads_keeps_the_order_of_its_items() -> None:
    assert in_threads(lambda k: k * k, list(range(20))) == [k * k for k in range(20)]
    assert in_threads(lambda k: k, []) == []
