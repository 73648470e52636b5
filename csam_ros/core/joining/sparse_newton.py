"""Algorithm 1's Newton solver on the sparse graph of the problem (:func:`sparse_newton`).

The unknowns are the robots' rendezvous poses and base nodes. Each robot's rendezvous prior
couples its own rendezvous poses (a dense block of the information matrix); a connector row
couples one pose of each of two robots and their base nodes. So the information matrix is
sparse by blocks: one dense block per robot, linked only where robots met. It is assembled by
the project's sparse normal equations (:class:`~csam_ros.core.sam.normal_equations.
NormalEquations`, the pattern built once) and factored by blocks
(:mod:`~csam_ros.core.sam.block_cholesky`: LAPACK on each block, the work on the coupled
rows only).

The step is Newton's (:class:`SparseNewtonStep`): ``A^T A`` plus the connectors' second
derivatives ``sum_i r_i d^2 r_i / dx^2``. Those couple only the variables of one connector row,
which ``A^T A`` couples already, so they are added into the same sparse pattern. Where that
matrix, damped by ``lambda diag(A^T A)``, is not positive definite (a Cholesky pivot whose
square is at most ``1e-14`` of its diagonal entry), the step is Gauss-Newton's, on ``A^T A``.
The iteration (damping, gain ratio, acceptance, stopping) is
:func:`csam_ros.core.sam.solver.minimise`. This is the dense Newton solver
(:mod:`csam_ros.core.joining.dense_newton`, the test oracle) step for step, on the sparse
matrix: the same steps up to rounding.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from csam_ros.core.joining.connector import Connector
from csam_ros.core.joining.state_covariance import FactoredStateCovariance
from csam_ros.core.sam.block_cholesky import BlockPattern, block_cholesky
from csam_ros.core.sam.factors import Factor
from csam_ros.core.sam.normal_equations import NormalEquations, SingularProblemError
from csam_ros.core.sam.solver import Problem, SolveReport, SolverOptions, minimise

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]


def factor_columns(problem: Problem, factor: Factor) -> tuple[IntArray, list[int]]:
    """Scalar columns (K, D) of each factor's variables and the split points of its blocks."""
    dims = [k.dim for k in factor.kinds]
    cols = np.concatenate(
        [
            problem.offsets[factor.variables[:, j]][:, None] + np.arange(d)
            for j, d in enumerate(dims)
        ],
        axis=1,
    )
    return cols, [int(x) for x in np.cumsum(dims)[:-1]]


class _ConnectorEntries:
    """Where one connector factor's per-row ``D x D`` blocks go in the upper-triangular CSC
    data of the normal equations: the upper-triangle pairs ``(first, second)`` of a block and
    the data position of each pair of each row."""

    def __init__(self, problem: Problem, factor: Connector, entry_keys: IntArray) -> None:
        n = problem.dim
        self.factor = factor
        self.columns, self.splits = factor_columns(problem, factor)
        self.first, self.second = np.triu_indices(self.columns.shape[1])
        a, b = self.columns[:, self.first], self.columns[:, self.second]
        keys = np.maximum(a, b) * n + np.minimum(a, b)  # column * n + row, upper triangle
        positions = np.searchsorted(entry_keys, keys)
        if np.any(entry_keys[np.minimum(positions, len(entry_keys) - 1)] != keys):
            raise ValueError("a connector's entries are not in the normal equations' pattern")
        self.positions = positions.reshape(-1)

    def curvature(self, values: Array) -> Array:
        """The rows' curvature at ``values`` on the pattern: (K * pairs,) weights for
        :attr:`positions`."""
        blocks = np.split(values[self.columns], self.splits, axis=1)
        block = self.factor.curvature(blocks)
        return block[:, self.first, self.second].reshape(-1)


class SparseNewtonStep:
    """Newton step of Algorithm 1's cost on the sparse normal equations, Gauss-Newton where
    the damped Newton matrix is not positive definite (module docstring); a
    :class:`~csam_ros.core.sam.solver.StepRule`."""

    def __init__(self, problem: Problem, system: NormalEquations, pattern: BlockPattern) -> None:
        self.problem = problem
        self.system = system
        self.pattern = pattern
        n = system.n
        self._indices = system.indices
        self._indptr = system.indptr
        # the CSC entries as sorted keys column * n + row
        entry_keys = np.repeat(np.arange(n, dtype=np.int64), np.diff(system.indptr)) * n
        entry_keys += system.indices.astype(np.int64)
        self._connectors = [
            _ConnectorEntries(problem, f, entry_keys)
            for f in problem.factors
            if isinstance(f, Connector)
        ]
        self._diagonal = system.diagonal_positions
        self.information: Array = np.zeros(system.nnz)
        self.curvature: Array = np.zeros(system.nnz)

    def relinearised(self) -> None:
        system = self.system
        self.information = system.hessian_data
        curvature = np.zeros(system.nnz)
        values = self.problem.values
        for entries in self._connectors:
            curvature += np.bincount(
                entries.positions, weights=entries.curvature(values), minlength=system.nnz
            )
        self.curvature = curvature

    def _product(self, data: Array, x: Array) -> Array:
        """The symmetric matrix of upper triangle ``data`` times ``x``."""
        upper = sp.csc_matrix((data, self._indices, self._indptr), shape=(self.system.n,) * 2)
        return upper @ x + upper.T @ x - data[self._diagonal] * x

    def propose(self, damping: float) -> tuple[Array, float] | None:
        gradient = self.system.gradient
        scale = damping * self.information[self._diagonal]
        for model in (self.information + self.curvature, self.information):
            damped = model.copy()
            damped[self._diagonal] += scale
            factor = block_cholesky(self.pattern, damped)
            if factor is not None:
                break
        else:
            if damping == 0.0:
                raise SingularProblemError(
                    "the Algorithm 1 information matrix is singular: some base node or "
                    "rendezvous pose is not determined"
                )
            return None
        step = -factor.solve(gradient)
        return step, -float(gradient @ step + 0.5 * step @ self._product(model, step))


def factor_at_estimate(problem: Problem, pattern: BlockPattern) -> FactoredStateCovariance:
    """The state's covariance from the block factor of ``A^T A`` at the problem's values (no
    damping, no curvature: the information whose inverse is the state's covariance), the
    information kept; SingularProblemError when it is not positive definite."""
    system = problem.normal_equations()
    system.linearize(problem.values)
    information = system.hessian_data.copy()
    factor = block_cholesky(pattern, information)
    if factor is None:
        raise SingularProblemError("the Algorithm 1 information matrix is singular")
    return FactoredStateCovariance(factor, information)


def block_pattern(system: NormalEquations, blocks: Sequence[IntArray]) -> BlockPattern:
    """The block pattern of normal equations, the last of ``blocks`` (scalar indices)
    eliminated last."""
    return BlockPattern(system.indptr, system.indices, blocks, len(blocks) - 1)


def sparse_newton(
    problem: Problem, options: SolverOptions, blocks: Sequence[IntArray]
) -> tuple[SolveReport, FactoredStateCovariance]:
    """Minimise Algorithm 1's cost in place by Newton's method on the sparse matrix, factored
    by ``blocks`` (scalar indices of each robot's rendezvous poses, then of the base nodes:
    :mod:`~csam_ros.core.sam.block_cholesky`); returns the report and the state's
    covariance from the factor of ``A^T A`` at the estimate (:func:`factor_at_estimate`).

    Why Newton: the rendezvous priors are weak along each map's rigid rotation (a tenth of a
    radian on MR.CLAM) and the connectors' residuals stay large, so the term ``sum_i r_i
    d^2 r_i`` that Gauss-Newton drops is comparable to ``A^T A`` along those directions;
    Gauss-Newton then converges linearly (about a hundred iterations on MR.CLAM Dataset 1,
    five robots), Newton quadratically (24).
    """
    system = problem.normal_equations(options.backend)  # the one minimise assembles
    pattern = block_pattern(system, blocks)
    report = minimise(problem, options, SparseNewtonStep(problem, system, pattern))
    return report, factor_at_estimate(problem, pattern)
