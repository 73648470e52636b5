"""Sparse nonlinear least squares for 2D smoothing and mapping (sqrt-SAM, paper eq. 1-2).

Public API (stable; other modules build on it)::

    from csam_ros.core.sam.factors import (POSE, POINT, VariableKind, PosePrior, PointPrior,
        RelativePose, PointObservation, RelativePosition, LinearPrior, Huber, Cauchy,
        sqrt_information_from_covariance, Factor)
    from csam_ros.core.sam.solver import Problem, SolverOptions, SolveReport

    problem = Problem()
    ids = problem.add_variables(POSE, keys, initial)          # keys: any hashables, (K, 3)
    lid = problem.add_variables(POINT, ["l1", "l2"], xy)     # (K, 2) -> ids (K,)
    problem.add_factor(PosePrior(ids[:1], [[0, 0, 0]], covariance=np.eye(3) * 1e-12))
    problem.add_factor(RelativePose(ids[:-1], ids[1:], z, covariance=cov))   # cov (K,3,3)
    problem.add_factor(PointObservation(pose_ids, point_ids, z_xy, covariance=cov_xy))
    report = problem.solve(SolverOptions())                   # Gauss-Newton / LM, in place
    problem.values_of(ids)                                    # (K, dim) current estimate
    problem.value("l1"); problem.index("l1"); problem.indices(keys)
    problem.cost()                                            # 0.5 * sum of squared whitened
                                                              # (robust) residuals, like GTSAM

    from csam_ros.core.sam.covariance import marginal_covariance, marginal_sqrt_information
    cov = marginal_covariance(problem, keys)                  # dense joint block, cross terms
    r_s, order = marginal_sqrt_information(problem, keys)     # upper R with R^T R = marginal info

A new pose-like block (e.g. a base node) is ``VariableKind("base_node", 3, angle_index=2)``;
a new factor kind subclasses ``factors.Factor`` (see its docstring).

Method. Every factor kind returns its whitened residuals and Jacobian blocks for all of its
factors in one vectorised call; the normal equations are assembled and factorised by
:class:`~csam_ros.core.sam.normal_equations.NormalEquations` (sparse, qdldl).

Iteration: pure Gauss-Newton steps while the cost falls by at least a quarter of what the
linear model predicts (gain ratio ``rho`` = actual / predicted decrease); otherwise
Levenberg-Marquardt damping ``lambda * diag(A^T A)`` is switched on (``initial_damping``),
divided by 10 after a step with ``rho > 0.75``, doubled after one with ``rho < 0.25``,
multiplied by 10 after a rejected step, and dropped (pure Gauss-Newton again) below
``1e-9``. A step is accepted when it does not raise the cost. (On Victoria Park from dead
reckoning this simple rule reached lower local minima than Nielsen's rule.) This loop
(:func:`minimise`, with :class:`StepControl`) is the only one: a :class:`StepRule` supplies the
step, the sparse Gauss-Newton step here (:class:`GaussNewtonStep`) or Algorithm 1's Newton
step (:class:`csam_ros.core.joining.sparse_newton.SparseNewtonStep`; the dense one of
:mod:`csam_ros.core.joining.dense_newton` is the tests' oracle).

Extrapolation (``max_step_scale`` > 1, off by default). With a robust kernel each step is
iteratively reweighted least squares: the model's curvature ``rho'(s) A^T A`` exceeds the
cost's true curvature wherever residuals lie in the kernel's flat part (for Cauchy, the
curvature along a residual is ``(1 - s/c^2) / (1 + s/c^2)^2``, zero at one scale and
negative beyond, against ``1 / (1 + s/c^2)``), so convergence becomes linear and slow along
nearly flat directions. The symptom is a gain ratio near 2 (actual decrease twice the
predicted one: no curvature along the step). After an undamped step with gain above
``extrapolation_gain`` the step is doubled (2, 4, ... up to ``max_step_scale``) while the
cost keeps falling, judged by cost evaluations only; the best point is then linearised as
usual. Every accepted point still lowers the cost. (The exact Hessian of the kernel, the
Triggs correction clamped to stay positive, led the C-SAM joint solve of MR.CLAM to local
minima 35 units higher; on the same solve extrapolation converges in 68 iterations
where plain reweighting needs 220.)

Convergence: after an accepted step whose cost decrease is below ``relative_tolerance``
times the previous cost, or below ``cost_tolerance`` (off by default: a decrease below 0.5,
half a unit of chi-square, is a Gauss-Newton step under one standard deviation in the
information metric, since its model predicts ``0.5 ||d||^2`` in ``A^T A``), or whose largest
component is below ``step_tolerance`` (metres / radians; the stretched step if extrapolated),
or when a rejected step is already below
``step_tolerance`` (numerical minimum). ``iterations`` counts factorisations (accepted and
rejected steps). A trial point is evaluated once, residuals and Jacobians together
(:meth:`~csam_ros.core.sam.normal_equations.NormalEquations.evaluate`); if the step is
accepted these are assembled into the next normal equations
(:meth:`~csam_ros.core.sam.normal_equations.NormalEquations.assemble`) without
evaluating the factors again.

Gauge: a smoother fixes its frame with a :class:`~csam_ros.core.sam.factors.PosePrior` on the
first pose whose sigma (default ``GAUGE_SIGMA = 1e-6`` m and rad) is far below every other
sigma; this module does not add it by itself. A singular system raises
:class:`~csam_ros.core.sam.normal_equations.SingularProblemError` naming the variable where it
became singular.

Parametrisation of covariances: global, additive ``(x, y, phi)`` per pose, ``(x, y)`` per point.
"""

from __future__ import annotations

import time
from collections.abc import Hashable, Iterable
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from csam_ros.core.model import se2
from csam_ros.core.sam.factors import Factor, VariableKind
from csam_ros.core.sam.normal_equations import NormalEquations

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]

GAUGE_SIGMA = 1e-6


@dataclass
class SolverOptions:
    """Settings of :meth:`Problem.solve`."""

    max_iterations: int = 100
    relative_tolerance: float = 1e-10
    cost_tolerance: float = 0.0  # absolute cost decrease (module docstring; 0: off)
    step_tolerance: float = 1e-9
    initial_damping: float = 1e-4
    max_damping: float = 1e12
    backend: str = "qdldl"  # or "splu" (scipy SuperLU with COLAMD)
    # largest factor an undamped step with gain ratio above ``extrapolation_gain`` is
    # stretched by, doubling while the cost falls (1: never; see the module docstring)
    max_step_scale: float = 1.0
    extrapolation_gain: float = 1.5

    def __post_init__(self) -> None:
        if not self.max_step_scale >= 1.0:
            raise ValueError(f"max_step_scale must be at least 1, got {self.max_step_scale}")
        if not self.cost_tolerance >= 0.0:
            raise ValueError(f"cost_tolerance must be at least 0, got {self.cost_tolerance}")
        if not self.extrapolation_gain > 1.0:
            raise ValueError(f"extrapolation_gain must be above 1, got {self.extrapolation_gain}")


@dataclass
class SolveReport:
    """What :meth:`Problem.solve` did."""

    iterations: int
    initial_cost: float
    final_cost: float
    converged: bool
    reason: str
    seconds: float
    cost_history: list[float] = field(default_factory=list)
    extrapolations: int = 0  # accepted steps that were stretched (``max_step_scale``)


class Problem:
    """Variables (blocks of given kinds, identified by hashable keys) and factors."""

    def __init__(self) -> None:
        self._keys: list[Hashable] = []
        self._index: dict[Hashable, int] = {}
        self._kinds: list[VariableKind] = []
        self._kind_codes: dict[VariableKind, int] = {}
        self._kind_of: IntArray = np.zeros(0, dtype=np.int64)
        self._dims: IntArray = np.zeros(0, dtype=np.int64)
        self.offsets: IntArray = np.zeros(0, dtype=np.int64)
        self.values: Array = np.zeros(0)
        self.factors: list[Factor] = []
        self._angle_positions: IntArray = np.zeros(0, dtype=np.int64)
        self._system: NormalEquations | None = None
        # variables grouped for a block factorisation, taken where it is cheaper than qdldl's
        # (NormalEquations._choose_blocks); None: never
        self.variable_blocks: list[IntArray] | None = None

    # -- variables ---------------------------------------------------------------------------

    @property
    def num_variables(self) -> int:
        return len(self._keys)

    @property
    def dim(self) -> int:
        """Total number of scalar unknowns."""
        return len(self.values)

    @property
    def keys(self) -> list[Hashable]:
        return list(self._keys)

    def kind(self, key: Hashable) -> VariableKind:
        return self._kinds[self.index(key)]

    def add_variables(
        self, kind: VariableKind, keys: Iterable[Hashable], initial: ArrayLike
    ) -> IntArray:
        """Add variables of one kind with initial values ``(K, kind.dim)``; returns their ids."""
        keys = list(keys)
        init = np.asarray(initial, dtype=float).reshape(len(keys), -1) if keys else np.zeros((0,))
        if keys and init.shape != (len(keys), kind.dim):
            raise ValueError(
                f"initial values of {kind.name} variables must have shape "
                f"({len(keys)}, {kind.dim}), got {np.shape(initial)}"
            )
        bad = np.flatnonzero(~np.isfinite(init.reshape(len(keys), -1)).all(axis=1)) if keys else []
        if len(bad):
            raise ValueError(f"initial value of variable {keys[bad[0]]!r} is not finite")
        start = len(self._keys)
        for i, key in enumerate(keys):
            if key in self._index:
                raise ValueError(f"variable {key!r} already exists")
            self._index[key] = start + i
        if len(self._index) != start + len(keys):
            raise ValueError("duplicate keys in one add_variables call")
        self._keys.extend(keys)
        self._kinds.extend([kind] * len(keys))
        code = self._kind_codes.setdefault(kind, len(self._kind_codes))
        self._kind_of = np.concatenate([self._kind_of, np.full(len(keys), code, dtype=np.int64)])
        offset0 = len(self.values)
        new_offsets = offset0 + kind.dim * np.arange(len(keys), dtype=np.int64)
        self.offsets = np.concatenate([self.offsets, new_offsets])
        self._dims = np.concatenate([self._dims, np.full(len(keys), kind.dim, dtype=np.int64)])
        if keys:
            init = init.copy()
            if kind.angle_index is not None:
                init[:, kind.angle_index] = se2.wrap_angle(init[:, kind.angle_index])
                self._angle_positions = np.concatenate(
                    [self._angle_positions, new_offsets + kind.angle_index]
                )
            self.values = np.concatenate([self.values, init.reshape(-1)])
        self._system = None
        return np.arange(start, start + len(keys), dtype=np.int64)

    def add_variable(self, kind: VariableKind, key: Hashable, initial: ArrayLike) -> int:
        """Add one variable; returns its id."""
        return int(self.add_variables(kind, [key], np.asarray(initial, dtype=float)[None])[0])

    def index(self, key: Hashable) -> int:
        try:
            return self._index[key]
        except KeyError:
            raise KeyError(f"no variable {key!r} in the problem") from None

    def indices(self, keys: Iterable[Hashable]) -> IntArray:
        return np.array([self.index(k) for k in keys], dtype=np.int64)

    def key(self, index: int) -> Hashable:
        return self._keys[index]

    def has(self, key: Hashable) -> bool:
        return key in self._index

    def scalar_indices(self, ids: ArrayLike) -> IntArray:
        """Positions in :attr:`values` of the components of variables ``ids`` (concatenated)."""
        ids = np.asarray(ids, dtype=np.int64).reshape(-1)
        dims = self._dims[ids]
        starts = np.repeat(self.offsets[ids], dims)
        within = np.arange(dims.sum()) - np.repeat(np.cumsum(dims) - dims, dims)
        return starts + within

    def values_of(self, ids: ArrayLike) -> Array:
        """Current values ``(K, dim)`` of variables ``ids`` (all of one dimension)."""
        ids = np.asarray(ids, dtype=np.int64)
        if ids.size == 0:
            return np.zeros((0, 0))
        dim = int(self._dims[ids[0]])
        if np.any(self._dims[ids] != dim):
            raise ValueError("values_of needs variables of one dimension")
        return self.values[self.offsets[ids][:, None] + np.arange(dim)]

    def value(self, key: Hashable) -> Array:
        i = self.index(key)
        return self.values[self.offsets[i] : self.offsets[i] + self._dims[i]].copy()

    def set_values(self, ids: ArrayLike, values: ArrayLike) -> None:
        """Overwrite the values of variables ``ids`` (all of one dimension)."""
        ids = np.asarray(ids, dtype=np.int64)
        if ids.size == 0:
            return
        dim = int(self._dims[ids[0]])
        vals = np.asarray(values, dtype=float).reshape(len(ids), dim)
        self.values[self.offsets[ids][:, None] + np.arange(dim)] = vals
        self.wrap_angles()

    def wrap_angles(self) -> None:
        self.values[self._angle_positions] = se2.wrap_angle(self.values[self._angle_positions])

    # -- factors -----------------------------------------------------------------------------

    def add_factor(self, factor: Factor) -> None:
        """Add a factor kind instance after checking its variable ids and kinds."""
        if len(factor) == 0:
            return
        ids = factor.variables
        bad = np.flatnonzero(((ids < 0) | (ids >= self.num_variables)).any(axis=1))
        if bad.size:
            raise ValueError(
                f"{factor.name}: factor {bad[0]} refers to unknown variable id(s) "
                f"{ids[bad[0]].tolist()}"
            )
        ordered = np.sort(ids, axis=1)
        twice = ordered[:, 1:] == ordered[:, :-1]
        if np.any(twice):
            row = int(np.flatnonzero(twice.any(axis=1))[0])
            variable = int(ordered[row, 1:][twice[row]][0])
            raise ValueError(
                f"{factor.name}: factor {row} connects variable {self._keys[variable]!r} twice"
            )
        for j, kind in enumerate(factor.kinds):
            code = self._kind_codes.get(kind, -1)
            wrong = np.flatnonzero(self._kind_of[ids[:, j]] != code)
            if wrong.size:
                got = self._kinds[ids[wrong[0], j]]
                raise ValueError(
                    f"{factor.name}: factor {wrong[0]} connects variable "
                    f"{self._keys[ids[wrong[0], j]]!r} of kind {got.name} where a "
                    f"{kind.name} is expected"
                )
        self.factors.append(factor)
        self._system = None

    # -- evaluation --------------------------------------------------------------------------

    def _blocks(self, factor: Factor, values: Array) -> list[Array]:
        return [
            values[self.offsets[factor.variables[:, j]][:, None] + np.arange(kind.dim)]
            for j, kind in enumerate(factor.kinds)
        ]

    def cost(self, values: Array | None = None) -> float:
        """``0.5 * sum`` of squared whitened residuals (robust cost where a kernel is set)."""
        vals = self.values if values is None else values
        return float(
            sum(f.whitened(self._blocks(f, vals), jacobians=False)[2].sum() for f in self.factors)
        )

    def take_if_cheaper(self, values: Array) -> bool:
        """Make ``values`` the estimate if they cost less than the current one (a warm start
        against the cold one); whether they did."""
        if np.array_equal(values, self.values) or not self.cost(values) < self.cost():
            return False
        self.values = values
        return True

    def factor_costs(self, values: Array | None = None) -> list[Array]:
        """Per-factor costs of each factor kind instance, in :attr:`factors` order."""
        vals = self.values if values is None else values
        return [f.whitened(self._blocks(f, vals), jacobians=False)[2] for f in self.factors]

    def squared_errors(self, values: Array | None = None) -> list[Array]:
        """Per factor kind, each factor's squared whitened error ``||W e||^2`` (no robust
        kernel), in :attr:`factors` order."""
        vals = self.values if values is None else values
        squared = []
        for f in self.factors:
            errors = f.evaluate(self._blocks(f, vals), False)[0]
            r = np.einsum("kij,kj->ki", f.sqrt_information, errors)
            squared.append(np.einsum("ki,ki->k", r, r))
        return squared

    def normal_equations(self, backend: str = "qdldl") -> NormalEquations:
        """The (cached) normal-equation structure of the current variables and factors."""
        if self._system is None or self._system.backend != backend:
            self._system = NormalEquations(self, backend)
        return self._system

    # -- solving -----------------------------------------------------------------------------

    def solve(self, options: SolverOptions | None = None) -> SolveReport:
        """Minimise the cost by Gauss-Newton with a Levenberg-Marquardt safeguard, in place."""
        return gauss_newton(self, options or SolverOptions())


@dataclass
class StepControl:
    """Levenberg-Marquardt damping and the stopping rules (module docstring), shared by the
    sparse solver and Algorithm 1's dense Newton solver."""

    options: SolverOptions
    damping: float = 0.0
    converged: bool = False
    reason: str = "maximum iterations reached"

    def accepted(
        self, decrease: float, previous_cost: float, step_norm: float, gain: float
    ) -> bool:
        """After a step that lowered the cost by ``decrease``, ``gain`` times the predicted
        decrease: whether to stop; otherwise start damping on a poor model, relax it on a
        good one."""
        o = self.options
        if decrease <= o.relative_tolerance * max(previous_cost, 1e-300):
            self.converged, self.reason = True, "relative cost decrease below tolerance"
        elif decrease <= o.cost_tolerance:
            self.converged, self.reason = True, "cost decrease below tolerance"
        elif step_norm <= o.step_tolerance:
            self.converged, self.reason = True, "step below tolerance"
        elif self.damping == 0.0:
            self.damping = o.initial_damping if gain < 0.25 else 0.0
        elif gain > 0.75:
            self.damping = self.damping / 10.0 if self.damping > 1e-9 else 0.0
        elif gain < 0.25:
            self.damping *= 2.0
        return self.converged

    def rejected(self, step_norm: float) -> bool:
        """After a step that raised the cost: whether to stop; otherwise damp more."""
        o = self.options
        if step_norm <= o.step_tolerance:
            self.converged, self.reason = True, "step below tolerance (cost at numerical minimum)"
            return True
        self.damping = o.initial_damping if self.damping == 0.0 else self.damping * 10.0
        if self.damping > o.max_damping:
            self.reason = "damping exceeded its maximum without lowering the cost"
            return True
        return False

    def indefinite(self) -> bool:
        """After a damped model that was not positive definite: whether to stop; otherwise
        damp ten times more."""
        self.damping *= 10.0
        if self.damping > self.options.max_damping:
            self.reason = "damping exceeded its maximum without a positive definite system"
            return True
        return False


class StepRule(Protocol):
    """How :func:`minimise` computes a step at the current linearisation: the sparse
    Gauss-Newton / Levenberg-Marquardt step (:class:`GaussNewtonStep`) or Algorithm 1's
    Newton step (:class:`csam_ros.core.joining.sparse_newton.SparseNewtonStep`)."""

    def propose(self, damping: float) -> tuple[Array, float] | None:
        """The step at ``damping`` and the decrease its model predicts, or ``None`` when the
        damped model is not positive definite (damp more and try again)."""
        ...

    def relinearised(self) -> None:
        """The problem's normal equations were reassembled at an accepted point."""
        ...


class GaussNewtonStep:
    """Gauss-Newton step of the sparse normal equations, damped by ``lambda diag(A^T A)``."""

    def __init__(self, system: NormalEquations) -> None:
        self.system = system

    def propose(self, damping: float) -> tuple[Array, float]:
        system = self.system
        system.factorize(damping)
        gradient = system.gradient
        step = system.solve(-gradient)
        # decrease predicted by the (damped) linear model: 0.5 (lambda d^T D d - g^T d)
        scaled = damping * float(step @ (system.diagonal * step)) if damping > 0.0 else 0.0
        return step, 0.5 * (scaled - float(gradient @ step))

    def relinearised(self) -> None:
        pass


def gauss_newton(problem: Problem, options: SolverOptions) -> SolveReport:
    """Gauss-Newton with Levenberg-Marquardt safeguard (see the module docstring)."""
    system = problem.normal_equations(options.backend)
    return minimise(problem, options, GaussNewtonStep(system))


def minimise(problem: Problem, options: SolverOptions, rule: StepRule) -> SolveReport:
    """Minimise the problem's cost in place with the steps of ``rule``: the one iteration of
    both solvers (acceptance, damping and stopping by :class:`StepControl`, extrapolation;
    module docstring). The normal equations are assembled at the current values first, then
    after every accepted step (``rule.relinearised()``)."""
    start = time.perf_counter()
    system = problem.normal_equations(options.backend)
    current = system.evaluate(problem.values)
    system.assemble(current)
    rule.relinearised()
    cost = current.cost
    history = [cost]
    initial = cost
    control = StepControl(options)
    iterations = 0
    extrapolations = 0
    angles = problem._angle_positions
    while iterations < options.max_iterations:
        damping = control.damping
        proposal = rule.propose(damping)
        iterations += 1
        if proposal is None:
            if control.indefinite():
                break
            continue
        step, predicted = proposal
        candidate = problem.values + step
        candidate[angles] = se2.wrap_angle(candidate[angles])
        # residuals and Jacobians at once: an accepted candidate is not evaluated again
        trial = system.evaluate(candidate)
        new_cost = trial.cost
        step_norm = float(np.abs(step).max()) if step.size else 0.0
        if new_cost <= cost:
            gain = (cost - new_cost) / predicted if predicted > 0.0 else 1.0
            if damping == 0.0 and gain > options.extrapolation_gain:
                scale, stretched = _extrapolate(
                    problem, system, step, new_cost, options.max_step_scale
                )
                if scale > 1.0:
                    candidate = stretched
                    trial = system.evaluate(candidate)
                    new_cost = trial.cost
                    step_norm *= scale
                    extrapolations += 1
            problem.values = candidate
            decrease, cost = cost - new_cost, new_cost
            history.append(cost)
            if control.accepted(decrease, history[-2], step_norm, gain):
                break
            system.assemble(trial)
            rule.relinearised()
        elif control.rejected(step_norm):
            break
    return SolveReport(
        iterations=iterations,
        initial_cost=initial,
        final_cost=cost,
        converged=control.converged,
        reason=control.reason,
        seconds=time.perf_counter() - start,
        cost_history=history,
        extrapolations=extrapolations,
    )


def _extrapolate(
    problem: Problem, system: NormalEquations, step: Array, cost: float, max_scale: float
) -> tuple[float, Array]:
    """Stretch ``step`` by 2, 4, ... (at most ``max_scale``) while the cost falls below
    ``cost`` (its value at the full step); returns the best scale and point (scale 1: no
    stretch helped). Only costs are evaluated here."""
    angles = problem._angle_positions
    scale, best, best_cost = 1.0, problem.values, cost
    while 2.0 * scale <= max_scale:
        candidate = problem.values + (2.0 * scale) * step
        candidate[angles] = se2.wrap_angle(candidate[angles])
        trial_cost = system.cost(candidate)
        if not trial_cost < best_cost:
            break
        scale, best, best_cost = 2.0 * scale, candidate, trial_cost
    return scale, best


def gauge_prior_sqrt_information(sigma: float = GAUGE_SIGMA) -> Array:
    """``(3, 3)`` square-root information of the gauge prior on a robot's first pose."""
    return np.eye(3) / sigma
