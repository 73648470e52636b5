"""The selected inverse of a qdldl factor against the dense inverse, on factors whose
elimination trees are deep and whose supernodes are wide (loop closures fill them in)."""

from __future__ import annotations

import numpy as np
import pytest
from sam_problems import dense_inverse_at_estimate
from scipy import sparse

from csam_ros.core.model import se2
from csam_ros.core.sam import selected_inverse
from csam_ros.core.sam.factors import POSE, PosePrior, RelativePose
from csam_ros.core.sam.selected_inverse import SelectedInverse, _supernodes
from csam_ros.core.sam.solver import Problem


def _pose_graph(seed: int, poses: int, closures: int) -> Problem:
    """A random walk of ``poses`` with odometry and ``closures`` random loop closures,
    linearised and factored at a perturbed estimate."""
    rng = np.random.default_rng(seed)
    truth = np.cumsum(rng.normal(0.0, 0.5, size=(poses, 3)), axis=0)
    problem = Problem()
    ids = problem.add_variables(
        POSE, [("x", i) for i in range(poses)], truth + rng.normal(0.0, 0.05, (poses, 3))
    )
    problem.add_factor(PosePrior(ids[:1], truth[:1], covariance=np.eye(3) * 1e-2))
    rel = se2.between(truth[:-1], truth[1:])
    problem.add_factor(RelativePose(ids[:-1], ids[1:], rel, covariance=np.diag([1e-3, 2e-3, 3e-3])))
    if closures:
        a = rng.integers(0, poses, closures)
        b = (a + rng.integers(2, poses - 1, closures)) % poses
        between = se2.between(truth[a], truth[b])
        problem.add_factor(RelativePose(ids[a], ids[b], between, covariance=np.eye(3) * 1e-2))
    return problem


@pytest.mark.parametrize(("seed", "closures"), [(0, 0), (1, 5), (2, 40), (3, 200)])
def test_every_entry_on_the_pattern_equals_the_dense_inverse(seed: int, closures: int) -> None:
    problem = _pose_graph(seed, 80, closures)
    system, dense = dense_inverse_at_estimate(problem)
    inverse = SelectedInverse(system)
    pattern = system._factorization.factors()[0].tocsc()
    pattern.sort_indices()
    # the factor has the structure asked for: supernodes wider than a pose, a deep tree
    indptr, indices = pattern.indptr.astype(np.int64), pattern.indices.astype(np.int64)
    begins, ends, depth = _supernodes(indptr, indices, system.n)
    assert (depth == 0).sum() == 1  # one tree: the problem is connected
    widths = ends - begins + 1
    if closures == 0:  # a chain: a pose per supernode, about a level per pose
        assert np.median(widths) == 3 and depth.max() >= 70
    else:  # filled in: supernodes of more than one pose, still many levels
        assert widths.max() > 3 and depth.max() > 5
    coo = pattern.tocoo()
    rows, cols = inverse.perm[coo.row], inverse.perm[coo.col]
    atol = 1e-11 * np.abs(dense).max()
    np.testing.assert_allclose(inverse.entries(rows, cols), dense[rows, cols], rtol=1e-8, atol=atol)
    every = np.arange(system.n)
    np.testing.assert_allclose(inverse.entries(every, every), np.diag(dense), rtol=1e-8, atol=atol)


@pytest.mark.parametrize("compiled", [True, False])
def test_pattern_positions_find_each_entry_and_miss_the_others(
    compiled: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    if not compiled:  # the numpy search, for a scipy without its compiled lookup
        monkeypatch.setattr(selected_inverse, "_sample_offsets", None)
    rng = np.random.default_rng(4)
    n = 60
    dense = np.tril(rng.random((n, n)) < 0.2, -1)
    pattern = sparse.csc_matrix(dense.astype(float))
    pattern.sort_indices()
    columns, rows = rng.integers(0, n, 2000), rng.integers(0, n, 2000)
    found = selected_inverse.PatternPositions(pattern.indptr, pattern.indices)(columns, rows)
    on = dense[rows, columns]
    assert on.any() and (~on).any()
    np.testing.assert_array_equal(found[~on], -1)
    np.testing.assert_array_equal(pattern.indices[found[on]], rows[on])
    start = pattern.indptr[columns[on]]
    assert ((found[on] >= start) & (found[on] < pattern.indptr[columns[on] + 1])).all()
