"""Algorithm 1's dense Newton solver (:func:`dense_newton`), kept as the test oracle of the
sparse one (:mod:`csam_ros.core.joining.sparse_newton`, ``AlignmentOptions.method =
"dense-newton"``): the same Newton step with the connectors' second derivatives, Gauss-Newton
where that matrix is not positive definite, in the one iteration of
:func:`csam_ros.core.sam.solver.minimise`, but on the dense matrix (LAPACK Cholesky) and with
the covariance of the whole state by the dense inverse (LAPACK ``potri``). Its cost grows with
the cube of the unknowns; nothing but the tests selects it."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import scipy.linalg
from numpy.typing import NDArray

from csam_ros.core.joining.connector import Connector
from csam_ros.core.joining.sparse_newton import factor_columns
from csam_ros.core.sam.normal_equations import NormalEquations, SingularProblemError
from csam_ros.core.sam.solver import Problem, SolveReport, SolverOptions, minimise

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]


def _connector_curvature(problem: Problem, values: Array, n: int) -> Array:
    """``sum_i r_i d^2 r_i / dx^2`` over all connector rows (dense (n, n)): the part of the
    Hessian of the cost that Gauss-Newton leaves out (the priors are linear;
    :meth:`~csam_ros.core.joining.connector.Connector.curvature`)."""
    out = np.zeros((n, n))
    for factor in problem.factors:
        if not isinstance(factor, Connector):
            continue
        cols, splits = factor_columns(problem, factor)
        curvature = factor.curvature(np.split(values[cols], splits, axis=1))
        rows = np.broadcast_to(cols[:, :, None], curvature.shape)
        np.add.at(out, (rows, np.broadcast_to(cols[:, None, :], curvature.shape)), curvature)
    return out


def _dense_information(system: NormalEquations) -> Array:
    """The assembled ``A^T A`` of normal equations as a full dense matrix."""
    n = system.n
    rows = system.indices
    cols = np.repeat(np.arange(n), np.diff(system.indptr))
    full = np.zeros((n, n))
    full[rows, cols] = system.hessian_data
    full[cols, rows] = system.hessian_data
    return full


def _damped(matrix: Array, scale: Array) -> Array:
    """``matrix + diag(scale)`` (a copy)."""
    out = matrix.copy()
    out.flat[:: len(out) + 1] += scale
    return out


def _cholesky(matrix: Array) -> tuple[Array, bool] | None:
    """Upper Cholesky factor (scipy ``cho_factor`` form, ``matrix`` is overwritten) or ``None``
    if not positive definite (a pivot below ``1e-14`` of its diagonal entry counts as zero,
    as in the sparse solver)."""
    reference = np.maximum(np.diag(matrix).copy(), 1e-300)
    try:
        factor = scipy.linalg.cho_factor(matrix, lower=False, overwrite_a=True, check_finite=False)
    except np.linalg.LinAlgError:
        return None
    if not np.all(np.diag(factor[0]) ** 2 > 1e-14 * reference):
        return None
    return factor


class DenseNewtonStep:
    """Newton step of Algorithm 1's cost with a positive-definite fallback (dense LAPACK
    Cholesky; :func:`dense_newton`): the model ``A^T A + sum r_i d^2 r_i`` when, damped by
    ``lambda diag(A^T A)``, it is positive definite, otherwise the Gauss-Newton ``A^T A``."""

    def __init__(self, problem: Problem, system: NormalEquations) -> None:
        self.problem = problem
        self.system = system
        self.information = np.zeros((0, 0))
        self.curvature = np.zeros((0, 0))

    def relinearised(self) -> None:
        problem = self.problem
        self.information = _dense_information(self.system)
        self.curvature = _connector_curvature(problem, problem.values, problem.dim)

    def propose(self, damping: float) -> tuple[Array, float] | None:
        gradient = self.system.gradient
        scale = damping * np.diag(self.information)
        model = self.information + self.curvature
        factor = _cholesky(_damped(model, scale))
        if factor is None:
            model = self.information
            factor = _cholesky(_damped(model, scale))
        if factor is None:
            if damping == 0.0:
                raise SingularProblemError(
                    "the Algorithm 1 information matrix is singular: some base node or "
                    "rendezvous pose is not determined"
                )
            return None
        step = -scipy.linalg.cho_solve(factor, gradient, check_finite=False)
        return step, -float(gradient @ step + 0.5 * step @ (model @ step))


def dense_newton(
    problem: Problem, options: SolverOptions, keys: Sequence[tuple]
) -> tuple[SolveReport, Array]:
    """Minimise Algorithm 1's cost in place by Newton's method; returns the report and the
    joint covariance of ``keys`` (inverse of ``A^T A`` at the estimate, as
    :func:`~csam_ros.core.sam.covariance.marginal_covariance`).

    Why Newton: the rendezvous priors are weak along each map's rigid rotation (a tenth of a
    radian on MR.CLAM) and the connectors' residuals stay large, so the term
    ``sum_i r_i d^2 r_i`` that Gauss-Newton drops is comparable to ``A^T A`` along those
    directions; Gauss-Newton then converges linearly (about a hundred iterations on MR.CLAM
    Dataset 1, five robots), Newton quadratically. The Newton matrix ``A^T A + sum r_i
    d^2 r_i`` is used whenever it is positive definite (with the damping), otherwise the
    Gauss-Newton matrix (:class:`DenseNewtonStep`); the iteration (damping, gain ratio,
    acceptance, stopping) is :func:`csam_ros.core.sam.solver.minimise`, the loop of
    :func:`~csam_ros.core.sam.solver.gauss_newton`, the gain measured against the model used.
    Dense LAPACK Cholesky: the priors make the system dense by blocks anyway (one robot's
    rendezvous poses are all coupled).
    """
    system = problem.normal_equations(options.backend)
    report = minimise(problem, options, DenseNewtonStep(problem, system))
    # covariance from A^T A at the estimate (no damping, no curvature), like the sparse path
    system.assemble(system.evaluate(problem.values))
    factor = _cholesky(_dense_information(system))
    if factor is None:
        raise SingularProblemError("the Algorithm 1 information matrix is singular")
    cols = problem.scalar_indices(problem.indices(keys))
    # the inverse from the factor (LAPACK potri, upper triangle), not n solves with unit columns
    inverse, info = scipy.linalg.lapack.dpotri(factor[0], lower=False, overwrite_c=True)
    if info != 0:
        raise SingularProblemError("the Algorithm 1 information matrix is singular")
    inverse = np.triu(inverse) + np.triu(inverse, 1).T
    return report, inverse[np.ix_(cols, cols)]
