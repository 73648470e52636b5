"""Covariances of a localisation with known landmarks."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from csam_ros.core.truth.localisation import chain_covariances


def test_chain_covariances_match_the_dense_inverse() -> None:
    rng = np.random.default_rng(1)
    n = 9
    information = np.zeros((3 * n, 3 * n))
    for k in range(n):
        a = rng.normal(size=(3, 3))
        information[3 * k : 3 * k + 3, 3 * k : 3 * k + 3] += a @ a.T + np.eye(3)
    for k in range(n - 1):
        j = rng.normal(size=(3, 6))
        information[3 * k : 3 * k + 6, 3 * k : 3 * k + 6] += j.T @ j
    dense = np.linalg.inv(information)
    cov, pair = chain_covariances(sp.csr_matrix(information), n)
    for k in range(n):
        np.testing.assert_allclose(cov[k], dense[3 * k : 3 * k + 3, 3 * k : 3 * k + 3], atol=1e-12)
    for k in range(n - 1):
        np.testing.assert_allclose(pair[k], dense[3 * k : 3 * k + 6, 3 * k : 3 * k + 6], atol=1e-12)
