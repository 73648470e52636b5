"""The sparse least-squares engine: assembly, GTSAM as oracle, LM safeguard, clear errors."""

import numpy as np
import pytest

from csam_ros.core.model import se2
from csam_ros.core.sam.covariance import marginal_covariance
from csam_ros.core.sam.factors import (
    POINT,
    POSE,
    Cauchy,
    Huber,
    LinearPrior,
    PointObservation,
    PointPrior,
    PosePrior,
    RelativePose,
    RelativePosition,
    VariableKind,
)
from csam_ros.core.sam.solver import WIDE_FACTOR_ROWS, Problem, SingularProblemError, SolverOptions
from csam_ros.testing.gtsam_oracle import build_gtsam, gtsam_estimate, gtsam_marginal_covariance
from csam_ros.testing.landmark_problem import build_problem, simulate_landmark_problem


def mixed_problem(seed=0):
    """A small problem with every factor kind (and a robust kernel)."""
    rng = np.random.default_rng(seed)
    p = Problem()
    truth = np.zeros((8, 3))
    for i in range(1, 8):
        truth[i] = se2.compose(truth[i - 1], [1.0, 0.1, 0.3])
    lms = rng.uniform(-2, 6, (4, 2))
    x = p.add_variables(POSE, [("x", i) for i in range(8)], truth + rng.normal(0, 0.1, (8, 3)))
    other = p.add_variables(POSE, ["y0", "y1"], truth[[2, 5]] + [[0.5, 1.0, 0.2], [0.4, 1.1, 0.1]])
    l_ids = p.add_variables(POINT, [("l", j) for j in range(4)], lms + rng.normal(0, 0.2, (4, 2)))
    p.add_factor(PosePrior(x[:1], truth[:1], np.eye(3) * 100.0))
    z = se2.between(truth[:-1], truth[1:]) + rng.normal(0, 0.01, (7, 3))
    p.add_factor(RelativePose(x[:-1], x[1:], z, covariance=np.eye(3) * 1e-3))
    pi, li = np.meshgrid(np.arange(8), np.arange(4), indexing="ij")
    pi, li = pi.ravel(), li.ravel()
    zz = se2.inverse_transform_point(truth[pi], lms[li]) + rng.normal(0, 0.02, (32, 2))
    p.add_factor(
        PointObservation(x[pi], l_ids[li], zz, covariance=np.eye(2) * 4e-4, robust=Huber())
    )
    p.add_factor(PointPrior(l_ids[:1], lms[:1], np.eye(2) * 2.0))
    yt = truth[[2, 5]] + [[0.5, 1.0, 0.2], [0.4, 1.1, 0.1]]
    rel = se2.between(truth[[1, 6, 1]], yt[[0, 1, 1]])[:, :2]
    p.add_factor(RelativePosition(x[[1, 6, 1]], other[[0, 1, 1]], rel, covariance=np.eye(2) * 1e-2))
    m = rng.normal(size=(5, 5))
    p.add_factor(
        LinearPrior(
            [other[0], l_ids[2]], [POSE, POINT], np.r_[yt[0], lms[2]], np.triu(m) + 4 * np.eye(5)
        )
    )
    p.add_factor(PosePrior(other[1:], yt[1:], np.eye(3) * 10.0))
    return p


def dense_system(p):
    """Dense A (whitened Jacobian) and r, scattered row by row from each factor kind."""
    rows, rhs = [], []
    for f in p.factors:
        blocks = p._blocks(f, p.values)
        r, a, _ = f.whitened(blocks)
        cols = np.concatenate(
            [
                p.scalar_indices(f.variables[:, j]).reshape(len(f), -1)
                for j in range(f.variables.shape[1])
            ],
            axis=1,
        )
        for k in range(len(f)):
            for d in range(r.shape[1]):
                row = np.zeros(p.dim)
                np.add.at(row, cols[k], a[k, d])
                rows.append(row)
                rhs.append(r[k, d])
    return np.array(rows), np.array(rhs)


def test_normal_equations_equal_dense_product_of_whitened_jacobian():
    p = mixed_problem()
    system = p.normal_equations()
    cost = system.linearize(p.values)
    A, r = dense_system(p)
    upper = system.matrix().toarray()
    np.testing.assert_allclose(upper, np.triu(A.T @ A), rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(system.gradient, A.T @ r, rtol=1e-12, atol=1e-9)
    assert cost == pytest.approx(p.cost())


def test_wide_factor_is_assembled_like_the_dense_product():
    """A LinearPrior with more rows than WIDE_FACTOR_ROWS takes the matrix-product path."""
    p = mixed_problem(seed=1)
    rng = np.random.default_rng(4)
    ids = [p.index(("x", i)) for i in (6, 2, 4)] + [p.index(("l", 3))]
    rows = WIDE_FACTOR_ROWS + 7
    p.add_factor(
        LinearPrior(
            ids, [POSE, POSE, POSE, POINT], rng.normal(size=11), rng.normal(size=(rows, 11))
        )
    )
    system = p.normal_equations()
    cost = system.linearize(p.values)
    A, r = dense_system(p)
    np.testing.assert_allclose(system.matrix().toarray(), np.triu(A.T @ A), rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(system.gradient, A.T @ r, rtol=1e-12, atol=1e-9)
    assert cost == pytest.approx(p.cost())


def test_evaluate_then_assemble_leaves_the_system_alone_until_assembled():
    p = mixed_problem()
    system = p.normal_equations()
    system.linearize(p.values)
    hessian, gradient = system.hessian_data.copy(), system.gradient.copy()
    elsewhere = p.values + 0.1
    trial = system.evaluate(elsewhere)  # a trial step: nothing assembled yet
    np.testing.assert_array_equal(system.hessian_data, hessian)
    np.testing.assert_array_equal(system.gradient, gradient)
    assert trial.cost == pytest.approx(p.cost(elsewhere))
    system.assemble(trial)
    assembled, assembled_gradient = system.hessian_data.copy(), system.gradient.copy()
    assert not np.allclose(assembled_gradient, gradient)
    assert system.linearize(elsewhere) == trial.cost
    np.testing.assert_array_equal(system.hessian_data, assembled)
    np.testing.assert_array_equal(system.gradient, assembled_gradient)


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
        ids = p.add_variables(POINT, ["l"], [[0.0, 0.0]])
        z = np.array([[1.0, 1.0], [1.1, 0.9], [0.9, 1.05], [8.0, -6.0]])
        p.add_factor(
            PointPrior(np.repeat(ids, 4), z, np.tile(np.eye(2) * 10, (4, 1, 1)), robust=robust)
        )
        p.solve()
        return p.value("l")

    plain, robust = solve(None), solve(Huber(1.0))
    assert np.linalg.norm(robust - [1.0, 1.0]) < 0.2 < np.linalg.norm(plain - [1.0, 1.0])


def flat_robust_problem(offset=0.95):
    """Six poses with exact odometry see one landmark twice each, at ``+-offset`` Cauchy
    scales across the truth: the truth is the minimum (by symmetry), where the cost's
    curvature in y is ``(1 - offset^2) / (1 + offset^2)`` of the reweighted model's."""
    rng = np.random.default_rng(1)
    truth = np.column_stack([np.arange(6.0), np.zeros(6), np.zeros(6)])
    p = Problem()
    x = p.add_variables(POSE, [("x", i) for i in range(6)], truth + rng.normal(0, 0.05, (6, 3)))
    landmark = p.add_variables(POINT, ["l"], [[3.2, 0.5]])
    p.add_factor(PosePrior(x[:1], truth[:1], np.eye(3) * 1e6))
    odometry = se2.between(truth[:-1], truth[1:])
    p.add_factor(RelativePose(x[:-1], x[1:], odometry, covariance=np.eye(3) * 1e-4))
    sigma = 0.1
    seen_from = np.repeat(np.arange(6), 2)
    z = se2.inverse_transform_point(truth[seen_from], np.array([3.0, 0.0]))
    z[:, 1] += np.tile([offset * sigma, -offset * sigma], 6)
    p.add_factor(
        PointObservation(
            x[seen_from],
            np.repeat(landmark, 12),
            z,
            covariance=np.eye(2) * sigma**2,
            robust=Cauchy(1.0),
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


def test_a_new_pose_like_kind_works_with_the_generic_factors():
    base = VariableKind("base_node", 3, angle_index=2)
    p = Problem()
    b = p.add_variable(base, "b", [0.0, 0.0, 3.0])
    p.add_factor(LinearPrior([b], [base], [1.0, 2.0, -3.1], np.eye(3)))
    p.solve()
    np.testing.assert_allclose(p.value("b"), [1.0, 2.0, -3.1], atol=1e-12)
    with pytest.raises(ValueError, match="kind base_node where a pose is expected"):
        p.add_factor(PosePrior([b], [[0, 0, 0]], np.eye(3)))


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


def chain(n=3):
    p = Problem()
    ids = p.add_variables(POSE, [("x", i) for i in range(n)], np.zeros((n, 3)))
    return p, ids


def test_unconstrained_variable_is_named():
    p, ids = chain()
    p.add_factor(PosePrior(ids[:1], np.zeros((1, 3)), np.eye(3)))
    p.add_factor(RelativePose(ids[:1], ids[1:2], np.zeros((1, 3)), np.eye(3)))
    with pytest.raises(SingularProblemError, match=r"\('x', 2\).*not constrained by any factor"):
        p.solve()


def test_under_constrained_pose_is_named():
    p, ids = chain(2)
    p.add_factor(PosePrior(ids[:1], np.zeros((1, 3)), np.eye(3)))
    p.add_factor(RelativePosition(ids[:1], ids[1:], [[1.0, 0.0]], np.eye(2)))
    with pytest.raises(SingularProblemError, match=r"\('x', 1\).*rank 2 < 3"):
        p.solve()


def test_missing_gauge_is_reported():
    p, ids = chain()
    p.add_factor(RelativePose(ids[:-1], ids[1:], np.ones((2, 3)), np.tile(np.eye(3), (2, 1, 1))))
    with pytest.raises(SingularProblemError, match="singular.*gauge"):
        p.solve()


def test_bad_variables_and_factors_are_rejected():
    p, ids = chain()
    with pytest.raises(ValueError, match="already exists"):
        p.add_variable(POSE, ("x", 1), [0, 0, 0])
    with pytest.raises(ValueError, match="not finite"):
        p.add_variable(POSE, "nan", [0, np.nan, 0])
    with pytest.raises(ValueError, match="must have shape"):
        p.add_variables(POINT, ["a", "b"], np.zeros((2, 3)))
    with pytest.raises(ValueError, match="unknown variable id"):
        p.add_factor(RelativePose([0], [7], np.zeros((1, 3)), np.eye(3)))
    with pytest.raises(ValueError, match="connects variable \\('x', 1\\) twice"):
        p.add_factor(RelativePose([0, 1], [1, 1], np.zeros((2, 3)), np.tile(np.eye(3), (2, 1, 1))))
    with pytest.raises(ValueError, match="kind pose where a point is expected"):
        p.add_factor(PointPrior([0], [[0, 0]], np.eye(2)))
    with pytest.raises(KeyError, match="no variable 'zzz'"):
        p.index("zzz")
