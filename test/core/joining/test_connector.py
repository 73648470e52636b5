"""The connector factor's Jacobians against central differences."""

from __future__ import annotations

import numpy as np
import pytest

from csam_ros.core.joining.connector import BASE_NODE, Connector
from csam_ros.core.sam.factors import POSE
from csam_ros.core.sam.solver import Problem


@pytest.mark.parametrize(
    ("observer_base", "observed_base"), [(False, True), (True, False), (True, True)]
)
def test_connector_jacobians(observer_base: bool, observed_base: bool) -> None:
    rng = np.random.default_rng(5)
    k = 6
    problem = Problem()
    poses = problem.add_variables(POSE, range(2 * k), rng.normal(0, 2, (2 * k, 3)))
    bases = problem.add_variables(BASE_NODE, ["b0", "b1"], rng.normal(0, 2, (2, 3)))
    factor = Connector(
        poses[:k],
        poses[k:],
        rng.normal(0, 1, (k, 2)),
        covariance=np.eye(2),
        observer_bases=np.full(k, bases[0]) if observer_base else None,
        observed_bases=np.full(k, bases[1]) if observed_base else None,
    )
    blocks = problem._blocks(factor, problem.values)
    _, jac = factor.evaluate(blocks)
    for j, block in enumerate(blocks):
        numeric = np.zeros_like(jac[j])
        for d in range(block.shape[1]):
            step = np.zeros_like(block)
            step[:, d] = 1e-6
            plus = [b if i != j else block + step for i, b in enumerate(blocks)]
            minus = [b if i != j else block - step for i, b in enumerate(blocks)]
            numeric[:, :, d] = (factor.evaluate(plus)[0] - factor.evaluate(minus)[0]) / 2e-6
        np.testing.assert_allclose(jac[j], numeric, atol=1e-7)
