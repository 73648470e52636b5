"""Each joined robot's latest pose in the reference frame: its newest local pose composed with
its base node, and the covariance propagated to first order (checked against central
differences of the composition), on joins of a simulated run."""

from __future__ import annotations

import numpy as np
import pytest
from growing_joins import maps_until
from jacobians import numeric_block_jacobians
from log_slices import robot_log_between

from csam_ros.core.joining.config import CsamConfig
from csam_ros.core.joining.join import join_maps
from csam_ros.core.joining.pipeline import robot_map_from_local_map
from csam_ros.core.joining.result import CsamResult
from csam_ros.core.merging.robot_poses import (
    LatestPoseCovariances,
    composed,
    latest_pose_covariance,
    robot_poses,
)
from csam_ros.core.model import se2
from csam_ros.core.model.log import MultiRobotLog
from csam_ros.core.sam.covariance import marginal_covariance
from csam_ros.core.smoothing.local_map_build import build_local_map
from csam_ros.core.smoothing.robot_map import RobotMap
from csam_ros.datasets.scenario import load_scenario
from csam_ros.datasets.simulation import simulate

CONFIG = CsamConfig(skip_missing_poses=True)


@pytest.fixture(scope="module")
def run() -> MultiRobotLog:
    return simulate(load_scenario("map_joining"), 1)


def _first_rendezvous(log: MultiRobotLog) -> float:
    return min(float(r.rendezvous.stamps.min()) for r in log.robots.values())


@pytest.fixture(scope="module")
def joined(run: MultiRobotLog) -> tuple[CsamResult, dict[str, RobotMap]]:
    """A join halfway through the run (both robots aligned) and the maps it joined."""
    end = max(float(r.odometry.stamps.max()) for r in run.robots.values())
    maps, logs = maps_until(run, (_first_rendezvous(run) + end) / 2)
    result = join_maps(maps, logs, CONFIG)
    assert [result.robots[m.name].alignment for m in maps] == ["reference", "aligned"]
    return result, {m.name: m for m in maps}


def _spd(rng: np.random.Generator) -> np.ndarray:
    a = rng.normal(size=(3, 3))
    return a @ a.T + 0.1 * np.eye(3)


@pytest.mark.parametrize("heading", [0.3, np.pi - 1e-3, -2.5])
def test_the_covariance_is_propagated_through_the_compositions_jacobians(heading: float) -> None:
    """P = J_b S_b J_b^T + J_x S_x J_x^T, with J the central differences of b (+) x (also
    where the composed heading crosses pi); the pose is b (+) x."""
    rng = np.random.default_rng(int(abs(heading) * 1000))
    base = np.array([1.5, -2.0, heading])
    local = np.array([3.0, 0.7, 0.4])
    base_cov, local_cov = _spd(rng), _spd(rng)
    pose, cov = composed(base, base_cov, local, local_cov)
    j_base, j_local = numeric_block_jacobians(
        lambda blocks: se2.compose(blocks[0], blocks[1]), [base, local], angles=[2]
    )
    expected = j_base @ base_cov @ j_base.T + j_local @ local_cov @ j_local.T
    np.testing.assert_allclose(cov, expected, rtol=1e-7, atol=1e-9)
    np.testing.assert_array_equal(pose, se2.compose(base, local))
    np.testing.assert_array_equal(cov, cov.T)
    # the headings add: their variances do
    assert cov[2, 2] == pytest.approx(base_cov[2, 2] + local_cov[2, 2], rel=1e-12)


def test_the_latest_local_marginal_is_the_maps_own_and_the_map_is_only_read(joined) -> None:
    result, maps = joined
    m = maps["robot2"]
    values = m.problem.values.copy()
    cov = latest_pose_covariance(m)
    assert np.array_equal(m.problem.values, values)
    key = m.problem.key(int(m.pose_ids[-1]))
    np.testing.assert_allclose(cov, marginal_covariance(m.problem, [key]), rtol=1e-9, atol=0)
    sigma_phi = result.robots["robot2"].sigma_phi_local[-1]
    assert np.sqrt(cov[2, 2]) == pytest.approx(sigma_phi, rel=1e-6)
    assert np.all(np.linalg.eigvalsh(cov) > 0)


def test_a_joined_robots_pose_is_its_base_node_and_latest_local_pose(joined) -> None:
    """Of the map the join used: the join's base node composed with the join's own last local
    pose; the reference's is its local pose with its local marginal."""
    result, maps = joined
    poses = {p.robot: p for p in robot_poses(result, maps)}
    assert list(poses) == ["robot1", "robot2"]
    for name, p in poses.items():
        robot = result.robots[name]
        local_cov = latest_pose_covariance(maps[name])
        pose, cov = composed(robot.base_node, robot.base_node_cov, robot.poses_local[-1], local_cov)
        np.testing.assert_array_equal(p.pose, pose)
        np.testing.assert_array_equal(p.covariance, cov)
        assert p.stamp == robot.stamps[-1]
        assert np.all(np.linalg.eigvalsh(p.covariance) > 0)
    np.testing.assert_allclose(poses["robot1"].pose, result.robots["robot1"].poses_local[-1])
    np.testing.assert_allclose(poses["robot1"].covariance, latest_pose_covariance(maps["robot1"]))
    base_cov = result.robots["robot2"].base_node_cov
    assert poses["robot2"].covariance[2, 2] > base_cov[2, 2] > 0


def test_a_newer_local_map_is_placed_by_the_last_joins_base_node(run, joined) -> None:
    result, maps = joined
    end = max(float(r.odometry.stamps.max()) for r in run.robots.values())
    newer = dict(maps)
    newer["robot2"] = next(m for m in maps_until(run, end)[0] if m.name == "robot2")
    assert newer["robot2"].stamps[-1] > result.robots["robot2"].stamps[-1]
    (p,) = [p for p in robot_poses(result, newer) if p.robot == "robot2"]
    base = result.robots["robot2"].base_node
    np.testing.assert_array_equal(p.pose, se2.compose(base, newer["robot2"].poses[-1]))
    assert p.stamp == newer["robot2"].stamps[-1]
    base_cov = result.robots["robot2"].base_node_cov
    local = newer["robot2"].poses[-1]
    _, cov = composed(base, base_cov, local, latest_pose_covariance(newer["robot2"]))
    np.testing.assert_array_equal(p.covariance, cov)


def test_no_pose_for_a_pending_robot_or_a_restarted_map(run, joined) -> None:
    """A robot pending in the join has none; nor has one whose newest map starts later than
    the joined one (a restarted smoother's new frame, not placed yet)."""
    maps, logs = maps_until(run, _first_rendezvous(run) - 1.0)
    early = join_maps(maps, logs, CONFIG)
    assert early.robots["robot2"].alignment.startswith("pending")
    assert [p.robot for p in robot_poses(early, {m.name: m for m in maps})] == ["robot1"]
    result, held = joined
    restarted_log = robot_log_between(run.robots["robot2"], start=5.0, end=30.0)
    restarted = robot_map_from_local_map(build_local_map(restarted_log))
    poses = robot_poses(result, {**held, "robot2": restarted})
    assert [p.robot for p in poses] == ["robot1"]
    assert [p.robot for p in robot_poses(result, {"robot2": held["robot2"]})] == ["robot2"]


def test_the_covariances_are_computed_once_per_map(joined) -> None:
    _, maps = joined
    covariances = LatestPoseCovariances()
    first = covariances(maps["robot2"])
    assert covariances(maps["robot2"]) is first
    # a new map object (of the same content here) is a new map: computed again
    copy = RobotMap(**{k: getattr(maps["robot2"], k) for k in RobotMap.__dataclass_fields__})
    fresh = covariances(copy)
    assert fresh is not first
    np.testing.assert_array_equal(fresh, first)
