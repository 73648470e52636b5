"""Algorithm 1's dense Newton matrix against the numerical Hessian of the cost."""

from __future__ import annotations

import numpy as np
from jacobians import numeric_hessian

from csam_ros.core.joining.connector import BASE_NODE, Connector
from csam_ros.core.joining.dense_newton import _connector_curvature, _dense_information
from csam_ros.core.sam.factors import POSE, LinearPrior
from csam_ros.core.sam.solver import Problem


def test_newton_matrix_is_the_hessian_of_the_cost() -> None:
    """``A^T A`` plus the connectors' curvature equals the numerical Hessian of the cost."""
    rng = np.random.default_rng(3)
    k = 5
    problem = Problem()
    poses = problem.add_variables(POSE, range(2 * k), rng.normal(0, 2, (2 * k, 3)))
    base = problem.add_variable(BASE_NODE, "b", rng.normal(0, 1, 3))
    prior_sqrt = np.triu(rng.normal(0, 1, (6 * k, 6 * k))) + 5 * np.eye(6 * k)
    problem.add_factor(LinearPrior(poses, [POSE] * 2 * k, rng.normal(0, 2, 6 * k), prior_sqrt))
    problem.add_factor(
        Connector(
            poses[:k],
            poses[k:],
            rng.normal(0, 3, (k, 2)),
            covariance=0.01 * np.eye(2),
            observed_bases=np.full(k, base),
        )
    )
    problem.add_factor(
        Connector(
            poses[k:],
            poses[:k],
            rng.normal(0, 3, (k, 2)),
            covariance=0.04 * np.eye(2),
            observer_bases=np.full(k, base),
        )
    )
    system = problem.normal_equations()
    x = problem.values.copy()
    system.linearize(x)
    newton = _dense_information(system) + _connector_curvature(problem, x, problem.dim)
    numeric = numeric_hessian(system, x)
    assert np.abs(_connector_curvature(problem, x, problem.dim)).max() > 1.0  # not trivial
    np.testing.assert_allclose(newton, numeric, atol=1e-4 * np.abs(numeric).max())
