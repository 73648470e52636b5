"""Warm starts: a join started from the previous one equals a cold join on the same inputs."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from growing_joins import largest_difference, maps_until

from csam_ros.core.joining.config import CsamConfig
from csam_ros.core.joining.join import join_maps
from csam_ros.core.joining.local_views import LocalViewCache
from csam_ros.core.joining.result import CsamResult
from csam_ros.core.joining.warm_start import WarmStart, carried_forward
from csam_ros.core.model import se2
from csam_ros.datasets.scenario import load_scenario
from csam_ros.datasets.simulation import simulate


@pytest.mark.parametrize("scenario", ["map_joining", "chain"])
def test_warm_equals_cold_over_growing_maps(scenario: str) -> None:
    log = simulate(load_scenario(scenario), 1)
    first = min(r.rendezvous.stamps.min() for r in log.robots.values() if len(r.rendezvous.stamps))
    end = max(r.odometry.stamps.max() for r in log.robots.values())
    config = CsamConfig(skip_missing_poses=True)
    cache = LocalViewCache()
    warm: CsamResult | None = None
    for t in np.arange(first + 2.0, end, 3.0):  # a solve every 3 s, as a merger does
        maps, logs = maps_until(log, float(t))
        cold = join_maps(maps, logs, config)
        warm = join_maps(maps, logs, config, previous=warm, cache=cache)
        assert largest_difference(cold, warm) < 1e-6, t
    assert len(warm.joined_robots()) == len(log.robots)
    assert cache.reused == 0  # every map grew between solves


@pytest.mark.parametrize("scenario", ["map_joining", "chain"])
def test_the_joint_solve_ahead_of_algorithm_2_is_the_join_without_it(scenario: str) -> None:
    """A warm join solves jointly beside Algorithm 2 on the previous associations; taken when
    Algorithm 2 finds them again, it is the same problem solved the same way as after it."""
    log = simulate(load_scenario(scenario), 1)
    first = min(r.rendezvous.stamps.min() for r in log.robots.values() if len(r.rendezvous.stamps))
    end = max(r.odometry.stamps.max() for r in log.robots.values())
    config = CsamConfig(skip_missing_poses=True)
    ahead: CsamResult | None = None
    after: CsamResult | None = None
    taken = []
    for t in np.arange(first + 2.0, end, 3.0):
        maps, logs = maps_until(log, float(t))
        ahead = join_maps(maps, logs, config, previous=ahead)
        after = join_maps(maps, logs, config, previous=after, overlap=False)
        assert largest_difference(ahead, after) == 0.0, t
        assert ahead.statistics["joint_iterations"] == after.statistics["joint_iterations"]
        assert after.statistics["joint_solve_ahead"] == 0.0
        taken.append(ahead.statistics["joint_solve_ahead"])
    # none without a previous join; taken where Algorithm 2 found the last associations again
    # (the simulated robots find new ones until late in the run)
    assert taken[0] == 0.0 and 1.0 in taken, taken


def test_a_cold_join_solves_ahead_on_the_associations_of_the_last_join() -> None:
    """Without a warm start (``csam.warm_start`` off) the last join's associations still
    start the joint solve ahead; the join is the cold one exactly."""
    log = simulate(load_scenario("map_joining"), 1)
    end = max(r.odometry.stamps.max() for r in log.robots.values())
    maps, logs = maps_until(log, float(end))
    cold = join_maps(maps, logs)
    assert cold.statistics["joint_solve_ahead"] == 0.0
    again = join_maps(maps, logs, last=cold)
    assert again.statistics["joint_solve_ahead"] == 1.0
    assert again.statistics["joint_warm_start"] == 0.0
    assert largest_difference(again, cold) == 0.0


def test_a_joint_solve_ahead_on_associations_not_found_again_is_not_taken() -> None:
    log = simulate(load_scenario("map_joining"), 1)
    end = max(r.odometry.stamps.max() for r in log.robots.values())
    maps, logs = maps_until(log, float(end))
    cold = join_maps(maps, logs)
    previous = join_maps(maps, logs, previous=cold)
    assert previous.statistics["joint_solve_ahead"] == 1.0
    merged = [f for f in previous.features if len(f.members) > 1]
    previous.features.remove(merged[0])  # the previous join without one association
    previous.features.extend(replace(merged[0], members=[m]) for m in merged[0].members)
    again = join_maps(maps, logs, previous=previous)
    assert again.statistics["joint_solve_ahead"] == 0.0
    assert largest_difference(again, join_maps(maps, logs, previous=previous, overlap=False)) == 0.0


def test_the_same_maps_again_reuse_their_views_and_change_nothing() -> None:
    log = simulate(load_scenario("map_joining"), 1)
    end = max(r.odometry.stamps.max() for r in log.robots.values())
    maps, logs = maps_until(log, float(end))
    cache = LocalViewCache()
    first = join_maps(maps, logs, previous=None, cache=cache)
    assert (cache.built, cache.reused) == (2, 0)
    again = join_maps(maps, logs, previous=first, cache=cache)
    assert (cache.built, cache.reused) == (2, 2)
    # both stop where the relative cost decrease falls below 1e-10 (CsamConfig): equal to the
    # 1e-6 of a converged solve (1.4e-8 on one machine, below 1e-8 on another, same code)
    assert largest_difference(first, again) < 1e-6
    assert again.statistics["joint_iterations"] <= 2
    # a new map object of one robot is a new view for that robot only
    maps[1] = replace(maps[1])
    join_maps(maps, logs, previous=again, cache=cache)
    assert (cache.built, cache.reused) == (3, 3)


def test_a_previous_result_of_another_reference_is_not_used() -> None:
    log = simulate(load_scenario("map_joining"), 1)
    end = max(r.odometry.stamps.max() for r in log.robots.values())
    maps, logs = maps_until(log, float(end))
    other = join_maps(maps[::-1], logs)
    cold = join_maps(maps, logs)
    warm = join_maps(maps, logs, previous=other)
    assert warm.reference == maps[0].name
    assert largest_difference(cold, warm) < 1e-9
    assert warm.statistics["joint_iterations"] == cold.statistics["joint_iterations"]


def test_a_warm_start_costlier_than_the_cold_one_is_not_taken() -> None:
    """Algorithm 1 and the joint solve start warm from a previous result when it costs less
    than their cold start; from one moved far off (maps that changed much since) they start
    cold, and the join is the cold one exactly."""
    log = simulate(load_scenario("map_joining"), 1)
    end = max(r.odometry.stamps.max() for r in log.robots.values())
    maps, logs = maps_until(log, float(end))
    cold = join_maps(maps, logs)
    good = join_maps(maps, logs, previous=cold)
    assert good.statistics["algorithm1_warm_start"] == good.statistics["joint_warm_start"] == 1.0
    off = np.array([3.0, -2.0, 1.0])
    for robot in cold.robots.values():  # the previous result, moved off
        robot.poses_joined = se2.compose(off, robot.poses_joined)
        robot.alignment_rendezvous_poses = robot.alignment_rendezvous_poses + off
        if robot.alignment_base_node is not None:
            robot.alignment_base_node = se2.compose(off, robot.alignment_base_node)
    cold.features[:] = [replace(f, xy=se2.transform_point(off, f.xy)) for f in cold.features]
    bad = join_maps(maps, logs, previous=cold)
    assert bad.statistics["algorithm1_warm_start"] == bad.statistics["joint_warm_start"] == 0.0
    again = join_maps(maps, logs)
    assert largest_difference(bad, again) == 0.0
    assert bad.statistics["joint_iterations"] == again.statistics["joint_iterations"]


def _previous(stamps: np.ndarray, corrections: np.ndarray) -> WarmStart:
    feature = (np.array([1.0, 2.0]), np.array([0.5, 0.5]))  # joined, local
    return WarmStart("robot1", {}, {"robot2": (stamps, corrections)}, {"robot2/4": feature})


def test_pose_start_carries_the_previous_corrections_to_the_new_local_poses() -> None:
    corrections = np.array([[2.0, -1.0, 0.3], [2.1, -1.05, 0.31]])  # joined (+) local^-1
    local = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.1], [2.0, 0.2, 0.2], [3.0, 0.5, 0.3]])
    previous = _previous(np.array([0.0, 0.5]), corrections)
    start = previous.pose_start("robot2", np.array([0.0, 0.5, 1.0, 1.5]), local, np.zeros(3), 1e-6)
    # held poses: their own correction; new poses: that of the last held pose
    expected = se2.compose(corrections[[0, 1, 1, 1]], local)
    np.testing.assert_allclose(start, expected, atol=1e-12)
    # a robot never joined before starts at its local map moved by the base node
    base = np.array([1.0, 1.0, 0.5])
    np.testing.assert_allclose(
        previous.pose_start("robot3", np.zeros(4), local, base, 1e-6),
        se2.compose(np.broadcast_to(base, (4, 3)), local),
    )


def test_pose_start_before_the_first_held_pose_uses_the_nearest_later_one() -> None:
    local = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [2.0, 0.0, 0.0]])
    correction = np.array([[5.0, 5.0, 0.5]])
    previous = _previous(np.array([2.0]), correction)
    start = previous.pose_start("robot2", np.array([1.0, 2.0, 3.0]), local, np.zeros(3), 1e-6)
    np.testing.assert_allclose(start, se2.compose(correction[[0, 0, 0]], local), atol=1e-12)


def test_feature_start_moves_the_joined_position_by_the_local_change() -> None:
    previous = _previous(np.zeros(1), np.zeros((1, 3)))
    base = np.array([0.0, 0.0, np.pi / 2])
    start = previous.feature_start(
        "robot2", np.array([4, 5]), np.array([[0.6, 0.5], [1.0, 0.0]]), base
    )
    # robot2/4 moved 0.1 along its x, which is the reference frame's y
    np.testing.assert_allclose(start, [[1.0, 2.1], [0.0, 1.0]], atol=1e-12)


def test_from_result_keeps_what_a_restart_needs() -> None:
    log = simulate(load_scenario("map_joining"), 1)
    end = max(r.odometry.stamps.max() for r in log.robots.values())
    maps, logs = maps_until(log, float(end))
    result = join_maps(maps, logs)
    warm = WarmStart.from_result(result)
    robot = result.robots["robot2"]
    stamps, corrections = warm.corrections["robot2"]
    np.testing.assert_allclose(se2.compose(corrections, robot.poses_local), robot.poses_joined)
    np.testing.assert_allclose(warm.base_nodes["robot2"], robot.alignment_base_node)
    assert "robot1" not in warm.base_nodes  # the reference has none
    assert len(warm.features) == sum(len(f.members) for f in result.features)


def test_rendezvous_start_carries_algorithm1s_moves_to_the_new_local_poses() -> None:
    """The rendezvous poses of the last join start where its Algorithm 1 moved them, a new
    one as the last before it; a robot without a previous Algorithm 1 at its local poses."""
    log = simulate(load_scenario("map_joining"), 1)
    end = max(r.odometry.stamps.max() for r in log.robots.values())
    maps, logs = maps_until(log, float(end))
    robot = join_maps(maps, logs).robots["robot2"]
    refined, stamps = robot.alignment_rendezvous_poses, robot.rendezvous_stamps
    assert refined is not None and len(stamps) > 1
    warm = WarmStart.from_result(join_maps(maps, logs))
    local = robot.poses_local[np.searchsorted(robot.stamps, stamps)]
    np.testing.assert_allclose(warm.rendezvous_start("robot2", stamps, local, 1e-6), refined)
    moved = local + [0.1, -0.2, 0.05]  # the local map changed since
    new = np.r_[stamps, stamps[-1] + 1.0]
    start = warm.rendezvous_start("robot2", new, np.r_[moved, moved[-1:]], 1e-6)
    correction = se2.compose(refined, se2.inverse(local))
    np.testing.assert_allclose(
        start,
        se2.compose(correction[np.r_[np.arange(len(stamps)), -1]], np.r_[moved, moved[-1:]]),
        atol=1e-12,
    )
    np.testing.assert_array_equal(warm.rendezvous_start("robot9", stamps, local, 1e-6), local)


def test_carried_forward_of_the_joined_maps_is_their_join() -> None:
    log = simulate(load_scenario("map_joining"), 1)
    end = max(r.odometry.stamps.max() for r in log.robots.values())
    maps, logs = maps_until(log, float(end))
    result = join_maps(maps, logs)
    carried = carried_forward(result, maps, CsamConfig().stamp_tolerance)
    assert any(len(f.members) > 1 for f in result.features)
    assert largest_difference(result, carried) < 1e-9
    assert [a.a for a in carried.associations] == [a.a for a in result.associations]


def test_carried_forward_places_grown_maps_by_the_last_join() -> None:
    """Poses held at the last join keep their correction, new ones take the last one; a
    feature seen since enters alone at its local position moved by the base node."""
    log = simulate(load_scenario("map_joining"), 1)
    end = max(r.odometry.stamps.max() for r in log.robots.values())
    config = CsamConfig(skip_missing_poses=True)
    before, logs = maps_until(log, float(end) - 10.0)
    last = join_maps(before, logs, config)
    now, _ = maps_until(log, float(end))
    carried = carried_forward(last, now, config.stamp_tolerance)
    assert carried.joined_robots() == last.joined_robots() == {"robot1", "robot2"}
    for m in now:
        robot, was = carried.robots[m.name], last.robots[m.name]
        held = len(was.stamps)
        np.testing.assert_array_equal(m.stamps[:held], was.stamps)
        correction = se2.compose(was.poses_joined, se2.inverse(was.poses_local))
        expected = se2.compose(correction[np.minimum(np.arange(len(m.stamps)), held - 1)], m.poses)
        np.testing.assert_allclose(robot.poses_joined, expected, atol=1e-12)
        assert len(robot.poses_joined) > held and np.all(np.isnan(robot.sigma_phi_local))
        np.testing.assert_array_equal(robot.base_node, was.base_node)
    members = {k for f in last.features for k in f.members}
    new = [f for f in carried.features if f.members[0] not in members]
    assert new and all(len(f.members) == 1 and np.isnan(f.cov).all() for f in new)
    for f in new:
        name, label = f.members[0].split("/")
        m = next(m for m in now if m.name == name)
        local = m.feature_positions[list(m.feature_labels).index(int(label))]
        base = carried.robots[name].base_node
        np.testing.assert_allclose(f.xy, se2.transform_point(base[None], local[None])[0])
    old = [f for f in carried.features if f.members[0] in members]
    assert len(old) == len(last.features)
    assert all(np.isfinite(f.cov).all() for f in old)


def test_carried_forward_keeps_a_robot_pending_until_a_join_places_it() -> None:
    log = simulate(load_scenario("map_joining"), 1)
    first = min(r.rendezvous.stamps.min() for r in log.robots.values() if len(r.rendezvous.stamps))
    maps, logs = maps_until(log, float(first) - 1.0)
    last = join_maps(maps, logs, CsamConfig(skip_missing_poses=True))
    assert last.joined_robots() == {"robot1"}
    later, _ = maps_until(log, float(first) + 5.0)
    carried = carried_forward(last, later, 1e-6)
    assert carried.robots["robot2"].alignment == last.robots["robot2"].alignment
    assert carried.robots["robot2"].poses_joined is None
    assert carried.joined_robots() == {"robot1"}
