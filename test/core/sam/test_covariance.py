"""Selected marginal covariances and marginal square-root information against dense algebra."""

import numpy as np
import pytest

from csam_ros.core.sam.covariance import (
    _elimination_tree,
    _reach,
    covariance_by_elimination,
    covariance_columns,
    factorize_at_estimate,
    marginal_covariance,
    marginal_covariances,
    marginal_sqrt_information,
)
from csam_ros.testing.landmark_problem import build_problem, simulate_landmark_problem


@pytest.fixture(scope="module")
def solved():
    sim = simulate_landmark_problem(120, 10, 200, seed=2, area=8.0)
    problem = build_problem(sim)
    problem.solve()
    system = factorize_at_estimate(problem)
    info = system.matrix().toarray()
    info = info + np.triu(info, 1).T
    return problem, system, info


def test_joint_marginal_with_cross_terms_equals_dense_inverse(solved):
    problem, system, info = solved
    keys = [("l", 4), ("x", 7), ("x", 119), ("l", 0)]
    cov = marginal_covariance(problem, keys, system)
    cols = problem.scalar_indices(problem.indices(keys))
    dense = np.linalg.inv(info)[np.ix_(cols, cols)]
    np.testing.assert_allclose(cov, dense, rtol=1e-8, atol=1e-12 * np.abs(dense).max())
    blocks = marginal_covariances(problem, keys, system)
    np.testing.assert_allclose(blocks[1], dense[2:5, 2:5], rtol=1e-8)
    np.testing.assert_allclose(blocks[3], dense[8:10, 8:10], rtol=1e-8)


def test_reach_is_the_union_of_the_tree_paths_to_the_roots():
    parent = np.array([2, 2, 4, 4, -1, -1])  # 0, 1 -> 2 -> 4 <- 3; 5 alone
    np.testing.assert_array_equal(_reach(parent, np.array([0])), [0, 2, 4])
    np.testing.assert_array_equal(_reach(parent, np.array([3, 1])), [1, 2, 3, 4])
    np.testing.assert_array_equal(_reach(parent, np.array([5])), [5])


def test_single_variables_whose_solve_reaches_part_of_the_factor(solved):
    problem, system, info = solved
    lower, _, perm = system._factorization.factors()
    parent = _elimination_tree(lower.tocsc())
    inverse_perm = np.argsort(perm)
    dense = np.linalg.inv(info)
    partial = 0
    for key in [("x", 0), ("x", 40), ("x", 80), ("x", 119), ("l", 3), ("l", 9)]:
        cols = problem.scalar_indices(problem.indices([key]))
        partial += len(_reach(parent, inverse_perm[cols])) < problem.dim
        cov = marginal_covariance(problem, [key], system)
        expected = dense[np.ix_(cols, cols)]
        np.testing.assert_allclose(cov, expected, rtol=1e-8, atol=1e-12 * np.abs(expected).max())
    assert partial > 0  # the restriction is exercised, not only the whole factor


def test_splu_backend_gives_the_same_covariance(solved):
    problem, _, info = solved
    keys = [("x", 50), ("l", 2)]
    cov = marginal_covariance(problem, keys, factorize_at_estimate(problem, "splu"))
    cols = problem.scalar_indices(problem.indices(keys))
    np.testing.assert_allclose(cov, np.linalg.inv(info)[np.ix_(cols, cols)], rtol=1e-8)
    problem.normal_equations("qdldl")  # restore the default backend for other tests


def test_marginal_sqrt_information_is_last_block_of_r_with_keys_ordered_last(solved):
    problem, system, info = solved
    keys = [("x", 30), ("x", 90), ("l", 5)]
    r_s, order = marginal_sqrt_information(problem, keys, system)
    assert order == keys
    assert np.allclose(np.tril(r_s, -1), 0)
    assert np.all(np.diag(r_s) > 0)
    last = problem.scalar_indices(problem.indices(keys))
    rest = np.setdiff1d(np.arange(problem.dim), last)
    perm = np.concatenate([rest, last])
    r_full = np.linalg.cholesky(info[np.ix_(perm, perm)]).T  # upper, R^T R = info
    expected = r_full[-len(last) :, -len(last) :]
    np.testing.assert_allclose(r_s, expected, rtol=1e-7, atol=1e-7 * np.abs(expected).max())


def test_bad_selection_is_rejected(solved):
    problem, system, _ = solved
    with pytest.raises(ValueError, match="duplicates"):
        marginal_covariance(problem, [("x", 1), ("x", 1)], system)
    with pytest.raises(KeyError, match="no variable"):
        marginal_covariance(problem, [("x", 1000)], system)


@pytest.mark.parametrize("backend", ["qdldl", "splu"])
def test_covariance_columns_are_the_dense_inverse_columns(solved, backend):
    problem, _, info = solved
    system = factorize_at_estimate(problem, backend)
    cols = problem.scalar_indices(problem.indices([("x", 3), ("l", 7), ("x", 118)]))
    columns = covariance_columns(system, cols)
    dense = np.linalg.inv(info)[:, cols]
    np.testing.assert_allclose(columns, dense, rtol=1e-8, atol=1e-10 * np.abs(dense).max())
    rows = problem.scalar_indices(problem.indices([("l", 2), ("x", 40), ("x", 3)]))
    some = covariance_columns(system, cols, rows)
    np.testing.assert_allclose(some, dense[rows], rtol=1e-8, atol=1e-10 * np.abs(dense).max())


def test_covariance_by_elimination_is_the_dense_inverse_on_the_selected_scalars(solved):
    """Poses and landmarks selected (in a mixed order), the other poses eliminated along the
    trajectory: a chain cut at the selected poses, the first segment holding the gauge."""
    problem, system, info = solved
    keys = [("x", 40), ("l", 3), ("x", 7), ("x", 41), ("x", 119), ("l", 0), ("l", 9)]
    selected = problem.scalar_indices(problem.indices(keys))
    poses = problem.scalar_indices(problem.indices([("x", i) for i in range(120)]))
    rest = poses[~np.isin(poses, selected)]
    landmarks = np.setdiff1d(np.arange(problem.dim), np.r_[poses, selected])
    # the landmarks not selected couple the chain widely: they are selected too
    selected = np.r_[selected, landmarks]
    cov = covariance_by_elimination(system, selected, rest)
    dense = np.linalg.inv(info)[np.ix_(selected, selected)]
    np.testing.assert_allclose(cov, dense, rtol=1e-8, atol=1e-10 * np.abs(dense).max())
    everything = np.arange(problem.dim)  # nothing to eliminate
    np.testing.assert_allclose(
        covariance_by_elimination(system, everything, everything[:0]),
        np.linalg.inv(info),
        rtol=1e-8,
        atol=1e-10 * np.abs(dense).max(),
    )
    # the rest in an order that is not a band: not eliminated this way
    shuffled = np.random.default_rng(0).permutation(rest)
    assert covariance_by_elimination(system, selected, shuffled) is None
