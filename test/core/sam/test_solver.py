"""The sparse least-squares engine: GTSAM as oracle, LM safeguard, clear errors."""

import numpy as np
import pytest
from sam_problems import chain, mixed_problem

from csam_ros.core.model import se2
from csam_ros.core.sam import factors as f
from csam_ros.core.sam.covariance import marginal_covariance
from csam_ros.core.sam.solver import Problem, SolverOptions
from csam_ros.testing.gtsam_oracle import build_gtsam, gtsam_estimate, gtsam_marginal_covariance
from csam_ros.testing.landmark_problem import build_problem, simulate_landmark_problem


def test_gauss_newton_converges_and_backends_agree():
    p = mixed_problem()
    q = mixed_problem()
    report = p.solve()
    assert report.converged
    assert np.all(np.diff(report.cost_history) <= 0)
    q.solve(SolverOptions(backend="splu"))
    np.testing.assert_allclose(p.values, q.values, atol=1e-9)
    # At the optimum the gradient vanishes.
    system = p.normal_equations()
    system.linearize(p.values)
    system.factorize()
    assert np.abs(system.solve(system.gradient)).max() < 1e-6


def test_levenberg_marquardt_safeguard_recovers_from_a_bad_start():
    sim = simulate_landmark_problem(60, 8, 120, seed=3, area=6.0)
    good = build_problem(sim)
    good.solve()
    bad = build_problem(sim)
    rng = np.random.default_rng(1)
    start = bad.values.copy()
    start[3 * 60 :] += rng.normal(0, 3.0, len(start) - 3 * 60)  # landmarks metres off
    start[2 : 3 * 60 : 3] += rng.normal(0, 0.6, 60)  # headings far off
    bad.values = start
    report = bad.solve()
    assert report.converged
    assert np.all(np.diff(report.cost_history) <= 0)
    assert report.final_cost == pytest.approx(good.cost(), rel=1e-9)


def test_robust_kernel_limits_an_outlier():
    def solve(robust):
        p = Problem()
        ids = p.add_variables(f.POINT, ["l"], [[0.0, 0.0]])
        z = np.array([[1.0, 1.0], [1.1, 0.9], [0.9, 1.05], [8.0, -6.0]])
        p.add_factor(
            f.PointPrior(np.repeat(ids, 4), z, np.tile(np.eye(2) * 10, (4, 1, 1)), robust=robust)
        )
        p.solve()
        return p.value("l")

    plain, robust = solve(None), solve(f.Huber(1.0))
    assert np.linalg.norm(robust - [1.0, 1.0]) < 0.2 < np.linalg.norm(plain - [1.0, 1.0])


def flat_robust_problem(offset=0.95):
    """Six poses with exact odometry see one landmark twice each, at ``+-offset`` f.Cauchy
    scales across the truth: the truth is the minimum (by symmetry), where the cost's
    curvature in y is ``(1 - offset^2) / (1 + offset^2)`` of the reweighted model's."""
    rng = np.random.default_rng(1)
    truth = np.column_stack([np.arange(6.0), np.zeros(6), np.zeros(6)])
    p = Problem()
    x = p.add_variables(f.POSE, [("x", i) for i in range(6)], truth + rng.normal(0, 0.05, (6, 3)))
    landmark = p.add_variables(f.POINT, ["l"], [[3.2, 0.5]])
    p.add_factor(f.PosePrior(x[:1], truth[:1], np.eye(3) * 1e6))
    odometry = se2.between(truth[:-1], truth[1:])
    p.add_factor(f.RelativePose(x[:-1], x[1:], odometry, covariance=np.eye(3) * 1e-4))
    sigma = 0.1
    seen_from = np.repeat(np.arange(6), 2)
    z = se2.inverse_transform_point(truth[seen_from], np.array([3.0, 0.0]))
    z[:, 1] += np.tile([offset * sigma, -offset * sigma], 6)
    p.add_factor(
        f.PointObservation(
            x[seen_from],
            np.repeat(landmark, 12),
            z,
            covariance=np.eye(2) * sigma**2,
            robust=f.Cauchy(1.0),
        )
    )
    return p, truth


def test_extrapolation_speeds_up_reweighted_steps_on_a_flat_robust_cost():
    options = SolverOptions(max_iterations=100, relative_tolerance=1e-12)
    plain, truth = flat_robust_problem()
    report = plain.solve(options)
    assert not report.converged  # reweighting alone creeps (gain ratio near 2)
    reference, _ = flat_robust_problem()
    assert reference.solve(SolverOptions(max_iterations=5000, relative_tolerance=1e-15)).converged

    p, _ = flat_robust_problem()
    report = p.solve(SolverOptions(max_iterations=100, relative_tolerance=1e-12, max_step_scale=64))
    assert report.converged and report.iterations < 40
    assert report.extrapolations > 0
    assert np.all(np.diff(report.cost_history) <= 0)
    np.testing.assert_allclose(p.value("l"), [3.0, 0.0], atol=1e-6)
    np.testing.assert_allclose(p.values, reference.values, atol=1e-6)
    assert report.final_cost == pytest.approx(reference.cost(), rel=1e-12)
    ids = p.indices([("x", i) for i in range(6)])
    np.testing.assert_allclose(p.values_of(ids), truth, atol=1e-6)


def test_extrapolation_options_are_checked():
    with pytest.raises(ValueError, match="max_step_scale"):
        SolverOptions(max_step_scale=0.5)
    with pytest.raises(ValueError, match="extrapolation_gain"):
        SolverOptions(extrapolation_gain=1.0)
    with pytest.raises(ValueError, match="cost_tolerance"):
        SolverOptions(cost_tolerance=-1.0)


def test_cost_tolerance_stops_at_the_first_step_that_lowers_the_cost_less():
    """The creeping robust solve stops after its first accepted step whose cost decrease is
    below ``cost_tolerance``, that step taken."""
    tolerance = 1e-3
    creeping, _ = flat_robust_problem()
    history = creeping.solve(SolverOptions(max_iterations=100, relative_tolerance=0.0)).cost_history
    decreases = -np.diff(history)
    assert np.all(decreases > 0)
    first_small = int(np.argmax(decreases < tolerance))
    assert 0 < first_small < len(decreases) - 1  # neither the first step nor never

    p, _ = flat_robust_problem()
    report = p.solve(SolverOptions(max_iterations=100, cost_tolerance=tolerance))
    assert report.converged and report.reason == "cost decrease below tolerance"
    assert report.iterations == first_small + 1
    np.testing.assert_allclose(report.cost_history, history[: first_small + 2], rtol=1e-12)


def test_a_new_pose_like_kind_works_with_the_generic_factors():
    base = f.VariableKind("base_node", 3, angle_index=2)
    p = Problem()
    b = p.add_variable(base, "b", [0.0, 0.0, 3.0])
    p.add_factor(f.LinearPrior([b], [base], [1.0, 2.0, -3.1], np.eye(3)))
    p.solve()
    np.testing.assert_allclose(p.value("b"), [1.0, 2.0, -3.1], atol=1e-12)
    with pytest.raises(ValueError, match="kind base_node where a pose is expected"):
        p.add_factor(f.PosePrior([b], [[0, 0, 0]], np.eye(3)))


# -- GTSAM as oracle ----------------------------------------------------------------------------


def test_same_map_estimate_and_marginals_as_gtsam():
    gtsam = pytest.importorskip("gtsam")
    sim = simulate_landmark_problem(300, 20, 450, seed=5, area=12.0)
    problem = build_problem(sim)
    report = problem.solve()
    assert report.converged
    graph, values = build_gtsam(sim, identical=True)
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(1e-14)
    params.setAbsoluteErrorTol(1e-14)
    params.setMaxIterations(100)
    result = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
    assert graph.error(result) == pytest.approx(report.final_cost, rel=1e-9)
    poses, lms = gtsam_estimate(sim, result)
    ours_poses = problem.values_of(problem.indices([("x", i) for i in range(300)]))
    ours_lms = problem.values_of(problem.indices([("l", j) for j in range(len(lms))]))
    scale = np.abs(poses[:, :2]).max()
    np.testing.assert_allclose(ours_poses[:, :2], poses[:, :2], atol=1e-6 * scale)
    np.testing.assert_allclose(se2.wrap_angle(ours_poses[:, 2] - poses[:, 2]), 0, atol=1e-6)
    np.testing.assert_allclose(ours_lms, lms, atol=1e-6 * scale)

    keys = [("x", 0), ("x", 150), ("l", 3), ("x", 299), ("l", 11)]
    ours = marginal_covariance(problem, keys)
    theirs = gtsam_marginal_covariance(sim, graph, result, keys)
    np.testing.assert_allclose(np.diag(ours)[3:], np.diag(theirs)[3:], rtol=1e-6)
    np.testing.assert_allclose(
        ours[3:, 3:], theirs[3:, 3:], atol=1e-6 * np.abs(theirs[3:, 3:]).max()
    )
    # the gauge-fixed first pose: variance of the prior (1e-12) in both
    np.testing.assert_allclose(np.diag(ours)[:3], np.diag(theirs)[:3], rtol=1e-3)


# -- clear errors -------------------------------------------------------------------------------


def test_bad_variables_and_factors_are_rejected():
    p, ids = chain()
    with pytest.raises(ValueError, match="already exists"):
        p.add_variable(f.POSE, ("x", 1), [0, 0, 0])
    with pytest.raises(ValueError, match="not finite"):
        p.add_variable(f.POSE, "nan", [0, np.nan, 0])
    with pytest.raises(ValueError, match="must have shape"):
        p.add_variables(f.POINT, ["a", "b"], np.zeros((2, 3)))
    with pytest.raises(ValueError, match="unknown variable id"):
        p.add_factor(f.RelativePose([0], [7], np.zeros((1, 3)), np.eye(3)))
    with pytest.raises(ValueError, match="connects variable \\('x', 1\\) twice"):
        p.add_factor(
            f.RelativePose([0, 1], [1, 1], np.zeros((2, 3)), np.tile(np.eye(3), (2, 1, 1)))
        )
    with pytest.raises(ValueError, match="kind pose where a point is expected"):
        p.add_factor(f.PointPrior([0], [[0, 0]], np.eye(2)))
    with pytest.raises(KeyError, match="no variable 'zzz'"):
        p.index("zzz")
