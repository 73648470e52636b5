"""The normal equations of a :class:`~csam_ros.core.sam.solver.Problem`: sparse assembly of
``A^T A`` and ``A^T r`` and their factorisation.

Every factor kind returns its whitened residuals and Jacobian blocks for all of its factors in
one vectorised call. The normal equations ``A^T A delta = -A^T r`` are assembled directly in
compressed sparse column form (upper triangle) from index arrays: the sparsity pattern and the
position of every Jacobian product in it are computed once per problem structure; each
iteration only refills values with one ``np.bincount`` (products of the whitened Jacobians
taken component-major, one contiguous vector operation per pair of columns; a factor kind with
more than ``WIDE_FACTOR_ROWS`` rows per factor, such as a dense ``LinearPrior`` of a few
hundred rows, by one BLAS product ``A_k^T A_k`` per factor instead). The factorisation is
sparse ``L D L^T`` by qdldl with its approximate-minimum-degree fill-reducing ordering; the
symbolic analysis is kept and only the numeric factorisation is redone (``update``). The
upper-triangular square-root information is ``R = sqrt(D) L^T`` (permuted), ``R^T R = A^T A``.
Chosen by benchmark (``python -m csam_ros.bench.smoothing``, 7,000 poses, 150 landmarks): one
Gauss-Newton iteration takes 11 ms with qdldl against 180 ms with scipy's SuperLU
(``backend="splu"``, COLAMD; kept as a fallback) and 58 ms for GTSAM's batch iteration (same
run, single-threaded). A whole solve from dead reckoning (5 factorisations) is dominated by
qdldl: the first factorisation with its AMD ordering takes about 15 ms, each refactorisation
about 5 ms.

A singular system raises :class:`SingularProblemError` naming the variable where it became
singular.
"""

from __future__ import annotations

import weakref
from collections.abc import Hashable
from dataclasses import dataclass
from typing import Protocol

import numpy as np
import scipy.sparse as sp
from numpy.typing import ArrayLike, NDArray

from csam_ros.core.sam.block_cholesky import BlockFactor, BlockPattern, block_cholesky, factor_flops
from csam_ros.core.sam.factors import Factor

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]

# factors with more residual rows than this are assembled by matrix products (see assemble)
WIDE_FACTOR_ROWS = 8

# a problem with variable blocks is factored by blocks when that takes at most this many times
# the multiply-adds of qdldl's factor (NormalEquations._choose_blocks); measured on the joint
# problems of rings of 32 and 64 robots: 16.7 multiply-adds per ns by blocks, 1.8-2.6 by qdldl
BLOCK_FLOPS_RATIO = 4.0


class ProblemStructure(Protocol):
    """What the normal equations read of a :class:`csam_ros.core.sam.solver.Problem`."""

    offsets: IntArray  # first scalar of each variable
    _dims: IntArray  # scalars of each variable
    factors: list[Factor]
    variable_blocks: list[IntArray] | None  # variables grouped for a block factorisation

    def scalar_indices(self, ids: ArrayLike) -> IntArray: ...

    @property
    def dim(self) -> int: ...

    @property
    def num_variables(self) -> int: ...

    def key(self, index: int) -> Hashable: ...


class SingularProblemError(ValueError):
    """The least-squares problem does not determine every variable."""


@dataclass
class Linearization:
    """Whitened residuals ``(K, d)`` and Jacobians ``(K, d, D)`` of each factor kind instance
    at ``values``, and the cost there (see :meth:`NormalEquations.evaluate`)."""

    values: Array
    cost: float
    residuals: list[Array]
    jacobians: list[Array]


class NormalEquations:
    """Sparse ``A^T A`` (upper triangle, CSC) and ``A^T r`` assembled from index arrays.

    The pattern is built at the block level: the unique pairs of variables that share a
    factor, sorted by (column variable, row variable), expanded to scalar CSC entries
    without any sort of scalar entries. For every factor kind, the CSC position of each
    entry of its per-factor ``A_k^T A_k`` (upper triangle) is computed once, so that each
    linearisation refills the values with one ``np.bincount``.
    """

    def __init__(self, problem: ProblemStructure, backend: str = "qdldl") -> None:
        if backend not in ("qdldl", "splu"):
            raise ValueError(f"unknown backend {backend!r}: use 'qdldl' or 'splu'")
        if not problem.factors:
            raise SingularProblemError("the problem has no factors")
        self._problem_ref = weakref.ref(problem)  # no cycle with Problem._system
        self.backend = backend
        self.n = n = problem.dim
        num_vars = problem.num_variables
        offsets = problem.offsets
        dims = problem._dims
        touched = np.zeros(num_vars, dtype=bool)
        pair_keys: list[IntArray] = [np.arange(num_vars, dtype=np.int64) * (num_vars + 1)]
        for f in problem.factors:
            touched[f.variables.reshape(-1)] = True
            s, t = np.triu_indices(f.variables.shape[1], 1)
            lo = np.minimum(f.variables[:, s], f.variables[:, t])
            hi = np.maximum(f.variables[:, s], f.variables[:, t])
            pair_keys.append((hi * num_vars + lo).reshape(-1))
        free = np.flatnonzero(~touched)
        if free.size:
            raise SingularProblemError(
                f"variable {problem.key(int(free[0]))!r} is not constrained by any factor"
                + (f" (and {free.size - 1} more)" if free.size > 1 else "")
            )
        keys = np.sort(np.concatenate(pair_keys))
        keys = keys[np.concatenate([[True], keys[1:] != keys[:-1]])]
        col_var = keys // num_vars
        row_var = keys % num_vars
        row_dim = dims[row_var]
        # pairs are grouped by column variable, diagonal pair last in each group
        group_start = np.searchsorted(col_var, np.arange(num_vars))
        group_size = np.diff(np.append(group_start, len(keys)))
        csum = np.cumsum(row_dim)
        rows_before = (
            csum - row_dim - np.repeat(csum[group_start] - row_dim[group_start], group_size)
        )
        self._pair_keys = keys
        self._rows_before = rows_before  # rows of earlier pairs in the same columns
        off_diag_rows = rows_before[group_start + group_size - 1]  # S_w
        within = np.arange(n) - np.repeat(offsets, dims)  # b of each scalar column
        col_variable = np.repeat(np.arange(num_vars), dims)
        col_counts = off_diag_rows[col_variable] + within + 1
        indptr = np.zeros(n + 1, dtype=np.int64)
        np.cumsum(col_counts, out=indptr[1:])
        self.nnz = int(indptr[-1])
        # runs: for each scalar column, one run of rows per pair of its group
        runs_per_col = group_size[col_variable]
        run_col = np.repeat(np.arange(n), runs_per_col)
        run_first = np.concatenate([[0], np.cumsum(runs_per_col)[:-1]])
        run_pair = np.repeat(group_start[col_variable], runs_per_col) + (
            np.arange(len(run_col)) - np.repeat(run_first, runs_per_col)
        )
        is_diag = row_var[run_pair] == col_var[run_pair]
        run_len = np.where(is_diag, within[run_col] + 1, row_dim[run_pair])
        run_start = np.concatenate([[0], np.cumsum(run_len)[:-1]])
        self.indices = (
            np.repeat(offsets[row_var[run_pair]], run_len)
            + np.arange(self.nnz)
            - np.repeat(run_start, run_len)
        ).astype(np.int32)
        self.indptr = indptr.astype(np.int32)
        self.diagonal_positions = indptr[1:] - 1
        self._off_diag_rows = off_diag_rows

        self._columns: list[IntArray] = []
        self._splits: list[list[int]] = []
        self._pairs: list[tuple[IntArray, IntArray]] = []
        self._slices: list[slice] = []
        positions: list[IntArray] = []
        gradient_index: list[IntArray] = []
        used = 0
        for f in problem.factors:
            var = f.variables
            kdims = [k.dim for k in f.kinds]
            starts = np.cumsum([0, *kdims])
            self._splits.append(list(starts[1:-1]))
            cols = np.concatenate(
                [offsets[var[:, j]][:, None] + np.arange(d) for j, d in enumerate(kdims)], axis=1
            )
            self._columns.append(cols)
            gradient_index.append(cols.T.reshape(-1))
            # the upper triangle of each factor's A_k^T A_k, one (p, q) pair per entry
            first, second = np.triu_indices(int(starts[-1]))
            self._pairs.append((first, second))
            block = np.repeat(np.arange(len(kdims)), kdims)
            # per pair of connected variables (s <= t): its pattern pair and which is higher
            m = len(kdims)
            pair_st = np.zeros((m, m, len(var)), dtype=np.int64)
            swap_st = np.zeros((m, m, len(var)), dtype=bool)
            hi_st = np.zeros((m, m, len(var)), dtype=np.int64)
            a, b = np.triu_indices(m)
            va, vb = var[:, a].T, var[:, b].T  # (pairs a <= b, K)
            hi_st[a, b] = np.maximum(va, vb)
            swap_st[a, b] = va > vb
            pair_st[a, b] = np.searchsorted(keys, hi_st[a, b] * num_vars + np.minimum(va, vb))
            pair = pair_st[block[first], block[second]]  # (pairs, K)
            swap = swap_st[block[first], block[second]]
            hi = hi_st[block[first], block[second]]
            local = (np.arange(int(starts[-1])) - starts[block])[:, None]
            row_local = np.where(swap, local[second], local[first])
            col_local = np.where(swap, local[first], local[second])
            positions.append(
                (indptr[offsets[hi] + col_local] + rows_before[pair] + row_local).reshape(-1)
            )
            self._slices.append(slice(used, used + positions[-1].size))
            used += positions[-1].size
        self._positions = np.concatenate(positions)
        self._gradient_index = np.concatenate(gradient_index)
        self._hessian_weights = np.empty(used)
        self._gradient_weights = np.empty(len(self._gradient_index))
        self._gradient_slices: list[slice] = []
        used = 0
        for cols in self._columns:
            self._gradient_slices.append(slice(used, used + cols.size))
            used += cols.size
        self._factorization: object | None = None
        self._checked = False
        self._variable_blocks = problem.variable_blocks  # decided on at the first factorisation
        self.block_pattern: BlockPattern | None = None  # set when the blocks are cheaper
        self.block_factor: BlockFactor | None = None  # the last factorisation, when by blocks
        self.hessian_data: Array = np.zeros(self.nnz)
        self.gradient: Array = np.zeros(n)

    @property
    def problem(self) -> ProblemStructure:
        problem = self._problem_ref()
        if problem is None:
            raise RuntimeError("the problem of these normal equations no longer exists")
        return problem

    def evaluate(self, values: Array) -> Linearization:
        """Whitened residuals, Jacobians and cost at ``values`` (nothing assembled yet)."""
        residuals: list[Array] = []
        jacobians: list[Array] = []
        cost = 0.0
        for f, cols, splits in zip(self.problem.factors, self._columns, self._splits, strict=True):
            r, a, costs = f.whitened(np.split(values[cols], splits, axis=1))
            residuals.append(r)
            jacobians.append(a)  # type: ignore[arg-type]
            cost += float(costs.sum())
        return Linearization(values, cost, residuals, jacobians)

    def assemble(self, linearization: Linearization) -> None:
        """Fill :attr:`hessian_data` and :attr:`gradient` from an :meth:`evaluate` result."""
        hess, grad = self._hessian_weights, self._gradient_weights
        for r, a, (first, second), hs, gs in zip(
            linearization.residuals,
            linearization.jacobians,
            self._pairs,
            self._slices,
            self._gradient_slices,
            strict=True,
        ):
            k, d, dim = a.shape
            h = hess[hs].reshape(len(first), k)
            g = grad[gs].reshape(dim, k)
            if d > WIDE_FACTOR_ROWS:
                # many rows per factor (a dense LinearPrior): one BLAS product per factor
                ata = np.matmul(a.transpose(0, 2, 1), a)
                h[:] = ata[:, first, second].T
                g[:] = np.einsum("kij,ki->jk", a, r)
                continue
            # component-major (d, D, K): each product below is one contiguous vector operation
            at = np.ascontiguousarray(a.transpose(1, 2, 0))
            rt = np.ascontiguousarray(r.T)
            np.multiply(at[0, first], at[0, second], out=h)
            np.multiply(at[0], rt[0], out=g)
            for i in range(1, d):
                h += at[i, first] * at[i, second]
                g += at[i] * rt[i]
        self.hessian_data = np.bincount(self._positions, weights=hess, minlength=self.nnz)
        self.gradient = np.bincount(self._gradient_index, weights=grad, minlength=self.n)
        if not np.isfinite(linearization.cost) or not np.all(np.isfinite(self.hessian_data)):
            raise FloatingPointError("the linearisation produced non-finite values")

    def linearize(self, values: Array) -> float:
        """Fill :attr:`hessian_data` and :attr:`gradient` at ``values``; return the cost."""
        linearization = self.evaluate(values)
        self.assemble(linearization)
        return linearization.cost

    def cost(self, values: Array) -> float:
        """Cost at ``values`` (no Jacobians)."""
        total = 0.0
        for f, cols, splits in zip(self.problem.factors, self._columns, self._splits, strict=True):
            total += float(f.whitened(np.split(values[cols], splits, axis=1), False)[2].sum())
        return total

    @property
    def diagonal(self) -> Array:
        """Diagonal of ``A^T A`` at the last linearisation."""
        return self.hessian_data[self.diagonal_positions]

    def matrix(self, damping: float = 0.0) -> sp.csc_matrix:
        """Upper triangle of ``A^T A + damping * diag(A^T A)`` as CSC."""
        data = self.hessian_data
        if damping > 0.0:
            data = data.copy()
            data[self.diagonal_positions] *= 1.0 + damping
        return sp.csc_matrix((data, self.indices, self.indptr), shape=(self.n, self.n))

    def full_matrix(self) -> sp.csr_matrix:
        """``A^T A`` as CSR, both triangles."""
        upper = self.matrix()
        return (upper + sp.triu(upper, 1).T).tocsr()

    def check_blocks(self) -> None:
        """Raise if a variable's own information block is singular (it is under-constrained)."""
        problem = self.problem
        indptr = self.indptr.astype(np.int64)
        for dim in np.unique(problem._dims):
            ids = np.flatnonzero(problem._dims == dim)
            a = np.arange(dim)[None, :, None]
            b = np.arange(dim)[None, None, :]
            lo, hi = np.minimum(a, b), np.maximum(a, b)
            pos = (
                indptr[problem.offsets[ids][:, None, None] + hi]
                + self._off_diag_rows[ids][:, None, None]
                + lo
            )
            eig = np.linalg.eigvalsh(self.hessian_data[pos])
            bad = np.flatnonzero(~(eig[:, 0] > 1e-12 * np.maximum(eig[:, -1], 1e-300)))
            if bad.size:
                key = problem.key(int(ids[bad[0]]))
                rank = int((eig[bad[0]] > 1e-12 * max(eig[bad[0], -1], 1e-300)).sum())
                raise SingularProblemError(
                    f"variable {key!r} is under-constrained: its information block has rank "
                    f"{rank} < {dim} (e.g. a pose seen only through a 2D relative position)"
                )

    def factorize(self, damping: float = 0.0) -> None:
        """Numeric factorisation of the damped system (symbolic analysis reused)."""
        self.block_factor = None
        if self._variable_blocks is not None and self._factorization is None:
            self._choose_blocks()
        if self.block_pattern is not None:
            data = self.hessian_data
            if damping > 0.0:
                data = data.copy()
                data[self.diagonal_positions] *= 1.0 + damping
            factor = block_cholesky(self.block_pattern, data)
            if factor is None:
                self._raise_singular(self.matrix(damping))
            self.block_factor = factor
            return
        mat = self.matrix(damping)
        if self.backend == "qdldl":
            import qdldl

            try:
                if self._factorization is None:
                    self._factorization = qdldl.Solver(mat, upper=True)
                else:
                    self._factorization.update(mat, upper=True)
            except RuntimeError:
                self._factorization = None
                self._raise_singular(mat)
            if not self._checked:
                self._check_pivots()
        else:
            from scipy.sparse.linalg import splu

            full = mat + sp.triu(mat, 1).T
            try:
                self._factorization = splu(full.tocsc(), permc_spec="COLAMD")
            except RuntimeError:
                self._raise_singular(mat)

    def _choose_blocks(self) -> None:
        """Factor by the problem's variable blocks when that takes at most
        ``BLOCK_FLOPS_RATIO`` times the multiply-adds of qdldl's factor (estimated:
        :meth:`_qdldl_flops`): dense kernels run that much faster per operation than qdldl's
        scalar loops, so where a problem's blocks are dense (robots that observe each other at
        every pose) the block factorisation wins, where they are sparse chains (long
        trajectories) qdldl does. Decided once, from the structure alone."""
        variable_blocks, self._variable_blocks = self._variable_blocks, None
        assert variable_blocks is not None
        blocks = [self.problem.scalar_indices(ids) for ids in variable_blocks]
        budget = BLOCK_FLOPS_RATIO * self._qdldl_flops()
        if sum(len(b) ** 3 / 3.0 for b in blocks) > budget:  # the diagonal blocks alone
            return
        degree = _block_degrees(self.indptr, self.indices, blocks, self.n)
        pattern = BlockPattern(self.indptr, self.indices, blocks, int(np.argmax(degree)))
        if factor_flops(pattern) <= budget:
            self.block_pattern = pattern

    def _qdldl_flops(self) -> float:
        """qdldl's multiply-adds on these equations, estimated from its factor of the graph of
        the variables (one scalar per variable, on which its minimum-degree ordering sees the
        same graph; 0.05 s for 5,000 variables): each variable's column with its dimension
        times the squared dimensions of the rows below it (within 20 % of the count on the
        joint problems of rings of 4 to 64 robots)."""
        import qdldl

        problem = self.problem
        count = problem.num_variables
        hi, lo = self._pair_keys // count, self._pair_keys % count
        off = hi != lo
        degree = np.bincount(np.concatenate([hi[off], lo[off]]), minlength=count)
        data = np.where(off, -1.0, degree[hi] + 1.0)  # a graph Laplacian plus I: definite
        graph = sp.csc_matrix((data, (lo, hi)), shape=(count, count))
        lower, _, perm = qdldl.Solver(graph, upper=True).factors()
        dims = problem._dims[np.asarray(perm)].astype(float)
        column = np.repeat(np.arange(count), np.diff(lower.indptr))
        below = np.bincount(column, weights=dims[lower.indices], minlength=count)
        return float(np.sum(dims * (below + (dims - 1.0) / 2.0) ** 2))

    def _check_pivots(self) -> None:
        _, d, perm = self._factorization.factors()  # type: ignore[union-attr]
        diag = self.hessian_data[self.diagonal_positions][perm]
        ratio = d / np.maximum(diag, 1e-300)
        bad = np.flatnonzero(~(ratio > 1e-14))
        if bad.size:
            self._name_singular(int(perm[bad[0]]))
        self._checked = True

    def _raise_singular(self, mat: sp.csc_matrix) -> None:
        self.check_blocks()
        raise SingularProblemError(
            "the information matrix is singular: some variables are determined only up to a "
            "common motion (is the gauge fixed by a prior on the first pose?)"
        )

    def _name_singular(self, scalar: int) -> None:
        self.check_blocks()
        var = int(np.searchsorted(self.problem.offsets, scalar, side="right") - 1)
        raise SingularProblemError(
            f"the information matrix is singular at variable {self.problem.key(var)!r}: it is "
            "determined only up to a motion shared with others (is the gauge fixed by a prior "
            "on the first pose?)"
        )

    def solve(self, rhs: Array) -> Array:
        """Solve with the last factorisation (rhs (n,), or (n, k) when it was by blocks)."""
        if self.block_factor is not None:
            return self.block_factor.solve(rhs)
        if self._factorization is None:
            raise RuntimeError("factorize() first")
        return np.asarray(self._factorization.solve(rhs))  # type: ignore[union-attr]


def _block_degrees(indptr: IntArray, indices: IntArray, blocks: list[IntArray], n: int) -> IntArray:
    """How many other blocks each block shares an entry with."""
    block_of = np.empty(n, dtype=np.int64)
    for b, idx in enumerate(blocks):
        block_of[idx] = b
    cols = np.repeat(np.arange(n), np.diff(np.asarray(indptr, dtype=np.int64)))
    a, b = block_of[np.asarray(indices, dtype=np.int64)], block_of[cols]
    pairs = np.unique(np.minimum(a, b) * len(blocks) + np.maximum(a, b))
    lo, hi = pairs // len(blocks), pairs % len(blocks)
    off = lo != hi
    return np.bincount(np.concatenate([lo[off], hi[off]]), minlength=len(blocks))
