"""Simulated landmark problems: asked sizes, every landmark seen, dead-reckoning start; this
project's problem built from them; the incremental policy's optimum; files."""

import numpy as np
import pytest

from csam_ros.core.model import motion, se2
from csam_ros.testing.landmark_problem import (
    build_problem,
    read_graph,
    save_graph,
    simulate_landmark_problem,
    solve_incremental,
)


@pytest.fixture(scope="module")
def sim():
    return simulate_landmark_problem(200, 10, 300, seed=2, area=8.0)


def test_simulated_problem_has_the_asked_sizes_and_sees_every_landmark(sim):
    assert sim.truth_poses.shape == (200, 3) and sim.truth_landmarks.shape == (10, 2)
    assert len(sim.obs_pose) == len(sim.obs_landmark) == len(sim.obs_range) == 300
    assert set(sim.obs_landmark.tolist()) == set(range(10))
    assert np.all(np.diff(sim.obs_pose) >= 0)  # in pose order
    # measured near the truth: within 5 sigma of the true range and bearing
    local = se2.inverse_transform_point(
        sim.truth_poses[sim.obs_pose], sim.truth_landmarks[sim.obs_landmark]
    )
    true_range = np.hypot(local[:, 0], local[:, 1])
    true_bearing = np.arctan2(local[:, 1], local[:, 0])
    assert np.all(np.abs(sim.obs_range - true_range) < 5 * sim.sigma_range)
    assert np.all(np.abs(se2.wrap_angle(sim.obs_bearing - true_bearing)) < 5 * sim.sigma_bearing)
    assert np.all(true_range < 5.0)
    # the start is dead reckoning of the odometry from the true first pose
    np.testing.assert_allclose(
        sim.initial_poses, motion.dead_reckoning(sim.odometry, sim.truth_poses[0])
    )


def test_too_few_observations_are_refused():
    with pytest.raises(ValueError, match="cannot see"):
        simulate_landmark_problem(50, 20, 10, seed=1, area=5.0)


def test_built_problem_holds_every_measurement_and_improves_on_the_start(sim):
    problem = build_problem(sim)
    g = sim.graph()
    assert len(problem.values) == 3 * 200 + 2 * 10
    assert [len(f) for f in problem.factors] == [1, 199, 300]  # gauge, odometry, observations
    np.testing.assert_array_equal(problem.factors[2].measured, g.obs_xy)
    np.testing.assert_array_equal(problem.values[: 3 * 200].reshape(-1, 3), g.initial_poses)
    start = problem.cost()
    report = problem.solve()
    assert report.converged and problem.cost() < 0.1 * start
    # at the optimum the residuals are of the size of the noise: cost near half the degrees of
    # freedom (measurement rows minus unknowns)
    rows = 3 + 3 * 199 + 2 * 300
    dof = rows - len(problem.values)
    assert 0.25 * dof < problem.cost() < 1.0 * dof


def test_incremental_policy_reaches_the_batch_optimum(sim):
    batch = build_problem(sim)
    batch.solve()
    problem, iterations, _ = solve_incremental(sim.graph(), 50, 1e-10, 50)
    assert iterations > 0
    np.testing.assert_allclose(problem.values, batch.values, atol=1e-7)


def test_graph_round_trip(tmp_path):
    g = simulate_landmark_problem(50, 5, 60, seed=1, area=5.0).graph()
    save_graph(g, tmp_path / "g.npz")
    h = read_graph(tmp_path / "g.npz")
    assert h.name == g.name
    for field, value in vars(g).items():
        if field != "name":
            np.testing.assert_array_equal(getattr(h, field), value, err_msg=field)
