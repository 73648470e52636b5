"""Normal equations of the sparse engine: assembly against the dense product, and singular
systems named by their variable."""

import numpy as np
import pytest
from sam_problems import chain, mixed_problem

from csam_ros.core.sam.factors import (
    POINT,
    POSE,
    LinearPrior,
    PosePrior,
    RelativePose,
    RelativePosition,
)
from csam_ros.core.sam.normal_equations import WIDE_FACTOR_ROWS, SingularProblemError


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


def test_variable_blocks_factor_by_blocks_where_cheaper(monkeypatch) -> None:
    """With variable blocks and a block factorisation within BLOCK_FLOPS_RATIO of qdldl's
    work, the factorisations after the first are by blocks: the same steps, solution and
    solves; beyond the ratio, qdldl throughout."""
    import csam_ros.core.sam.normal_equations as normal_equations

    plain = mixed_problem(3)
    plain.solve()
    for ratio, by_blocks in ((1e9, True), (0.0, False)):
        monkeypatch.setattr(normal_equations, "BLOCK_FLOPS_RATIO", ratio)
        p = mixed_problem(3)
        p.variable_blocks = [np.arange(0, 8), np.arange(8, 14)]
        report = p.solve()
        system = p.normal_equations()
        assert (system.block_pattern is not None) == by_blocks
        assert report.converged
        np.testing.assert_allclose(p.values, plain.values, atol=1e-10)
        system.linearize(p.values)
        system.factorize()
        assert (system.block_factor is not None) == by_blocks
        rhs = np.random.default_rng(0).normal(size=system.n)
        expected = np.linalg.solve(system.full_matrix().toarray(), rhs)
        np.testing.assert_allclose(system.solve(rhs), expected, rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("blocks", [[[0], [1]], [[0, 1]]])
def test_a_singular_problem_by_blocks_is_named_as_by_qdldl(monkeypatch, blocks) -> None:
    import csam_ros.core.sam.normal_equations as normal_equations

    monkeypatch.setattr(normal_equations, "BLOCK_FLOPS_RATIO", 1e9)
    p, ids = chain(2)
    p.add_factor(PosePrior(ids[:1], np.zeros((1, 3)), np.eye(3)))
    p.add_factor(RelativePosition(ids[:1], ids[1:], [[1.0, 0.0]], np.eye(2)))
    p.variable_blocks = [np.asarray(b) for b in blocks]
    with pytest.raises(SingularProblemError, match=r"\('x', 1\).*rank 2 < 3"):
        p.solve()
    assert p.normal_equations().block_pattern is not None
