"""Algorithm 1's sparse Newton solver: its matrix is the numerical Hessian of the cost, on the
normal equations' sparse pattern; it takes the dense oracle's steps; a singular system is an
error."""

from __future__ import annotations

import numpy as np
import pytest
from jacobians import numeric_hessian

from csam_ros.core.joining.connector import BASE_NODE, Connector
from csam_ros.core.joining.dense_newton import dense_newton
from csam_ros.core.joining.sparse_newton import SparseNewtonStep, block_pattern, sparse_newton
from csam_ros.core.sam.factors import POSE, LinearPrior
from csam_ros.core.sam.normal_equations import SingularProblemError
from csam_ros.core.sam.solver import Problem, SolverOptions


def _problem(seed: int, k: int = 5, prior_scale: float = 5.0) -> tuple[Problem, list]:
    """Two robots' poses (k each) under one dense prior each, connectors both ways through a
    base node; and the blocks (each robot's poses, the base node)."""
    rng = np.random.default_rng(seed)
    problem = Problem()
    first = problem.add_variables(POSE, range(k), rng.normal(0, 2, (k, 3)))
    second = problem.add_variables(POSE, range(k, 2 * k), rng.normal(0, 2, (k, 3)))
    base = problem.add_variable(BASE_NODE, "b", rng.normal(0, 1, 3))
    for ids in (first, second):
        root = np.triu(rng.normal(0, 1, (3 * k, 3 * k))) + prior_scale * np.eye(3 * k)
        problem.add_factor(LinearPrior(ids, [POSE] * k, rng.normal(0, 2, 3 * k), root))
    problem.add_factor(
        Connector(
            first,
            second,
            rng.normal(0, 3, (k, 2)),
            covariance=0.01 * np.eye(2),
            observed_bases=np.full(k, base),
        )
    )
    problem.add_factor(
        Connector(
            second[::2],
            first[::2],
            rng.normal(0, 3, (len(second[::2]), 2)),
            covariance=0.04 * np.eye(2),
            observer_bases=np.full(len(second[::2]), base),
        )
    )
    blocks = [problem.scalar_indices(ids) for ids in (first, second, [base])]
    return problem, blocks


def _symmetric(upper_data: np.ndarray, system) -> np.ndarray:
    n = system.n
    cols = np.repeat(np.arange(n), np.diff(system.indptr))
    out = np.zeros((n, n))
    out[system.indices, cols] = upper_data
    out[cols, system.indices] = upper_data
    return out


def test_newton_matrix_on_the_pattern_is_the_hessian_of_the_cost() -> None:
    problem, blocks = _problem(3)
    system = problem.normal_equations()
    x = problem.values.copy()
    system.linearize(x)
    step = SparseNewtonStep(problem, system, block_pattern(system, blocks))
    step.relinearised()
    newton = _symmetric(step.information + step.curvature, system)
    numeric = numeric_hessian(system, x)
    assert np.abs(step.curvature).max() > 1.0  # not trivial
    np.testing.assert_allclose(newton, numeric, atol=1e-4 * np.abs(numeric).max())


def test_sparse_newton_takes_the_dense_oracles_steps() -> None:
    options = SolverOptions(max_iterations=200)
    sparse, blocks = _problem(7, prior_scale=2.0)
    dense, _ = _problem(7, prior_scale=2.0)
    report, covariance_sparse = sparse_newton(sparse, options, blocks)
    keys = dense.keys
    oracle, covariance = dense_newton(dense, options, keys)
    assert report.converged and oracle.converged
    # the same accepted steps (they may part at the numerical minimum only, where a step
    # within rounding is taken by one and rejected by the other)
    shared = min(len(report.cost_history), len(oracle.cost_history))
    assert shared > 3
    np.testing.assert_allclose(
        report.cost_history[:shared], oracle.cost_history[:shared], rtol=1e-9
    )
    np.testing.assert_allclose(sparse.values, dense.values, atol=1e-9)
    np.testing.assert_allclose(covariance_sparse.dense(), covariance, rtol=1e-7, atol=1e-12)


def test_an_undetermined_base_node_is_singular() -> None:
    problem, blocks = _problem(5)
    problem.factors = problem.factors[:2]  # the priors only: the base node is free
    problem.add_factor(
        Connector(
            [0],
            [6],
            [[1.0, 0.0]],
            covariance=np.eye(2),
            observed_bases=[problem.index("b")],
        )
    )  # one row: two of the base node's three degrees of freedom
    with pytest.raises(SingularProblemError):
        sparse_newton(problem, SolverOptions(), blocks)
