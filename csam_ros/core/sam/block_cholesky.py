"""Cholesky factorisation of a symmetric matrix that is sparse by dense blocks: Algorithm 1's
information matrix, one block per robot's rendezvous poses and one of all base nodes
(docs/METHOD.md section 5).

A robot's rendezvous prior couples all its rendezvous poses, so its block is dense; a
rendezvous row couples one pose of each of two robots and their base nodes, so the block of two
robots that met is nonzero on a few rows only, and robots that never met share no block.
:class:`BlockPattern` takes the upper-triangular CSC pattern of the normal equations
(:class:`~csam_ros.core.sam.normal_equations.NormalEquations`) and the blocks, orders the robot
blocks by minimum degree on the graph of blocks (the base nodes last), and scatters the CSC
values into dense blocks. :func:`block_cholesky` is right-looking block elimination, LAPACK on
each block: ``L_kk = chol(H_kk)``, ``L_ik = H_ik L_kk^-T`` on the rows of ``H_ik`` that are
not zero, ``H_ij -= L_ik L_jk^T`` on those rows (creating a block where robots that never met
become coupled). So the work follows the coupled rows, as a scalar sparse factorisation's does,
at the speed of dense kernels. One factorisation (single-threaded BLAS), against qdldl's scalar
``L D L^T`` on the same pattern and dense LAPACK: MR.CLAM Dataset 1 (1,941 unknowns, qdldl's
factor 42 % of the triangle) 0.034 s, 0.124 s, 0.076 s; a ring of 16 robots observing at every
sample (1,917 unknowns) 0.015 s, 0.027 s, 0.072 s; a ring of 32 (5,949 unknowns) 0.08 s,
0.45 s, 1.7 s.

With the base nodes last, their joint covariance is ``(L_BB L_BB^T)^-1`` (the last block of
the inverse needs only the last block of the factor). The kernels are BLAS's and LAPACK's own
(``potrf``, ``trsm``, ``syrk`` for the half of a diagonal update that is kept, ``potri``),
updates go to views where a block's rows are a range, and the selected inverse can stay on the
factor's rows (:meth:`BlockFactor.selected_inverse_rows`, what the joint marginals need).
"""

from __future__ import annotations

from collections.abc import Sequence
from functools import cached_property

import numpy as np
from numpy.typing import NDArray
from scipy.linalg import solve_triangular
from scipy.linalg.blas import dsyrk, dtrsm
from scipy.linalg.lapack import dlauum, dpotrf, dpotri, dtrtri

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]
Index = slice | IntArray

# a Cholesky pivot whose square is at most this fraction of its diagonal entry counts as zero
# (as in the sparse normal equations and the dense oracle)
PIVOT_TOLERANCE = 1e-14


def _rows(rows: IntArray) -> Index:
    """``rows`` (ascending) as a slice where they are a contiguous range: a view, not a copy."""
    if len(rows) and rows[-1] - rows[0] + 1 == len(rows):
        return slice(int(rows[0]), int(rows[-1]) + 1)
    return rows


def _subtract(target: Array, rows: IntArray, cols: IntArray, update: Array) -> None:
    """``target[rows][:, cols] -= update`` in place (views where the indices are ranges)."""
    r, c = _rows(rows), _rows(cols)
    if isinstance(r, slice) and isinstance(c, slice):
        target[r, c] -= update
    else:
        target[np.ix_(rows, cols)] -= update


def _right_solve(lower: Array, rhs: Array, transposed: bool) -> Array:
    """``rhs L^-T`` (``transposed``) or ``rhs L^-1`` for lower-triangular ``L`` (BLAS trsm)."""
    if not len(rhs):
        return np.zeros((0, len(lower)))
    return dtrsm(1.0, lower, rhs, side=1, lower=1, trans_a=int(transposed))


def _elimination_order(edges: set[tuple[int, int]], count: int, last: int) -> list[int]:
    """Blocks in minimum-degree order on the block graph (``edges`` between blocks, fill
    added as blocks are eliminated; ties to the lower index), ``last`` at the end."""
    neighbours: dict[int, set[int]] = {b: set() for b in range(count) if b != last}
    for a, b in edges:
        if a != b and last not in (a, b):
            neighbours[a].add(b)
            neighbours[b].add(a)
    order: list[int] = []
    while neighbours:
        pick = min(neighbours, key=lambda b: (len(neighbours[b]), b))
        adjacent = neighbours.pop(pick)
        for b in adjacent:
            neighbours[b] |= adjacent - {b}
            neighbours[b].discard(pick)
        order.append(pick)
    return [*order, last]


class BlockPattern:
    """Blocks of a symmetric matrix given as the upper triangle of a CSC pattern, their
    elimination order, and where each stored entry goes in the dense blocks.

    ``blocks[b]`` are the scalar indices of block ``b`` (together every index once); block
    ``last`` is eliminated last. Blocks are kept by elimination position ``i >= j`` as
    ``(size_i, size_j)`` arrays; diagonal blocks are filled on both triangles.
    """

    def __init__(
        self, indptr: IntArray, indices: IntArray, blocks: Sequence[IntArray], last: int
    ) -> None:
        n = len(indptr) - 1
        block_of = np.full(n, -1, dtype=np.int64)
        local = np.zeros(n, dtype=np.int64)
        for b, idx in enumerate(blocks):
            block_of[idx] = b
            local[idx] = np.arange(len(idx))
        if np.any(block_of < 0) or sum(len(b) for b in blocks) != n:
            raise ValueError("the blocks must hold every scalar index exactly once")
        rows = np.asarray(indices, dtype=np.int64)
        cols = np.repeat(np.arange(n, dtype=np.int64), np.diff(np.asarray(indptr, np.int64)))
        row_block, col_block = block_of[rows], block_of[cols]
        count = len(blocks)
        pairs = np.flatnonzero(np.bincount(row_block * count + col_block, minlength=count**2))
        edges = {(int(p // count), int(p % count)) for p in pairs}
        order = _elimination_order(edges, len(blocks), last)
        position = np.empty(len(blocks), dtype=np.int64)
        position[order] = np.arange(len(blocks))
        self.n = n
        self.sizes = [len(blocks[b]) for b in order]
        self.scalars = [np.asarray(blocks[b], dtype=np.int64) for b in order]
        # every entry as (i, j) positions with i >= j, and its flat index in that block
        pr, pc = position[row_block], position[col_block]
        swap = pr < pc
        i = np.where(swap, pc, pr)
        j = np.where(swap, pr, pc)
        li = np.where(swap, local[cols], local[rows])
        lj = np.where(swap, local[rows], local[cols])
        width = np.asarray(self.sizes, dtype=np.int64)[j]
        flat = li * width + lj
        self._entries: dict[tuple[int, int], tuple[IntArray, IntArray]] = {}
        key = i * count + j
        if count**2 <= np.iinfo(np.int16).max:  # NumPy sorts 16-bit keys by radix: O(entries)
            key = key.astype(np.int16)
        by_pair = np.argsort(key, kind="stable")
        cuts = np.flatnonzero(np.diff(key[by_pair])) + 1
        for group in np.split(by_pair, cuts):
            a, b = int(i[group[0]]), int(j[group[0]])
            positions = flat[group]
            if a == b:  # both triangles of a diagonal block
                size = self.sizes[a]
                mirrored = lj[group] * size + li[group]
                positions = np.concatenate([positions, mirrored])
                group = np.concatenate([group, group])
            self._entries[a, b] = (group, positions)
        self.diagonal_entries = [
            np.arange(size) * (size + 1) for size in self.sizes
        ]  # flat positions of each diagonal block's diagonal

    def blocks(self, data: Array) -> dict[tuple[int, int], Array]:
        """The dense blocks of the matrix whose CSC values are ``data``."""
        out: dict[tuple[int, int], Array] = {}
        for (a, b), (entries, positions) in self._entries.items():
            block = np.zeros(self.sizes[a] * self.sizes[b])
            block[positions] = data[entries]
            out[a, b] = block.reshape(self.sizes[a], self.sizes[b])
        return out


class BlockFactor:
    """``L`` with ``L L^T`` the matrix in the pattern's block order: the diagonal blocks
    (lower triangular) and, per block column, the nonzero rows of each block below."""

    def __init__(
        self,
        pattern: BlockPattern,
        diagonal: list[Array],
        below: list[list[tuple[int, IntArray, Array]]],
    ) -> None:
        self.pattern = pattern
        self.diagonal = diagonal
        self.below = below

    @cached_property
    def _below_views(self) -> list[list[tuple[int, Index, Array]]]:
        """:attr:`below` with each block's rows as a slice where they are a range."""
        return [[(i, _rows(rows), lik) for i, rows, lik in column] for column in self.below]

    def solve(self, rhs: Array) -> Array:
        """``x`` with ``L L^T x = rhs`` (rhs (n,) or (n, m), the problem's scalar order)."""
        parts = [np.array(rhs[s], dtype=float) for s in self.pattern.scalars]
        below = self._below_views
        for k, lkk in enumerate(self.diagonal):
            parts[k] = solve_triangular(lkk, parts[k], lower=True, check_finite=False)
            for i, rows, lik in below[k]:
                parts[i][rows] -= lik @ parts[k]
        for k in range(len(self.diagonal) - 1, -1, -1):
            for i, rows, lik in below[k]:
                parts[k] -= lik.T @ parts[i][rows]
            parts[k] = solve_triangular(
                self.diagonal[k], parts[k], lower=True, trans="T", check_finite=False
            )
        out = np.empty(np.shape(rhs))
        for s, part in zip(self.pattern.scalars, parts, strict=True):
            out[s] = part
        return out

    @cached_property
    def flops(self) -> float:
        """Multiply-adds of the factorisation that made this factor (:func:`factor_flops`)."""
        sizes = self.pattern.sizes
        return sum(
            _column_flops(sizes[k], [len(rows) for _, rows, _ in column])
            for k, column in enumerate(self.below)
        )

    @cached_property
    def nonzeros(self) -> int:
        """Entries of ``L`` kept: a triangular solve's multiply-adds per right-hand side."""
        sizes = self.pattern.sizes
        return sum(
            size * (size + 1) // 2 + sum(len(rows) * size for _, rows, _ in column)
            for size, column in zip(sizes, self.below, strict=True)
        )

    def last_block_inverse(self) -> Array:
        """The inverse's block of the last block (the base nodes): ``(L_BB L_BB^T)^-1``."""
        inverse, info = dpotri(self.diagonal[-1], lower=1)
        if info != 0:
            raise np.linalg.LinAlgError(f"the last block's inverse failed (LAPACK info {info})")
        return np.tril(inverse) + np.tril(inverse, -1).T

    def selected_inverse(self) -> dict[tuple[int, int], Array]:
        """The inverse's blocks on the factor's pattern (``(i, j)``, ``i >= j`` in elimination
        order, each whole), by the block form of Takahashi's recurrence from the last block
        back: with ``W_jk = L_jk L_kk^-1`` on the blocks ``j`` below ``k``, ``Sigma_ik = -sum_j
        Sigma_ij W_jk`` and ``Sigma_kk = (L_kk L_kk^T)^-1 - sum_j W_jk^T Sigma_jk``. The blocks
        ``Sigma_ij`` it needs are on the pattern (the fill makes the blocks below one column a
        clique), so the cost follows the factor's, not ``n^3``."""
        return self._takahashi(whole=True)[0]

    def selected_inverse_rows(
        self,
    ) -> tuple[dict[tuple[int, int], Array], dict[tuple[int, int], IntArray]]:
        """:meth:`selected_inverse` on the factor's nonzero rows only: ``Sigma_ik`` (``i > k``)
        on the rows of ``L_ik`` (by ``held[i, k]``), the diagonal blocks whole. The recurrence
        needs no other rows (the rows of a block below a column are among those of the blocks
        its update fills), so it does less work where the coupling is partial."""
        return self._takahashi(whole=False)

    def _takahashi(
        self, whole: bool
    ) -> tuple[dict[tuple[int, int], Array], dict[tuple[int, int], IntArray]]:
        """The selected inverse's blocks and the rows each off-diagonal block holds."""
        sizes = self.pattern.sizes
        inverse: dict[tuple[int, int], Array] = {}
        held: dict[tuple[int, int], IntArray] = {}

        def part(i: int, j: int, rows: IntArray, cols: Index) -> Array:
            """``Sigma_ij[rows, cols]``."""
            if i == j:
                return inverse[i, i][_rows(rows)][:, cols]
            if i < j:  # Sigma_ij = Sigma_ji^T
                return part(j, i, np.arange(sizes[j])[cols], _rows(rows)).T
            if whole:
                return inverse[i, j][_rows(rows)][:, cols]
            at = np.searchsorted(held[i, j], rows)
            if not np.array_equal(held[i, j][np.minimum(at, len(held[i, j]) - 1)], rows):
                raise np.linalg.LinAlgError(f"rows of block ({i}, {j}) not on the factor's pattern")
            return inverse[i, j][_rows(at)][:, cols]

        for k in range(len(self.diagonal) - 1, -1, -1):
            lkk = self.diagonal[k]
            diagonal, info = dpotri(lkk, lower=1)  # (L_kk L_kk^T)^-1, its lower triangle
            if info != 0:
                raise np.linalg.LinAlgError(f"a block's inverse failed (LAPACK info {info})")
            diagonal = np.tril(diagonal) + np.tril(diagonal, -1).T
            below = [
                (i, rows, _right_solve(lkk, lik, transposed=False))
                for i, rows, lik in self.below[k]
            ]
            for i, rows_i, _ in below:
                wanted = np.arange(sizes[i]) if whole else rows_i
                column = np.zeros((len(wanted), len(lkk)))
                for j, rows_j, wjk in below:
                    if len(wjk) and len(wanted):
                        column -= part(i, j, wanted, _rows(rows_j)) @ wjk
                inverse[i, k], held[i, k] = column, wanted
            for j, rows_j, wjk in below:
                if len(wjk):
                    diagonal -= wjk.T @ part(j, k, rows_j, slice(None))
            inverse[k, k] = 0.5 * (diagonal + diagonal.T)
        return inverse, held

    def dense_inverse(self) -> Array:
        """The whole inverse (n, n), problem order: ``L^-1`` (LAPACK ``trtri``) then
        ``L^-T L^-1`` (``lauum``) on the dense ``L``, in place."""
        pattern = self.pattern
        n = pattern.n
        offsets = np.concatenate([[0], np.cumsum(pattern.sizes)])
        lower = np.zeros((n, n), order="F")
        for k, lkk in enumerate(self.diagonal):
            lower[offsets[k] : offsets[k + 1], offsets[k] : offsets[k + 1]] = np.tril(lkk)
            for i, rows, lik in self.below[k]:
                lower[offsets[i] + rows, offsets[k] : offsets[k + 1]] = lik
        inverse, info = dtrtri(lower, lower=1, overwrite_c=1)
        if info == 0:
            inverse, info = dlauum(inverse, lower=1, overwrite_c=1)
        if info != 0:
            raise np.linalg.LinAlgError(f"the inverse of the factor failed (LAPACK info {info})")
        for start in range(0, n, 256):  # the lower triangle mirrored, a band of rows at a time
            stop = min(start + 256, n)
            square = inverse[start:stop, start:stop]
            square[:] = np.tril(square) + np.tril(square, -1).T
            inverse[start:stop, stop:] = inverse[stop:, start:stop].T
        back = np.empty(n, dtype=np.int64)
        back[np.concatenate(pattern.scalars)] = np.arange(n)
        return inverse[np.ix_(back, back)]


def block_cholesky(pattern: BlockPattern, data: Array) -> BlockFactor | None:
    """The factor of the matrix of CSC values ``data`` (:class:`BlockPattern`), or ``None``
    when it is not positive definite (a pivot whose square is at most ``PIVOT_TOLERANCE`` of
    its diagonal entry, as the dense Cholesky check)."""
    return factor_blocks(pattern, pattern.blocks(data))


def factor_blocks(
    pattern: BlockPattern, blocks: dict[tuple[int, int], Array]
) -> BlockFactor | None:
    """:func:`block_cholesky` of the matrix given by its dense blocks (``(i, j)``, ``i >= j``
    in the pattern's elimination order, diagonal blocks whole), consumed. A block present but
    zero is kept in the structure (its rows empty), so the factor and its
    :meth:`~BlockFactor.selected_inverse` cover it."""
    count = len(pattern.sizes)
    references = [
        np.maximum(blocks[k, k].flat[pattern.diagonal_entries[k]], 1e-300) for k in range(count)
    ]
    columns: list[set[int]] = [set() for _ in range(count)]  # blocks i > j present in column j
    for a, b in blocks:
        if a != b:
            columns[b].add(a)
    diagonal: list[Array] = []
    below: list[list[tuple[int, IntArray, Array]]] = []
    filled: dict[tuple[int, int], NDArray[np.bool_]] = {}  # rows an update reached
    for k in range(count):
        # the block is symmetric: its transpose is the Fortran-ordered array LAPACK takes
        lkk, info = dpotrf(blocks.pop((k, k)).T, lower=1, clean=1, overwrite_a=1)
        if info != 0 or not np.all(np.diag(lkk) ** 2 > PIVOT_TOLERANCE * references[k]):
            return None
        diagonal.append(lkk)
        column: list[tuple[int, IntArray, Array]] = []
        for i in sorted(columns[k]):
            hik = blocks.pop((i, k))
            nonzero = np.any(hik != 0.0, axis=1)
            if (i, k) in filled:  # kept even where the update cancelled to zero
                nonzero |= filled.pop((i, k))
            rows = np.flatnonzero(nonzero)
            part = hik if len(rows) == len(hik) else hik[rows]
            column.append((i, rows, _right_solve(lkk, part, transposed=True)))
        for a, (i, rows_i, lik) in enumerate(column):
            for j, rows_j, ljk in column[: a + 1]:
                target = blocks.get((i, j))
                if target is None:  # i > j: diagonal blocks are never missing
                    target = blocks[i, j] = np.zeros((pattern.sizes[i], pattern.sizes[j]))
                    columns[j].add(i)
                if not (len(rows_i) and len(rows_j)):
                    continue
                if i == j:  # half the work: the lower triangle, mirrored
                    update = dsyrk(1.0, lik, lower=1)
                    update += np.tril(update, -1).T
                else:
                    update = lik @ ljk.T
                    filled.setdefault((i, j), np.zeros(pattern.sizes[i], dtype=bool))[rows_i] = True
                _subtract(target, rows_i, rows_j, update)
        below.append(column)
    return BlockFactor(pattern, diagonal, below)


def _column_flops(size: int, rows: Sequence[int]) -> float:
    """Multiply-adds of eliminating one block column of ``size`` whose blocks below have
    ``rows`` nonzero rows: ``s^3 / 3`` for its diagonal block, ``r s^2`` per block below,
    ``r_i r_j s`` per update."""
    flops = size**3 / 3.0 + sum(r * size * size for r in rows)
    return flops + sum(ri * rj * size for a, ri in enumerate(rows) for rj in rows[: a + 1])


def factor_flops(pattern: BlockPattern) -> float:
    """Multiply-adds of :func:`block_cholesky` on the pattern, from a symbolic run of its
    elimination (the nonzero rows of each block below the diagonal, as the numeric one keeps
    them; :attr:`BlockFactor.flops` counts the same on a numeric factor)."""
    count = len(pattern.sizes)
    rows: dict[tuple[int, int], IntArray] = {}
    for (a, b), (_, positions) in pattern._entries.items():
        if a != b:
            rows[a, b] = np.unique(positions // pattern.sizes[b])
    columns: list[set[int]] = [set() for _ in range(count)]
    for a, b in rows:
        columns[b].add(a)
    flops = 0.0
    for k in range(count):
        below = [(i, rows.pop((i, k))) for i in sorted(columns[k])]
        flops += _column_flops(pattern.sizes[k], [len(rows_i) for _, rows_i in below])
        for a, (i, rows_i) in enumerate(below):
            for j, _ in below[:a]:
                held = rows.get((i, j))
                rows[i, j] = rows_i if held is None else np.union1d(held, rows_i)
                columns[j].add(i)
    return flops
