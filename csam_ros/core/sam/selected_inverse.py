"""Selected entries of the inverse of a sparse information matrix (the selected inverse),
from its sparse LDL^T factor by supernodes (docs/METHOD.md 4.5)."""

from __future__ import annotations

from functools import cache

import numpy as np
from numpy.typing import NDArray

try:  # the compiled lookup behind scipy's sparse indexing
    from scipy.sparse._sparsetools import csr_sample_offsets as _sample_offsets
except ImportError:  # pragma: no cover - scipy without it: the numpy search
    _sample_offsets = None

from csam_ros.core.sam.block_cholesky import BlockFactor
from csam_ros.core.sam.normal_equations import NormalEquations
from csam_ros.core.sam.solver import Problem

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]


def _unit_lower_inverse(strict: Array, w: int, rows: IntArray, cols: IntArray) -> Array:
    """Inverses (k, w, w) of unit lower triangular ``w x w`` matrices with strict parts
    ``strict`` (k, w (w - 1) / 2) at ``rows, cols``; closed form up to 3 x 3 (poses)."""
    k = len(strict)
    out = np.zeros((k, w, w))
    diagonal = np.arange(w)
    out[:, diagonal, diagonal] = 1.0
    if w == 2:
        out[:, 1, 0] = -strict[:, 0]
    elif w == 3:
        l10, l20, l21 = strict.T  # tril_indices order: (1,0), (2,0), (2,1)
        out[:, 1, 0], out[:, 2, 0], out[:, 2, 1] = -l10, l10 * l21 - l20, -l21
    elif w > 3:
        out[:, rows, cols] = strict
        out = np.linalg.inv(out)
    return out


class PatternPositions:
    """Where entries ``(rows, columns)`` are in the data of a CSC pattern with sorted rows in
    each column, -1 where the pattern has none: scipy's compiled lookup, one short binary
    search per entry in its column (4-5 times faster than one search over the whole pattern),
    or that search over the whole pattern where scipy lacks it (it is not public API)."""

    def __init__(self, indptr: IntArray, indices: IntArray) -> None:
        self.indptr, self.indices = indptr, indices
        self.n = len(indptr) - 1
        self._keys = (
            None
            if _sample_offsets is not None
            else np.repeat(np.arange(self.n, dtype=np.int64), np.diff(indptr)) * self.n + indices
        )

    def __call__(self, columns: IntArray, rows: IntArray) -> IntArray:
        columns = np.asarray(columns, dtype=self.indptr.dtype)
        rows = np.asarray(rows, dtype=self.indptr.dtype)
        if self._keys is None:
            out = np.empty(len(rows), dtype=self.indptr.dtype)
            _sample_offsets(
                self.n, self.n, self.indptr, self.indices, len(rows), columns, rows, out
            )
            return out.astype(np.int64)
        wanted = columns.astype(np.int64) * self.n + rows
        if not len(self._keys):
            return np.full(len(rows), -1, dtype=np.int64)
        found = np.minimum(np.searchsorted(self._keys, wanted), len(self._keys) - 1)
        return np.where(self._keys[found] == wanted, found, -1)


@cache
def _tril(w: int) -> tuple[IntArray, IntArray]:
    """Rows and columns of the strict lower triangle of a ``w x w`` matrix."""
    return np.tril_indices(w, -1)


def _supernodes(indptr: IntArray, indices: IntArray, n: int) -> tuple[IntArray, IntArray, IntArray]:
    """The fundamental supernodes of a sorted CSC strict lower factor: their first and last
    columns, and each one's depth in the supernodal elimination tree (roots 0)."""
    counts = np.diff(indptr)
    first = np.full(n, -1, dtype=np.int64)
    first[counts > 0] = indices[indptr[:-1][counts > 0]]
    merges = np.zeros(n, dtype=bool)  # column j is in the supernode of column j + 1
    merges[:-1] = (first[:-1] == np.arange(1, n)) & (counts[:-1] == counts[1:] + 1)
    ends = np.flatnonzero(np.r_[~merges[:-1], True])
    begins = np.r_[0, ends[:-1] + 1]
    supernode_of = np.repeat(np.arange(len(ends)), ends - begins + 1)
    # the parent holds the first row below the supernode; it comes later in the order
    parent = np.where(counts[ends] > 0, supernode_of[np.maximum(first[ends], 0)], -1).tolist()
    depth = [0] * len(ends)
    for s in range(len(ends) - 1, -1, -1):
        if parent[s] >= 0:
            depth[s] = depth[parent[s]] + 1
    return begins, ends, np.asarray(depth, dtype=np.int64)


class _MarginalBlocks:
    """Marginal covariance blocks of variables from :meth:`entries`."""

    def entries(self, rows: IntArray, cols: IntArray) -> Array:
        raise NotImplementedError

    def blocks(self, problem: Problem, ids: IntArray) -> Array:
        """Marginal covariance blocks (K, dim, dim) of variables ``ids`` (one dimension)."""
        ids = np.asarray(ids, dtype=np.int64)
        if len(ids) == 0:
            return np.zeros((0, 0, 0))
        scalars = problem.scalar_indices(ids).reshape(len(ids), -1)
        dim = scalars.shape[1]
        rows = np.repeat(scalars, dim, axis=1)
        cols = np.tile(scalars, (1, dim))
        return self.entries(rows.ravel(), cols.ravel()).reshape(len(ids), dim, dim)


class SelectedInverse(_MarginalBlocks):
    """Entries of ``(A^T A)^-1`` on the sparsity pattern of its factor (Takahashi et al.).

    With ``P (A^T A) P^T = L D L^T`` (the solver's qdldl factorisation at the estimate) the
    inverse ``Z`` is computed on the (filled) pattern of ``L`` one supernode at a time
    (consecutive columns ``J`` sharing their rows ``S`` below, e.g. the components of one
    pose): with ``U = L_SJ L_JJ^-1``,

        Z_SJ = -Z_SS U,        Z_JJ = L_JJ^-T D_J^-1 L_JJ^-1 - U^T Z_SJ,

    where ``Z_SS`` lies on the pattern already computed: ``S`` is a clique of the filled
    graph, of ancestors in the elimination tree. So the supernodes of one depth in the tree
    are independent, and are computed together, in stacks of equal shape, from the root
    down. This gives every marginal covariance block of single variables, and of variables
    that share a factor, in time linear in the size of the factor, instead of one triangular
    solve per wanted column.
    """

    def __init__(self, system: NormalEquations) -> None:
        factorization = system._factorization  # the solver's qdldl factor
        if factorization is None or system.backend != "qdldl":
            raise ValueError("SelectedInverse needs a qdldl factorisation (factorize() first)")
        lower, d, perm = factorization.factors()
        lower = lower.tocsc()
        lower.sort_indices()
        n = system.n
        self.n = n
        self.perm = np.asarray(perm, dtype=np.int64)
        self.inverse_perm = np.empty(n, dtype=np.int64)
        self.inverse_perm[self.perm] = np.arange(n)
        self._locate = PatternPositions(lower.indptr, lower.indices)
        indptr = lower.indptr.astype(np.int64)
        indices = lower.indices.astype(np.int64)
        data = lower.data
        d = np.asarray(d, dtype=float)
        nnz = len(data)
        # Z on the pattern, then its diagonal: one array, so Z_SS is one gather
        store = np.zeros(nnz + n)
        begins, ends, depth = _supernodes(indptr, indices, n)
        widths = ends - begins + 1
        below_counts = indptr[ends + 1] - indptr[ends]
        groups = self._by_shape(widths, below_counts, depth)
        shapes = [
            _SupernodeShape(self._locate, indptr, indices, data, d, begins[members], ends[members])
            for members in groups
        ]
        steps = sorted(
            (level, k, lo, hi)
            for k, members in enumerate(groups)
            for level, lo, hi in _SupernodeShape.levels(depth[members])
        )
        for _, k, lo, hi in steps:  # root first; the supernodes of one depth are independent
            shape = shapes[k]
            z_jj = shape.z_jj[lo:hi]
            if shape.ms:
                u = shape.u[lo:hi]
                z_sj = -(store[shape.ss_index[lo:hi]] @ u)
                z_jj = z_jj - u.transpose(0, 2, 1) @ z_sj
                store[shape.s_pos[lo:hi]] = z_sj
            store[shape.jj_index[lo:hi]] = z_jj[:, shape.ti, shape.tj]
        self._values = store[:nnz]
        self._diag = store[nnz:]

    @staticmethod
    def _by_shape(widths: IntArray, below_counts: IntArray, depth: IntArray) -> list[IntArray]:
        """The supernodes of each shape (width, rows below), each list by depth."""
        order = np.lexsort((depth, below_counts, widths))
        key = np.stack([widths, below_counts])[:, order]
        cuts = np.flatnonzero(np.any(np.diff(key, axis=1) != 0, axis=0)) + 1
        return np.split(order, cuts)

    def entries(self, rows: IntArray, cols: IntArray) -> Array:
        """``Z[rows, cols]`` (original scalar order) for pairs on the factor's pattern."""
        pr = self.inverse_perm[np.asarray(rows, dtype=np.int64)]
        pc = self.inverse_perm[np.asarray(cols, dtype=np.int64)]
        lo, hi = np.minimum(pr, pc), np.maximum(pr, pc)
        out = np.empty(lo.shape)
        same = lo == hi
        out[same] = self._diag[lo[same]]
        off = ~same
        pos = self._locate(lo[off], hi[off])
        if np.any(pos < 0):
            raise ValueError("requested covariance entries are not on the factor's pattern")
        out[off] = self._values[pos]
        return out


class _SupernodeShape:
    """Supernodes of one shape (width ``w``, ``ms`` rows below), ordered by depth, with what
    :class:`SelectedInverse` needs of them that depends on the factor only: ``Z_JJ``'s first
    term ``L_JJ^-T D_J^-1 L_JJ^-1``, ``U = L_SJ L_JJ^-1`` and where ``Z_SS``, ``Z_SJ`` and
    ``Z_JJ`` are in the store (pattern entries, then the diagonal)."""

    def __init__(
        self,
        locate: PatternPositions,
        indptr: IntArray,
        indices: IntArray,
        data: Array,
        d: Array,
        begins: IntArray,
        ends: IntArray,
    ) -> None:
        nnz = len(data)
        w = int(ends[0] - begins[0] + 1)
        ms = self.ms = int(indptr[ends[0] + 1] - indptr[ends[0]])
        jj_i, jj_j = _tril(w)
        columns = begins[:, None] + np.arange(w)  # (k, w)
        col_start = indptr[columns]
        inv_l = _unit_lower_inverse(data[col_start[:, jj_j] + (jj_i - jj_j - 1)], w, jj_i, jj_j)
        self.z_jj = inv_l.transpose(0, 2, 1) @ (inv_l / d[columns][:, :, None])
        # Z_JJ is stored as its lower triangle and diagonal
        self.ti, self.tj = np.tril_indices(w)
        strict = self.ti > self.tj
        self.jj_index = np.where(
            strict,
            col_start[:, self.tj] + (self.ti - self.tj - 1),
            nnz + columns[:, self.tj],
        )
        if ms:
            below = indices[indptr[ends][:, None] + np.arange(ms)]  # (k, ms), ascending
            ia, ib = _tril(ms)[::-1]  # upper: row below[ia] < column below[ib]
            ss_index = np.empty((len(begins), ms, ms), dtype=np.int64)
            every = np.arange(ms)
            ss_index[:, every, every] = nnz + below
            if len(ia):
                found = locate(below[:, ia].ravel(), below[:, ib].ravel())
                found = found.reshape(len(begins), len(ia))
                ss_index[:, ia, ib] = found
                ss_index[:, ib, ia] = found
            self.ss_index = ss_index
            # L_SJ: column j's rows below the supernode start e - j entries into it
            self.s_pos = (col_start + (ends[:, None] - columns))[:, None, :] + every[:, None]
            self.u = data[self.s_pos] @ inv_l

    @staticmethod
    def levels(depth: IntArray) -> list[tuple[int, int, int]]:
        """``(depth, lo, hi)`` of the runs of equal depth (``depth`` is sorted)."""
        cuts = np.flatnonzero(np.diff(depth)) + 1
        lo = np.r_[0, cuts]
        hi = np.r_[cuts, len(depth)]
        return list(zip(depth[lo].tolist(), lo.tolist(), hi.tolist(), strict=True))


class BlockInverse(_MarginalBlocks):
    """Entries of the inverse of the matrix factored by a :class:`BlockFactor`, on its
    pattern (:meth:`BlockFactor.selected_inverse_rows`: the diagonal blocks whole, the others
    on the factor's nonzero rows), asked for in the problem's scalar order."""

    def __init__(self, factor: BlockFactor) -> None:
        pattern = factor.pattern
        self._inverse, held = factor.selected_inverse_rows()
        self._position = np.empty(pattern.n, dtype=np.int64)
        self._local = np.empty(pattern.n, dtype=np.int64)
        for p, scalars in enumerate(pattern.scalars):
            self._position[scalars] = p
            self._local[scalars] = np.arange(len(scalars))
        self._row_at: dict[tuple[int, int], IntArray] = {}  # block row -> stored row, or -1
        for key, rows in held.items():
            at = np.full(pattern.sizes[key[0]], -1, dtype=np.int64)
            at[rows] = np.arange(len(rows))
            self._row_at[key] = at

    def entries(self, rows: IntArray, cols: IntArray) -> Array:
        """``Z[rows, cols]`` (pairs, the problem's scalar order) for pairs on the pattern."""
        rows = np.asarray(rows, dtype=np.int64)
        cols = np.asarray(cols, dtype=np.int64)
        pr, pc = self._position[rows], self._position[cols]
        lr, lc = self._local[rows], self._local[cols]
        swap = pr < pc
        hi, lo = np.where(swap, pc, pr), np.where(swap, pr, pc)
        hi_local, lo_local = np.where(swap, lc, lr), np.where(swap, lr, lc)
        out = np.empty(rows.shape)
        key = hi * len(self._local) + lo
        for value in np.unique(key):
            sel = key == value
            pair = (int(value // len(self._local)), int(value % len(self._local)))
            block = self._inverse.get(pair)
            at = hi_local[sel]
            if block is not None and pair in self._row_at:
                at = self._row_at[pair][at]
            if block is None or np.any(at < 0):
                raise ValueError("requested covariance entries are not on the factor's pattern")
            out[sel] = block[at, lo_local[sel]]
        return out
