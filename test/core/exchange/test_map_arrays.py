"""A map built from updates, checked and refined: from its held estimate, or from the robot's
map refined one update before (what a merger holds between solves)."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import pytest
from growing_joins import maps_until

from csam_ros.core.exchange.local_map_checks import LocalMapArrays
from csam_ros.core.exchange.map_arrays import (
    Refined,
    held_robot_map,
    refine_start,
    robot_map_arrays,
    robot_map_from_arrays,
    values_with,
)
from csam_ros.core.exchange.map_updates import (
    HeldMap,
    UpdateSender,
    apply_update,
)
from csam_ros.core.model import se2
from csam_ros.core.smoothing.robot_map import RobotMap
from csam_ros.datasets.scenario import load_scenario
from csam_ros.datasets.simulation import simulate


@dataclass
class Growth:
    """One robot's map at three moments, as an online smoother sends it (its optimum off by a
    few millimetres that stay between updates, as a capped solve leaves them; at the last
    moment a tenth of the poses moved 3 cm, beyond the update tolerance) and as a receiver of
    its updates holds it."""

    optimum: list[RobotMap]
    held: list[HeldMap]


def _as_sent(robot_map: RobotMap, moved: bool) -> LocalMapArrays:
    """The map's arrays off its optimum as a capped solve leaves it: each pose but the first
    by a few millimetres that vary slowly along the trajectory (the same at a stamp every
    time); when ``moved``, the poses of one stretch 3 cm further."""
    arrays = robot_map_arrays(robot_map)
    t = arrays.stamps
    off = 0.004 * np.column_stack([np.sin(t / 7.0), np.cos(t / 5.0) - 1.0, np.sin(t / 11.0)])
    if moved:
        off[(t > 10.0) & (t < 15.0), 1] += 0.03
    return replace(arrays, poses=arrays.poses + off)


@pytest.fixture(scope="module")
def growth() -> Growth:
    run = simulate(load_scenario("map_joining"), 1)
    end = max(r.odometry.stamps.max() for r in run.robots.values())
    sender = UpdateSender(3)
    optimum, held = [], []
    for k, t in enumerate((0.5 * end, 0.7 * end, 0.9 * end)):
        robot_map = maps_until(run, t)[0][1]
        optimum.append(robot_map)
        update = sender.update(_as_sent(robot_map, moved=k == 2))
        held.append(apply_update(held[-1] if held else None, update))
    return Growth(optimum, held)


def _held_problem(growth: Growth) -> RobotMap:
    """The last map as held, unrefined."""
    return robot_map_from_arrays(growth.optimum[-1].name, growth.held[-1].map.arrays())


def _last_refined(growth: Growth) -> Refined:
    """The map before the last as a merger refined it (from the one before)."""
    name = growth.optimum[0].name
    first = Refined(held_robot_map(name, growth.held[0]), growth.held[0].map)
    return Refined(held_robot_map(name, growth.held[1], last=first), growth.held[1].map)


def test_the_start_keeps_what_was_not_sent_again_at_its_refined_value(growth: Growth) -> None:
    last = _last_refined(growth)
    held, before = growth.held[2].map, last.held
    poses, features = refine_start(held, last)
    at = np.searchsorted(before.pose_stamps, held.pose_stamps)
    matched = at < len(before.pose_stamps)
    matched[matched] = before.pose_stamps[at[matched]] == held.pose_stamps[matched]
    unchanged = matched.copy()
    unchanged[matched] = np.all(before.poses[at[matched]] == held.poses[matched], axis=1)
    resent = matched & ~unchanged
    assert unchanged.any() and resent.any() and not matched.all()  # kept, sent again, new
    np.testing.assert_allclose(poses[unchanged], last.robot_map.poses[at[unchanged]], atol=1e-12)
    np.testing.assert_allclose(poses[resent], held.poses[resent], atol=1e-12)
    # a new pose: moved as the nearest pose before it that was held
    new = np.flatnonzero(~matched)
    k = new[-1]
    nearest = np.flatnonzero(matched[:k])[-1]
    correction = se2.compose(poses[nearest], se2.inverse(held.poses[nearest]))
    np.testing.assert_allclose(poses[k], se2.compose(correction, held.poses[k]), atol=1e-12)
    old = {int(label): k for k, label in enumerate(before.feature_labels)}
    for k, label in enumerate(held.feature_labels):
        j = old.get(int(label))
        if j is not None and np.array_equal(before.feature_xy[j], held.feature_xy[k]):
            np.testing.assert_array_equal(features[k], last.robot_map.feature_positions[j])
        else:
            np.testing.assert_array_equal(features[k], held.feature_xy[k])


def test_a_refine_from_the_last_map_ends_within_a_step_under_a_sigma(growth: Growth) -> None:
    """The start costs less than the held estimate, so the refine takes it, and stops at the
    first step that lowers the cost by less than 0.5: within that of the optimum of the map's
    factors, which the refine from the held estimate reaches (1e-6), and within 0.1 mm."""
    name = growth.optimum[0].name
    last = _last_refined(growth)
    now = _held_problem(growth)
    start = values_with(now, *refine_start(growth.held[2].map, last))
    assert now.problem.cost(start) < now.problem.cost()
    warm = held_robot_map(name, growth.held[2], last=last)
    cold = held_robot_map(name, growth.held[2])
    optimum = growth.optimum[2]
    for refined, tolerance in ((cold, 1e-6), (warm, 1e-4)):
        np.testing.assert_allclose(refined.poses, optimum.poses, atol=tolerance)
        np.testing.assert_allclose(
            refined.feature_positions, optimum.feature_positions, atol=tolerance
        )
    assert cold.problem.cost() <= warm.problem.cost() <= cold.problem.cost() + 0.5
    assert warm.problem.cost() < now.problem.cost(start)


def test_a_last_map_that_costs_more_is_not_taken(growth: Growth) -> None:
    """A last refined map far from the one held (here moved 5 m): the refine starts from the
    held estimate, exactly as without a last map."""
    name = growth.optimum[0].name
    last = _last_refined(growth)
    robot_map = last.robot_map
    moved = robot_map.problem.values.copy()
    moved[robot_map.problem.scalar_indices(robot_map.pose_ids)] += np.tile(
        [5.0, 0.0, 0.0], len(robot_map.pose_ids)
    )
    robot_map.problem.values = moved
    now = _held_problem(growth)
    start = values_with(now, *refine_start(growth.held[2].map, last))
    assert now.problem.cost(start) > now.problem.cost()
    from_far = held_robot_map(name, growth.held[2], last=last)
    cold = held_robot_map(name, growth.held[2])
    np.testing.assert_array_equal(from_far.problem.values, cold.problem.values)
