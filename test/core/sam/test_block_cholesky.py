"""The block Cholesky factorisation against dense linear algebra: solves, the last block of
the inverse, the whole inverse, fill between blocks that share no entry, the minimum-degree
order of the blocks, and matrices that are not positive definite."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from csam_ros.core.sam.block_cholesky import (
    BlockPattern,
    _elimination_order,
    block_cholesky,
    factor_blocks,
    factor_flops,
)
from csam_ros.core.sam.selected_inverse import BlockInverse


def _ring_matrix(rng: np.random.Generator, sizes: list[int], last: int) -> np.ndarray:
    """A symmetric positive definite matrix: dense blocks, a few entries between neighbouring
    blocks of a ring (so elimination fills blocks that share no entry), and a last block
    coupled to a few rows of every other block."""
    starts = np.concatenate([[0], np.cumsum(sizes)])
    n = int(starts[-1])
    rows = []
    for b, size in enumerate(sizes):
        own = np.arange(starts[b], starts[b + 1])
        row = np.zeros(n)
        row[own] = rng.normal(size=size)
        rows.append(row)
        if b != last:
            for other in ((b + 1) % last, last):  # its ring neighbour and the last block
                row = np.zeros(n)
                row[rng.choice(own, 2, replace=False)] = rng.normal(size=2)
                pick = np.arange(starts[other], starts[other + 1])
                row[rng.choice(pick, 2, replace=False)] = rng.normal(size=2)
                rows.append(row)
    a = np.array(rows)
    dense_blocks = np.zeros((n, n))
    for b, size in enumerate(sizes):
        root = rng.normal(size=(size, size))
        dense_blocks[starts[b] : starts[b + 1], starts[b] : starts[b + 1]] = root @ root.T
    return a.T @ a + dense_blocks + 0.1 * np.eye(n)


def _pattern(matrix: np.ndarray, sizes: list[int], last: int) -> tuple[BlockPattern, np.ndarray]:
    upper = sp.csc_matrix(np.triu(matrix))
    upper.sort_indices()
    starts = np.concatenate([[0], np.cumsum(sizes)])
    blocks = [np.arange(starts[b], starts[b + 1]) for b in range(len(sizes))]
    return BlockPattern(upper.indptr, upper.indices, blocks, last), upper.data


SIZES = [9, 12, 6, 9, 15, 6]  # five blocks in a ring, the last coupled to all


@pytest.fixture
def ring() -> tuple[np.ndarray, BlockPattern, np.ndarray]:
    sizes = SIZES
    matrix = _ring_matrix(np.random.default_rng(4), sizes, last=5)
    pattern, data = _pattern(matrix, sizes, last=5)
    return matrix, pattern, data


@pytest.mark.parametrize("sizes", [SIZES, [120, 90, 150, 60, 9]])
def test_solves_and_inverses_equal_dense_algebra(sizes: list[int]) -> None:
    last = len(sizes) - 1
    matrix = _ring_matrix(np.random.default_rng(4), sizes, last=last)
    pattern, data = _pattern(matrix, sizes, last=last)
    factor = block_cholesky(pattern, data)
    assert factor is not None
    rhs = np.random.default_rng(1).normal(size=(len(matrix), 3))
    expected = np.linalg.solve(matrix, rhs)
    tolerance = 1e-10 * np.abs(expected).max()
    np.testing.assert_allclose(factor.solve(rhs), expected, atol=tolerance)
    np.testing.assert_allclose(factor.solve(rhs[:, 0]), expected[:, 0], atol=tolerance)
    inverse = np.linalg.inv(matrix)
    tolerance = 1e-10 * np.abs(inverse).max()
    np.testing.assert_allclose(factor.dense_inverse(), inverse, atol=tolerance)
    last = pattern.scalars[-1]
    np.testing.assert_allclose(
        factor.last_block_inverse(), inverse[np.ix_(last, last)], atol=tolerance
    )


def _inverse_blocks(pattern: BlockPattern, inverse: np.ndarray, pairs) -> dict:
    return {(i, j): inverse[np.ix_(pattern.scalars[i], pattern.scalars[j])] for i, j in pairs}


def test_selected_inverse_equals_the_dense_inverse_on_the_pattern(ring) -> None:
    matrix, pattern, data = ring
    factor = block_cholesky(pattern, data)
    assert factor is not None
    selected = factor.selected_inverse()
    pairs = {(i, i) for i in range(len(pattern.sizes))}
    pairs |= {(i, k) for k, column in enumerate(factor.below) for i, _, _ in column}
    assert set(selected) == pairs
    expected = _inverse_blocks(pattern, np.linalg.inv(matrix), pairs)
    scale = max(np.abs(b).max() for b in expected.values())
    for key, block in expected.items():
        np.testing.assert_allclose(selected[key], block, atol=1e-10 * scale, err_msg=str(key))


def test_selected_inverse_on_rows_equals_the_dense_inverse_on_the_factors_rows(ring) -> None:
    matrix, pattern, data = ring
    factor = block_cholesky(pattern, data)
    assert factor is not None
    selected, held = factor.selected_inverse_rows()
    inverse = np.linalg.inv(matrix)
    scale = np.abs(inverse).max()
    partial = 0
    for k, column in enumerate(factor.below):
        for i, rows, _ in column:
            np.testing.assert_array_equal(held[i, k], rows)
            partial += len(rows) < pattern.sizes[i]
            expected = inverse[np.ix_(pattern.scalars[i][rows], pattern.scalars[k])]
            np.testing.assert_allclose(selected[i, k], expected, atol=1e-10 * scale)
    assert partial  # some blocks held on part of their rows
    for k, scalars in enumerate(pattern.scalars):
        expected = inverse[np.ix_(scalars, scalars)]
        np.testing.assert_allclose(selected[k, k], expected, atol=1e-10 * scale)


def test_block_inverse_entries_off_the_factors_rows_are_refused(ring) -> None:
    matrix, pattern, data = ring
    factor = block_cholesky(pattern, data)
    assert factor is not None
    inverse = BlockInverse(factor)
    k, (i, rows, _) = next(
        (k, entry)
        for k, column in enumerate(factor.below)
        for entry in column
        if len(entry[1]) < pattern.sizes[entry[0]]
    )
    on, off = rows[0], np.setdiff1d(np.arange(pattern.sizes[i]), rows)[0]
    first = pattern.scalars[k][0]
    expected = np.linalg.inv(matrix)[pattern.scalars[i][on], first]
    got = inverse.entries(np.array([pattern.scalars[i][on]]), np.array([first]))
    np.testing.assert_allclose(got, [expected], atol=1e-10 * np.abs(expected))
    with pytest.raises(ValueError, match="not on the factor's pattern"):
        inverse.entries(np.array([pattern.scalars[i][off]]), np.array([first]))


def test_a_zero_block_given_stays_in_the_structure(ring) -> None:
    # blocks 0 and 2 share no entry; given as a zero block, the inverse covers them
    matrix, pattern, data = ring
    blocks = pattern.blocks(data)
    first, second = sorted(
        int(np.flatnonzero([s[0] == x for s in pattern.scalars])[0]) for x in (0, 21)
    )
    assert (second, first) not in blocks
    blocks[second, first] = np.zeros((pattern.sizes[second], pattern.sizes[first]))
    factor = factor_blocks(pattern, blocks)
    assert factor is not None
    selected = factor.selected_inverse()
    expected = _inverse_blocks(pattern, np.linalg.inv(matrix), [(second, first)])
    np.testing.assert_allclose(selected[second, first], expected[second, first], atol=1e-12)
    np.testing.assert_allclose(factor.solve(np.eye(len(matrix))), np.linalg.inv(matrix), atol=1e-10)


def test_elimination_fills_blocks_that_shared_no_entry(ring) -> None:
    _, pattern, data = ring
    factor = block_cholesky(pattern, data)
    assert factor is not None
    original = set(pattern._entries)
    filled = {(i, k) for k, column in enumerate(factor.below) for i, _, _ in column}
    assert filled - original  # the ring closes: some block of L was zero in the matrix
    # only the coupled rows of a block below the diagonal are kept
    assert any(len(rows) < pattern.sizes[i] for column in factor.below for i, rows, _ in column)


def test_not_positive_definite_is_none(ring) -> None:
    matrix = ring[0]
    indefinite = matrix - (np.linalg.eigvalsh(matrix)[0] + 1.0) * np.eye(len(matrix))
    assert block_cholesky(*_pattern(indefinite, SIZES, 5)) is None
    singular = matrix.copy()  # its second variable repeats its first
    singular[:, 1] = singular[:, 0]
    singular[1, :] = singular[0, :]
    assert np.linalg.matrix_rank(singular) < len(matrix)
    assert block_cholesky(*_pattern(singular, SIZES, 5)) is None
    assert block_cholesky(*_pattern(matrix, SIZES, 5)) is not None


def test_minimum_degree_order_keeps_the_last_block_last() -> None:
    # a star: the centre has three neighbours, the leaves one; a leaf goes first
    edges = {(0, 1), (0, 2), (0, 3), (1, 4), (2, 4), (3, 4), (0, 4)}
    order = _elimination_order(edges, 5, last=4)
    assert order[-1] == 4
    assert order[0] == 1
    assert sorted(order) == list(range(5))


def test_blocks_must_cover_every_index_once() -> None:
    upper = sp.csc_matrix(np.eye(4))
    with pytest.raises(ValueError, match="every scalar index exactly once"):
        BlockPattern(upper.indptr, upper.indices, [np.arange(2), np.arange(1, 3)], 1)


@pytest.mark.parametrize("sizes", [SIZES, [30, 24, 18, 27, 12]])
def test_factor_flops_count_the_numeric_factors_work(sizes: list[int]) -> None:
    last = len(sizes) - 1
    matrix = _ring_matrix(np.random.default_rng(2), sizes, last)
    pattern, data = _pattern(matrix, sizes, last)
    factor = block_cholesky(pattern, data)
    assert factor is not None
    expected = 0.0
    for k, column in enumerate(factor.below):
        size = pattern.sizes[k]
        expected += size**3 / 3 + sum(len(rows) * size * size for _, rows, _ in column)
        expected += sum(
            len(rows_i) * len(rows_j) * size
            for a, (_, rows_i, _) in enumerate(column)
            for _, rows_j, _ in column[: a + 1]
        )
    assert factor_flops(pattern) == pytest.approx(expected)
