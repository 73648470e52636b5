"""Map alignment through base nodes (paper section IV-A, Algorithm 1; docs/METHOD.md sections 5, 7).

Every robot ``r`` connected to the reference robot (the first one) through the rendezvous
graph gets a base node ``B_r``: the pose of its local frame ``G_r`` in the reference frame.

Initial value, from what is observable (docs/METHOD.md section 5). For a pair of robots ``a``
(already placed) and ``c``:

- if both measured each other at (nearly) the same stamp, the relative heading of the two
  robots is ``pi + beta_ac - beta_ca`` and the paper's eq. 19 gives ``b_ac``;
- otherwise, with two or more measurements, the closed-form 2D rigid registration
  (weighted Kabsch/Umeyama) of the observed robot's positions in one frame onto the measured
  positions in the other;
- then a few Gauss-Newton steps on ``b_ac`` alone (local poses fixed). If the heading standard
  deviation of ``b_ac`` implied by the rendezvous rows (local poses taken as exact) exceeds
  ``max_heading_sigma`` (one measurement, or positions not spread enough compared with the
  noise), ``c`` stays ``pending``: a map joined on an unobservable base node is a wrong map.

``B_c = B_a (+) b_ac``, in breadth-first order from the reference through the robots' order.

Refinement (Algorithm 1): the rendezvous poses of all placed robots and all their base nodes.
Each local map enters only through its :class:`RendezvousPart`, the marginal square-root
information ``R_r`` of its rendezvous poses at its own estimate (a dense linear prior
``||R_r (rho_r - rho_r^0)||^2`` that is never relinearised); only the connector rows (eq.
22-24, :class:`~csam_ros.core.joining.connector.Connector`) are relinearised. The problem is
solved as the sparse graph it is, one dense block per robot, linked where robots met
(:func:`~csam_ros.core.joining.sparse_newton.sparse_newton`): Newton's method with the
connectors' second derivatives, Gauss-Newton where that matrix is not positive definite,
Levenberg-Marquardt safeguard, the sparse normal equations factored by blocks
(:mod:`~csam_ros.core.sam.block_cholesky`). Gauss-Newton alone converges linearly here (the
priors are weak along each map's rigid rotation and the connector residuals stay large): on
MR.CLAM Dataset 1 (five robots, 1,941 unknowns) it took about 100 iterations, Newton 24 to a
lower cost (``method="gauss-newton"`` runs it, the generic sparse solver).
``method="dense-newton"`` is the same Newton iteration on the dense matrix
(:mod:`~csam_ros.core.joining.dense_newton`), the tests' oracle. Stopping rule: after a step
whose largest component is below ``step_tolerance`` (m, rad) or whose relative cost decrease is
below ``relative_tolerance``, at most ``max_iterations`` steps. The state's covariance comes
from the block factor at the estimate
(:class:`~csam_ros.core.joining.state_covariance.FactoredStateCovariance`: the base nodes' from
the factor's last block, other blocks by solves, the whole matrix only when
:attr:`Alignment.covariance` is read).

The observability check is on what the rendezvous rows determine (local poses fixed), not on
the base node's marginal after Algorithm 1, which also carries each map's own drift between
its first pose and the rendezvous and may legitimately be large.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
from numpy.typing import ArrayLike, NDArray

from csam_ros.core.joining.connector import BASE_NODE, Connector
from csam_ros.core.joining.dense_newton import dense_newton
from csam_ros.core.joining.sparse_newton import block_pattern, factor_at_estimate, sparse_newton
from csam_ros.core.joining.state_covariance import (
    DenseStateCovariance,
    StateCovariance,
)
from csam_ros.core.model import rendezvous, se2
from csam_ros.core.model.rendezvous import RendezvousSet
from csam_ros.core.sam.factors import POSE, LinearPrior, sqrt_information_from_covariance
from csam_ros.core.sam.normal_equations import SingularProblemError
from csam_ros.core.sam.solver import Problem, SolverOptions

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]

# AlignmentOptions.method: the sparse Newton solver ("auto" is "newton"), the sparse
# Gauss-Newton solver, and the dense Newton solver (the tests' oracle)
METHODS = ("auto", "newton", "gauss-newton", "dense-newton")

# a robot's alignment status: the reference, aligned, or "pending: <reason>"
REFERENCE = "reference"
ALIGNED = "aligned"


def joined(status: str) -> bool:
    """Whether a robot of alignment ``status`` is in the joined map (the reference or aligned)."""
    return status in (REFERENCE, ALIGNED)


@dataclass
class RendezvousPart:
    """What a robot shares first (paper IV-A): its rendezvous poses and their information.

    ``pose_indices`` (n,) index the robot's poses (its local map's pose list), ``poses``
    (n, 3) are their estimates in ``G_r`` and ``sqrt_information`` (3n, 3n) is upper
    triangular with ``R^T R`` their marginal information (columns in the same order).
    """

    pose_indices: IntArray
    poses: Array
    sqrt_information: Array

    def __post_init__(self) -> None:
        n = len(self.pose_indices)
        if self.poses.shape != (n, 3) or self.sqrt_information.shape != (3 * n, 3 * n):
            raise ValueError(
                f"RendezvousPart: {n} pose indices need poses (n, 3) and sqrt_information "
                f"(3n, 3n), got {self.poses.shape} and {self.sqrt_information.shape}"
            )

    def local_index(self, pose_indices: ArrayLike, robot: str) -> IntArray:
        """Positions in this part of the given robot pose indices (error when absent)."""
        idx = np.asarray(pose_indices, dtype=np.int64)
        order = np.argsort(self.pose_indices)
        sorted_idx = self.pose_indices[order]
        pos = np.clip(np.searchsorted(sorted_idx, idx), 0, max(len(sorted_idx) - 1, 0))
        bad = np.flatnonzero(sorted_idx[pos] != idx) if len(sorted_idx) else np.arange(len(idx))
        if bad.size:
            raise ValueError(
                f"robot {robot!r}: pose {idx[bad[0]]} of a rendezvous measurement is not among "
                "the rendezvous poses of its map"
            )
        return order[pos].astype(np.int64)


@dataclass
class AlignmentOptions:
    """Settings of base-node initialisation and Algorithm 1."""

    max_heading_sigma: float = np.deg2rad(5.0)  # rad; relative heading from the rendezvous
    mutual_time_tolerance: float = 1e-3  # s; "same stamp" for mutual measurements
    max_iterations: int = 50
    step_tolerance: float = 1e-9
    relative_tolerance: float = 1e-12
    # METHODS: "auto" and "newton" are sparse Newton, "gauss-newton" the generic sparse
    # solver, "dense-newton" the dense oracle of the tests
    method: str = "auto"

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise ValueError(f"AlignmentOptions.method must be one of {METHODS}: {self.method!r}")


@dataclass
class PairInitialisation:
    """Initial ``b_ac`` between two robots, or why there is none."""

    base: Array | None
    heading_sigma: float
    method: str  # "mutual" | "registration" | "" when failed
    measurements: int
    reason: str = ""


@dataclass
class Alignment:
    """Result of Algorithm 1 over all robots (index ``r`` follows :attr:`robots`).

    ``state_keys`` lists the variables of the Algorithm 1 system in the order of the rows
    and columns of its covariance: ``("rho", r, k)`` for the ``k``-th rendezvous pose of
    robot ``r`` and ``("base", r)`` for its base node (the reference has none).
    ``state_covariance`` answers for blocks (:meth:`covariance_block`) without the whole
    matrix; :attr:`covariance` forms the whole matrix on first use.
    """

    robots: list[str]
    reference: int
    status: list[str]  # "reference" | "aligned" | "pending: <reason>"
    base_nodes: Array  # (R, 3), NaN rows for pending robots
    initial_base_nodes: Array  # (R, 3) before refinement, NaN where none
    rendezvous_poses: dict[int, Array]  # robot -> (n, 3) refined rendezvous poses
    rendezvous_shift: dict[int, Array]  # robot -> (n, 3) refined minus local (angle wrapped)
    state_keys: list[tuple]
    state_covariance: StateCovariance  # joint covariance of the state
    iterations: int = 0
    final_cost: float = 0.0
    converged: bool = True  # False: Algorithm 1 stopped at its iteration limit or failed
    stop_reason: str = ""
    parents: dict[int, int] = field(default_factory=dict)  # robot -> robot it was placed from
    methods: dict[int, str] = field(default_factory=dict)
    warm_start: bool = False  # refined from the start given (lower cost), not the cold one

    def aligned(self, r: int) -> bool:
        """Whether robot ``r`` is in the joined map (:func:`joined`)."""
        return joined(self.status[r])

    @cached_property
    def covariance(self) -> Array:
        """The whole joint covariance of the state (dim, dim), formed on first use."""
        return self.state_covariance.dense()

    @property
    def state_dim(self) -> int:
        """Scalars of the state (rows of its covariance)."""
        return 3 * len(self.state_keys)

    def covariance_block(self, rows: IntArray, cols: IntArray) -> Array:
        """Entries (len(rows), len(cols)) of the state's covariance, without the whole."""
        return self.state_covariance.block(rows, cols)

    def state_columns(self, key: tuple) -> IntArray:
        """Rows/columns of ``covariance`` of one state variable."""
        i = self._key_index[key]
        return np.arange(3 * i, 3 * i + 3)

    def rho_columns(self, r: int) -> IntArray:
        """Rows/columns of ``covariance`` of all rendezvous poses of robot ``r`` (in order)."""
        n = len(self.rendezvous_poses.get(r, ()))
        return np.concatenate([self.state_columns(("rho", r, k)) for k in range(n)])

    def base_columns(self, r: int) -> IntArray | None:
        """Rows/columns of robot ``r``'s base node, ``None`` for the reference."""
        return self.state_columns(("base", r)) if ("base", r) in self._key_index else None

    def base_covariance(self, r: int) -> Array:
        """Covariance (3, 3) of robot ``r``'s base node after Algorithm 1 (zero: reference)."""
        cols = self.base_columns(r)
        return np.zeros((3, 3)) if cols is None else self.covariance_block(cols, cols)

    def __post_init__(self) -> None:
        self._key_index = {k: i for i, k in enumerate(self.state_keys)}


def _rows_between(
    measurements: RendezvousSet, a: int, c: int
) -> tuple[NDArray[np.bool_], RendezvousSet]:
    mask = measurements.between(a, c)
    return mask, measurements.subset(mask)


def _pair_prediction(
    rows: RendezvousSet, a: int, poses: dict[int, Array], base: Array
) -> tuple[Array, Array]:
    """Connector residuals (K, 2) and Jacobians w.r.t. ``b_ac`` (K, 2, 3) in ``a``'s frame."""
    forward = (rows.observer == a)[:, None]
    x_obs = _pick(poses, rows.observer, rows.observer_pose)
    x_tgt = _pick(poses, rows.observed, rows.observed_pose)
    zero = np.zeros((len(rows), 3))
    b = np.broadcast_to(base, (len(rows), 3))
    pred = rendezvous.predict(
        x_obs, np.where(forward, zero, b), x_tgt[:, :2], np.where(forward, b, zero)
    )
    jac = np.where(forward[:, :, None], pred.d_observed_base, pred.d_observer_base)
    return pred.position - rows.position, jac


def _pick(poses: dict[int, Array], robots: IntArray, indices: IntArray) -> Array:
    out = np.empty((len(robots), 3))
    for r in np.unique(robots):
        sel = robots == r
        out[sel] = poses[int(r)][indices[sel]]
    return out


def _whitening(rows: RendezvousSet) -> Array:
    return sqrt_information_from_covariance(rows.covariance, "rendezvous measurement")


def _centred(jac: Array, base: Array, pivot: Array) -> tuple[Array, Array]:
    """Jacobians w.r.t. ``b`` re-expressed about ``pivot`` (a point of ``G_c``) and the map
    from a step in that parametrisation to a step of ``b``.

    ``b``'s translation and heading are nearly collinear when the rendezvous happen far from
    ``G_c``'s origin; turning about the rendezvous instead of about that origin decouples
    them (the heading marginal is the same in both parametrisations).
    """
    c, s = np.cos(base[2]), np.sin(base[2])
    to_base = np.eye(3)
    to_base[0, 2] = s * pivot[0] + c * pivot[1]  # t = t' - R(phi) pivot
    to_base[1, 2] = -c * pivot[0] + s * pivot[1]
    return jac @ to_base, to_base


def _heading_sigma(jac: Array, w: Array) -> float:
    """Heading standard deviation from whitened rows ``W J`` (inf if unobservable); ``J``
    should be centred (:func:`_centred`)."""
    a = np.matmul(w, jac).reshape(-1, 3)
    info = a.T @ a
    eig = np.linalg.eigvalsh(info)
    if eig[0] <= 1e-9 * max(eig[-1], 1e-300):
        return float("inf")
    return float(np.sqrt(np.linalg.inv(info)[2, 2]))


def initial_pair_base(
    measurements: RendezvousSet,
    a: int,
    c: int,
    poses: dict[int, Array],
    options: AlignmentOptions | None = None,
) -> PairInitialisation:
    """Initial ``b_ac`` (pose of ``G_c`` in ``G_a``) from the measurements between a and c.

    ``poses[r]`` holds robot ``r``'s local poses indexed like the measurements' pose fields.
    """
    options = options or AlignmentOptions()
    _, rows = _rows_between(measurements, a, c)
    k = len(rows)
    if k == 0:
        return PairInitialisation(None, float("inf"), "", 0, "no rendezvous measurement")
    if k == 1:
        return PairInitialisation(
            None,
            float("inf"),
            "",
            1,
            "one rendezvous measurement only: the relative heading is unobservable",
        )
    forward = rows.observer == a
    x_obs = _pick(poses, rows.observer, rows.observer_pose)
    x_tgt = _pick(poses, rows.observed, rows.observed_pose)
    measured_in_observer = se2.transform_point(x_obs, rows.position)  # target in observer frame
    # point pairs P (in G_a) = R(b) Q (in G_c) + t(b)
    p_pts = np.where(forward[:, None], measured_in_observer, x_tgt[:, :2])
    q_pts = np.where(forward[:, None], x_tgt[:, :2], measured_in_observer)

    heading = None
    method = "registration"
    fwd_idx, bwd_idx = np.flatnonzero(forward), np.flatnonzero(~forward)
    if fwd_idx.size and bwd_idx.size:
        dt = np.abs(rows.stamps[fwd_idx][:, None] - rows.stamps[bwd_idx][None, :])
        nearest = np.argmin(dt, axis=1)
        close = dt[np.arange(len(fwd_idx)), nearest] <= options.mutual_time_tolerance
        if close.any():
            i, j = fwd_idx[close], bwd_idx[nearest[close]]
            # global heading of c minus that of a is pi + beta_ac - beta_ca
            phi = x_obs[i, 2] + np.pi + rows.bearing[i] - rows.bearing[j] - x_obs[j, 2]
            heading = float(np.arctan2(np.sin(phi).mean(), np.cos(phi).mean()))
            method = "mutual"
    weights = 1.0 / np.linalg.eigvalsh(rows.covariance)[:, -1]
    if heading is None:
        wsum = weights.sum()
        p_bar = weights @ p_pts / wsum
        q_bar = weights @ q_pts / wsum
        pc, qc = p_pts - p_bar, q_pts - q_bar
        cross = np.einsum("k,ki,kj->ij", weights, qc, pc)
        heading = float(np.arctan2(cross[0, 1] - cross[1, 0], cross[0, 0] + cross[1, 1]))
    rot = se2.rotation(heading)
    translation = weights @ (p_pts - q_pts @ rot.T) / weights.sum()
    base = np.array([translation[0], translation[1], heading])

    w = _whitening(rows)
    pivot = q_pts.mean(axis=0)
    for _ in range(10):  # Gauss-Newton on b_ac alone, local poses fixed
        err, jac = _pair_prediction(rows, a, poses, base)
        jac, to_base = _centred(jac, base, pivot)
        a_mat = np.matmul(w, jac).reshape(-1, 3)
        r_vec = np.einsum("kij,kj->ki", w, err).reshape(-1)
        info = a_mat.T @ a_mat
        eig = np.linalg.eigvalsh(info)
        if eig[0] <= 1e-9 * max(eig[-1], 1e-300):
            break
        step = to_base @ -np.linalg.solve(info, a_mat.T @ r_vec)
        base = base + step
        base[2] = float(se2.wrap_angle(base[2]))
        if np.abs(step).max() < 1e-10:
            break
    _, jac = _pair_prediction(rows, a, poses, base)
    sigma = _heading_sigma(_centred(jac, base, pivot)[0], w)
    if not sigma <= options.max_heading_sigma:
        return PairInitialisation(
            None,
            sigma,
            "",
            k,
            f"relative heading undetermined by {k} rendezvous measurements (sigma "
            f"{np.rad2deg(sigma):.3g} deg > {np.rad2deg(options.max_heading_sigma):.3g} deg): "
            "positions not spread enough",
        )
    return PairInitialisation(base, sigma, method, k)


def align(
    parts: Sequence[RendezvousPart | None],
    measurements: RendezvousSet,
    options: AlignmentOptions | None = None,
    start: Array | None = None,
    excluded: Mapping[int, str] | None = None,
    rendezvous_start: Sequence[Array | None] | None = None,
) -> Alignment:
    """Place every robot connected to the reference (robot 0) and refine by Algorithm 1.

    ``parts[r]`` is robot ``r``'s rendezvous part (``None`` if it has no rendezvous poses).
    ``start`` (R, 3), when given, holds initial base nodes (a previous solution; NaN rows
    where none): a placed robot with one starts Algorithm 1 there instead of at its pairwise
    initialisation, which still decides whether it can be placed. ``rendezvous_start[r]``
    (``parts[r].poses``' shape), when given, is where robot ``r``'s rendezvous poses start
    (a previous solution) instead of at their local estimate. Such a warm start is taken only
    when its cost is below the cold start's (pairwise base nodes, local rendezvous poses):
    maps that changed much since can make it the worse start, and a descent from there may
    end in another minimum. ``excluded`` robots (index:
    reason) are not placed and stay ``pending: <reason>``.
    """
    options = options or AlignmentOptions()
    robots = measurements.robots
    n_robots = len(robots)
    if len(parts) != n_robots:
        raise ValueError(f"align: {len(parts)} rendezvous parts for {n_robots} robots")
    poses: dict[int, Array] = {}
    for r, part in enumerate(parts):
        if part is None:
            continue
        full = np.full(
            (int(part.pose_indices.max()) + 1 if len(part.pose_indices) else 0, 3), np.nan
        )
        full[part.pose_indices] = part.poses
        poses[r] = full
    # every measured pose must be a rendezvous pose of its robot
    for field_robot, field_pose in (
        (measurements.observer, measurements.observer_pose),
        (measurements.observed, measurements.observed_pose),
    ):
        for r in np.unique(field_robot):
            part = parts[int(r)]
            if part is None:
                raise ValueError(f"robot {robots[int(r)]!r} has rendezvous but no RendezvousPart")
            part.local_index(field_pose[field_robot == r], robots[int(r)])

    excluded = dict(excluded or {})
    while True:
        placed, status, initial, parents, methods = _place(
            measurements, poses, n_robots, excluded, options
        )
        result = _refine(
            parts, measurements, placed, initial, status, options, start, rendezvous_start
        )
        if result is not None:
            result.parents, result.methods = parents, methods
            return result
        # a singular Algorithm 1 system (the pairwise checks should prevent it): do not join
        excluded.update({r: "the Algorithm 1 system is singular" for r in placed[1:]})


def _place(
    measurements: RendezvousSet,
    poses: dict[int, Array],
    n_robots: int,
    excluded: dict[int, str],
    options: AlignmentOptions,
) -> tuple[list[int], list[str], Array, dict[int, int], dict[int, str]]:
    """Breadth-first placement from the reference over initialisable rendezvous edges."""
    initial = np.full((n_robots, 3), np.nan)
    initial[0] = 0.0
    status = ["pending: never met an aligned robot"] * n_robots
    status[0] = REFERENCE
    placed = [0]
    parents: dict[int, int] = {}
    methods: dict[int, str] = {}
    reasons: dict[int, list[str]] = {}
    queue = [0]
    while queue:
        a = queue.pop(0)
        for c in range(n_robots):
            if c in placed or c in excluded or not measurements.between(a, c).any():
                continue
            init = initial_pair_base(measurements, a, c, poses, options)
            if init.base is None:
                reasons.setdefault(c, []).append(f"with {measurements.robots[a]}: {init.reason}")
                continue
            initial[c] = se2.compose(initial[a], init.base)
            status[c] = ALIGNED
            placed.append(c)
            parents[c] = a
            methods[c] = init.method
            queue.append(c)
    for c in range(n_robots):
        if c in placed:
            continue
        if c in excluded:
            status[c] = "pending: " + excluded[c]
        elif c in reasons:
            status[c] = "pending: " + "; ".join(reasons[c])
        elif np.any((measurements.observer == c) | (measurements.observed == c)):
            status[c] = "pending: met only robots that are not aligned"
        else:
            status[c] = "pending: no rendezvous with any robot"
    return placed, status, initial, parents, methods


def _refine(
    parts: Sequence[RendezvousPart | None],
    measurements: RendezvousSet,
    placed: list[int],
    initial: Array,
    status: list[str],
    options: AlignmentOptions,
    start: Array | None = None,
    rendezvous_start: Sequence[Array | None] | None = None,
) -> Alignment | None:
    """Algorithm 1 on the rendezvous poses and base nodes of the placed robots, from the
    cold start or the warm one given, whichever costs less (:func:`align`); ``None`` when
    its system is singular. The problem's variables are in the order of the state's keys."""
    robots = measurements.robots
    inside = np.isin(measurements.observer, placed) & np.isin(measurements.observed, placed)
    rows = measurements.subset(inside)
    problem = Problem()
    rho_ids: dict[int, IntArray] = {}
    keys: list[tuple] = []
    for r in placed:
        part = parts[r]
        if part is None:
            continue
        k = [("rho", r, i) for i in range(len(part.pose_indices))]
        rho_ids[r] = problem.add_variables(POSE, k, part.poses)
        keys.extend(k)
    base_ids: dict[int, int] = {}
    for r in placed:
        if r != 0:
            base_ids[r] = problem.add_variable(BASE_NODE, ("base", r), initial[r])
            keys.append(("base", r))
    if not base_ids:
        nothing = DenseStateCovariance(np.zeros((0, 0)))
        return Alignment(robots, 0, status, initial.copy(), initial.copy(), {}, {}, [], nothing)
    for r, ids in rho_ids.items():
        part = parts[r]
        assert part is not None
        problem.add_factor(
            LinearPrior(
                ids,
                [POSE] * len(ids),
                part.poses.reshape(-1),
                part.sqrt_information,
                name=f"rendezvous prior of {robots[r]}",
            )
        )
    obs_local = np.empty(len(rows), dtype=np.int64)
    tgt_local = np.empty(len(rows), dtype=np.int64)
    for r in rho_ids:
        part = parts[r]
        assert part is not None
        sel = rows.observer == r
        obs_local[sel] = rho_ids[r][part.local_index(rows.observer_pose[sel], robots[r])]
        sel = rows.observed == r
        tgt_local[sel] = rho_ids[r][part.local_index(rows.observed_pose[sel], robots[r])]
    observer_ref = rows.observer == 0
    observed_ref = rows.observed == 0
    base_of = np.array([base_ids.get(int(r), -1) for r in range(len(robots))], dtype=np.int64)
    for o_ref, t_ref in ((True, False), (False, True), (False, False)):
        sel = (observer_ref == o_ref) & (observed_ref == t_ref)
        if not sel.any():
            continue
        problem.add_factor(
            Connector(
                obs_local[sel],
                tgt_local[sel],
                rows.position[sel],
                covariance=rows.covariance[sel],
                observer_bases=None if o_ref else base_of[rows.observer[sel]],
                observed_bases=None if t_ref else base_of[rows.observed[sel]],
                name="rendezvous connector",
            )
        )
    warm_start = _take_warm_start(problem, rho_ids, base_ids, start, rendezvous_start, robots)
    solver_options = SolverOptions(
        max_iterations=options.max_iterations,
        relative_tolerance=options.relative_tolerance,
        step_tolerance=options.step_tolerance,
    )
    covariance: StateCovariance
    try:
        if options.method == "dense-newton":
            report, dense = dense_newton(problem, solver_options, keys)
            covariance = DenseStateCovariance(dense)
            singular = not np.all(np.isfinite(dense))
        else:
            # the blocks of the factorisation: each robot's rendezvous poses, the base nodes
            blocks = [problem.scalar_indices(ids) for ids in rho_ids.values() if len(ids)]
            blocks.append(problem.scalar_indices(list(base_ids.values())))
            if options.method == "gauss-newton":
                report = problem.solve(solver_options)
                pattern = block_pattern(problem.normal_equations(), blocks)
                covariance = factor_at_estimate(problem, pattern)
            else:
                report, covariance = sparse_newton(problem, solver_options, blocks)
            singular = False
    except SingularProblemError:
        singular = True
    if singular:
        return None  # cannot happen when every placed pair passed its heading check
    bases = np.full((len(robots), 3), np.nan)
    bases[0] = 0.0
    refined = {r: problem.values_of(ids) for r, ids in rho_ids.items()}
    shift = {}
    for r, values in refined.items():
        d = values - parts[r].poses  # type: ignore[union-attr]
        d[:, 2] = se2.wrap_angle(d[:, 2])
        shift[r] = d
    for r, i in base_ids.items():
        bases[r] = problem.values_of([i])[0]
    return Alignment(
        robots=robots,
        reference=0,
        status=status,
        base_nodes=bases,
        initial_base_nodes=initial.copy(),
        rendezvous_poses=refined,
        rendezvous_shift=shift,
        state_keys=keys,
        state_covariance=covariance,
        iterations=report.iterations,
        final_cost=report.final_cost,
        converged=report.converged,
        stop_reason=report.reason,
        warm_start=warm_start,
    )


def _take_warm_start(
    problem: Problem,
    rho_ids: Mapping[int, IntArray],
    base_ids: Mapping[int, int],
    start: Array | None,
    rendezvous_start: Sequence[Array | None] | None,
    robots: Sequence[str],
) -> bool:
    """Set the problem (at the cold start) to the warm start given, base nodes (finite rows
    of ``start``) and rendezvous poses, if that costs less; whether it did."""
    warm = problem.values.copy()
    for r, i in base_ids.items():
        if start is not None and np.isfinite(start[r]).all():
            warm[problem.scalar_indices([i])] = start[r]
    for r, ids in rho_ids.items():
        poses = rendezvous_start[r] if rendezvous_start is not None else None
        if poses is None:
            continue
        if np.shape(poses) != (len(ids), 3):
            raise ValueError(
                f"align: rendezvous start of {robots[r]!r} has shape {np.shape(poses)}, its "
                f"part {(len(ids), 3)}"
            )
        warm[problem.scalar_indices(ids)] = np.asarray(poses, dtype=float).reshape(-1)
    return problem.take_if_cheaper(warm)
