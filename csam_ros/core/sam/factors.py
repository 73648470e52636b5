"""Variable kinds and factor kinds of 2D square-root smoothing (sqrt-SAM, paper eq. 1-2).

A factor kind holds ``K`` factors of the same shape at once: an integer array of connected
variable ids ``(K, m)``, the measurements and the square-root information ``W`` ``(K, d, d)``
with ``W^T W = Sigma^-1``. One vectorised call returns the errors ``e`` ``(K, d)`` and the
Jacobian blocks ``de/dx_j`` ``(K, d, dim_j)`` of all ``K`` factors; the solver whitens them
(``r = W e``, ``A_j = W de/dx_j``) and applies the optional robust kernel.

Parametrisation: every variable is a plain vector in the global frame (pose ``(x, y, phi)``,
point ``(x, y)``); updates are additive and the angle component is wrapped to (-pi, pi]
after each update. Angle differences inside errors are wrapped too.

Error conventions (``e = prediction - measurement``):

- ``PosePrior``: ``(t - t0, wrap(phi - phi0))``, covariance in the global frame.
- ``PointPrior``: ``l - l0``.
- ``RelativePose`` (odometry, docs/METHOD.md section 2): ``between(x_a, x_b) - z`` with the angle
  wrapped, i.e. the pose of ``x_b`` in the frame of ``x_a`` minus the measured one; the
  covariance is expressed in the frame of ``x_a`` (independent of heading).
- ``CalibratedRelativePose`` (odometry with calibration unknowns ``c``):
  ``between(x_a, x_b) - (z0 + J (c - c0))``, the composed odometry linearised in ``c`` at
  ``c0`` (as IMU preintegration corrects for a bias).
- ``PointObservation`` (paper eq. 11-17): ``R(phi)^T (l - t) - z``.
- ``RelativePosition`` (rendezvous in global parametrisation): translation of
  ``(-)x_a (+) x_b`` minus ``z``, i.e. ``R(phi_a)^T (t_b - t_a) - z``.
- ``LinearPrior``: ``x - x0`` over several blocks (angles wrapped), whitened by a dense
  ``R`` (how a local map enters through its marginal square-root information).

To add a factor kind, subclass :class:`Factor`, set ``kinds`` and ``residual_dim`` and
implement :meth:`Factor.evaluate`.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from csam_ros.core.model import se2, sensor

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]


@dataclass(frozen=True)
class VariableKind:
    """A kind of variable block: its dimension and which component is an angle."""

    name: str
    dim: int
    angle_index: int | None = None


POSE = VariableKind("pose", 3, 2)
POINT = VariableKind("point", 2, None)
CALIBRATION = VariableKind("odometry calibration", 3, None)  # (s, k_d, k_s), motion.py


# ---------------------------------------------------------------------------------------------
# robust kernels


class RobustKernel(ABC):
    """An M-estimator applied per factor to ``s = ||W e||^2`` by iteratively reweighted rows.

    The factor's cost ``0.5 ||W e||^2`` becomes ``0.5 rho(s)``; the rows of the factor are
    scaled by ``sqrt(rho'(s))`` at each linearisation.
    """

    @abstractmethod
    def rho(self, s: Array) -> Array:
        """Robust cost of squared whitened norms ``s``."""

    @abstractmethod
    def weight(self, s: Array) -> Array:
        """``rho'(s)``, the weight of the squared residual."""

    @property
    @abstractmethod
    def parameter(self) -> float:
        """The kernel's threshold or scale, in whitened units."""


@dataclass(frozen=True)
class Huber(RobustKernel):
    """Huber kernel: quadratic up to ``threshold`` whitened units, linear beyond."""

    threshold: float = 1.345

    def __post_init__(self) -> None:
        if not self.threshold > 0:
            raise ValueError(f"Huber threshold must be positive, got {self.threshold}")

    def rho(self, s: Array) -> Array:
        k = self.threshold
        r = np.sqrt(s)
        return np.where(r <= k, s, 2.0 * k * r - k * k)

    def weight(self, s: Array) -> Array:
        k = self.threshold
        r = np.sqrt(s)
        return np.where(r <= k, 1.0, k / np.maximum(r, k))

    @property
    def parameter(self) -> float:
        return float(self.threshold)


@dataclass(frozen=True)
class Cauchy(RobustKernel):
    """Cauchy (Lorentzian) kernel with scale ``scale`` in whitened units."""

    scale: float = 2.3849

    def __post_init__(self) -> None:
        if not self.scale > 0:
            raise ValueError(f"Cauchy scale must be positive, got {self.scale}")

    def rho(self, s: Array) -> Array:
        c2 = self.scale**2
        return c2 * np.log1p(s / c2)

    def weight(self, s: Array) -> Array:
        return 1.0 / (1.0 + s / self.scale**2)

    @property
    def parameter(self) -> float:
        return float(self.scale)


# the kernels by the names that parameter files, local map messages and saved states give them
ROBUST_KERNELS: dict[str, type[RobustKernel]] = {"huber": Huber, "cauchy": Cauchy}


def robust_kernel(name: str, parameter: float = 0.0) -> RobustKernel | None:
    """The kernel called ``name`` in :data:`ROBUST_KERNELS` with its threshold or scale
    ``parameter`` (0: the kernel's default); ``None`` for the name ``""``."""
    if not name:
        return None
    kind = ROBUST_KERNELS[name]
    return kind(parameter) if parameter > 0 else kind()


def robust_kernel_name(kernel: RobustKernel | None) -> tuple[str, float] | None:
    """The name in :data:`ROBUST_KERNELS` and the parameter of ``kernel`` (``("", 0.0)`` for
    none), or ``None`` for a kernel of another kind."""
    if kernel is None:
        return "", 0.0
    for name, kind in ROBUST_KERNELS.items():
        if type(kernel) is kind:
            return name, kernel.parameter
    return None


# ---------------------------------------------------------------------------------------------
# checks shared by the factor kinds


def sqrt_information_from_covariance(covariance: ArrayLike, name: str = "factor") -> Array:
    """Square-root information ``W`` with ``W^T W = Sigma^-1`` for covariances ``(K, d, d)``.

    ``W = L^-1`` for the Cholesky factor ``Sigma = L L^T``. A covariance that is not
    symmetric positive definite raises ``ValueError`` naming ``name`` and the factor index.
    """
    cov = np.asarray(covariance, dtype=float)
    if cov.ndim != 3 or cov.shape[1] != cov.shape[2]:
        raise ValueError(f"{name}: covariance must have shape (K, d, d), got {cov.shape}")
    _check_finite(cov.reshape(len(cov), -1), f"{name} covariance")
    asym = np.abs(cov - cov.transpose(0, 2, 1)).max(axis=(1, 2)) if len(cov) else np.zeros(0)
    scale = np.abs(cov).max(axis=(1, 2)) if len(cov) else np.zeros(0)
    bad = np.flatnonzero(asym > 1e-9 * np.maximum(scale, 1e-300))
    if bad.size:
        raise ValueError(f"{name}: covariance of factor {bad[0]} is not symmetric")
    eig_min = np.linalg.eigvalsh(cov)[:, 0] if len(cov) else np.zeros(0)
    bad = np.flatnonzero(~(eig_min > 1e-14 * np.maximum(scale, 1e-300)))
    if bad.size:
        raise ValueError(
            f"{name}: covariance of factor {bad[0]} is not positive definite "
            f"(smallest eigenvalue {eig_min[bad[0]]:.3g})"
        )
    lower = np.linalg.cholesky(cov)
    eye = np.broadcast_to(np.eye(cov.shape[1]), cov.shape)
    return np.linalg.solve(lower, eye)


def _check_finite(array: Array, what: str) -> None:
    flat = array.reshape(len(array), -1) if array.ndim > 1 else array.reshape(-1, 1)
    bad = np.flatnonzero(~np.isfinite(flat).all(axis=1))
    if bad.size:
        raise ValueError(f"{what}: entry {bad[0]} is not finite ({flat[bad[0]].tolist()})")


def _as_ids(ids: ArrayLike, name: str) -> IntArray:
    arr = np.asarray(ids)
    if arr.ndim != 1:
        raise ValueError(f"{name}: variable ids must be one-dimensional, got shape {arr.shape}")
    if arr.size and not np.issubdtype(arr.dtype, np.integer):
        raise ValueError(f"{name}: variable ids must be integers, got dtype {arr.dtype}")
    return arr.astype(np.int64)


def _as_measurements(values: ArrayLike, count: int, dim: int, name: str) -> Array:
    arr = np.asarray(values, dtype=float)
    if arr.shape != (count, dim):
        raise ValueError(f"{name}: measurements must have shape ({count}, {dim}), got {arr.shape}")
    _check_finite(arr, f"{name} measurement")
    return arr


def _as_sqrt_information(
    sqrt_information: ArrayLike | None,
    covariance: ArrayLike | None,
    count: int,
    dim: int,
    name: str,
) -> Array:
    if (sqrt_information is None) == (covariance is None):
        raise ValueError(f"{name}: give exactly one of sqrt_information and covariance")
    if covariance is not None:
        cov = np.asarray(covariance, dtype=float)
        if cov.shape == (dim, dim):
            cov = np.broadcast_to(cov, (count, dim, dim))
        if cov.shape != (count, dim, dim):
            raise ValueError(
                f"{name}: covariance must have shape ({count}, {dim}, {dim}), got {cov.shape}"
            )
        return sqrt_information_from_covariance(cov, name)
    w = np.asarray(sqrt_information, dtype=float)
    if w.shape == (dim, dim):
        w = np.broadcast_to(w, (count, dim, dim))
    if w.shape != (count, dim, dim):
        raise ValueError(
            f"{name}: sqrt_information must have shape ({count}, {dim}, {dim}), got {w.shape}"
        )
    _check_finite(w.reshape(count, -1), f"{name} sqrt_information")
    bad = singular_sqrt_information(w)
    if bad.size:
        raise ValueError(f"{name}: sqrt_information of factor {bad[0]} is singular")
    return np.ascontiguousarray(w)


def singular_sqrt_information(w: Array) -> NDArray[np.int64]:
    """Indices of the (K, d, d) finite square-root information matrices a factor refuses as
    singular: |det W| not above 1e-12 of the scale of its entries to the power d."""
    if len(w) == 0:
        return np.zeros(0, dtype=np.int64)
    dim = w.shape[-1]
    scale = np.abs(w).max(axis=(1, 2))
    det = np.abs(np.linalg.det(w))
    return np.flatnonzero(~(det > 1e-12 * np.maximum(scale, 1e-300) ** dim))


# ---------------------------------------------------------------------------------------------
# factor base class


class Factor(ABC):
    """``K`` factors of one kind, each connecting ``len(kinds)`` variables.

    Attributes:
        kinds: kinds of the connected variables, one per column of ``variables``.
        residual_dim: dimension ``d`` of one factor's error.
        variables: ``(K, m)`` variable ids (as returned by ``Problem.add_variables``).
        sqrt_information: ``(K, d, d)`` with ``W^T W = Sigma^-1``.
        robust: optional robust kernel applied per factor.
        name: used in error messages.
    """

    kinds: tuple[VariableKind, ...]
    residual_dim: int

    def __init__(
        self,
        variables: Sequence[ArrayLike],
        sqrt_information: Array,
        robust: RobustKernel | None,
        name: str,
    ) -> None:
        cols = [_as_ids(v, name) for v in variables]
        count = len(cols[0])
        for c in cols:
            if len(c) != count:
                raise ValueError(f"{name}: variable id arrays have different lengths")
        self.variables: IntArray = (
            np.stack(cols, axis=1) if count else np.zeros((0, len(cols)), int)
        )
        self.sqrt_information: Array = sqrt_information
        self.robust = robust
        self.name = name

    def __len__(self) -> int:
        return len(self.variables)

    @abstractmethod
    def evaluate(
        self, blocks: Sequence[Array], jacobians: bool = True
    ) -> tuple[Array, list[Array]]:
        """Errors ``(K, d)`` and, if asked, Jacobian blocks ``[(K, d, dim_j)]`` at ``blocks``.

        ``blocks[j]`` holds the values ``(K, dim_j)`` of the ``j``-th connected variable.
        """

    def evaluate_stacked(self, blocks: Sequence[Array]) -> tuple[Array, Array]:
        """Errors and the Jacobian blocks side by side ``(K, d, D)``; override to avoid a copy."""
        errors, jac = self.evaluate(blocks, True)
        return errors, (np.concatenate(jac, axis=2) if len(jac) > 1 else jac[0])

    def whitened(
        self, blocks: Sequence[Array], jacobians: bool = True
    ) -> tuple[Array, Array | None, Array]:
        """Whitened (and robustly reweighted) residuals, Jacobian and per-factor costs.

        Returns ``r = W e`` ``(K, d)``; the whitened Jacobian ``W [de/dx_1, ..., de/dx_m]``
        ``(K, d, D)`` with the connected variables' blocks side by side (``None`` unless
        ``jacobians``); and the cost of each factor ``0.5 rho(||W e||^2)``
        (``0.5 ||W e||^2`` without robust kernel).
        """
        w = self.sqrt_information
        if jacobians:
            errors, jac = self.evaluate_stacked(blocks)
            stacked = np.matmul(w, jac)
        else:
            errors, stacked = self.evaluate(blocks, False)[0], None
        r = np.einsum("kij,kj->ki", w, errors)
        s = np.einsum("ki,ki->k", r, r)
        if self.robust is None:
            return r, stacked, 0.5 * s
        scale = np.sqrt(self.robust.weight(s))
        r = r * scale[:, None]
        if stacked is not None:
            stacked = stacked * scale[:, None, None]
        return r, stacked, 0.5 * self.robust.rho(s)


# ---------------------------------------------------------------------------------------------
# factor kinds


class PosePrior(Factor):
    """Prior on poses: ``e = (t - t0, wrap(phi - phi0))``, covariance in the global frame."""

    kinds = (POSE,)
    residual_dim = 3

    def __init__(
        self,
        poses: ArrayLike,
        prior: ArrayLike,
        sqrt_information: ArrayLike | None = None,
        *,
        covariance: ArrayLike | None = None,
        robust: RobustKernel | None = None,
        name: str = "PosePrior",
    ) -> None:
        ids = _as_ids(poses, name)
        w = _as_sqrt_information(sqrt_information, covariance, len(ids), 3, name)
        super().__init__([ids], w, robust, name)
        self.prior = _as_measurements(prior, len(ids), 3, name)

    def evaluate(
        self, blocks: Sequence[Array], jacobians: bool = True
    ) -> tuple[Array, list[Array]]:
        e = blocks[0] - self.prior
        e[:, 2] = se2.wrap_angle(e[:, 2])
        if not jacobians:
            return e, []
        return e, [np.broadcast_to(np.eye(3), (len(e), 3, 3))]


class PointPrior(Factor):
    """Prior on points: ``e = l - l0``."""

    kinds = (POINT,)
    residual_dim = 2

    def __init__(
        self,
        points: ArrayLike,
        prior: ArrayLike,
        sqrt_information: ArrayLike | None = None,
        *,
        covariance: ArrayLike | None = None,
        robust: RobustKernel | None = None,
        name: str = "PointPrior",
    ) -> None:
        ids = _as_ids(points, name)
        w = _as_sqrt_information(sqrt_information, covariance, len(ids), 2, name)
        super().__init__([ids], w, robust, name)
        self.prior = _as_measurements(prior, len(ids), 2, name)

    def evaluate(
        self, blocks: Sequence[Array], jacobians: bool = True
    ) -> tuple[Array, list[Array]]:
        e = blocks[0] - self.prior
        if not jacobians:
            return e, []
        return e, [np.broadcast_to(np.eye(2), (len(e), 2, 2))]


def _between_error(xa: Array, xb: Array, z: Array, jacobians: bool) -> tuple[Array, Array | None]:
    """``between(x_a, x_b) - z`` (angle wrapped) and its Jacobian ``(K, 3, 6)`` in ``x_a, x_b``."""
    c, s = np.cos(xa[:, 2]), np.sin(xa[:, 2])
    dx = xb[:, 0] - xa[:, 0]
    dy = xb[:, 1] - xa[:, 1]
    lx = c * dx + s * dy
    ly = -s * dx + c * dy
    e = np.stack([lx - z[:, 0], ly - z[:, 1], se2.wrap_angle(xb[:, 2] - xa[:, 2] - z[:, 2])], 1)
    if not jacobians:
        return e, None
    jac = np.zeros((len(c), 3, 6))
    jac[:, 0, 0], jac[:, 0, 1], jac[:, 0, 2] = -c, -s, ly
    jac[:, 1, 0], jac[:, 1, 1], jac[:, 1, 2] = s, -c, -lx
    jac[:, 2, 2] = -1.0
    jac[:, 0, 3], jac[:, 0, 4] = c, s
    jac[:, 1, 3], jac[:, 1, 4] = -s, c
    jac[:, 2, 5] = 1.0
    return e, jac


class RelativePose(Factor):
    """Relative pose (odometry): ``e = between(x_a, x_b) - z``, angle wrapped, frame of ``x_a``."""

    kinds = (POSE, POSE)
    residual_dim = 3

    def __init__(
        self,
        first: ArrayLike,
        second: ArrayLike,
        measured: ArrayLike,
        sqrt_information: ArrayLike | None = None,
        *,
        covariance: ArrayLike | None = None,
        robust: RobustKernel | None = None,
        name: str = "RelativePose",
    ) -> None:
        a = _as_ids(first, name)
        w = _as_sqrt_information(sqrt_information, covariance, len(a), 3, name)
        super().__init__([a, second], w, robust, name)
        self.measured = _as_measurements(measured, len(a), 3, name)

    def evaluate(
        self, blocks: Sequence[Array], jacobians: bool = True
    ) -> tuple[Array, list[Array]]:
        e, jac = self._evaluate(blocks, jacobians)
        return e, ([jac[:, :, :3], jac[:, :, 3:]] if jac is not None else [])

    def evaluate_stacked(self, blocks: Sequence[Array]) -> tuple[Array, Array]:
        e, jac = self._evaluate(blocks, True)
        return e, jac  # type: ignore[return-value]

    def _evaluate(self, blocks: Sequence[Array], jacobians: bool) -> tuple[Array, Array | None]:
        return _between_error(blocks[0], blocks[1], self.measured, jacobians)


class CalibratedRelativePose(Factor):
    """Odometry with calibration unknowns: ``e = between(x_a, x_b) - (z0 + J (c - c0))``,
    angle wrapped, frame of ``x_a``; ``J = dz/dc`` ``(K, 3, 3)`` at ``c0`` ``(K, 3)``."""

    kinds = (POSE, POSE, CALIBRATION)
    residual_dim = 3

    def __init__(
        self,
        first: ArrayLike,
        second: ArrayLike,
        calibration: ArrayLike,
        measured: ArrayLike,
        calibration_jacobians: ArrayLike,
        linearisation: ArrayLike,
        sqrt_information: ArrayLike | None = None,
        *,
        covariance: ArrayLike | None = None,
        robust: RobustKernel | None = None,
        name: str = "CalibratedRelativePose",
    ) -> None:
        a = _as_ids(first, name)
        w = _as_sqrt_information(sqrt_information, covariance, len(a), 3, name)
        super().__init__([a, second, calibration], w, robust, name)
        self.measured = _as_measurements(measured, len(a), 3, name)
        jac = np.asarray(calibration_jacobians, dtype=float)
        if jac.shape != (len(a), 3, 3):
            raise ValueError(f"{name}: calibration_jacobians must be ({len(a)}, 3, 3)")
        _check_finite(jac.reshape(len(a), -1), f"{name} calibration_jacobians")
        self.calibration_jacobians = jac
        lin = np.asarray(linearisation, dtype=float)
        self.linearisation = _as_measurements(
            np.broadcast_to(lin, (len(a), 3)) if lin.shape == (3,) else lin, len(a), 3, name
        )

    def evaluate(
        self, blocks: Sequence[Array], jacobians: bool = True
    ) -> tuple[Array, list[Array]]:
        xa, xb, cal = blocks
        z = self.measured + np.einsum(
            "kij,kj->ki", self.calibration_jacobians, cal - self.linearisation
        )
        e, jac = _between_error(xa, xb, z, jacobians)
        if jac is None:
            return e, []
        return e, [jac[:, :, :3], jac[:, :, 3:], -self.calibration_jacobians]


def _point_in_body(
    pose: Array, point: Array, jacobians: bool
) -> tuple[Array, Array | None, Array | None]:
    """``R(phi)^T (l - t)`` with its Jacobians w.r.t. the pose and the point."""
    if not jacobians:
        return sensor.predict(pose, point), None, None
    return sensor.predict_jacobians(pose, point)


class PointObservation(Factor):
    """Point seen from a pose in Cartesian body coordinates: ``e = R(phi)^T (l - t) - z``."""

    kinds = (POSE, POINT)
    residual_dim = 2

    def __init__(
        self,
        poses: ArrayLike,
        points: ArrayLike,
        measured: ArrayLike,
        sqrt_information: ArrayLike | None = None,
        *,
        covariance: ArrayLike | None = None,
        robust: RobustKernel | None = None,
        name: str = "PointObservation",
    ) -> None:
        a = _as_ids(poses, name)
        w = _as_sqrt_information(sqrt_information, covariance, len(a), 2, name)
        super().__init__([a, points], w, robust, name)
        self.measured = _as_measurements(measured, len(a), 2, name)

    def evaluate(
        self, blocks: Sequence[Array], jacobians: bool = True
    ) -> tuple[Array, list[Array]]:
        h, jp, jl = _point_in_body(blocks[0], blocks[1], jacobians)
        e = h - self.measured
        return e, ([jp, jl] if jacobians else [])

    def evaluate_stacked(self, blocks: Sequence[Array]) -> tuple[Array, Array]:
        pose, point = blocks
        c, s = np.cos(pose[:, 2]), np.sin(pose[:, 2])
        dx = point[:, 0] - pose[:, 0]
        dy = point[:, 1] - pose[:, 1]
        lx = c * dx + s * dy
        ly = -s * dx + c * dy
        e = np.stack([lx, ly], 1) - self.measured
        jac = np.zeros((len(c), 2, 5))
        jac[:, 0, 0], jac[:, 0, 1], jac[:, 0, 2] = -c, -s, ly
        jac[:, 1, 0], jac[:, 1, 1], jac[:, 1, 2] = s, -c, -lx
        jac[:, 0, 3], jac[:, 0, 4] = c, s
        jac[:, 1, 3], jac[:, 1, 4] = -s, c
        return e, jac


class RelativePosition(Factor):
    """Position of pose ``x_b`` seen from pose ``x_a``: ``e = R(phi_a)^T (t_b - t_a) - z``.

    The rendezvous measurement of two poses in one frame (global parametrisation); the
    heading of ``x_b`` does not enter.
    """

    kinds = (POSE, POSE)
    residual_dim = 2

    def __init__(
        self,
        observers: ArrayLike,
        observed: ArrayLike,
        measured: ArrayLike,
        sqrt_information: ArrayLike | None = None,
        *,
        covariance: ArrayLike | None = None,
        robust: RobustKernel | None = None,
        name: str = "RelativePosition",
    ) -> None:
        a = _as_ids(observers, name)
        w = _as_sqrt_information(sqrt_information, covariance, len(a), 2, name)
        super().__init__([a, observed], w, robust, name)
        self.measured = _as_measurements(measured, len(a), 2, name)

    def evaluate(
        self, blocks: Sequence[Array], jacobians: bool = True
    ) -> tuple[Array, list[Array]]:
        h, jp, jl = _point_in_body(blocks[0], blocks[1][:, :2], jacobians)
        e = h - self.measured
        if not jacobians:
            return e, []
        jb = np.zeros((len(e), 2, 3))
        jb[:, :, :2] = jl
        return e, [jp, jb]


class LinearPrior(Factor):
    """Dense Gaussian prior over several blocks: ``r = R (x - x0)``, angle differences wrapped.

    One factor (``K = 1``) connecting ``variables`` of the given ``kinds``; ``mean`` and the
    columns of ``sqrt_information`` (``(D', D)``, ``D`` the summed block dimensions, any
    number ``D'`` of rows) follow the order of ``variables``. This is how a local map
    enters a joint problem through its marginal square-root information.
    """

    residual_dim = 0

    def __init__(
        self,
        variables: ArrayLike,
        kinds: Sequence[VariableKind],
        mean: ArrayLike,
        sqrt_information: ArrayLike,
        *,
        robust: RobustKernel | None = None,
        name: str = "LinearPrior",
    ) -> None:
        ids = _as_ids(variables, name)
        kinds = tuple(kinds)
        if len(kinds) != len(ids):
            raise ValueError(f"{name}: {len(ids)} variables but {len(kinds)} kinds")
        dim = sum(k.dim for k in kinds)
        mean = np.asarray(mean, dtype=float).reshape(-1)
        if mean.shape != (dim,):
            raise ValueError(f"{name}: mean must have {dim} entries, got {mean.shape}")
        _check_finite(mean[None], f"{name} mean")
        r = np.asarray(sqrt_information, dtype=float)
        if r.ndim != 2 or r.shape[1] != dim:
            raise ValueError(f"{name}: sqrt_information must have shape (*, {dim}), got {r.shape}")
        _check_finite(r[None], f"{name} sqrt_information")
        self.kinds = kinds
        self.residual_dim = r.shape[0]
        super().__init__([ids[j : j + 1] for j in range(len(ids))], r[None], robust, name)
        self.mean = mean
        offsets = np.cumsum([0] + [k.dim for k in kinds])
        self._slices = [slice(offsets[j], offsets[j + 1]) for j in range(len(kinds))]
        self._angles = np.array(
            [offsets[j] + k.angle_index for j, k in enumerate(kinds) if k.angle_index is not None],
            dtype=np.int64,
        )

    def evaluate(
        self, blocks: Sequence[Array], jacobians: bool = True
    ) -> tuple[Array, list[Array]]:
        x = np.concatenate([b[0] for b in blocks])
        delta = x - self.mean
        delta[self._angles] = se2.wrap_angle(delta[self._angles])
        # The errors are the raw differences; the solver whitens them by R. Jacobians are the
        # identity columns of each block.
        e = delta[None]
        if not jacobians:
            return e, []
        dim = len(x)
        eye = np.eye(dim)
        return e, [eye[:, s][None] for s in self._slices]

    def whitened(
        self, blocks: Sequence[Array], jacobians: bool = True
    ) -> tuple[Array, Array | None, Array]:
        e, _ = self.evaluate(blocks, jacobians=False)
        rmat = self.sqrt_information[0]
        r = (rmat @ e[0])[None]
        jac = rmat[None].copy() if jacobians else None
        s2 = np.array([r[0] @ r[0]])
        if self.robust is None:
            return r, jac, 0.5 * s2
        scale = float(np.sqrt(self.robust.weight(s2))[0])
        return r * scale, (None if jac is None else jac * scale), 0.5 * self.robust.rho(s2)
