"""Marginal covariances and marginal square-root information of selected variables.

With ``A^T A = P L D L^T P^T`` (the solver's factorisation at the current estimate) the
joint covariance of a set ``S`` of variables is ``E_S^T (A^T A)^-1 E_S = Y^T D^-1 Y`` with
``Y = L^-1 P^T E_S``: one sparse forward substitution per needed column, never the dense
inverse (paper section III, docs/METHOD.md section 4.5). ``Y`` is nonzero only on the rows
reached from ``S`` in the elimination tree, so the substitution runs on those rows of ``L``
alone (at the end of an MR.CLAM robot's map, 60 poses reach 6,162 of 15,051 rows: 101 -> 44
ms).

The marginal square-root information of ``S`` is the last block of the upper-triangular
square-root information ``R`` when ``S`` is ordered last; it equals the upper Cholesky factor
of the Schur complement ``(A^T A)_SS - (A^T A)_SO (A^T A)_OO^-1 (A^T A)_OS``, which is the
inverse of the marginal covariance of ``S``. It is returned as that upper-triangular ``R_S``
(``R_S^T R_S`` = marginal information) with the order of its columns.

Parametrisation: global, additive ``(x, y, phi)`` per pose and ``(x, y)`` per point.
"""

from __future__ import annotations

from collections.abc import Hashable, Sequence

import numpy as np
import scipy.sparse as sp
from numpy.typing import ArrayLike, NDArray
from scipy.linalg import cho_factor, cho_solve_banded, cholesky_banded, solve_triangular
from scipy.linalg.lapack import dpotri
from scipy.sparse.linalg import spsolve_triangular

from csam_ros.core.sam.normal_equations import NormalEquations
from csam_ros.core.sam.solver import Problem

Array = NDArray[np.float64]

# the widest band (scalars off the diagonal) of H_OO that covariance_by_elimination factors:
# a chain of 3-scalar poses has 5
BAND_LIMIT = 8


def factorize_at_estimate(problem: Problem, backend: str = "qdldl") -> NormalEquations:
    """Linearise and factor the problem at its current values (no damping)."""
    system = problem.normal_equations(backend)
    system.linearize(problem.values)
    system.factorize(0.0)
    return system


def _columns_of(problem: Problem, keys: Sequence[Hashable]) -> NDArray[np.int64]:
    if len(keys) == 0:
        raise ValueError("no variables selected")
    if len(set(keys)) != len(keys):
        raise ValueError("selected variables contain duplicates")
    return problem.scalar_indices(problem.indices(keys))


def marginal_covariance(
    problem: Problem,
    keys: Sequence[Hashable],
    system: NormalEquations | None = None,
) -> Array:
    """Joint marginal covariance ``(D, D)`` of ``keys`` (blocks in the given order).

    ``system`` is a factorisation at the estimate (from :func:`factorize_at_estimate`); one is
    made when not given. Cost: one sparse triangular solve per selected scalar column.
    """
    system = system or factorize_at_estimate(problem)
    return covariance_block(system, _columns_of(problem, keys))


def covariance_block(system: NormalEquations, scalar_indices: ArrayLike) -> Array:
    """``(A^T A)^-1`` at the given scalar positions (rows and columns in that order) from the
    factorisation ``system``: the joint covariance of those components."""
    cols = np.asarray(scalar_indices, dtype=np.int64)
    if system.block_factor is not None:
        rhs = np.zeros((system.n, len(cols)))
        rhs[cols, np.arange(len(cols))] = 1.0
        cov = system.block_factor.solve(rhs)[cols]
        return 0.5 * (cov + cov.T)
    if system.backend != "qdldl":
        rhs = np.zeros((system.n, len(cols)))
        rhs[cols, np.arange(len(cols))] = 1.0
        x = np.column_stack([system.solve(rhs[:, j]) for j in range(len(cols))])
        cov = x[cols]
        return 0.5 * (cov + cov.T)
    strict_lower, d, perm = system._factorization.factors()  # type: ignore[union-attr]
    strict_lower = sp.csc_matrix(strict_lower)
    n = system.n
    inverse_perm = np.empty(n, dtype=np.int64)
    inverse_perm[perm] = np.arange(n)
    # Y is zero outside the rows the forward substitution reaches from the selected columns
    rows = _reach(_elimination_tree(strict_lower), inverse_perm[cols])
    restricted = strict_lower[rows][:, rows]
    unit_lower = (restricted + sp.eye(len(rows), format="csc")).tocsr()
    rhs = np.zeros((len(rows), len(cols)))
    rhs[np.searchsorted(rows, inverse_perm[cols]), np.arange(len(cols))] = 1.0
    y = spsolve_triangular(unit_lower, rhs, lower=True, unit_diagonal=True)
    y = np.atleast_2d(y.T).T
    cov = (y / d[rows, None]).T @ y
    return 0.5 * (cov + cov.T)


def covariance_columns(
    system: NormalEquations, scalar_indices: ArrayLike, rows: ArrayLike | None = None
) -> Array:
    """``(A^T A)^-1`` at ``rows`` (default: every scalar, in the problem's order) and the
    columns ``S = scalar_indices``: the cross covariance of those unknowns with ``S``.

    ``Y = L^-1 P^T E_S`` on the rows the forward substitution reaches from ``S``, then the
    backward substitution ``L^-T D^-1 Y`` on the rows the wanted ones need (their ancestors in
    the elimination tree: ``z_j`` takes ``z_i`` only for ``L_ij != 0``, ``i`` above ``j``).
    Cost ``O(nnz(L) |S|)`` at most, linear in the map for a fixed ``S``, where
    :func:`covariance_block` over ``S`` and the wanted rows grows with their square.
    """
    cols = np.asarray(scalar_indices, dtype=np.int64)
    n = system.n
    wanted = np.arange(n) if rows is None else np.asarray(rows, dtype=np.int64)
    if system.backend != "qdldl":
        rhs = np.zeros((n, len(cols)))
        rhs[cols, np.arange(len(cols))] = 1.0
        return np.column_stack([system.solve(rhs[:, j]) for j in range(len(cols))])[wanted]
    strict_lower, d, perm = system._factorization.factors()  # type: ignore[union-attr]
    strict_lower = sp.csc_matrix(strict_lower)
    inverse_perm = np.empty(n, dtype=np.int64)
    inverse_perm[perm] = np.arange(n)
    parent = _elimination_tree(strict_lower)
    forward = _reach(parent, inverse_perm[cols])
    unit_lower = (strict_lower[forward][:, forward] + sp.eye(len(forward), format="csc")).tocsr()
    rhs = np.zeros((len(forward), len(cols)))
    rhs[np.searchsorted(forward, inverse_perm[cols]), np.arange(len(cols))] = 1.0
    y = spsolve_triangular(unit_lower, rhs, lower=True, unit_diagonal=True).reshape(rhs.shape)
    backward = _reach(parent, inverse_perm[wanted])
    w = np.zeros((len(backward), len(cols)))
    inside = np.isin(forward, backward, assume_unique=True)
    w[np.searchsorted(backward, forward[inside])] = y[inside] / d[forward[inside], None]
    restricted = strict_lower[backward][:, backward]
    unit_upper = (restricted.T + sp.eye(len(backward), format="csr")).tocsr()
    z = spsolve_triangular(unit_upper, w, lower=False, unit_diagonal=True).reshape(w.shape)
    return z[np.searchsorted(backward, inverse_perm[wanted])]


def covariance_by_elimination(
    system: NormalEquations, selected: ArrayLike, rest: ArrayLike
) -> Array | None:
    """``(A^T A)^-1`` on ``S = selected`` (rows and columns in that order): the inverse of
    the Schur complement ``H_SS - H_SO H_OO^-1 H_OS`` of ``H = A^T A``, every other scalar
    ``O = rest`` eliminated in the order given. None when ``H_OO`` in that order is not
    banded within :data:`BAND_LIMIT`, or it or the Schur complement is not numerically
    positive definite (then :func:`covariance_columns` serves).

    Made for a robot's map with ``S`` its rendezvous poses and features and ``O`` its other
    poses in stamp order: ``H_OO`` is then an odometry chain cut at every rendezvous pose into
    independent segments. One banded Cholesky factor of ``H_OO``; each segment solved only for
    the few columns of ``S`` it touches (the rendezvous poses at its ends and the features seen
    from it). Linear in the map, where the columns of ``S`` by substitution through the whole
    factor cost ``O(nnz(L) |S|)``.
    """
    s = np.asarray(selected, dtype=np.int64)
    o = np.asarray(rest, dtype=np.int64)
    full = system.full_matrix()
    by_rest = full[o]
    h_oo = by_rest[:, o].tocsr()
    h_oo.sort_indices()
    rows = np.repeat(np.arange(len(o)), np.diff(h_oo.indptr))
    offset = h_oo.indices - rows
    width = int(np.max(np.abs(offset), initial=0))
    if width > BAND_LIMIT:
        return None
    banded = np.zeros((width + 1, len(o)))
    up = offset >= 0
    banded[width - offset[up], h_oo.indices[up]] = h_oo.data[up]
    try:
        factor = cholesky_banded(banded, lower=False, check_finite=False)
    except np.linalg.LinAlgError:
        return None
    # segments: no entry of H_OO couples the scalars before a boundary with those after it
    # (every row holds its diagonal entry, so its last column is at least the row)
    last = h_oo.indices[h_oo.indptr[1:] - 1]
    ends = np.flatnonzero(np.maximum.accumulate(last) == np.arange(len(o))) + 1
    h_os = by_rest[:, s].tocsr()
    schur = full[s][:, s].toarray()
    for lo, hi in zip(np.r_[0, ends][:-1], ends, strict=True):
        first, stop = h_os.indptr[lo], h_os.indptr[hi]
        if first == stop:
            continue
        touched, columns = np.unique(h_os.indices[first:stop], return_inverse=True)
        rhs = np.zeros((hi - lo, len(touched)))
        segment_rows = np.repeat(np.arange(hi - lo), np.diff(h_os.indptr[lo : hi + 1]))
        rhs[segment_rows, columns] = h_os.data[first:stop]
        x = cho_solve_banded((factor[:, lo:hi], False), rhs, check_finite=False)
        schur[np.ix_(touched, touched)] -= rhs.T @ x
    try:
        cholesky = cho_factor(schur, lower=False, check_finite=False)
    except np.linalg.LinAlgError:
        return None
    inverse, info = dpotri(cholesky[0], lower=False, overwrite_c=True)
    return None if info != 0 else np.triu(inverse) + np.triu(inverse, 1).T


def _elimination_tree(strict_lower: sp.csc_matrix) -> NDArray[np.int64]:
    """Parent of each column in the elimination tree of a factor with this strictly lower
    pattern (its first row below the diagonal; -1 for a root)."""
    counts = np.diff(strict_lower.indptr)
    parent = np.full(strict_lower.shape[1], -1, dtype=np.int64)
    filled = counts > 0
    if filled.any():
        parent[filled] = np.minimum.reduceat(strict_lower.indices, strict_lower.indptr[:-1][filled])
    return parent


def _reach(parent: NDArray[np.int64], columns: NDArray[np.int64]) -> NDArray[np.int64]:
    """Sorted union of the paths from ``columns`` to their roots: the rows where a forward
    substitution with right-hand sides at ``columns`` can be nonzero (Gilbert's theorem)."""
    marked = bytearray(len(parent))
    up = parent.tolist()
    for start in np.asarray(columns).tolist():
        c = start
        while c >= 0 and not marked[c]:
            marked[c] = 1
            c = up[c]
    return np.flatnonzero(np.frombuffer(marked, dtype=np.uint8))


def marginal_covariances(
    problem: Problem,
    keys: Sequence[Hashable],
    system: NormalEquations | None = None,
) -> list[Array]:
    """The diagonal covariance block of each variable in ``keys`` (no cross terms)."""
    system = system or factorize_at_estimate(problem)
    out: list[Array] = []
    chunk = 64
    for start in range(0, len(keys), chunk):
        part = list(keys[start : start + chunk])
        cov = marginal_covariance(problem, part, system)
        dims = [problem.kind(k).dim for k in part]
        edges = np.cumsum([0, *dims])
        out.extend(cov[edges[i] : edges[i + 1], edges[i] : edges[i + 1]] for i in range(len(part)))
    return out


def marginal_sqrt_information(
    problem: Problem,
    keys: Sequence[Hashable],
    system: NormalEquations | None = None,
) -> tuple[Array, list[Hashable]]:
    """Upper-triangular ``R_S`` with ``R_S^T R_S`` the marginal information of ``keys``.

    Returns ``(R_S, order)``; the columns of ``R_S`` follow ``order`` (= ``keys``), block by
    block, and ``R_S`` is the last block of ``R`` for an ordering with ``keys`` last.
    """
    return upper_sqrt_information(marginal_covariance(problem, keys, system)), list(keys)


def upper_sqrt_information(covariance: Array) -> Array:
    """Upper-triangular ``R`` with positive diagonal and ``R^T R = covariance^-1``."""
    # covariance = U U^T with U upper gives covariance^-1 = U^-T U^-1, so R = U^-1
    flip = np.arange(len(covariance))[::-1]
    lower_of_flipped = np.linalg.cholesky(covariance[np.ix_(flip, flip)])
    upper = lower_of_flipped[np.ix_(flip, flip)]
    r = solve_triangular(upper, np.eye(len(covariance)), lower=False)
    signs = np.sign(np.diag(r))
    return r * signs[:, None]
