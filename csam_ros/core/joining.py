"""The joint solve of C-SAM (paper section IV-B, last step of Algorithm 2; docs/METHOD.md
sections 6-7).

After alignment and association, one nonlinear least-squares problem holds every pose and
every feature of every aligned robot, all factors of their local maps, the rendezvous rows
and the associations, and is solved once to convergence. Its result is the joined map in the
reference robot's frame with every robot's full trajectory.

Parametrisation (global). Each aligned robot's poses and features are unknowns in the
reference frame, initialised from its local map moved by its base node. The reference robot
keeps its local gauge prior (first pose at the origin); every other robot's gauge prior is
dropped, so its base node *is* its first pose in the reference frame (``G_r`` is defined by
that pose). This is the same problem as local unknowns plus base nodes with every gauge prior
kept (any global configuration has exactly one such representation with zero gauge cost), but
it has no redundant unknowns. An association merges its features into one unknown (no
association rows with an artificial sigma). Rendezvous rows are the relative position of one
pose seen from another (:class:`~csam_ros.core.factors.RelativePosition`). Given the same
associations this is the centralised maximum a posteriori estimate of everything all robots
measured (tested against GTSAM).
"""

from __future__ import annotations

import copy
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from functools import cache

import numpy as np
from numpy.typing import NDArray

from csam_ros.core import se2
from csam_ros.core.factors import POINT, POSE, PosePrior, RelativePosition
from csam_ros.core.rendezvous import RendezvousSet
from csam_ros.core.solver import NormalEquations, Problem, SolveReport, SolverOptions

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]


@dataclass
class RobotMap:
    """One robot's solved local map, as C-SAM uses it.

    ``problem`` holds the robot's factors with its poses and features as unknowns in its
    frame ``G_r`` (first pose at the origin, fixed by the gauge prior
    ``problem.factors[gauge_factor]``). ``pose_ids`` (N,) are the ids of the poses in stamp
    order, ``feature_ids`` (F,) those of the features with the robot's own ``feature_labels``.
    """

    name: str
    problem: Problem
    stamps: Array
    pose_ids: IntArray
    feature_labels: IntArray
    feature_ids: IntArray
    gauge_factor: int
    feature_covariances: Array | None = None

    def __post_init__(self) -> None:
        if len(self.stamps) != len(self.pose_ids) or len(self.pose_ids) == 0:
            raise ValueError(
                f"robot {self.name!r}: {len(self.stamps)} stamps for {len(self.pose_ids)} poses"
            )
        if len(self.feature_labels) != len(self.feature_ids):
            raise ValueError(f"robot {self.name!r}: feature labels and ids differ in length")
        if self.feature_covariances is not None and np.shape(self.feature_covariances) != (
            len(self.feature_ids),
            2,
            2,
        ):
            raise ValueError(
                f"robot {self.name!r}: feature_covariances must have shape "
                f"({len(self.feature_ids)}, 2, 2), got {np.shape(self.feature_covariances)}"
            )
        gauge = self.problem.factors[self.gauge_factor]
        if not isinstance(gauge, PosePrior) or np.any(gauge.variables != self.pose_ids[0]):
            raise ValueError(
                f"robot {self.name!r}: factor {self.gauge_factor} is not the gauge prior on "
                "the first pose"
            )

    @property
    def poses(self) -> Array:
        return self.problem.values_of(self.pose_ids)

    @property
    def feature_positions(self) -> Array:
        if len(self.feature_ids) == 0:
            return np.zeros((0, 2))
        return self.problem.values_of(self.feature_ids)


def find_gauge_factor(problem: Problem, first_pose: int) -> int:
    """Index of the pose prior that fixes ``first_pose`` alone (the local gauge)."""
    for i, f in enumerate(problem.factors):
        if isinstance(f, PosePrior) and len(f) == 1 and int(f.variables[0, 0]) == first_pose:
            return i
    raise ValueError(f"no gauge prior on pose id {first_pose} in the local problem")


@dataclass
class JointSolution:
    """The joint problem after its solve, with where each robot's unknowns are in it."""

    problem: Problem
    robots: list[int]  # aligned robots, in order
    pose_ids: dict[int, IntArray]  # robot -> joint ids of its poses (stamp order)
    feature_ids: dict[int, IntArray]  # robot -> joint id of each of its local features
    features: list[list[tuple[int, int]]]  # joint feature -> (robot, label) members
    feature_var_ids: IntArray  # joint ids of the features, in the order of ``features``
    report: SolveReport
    warm_start: bool = False  # solved from the initial values given (lower cost), not cold


def joint_solve(
    maps: Sequence[RobotMap],
    robots: Sequence[int],
    base_nodes: Array,
    clusters: Sequence[Sequence[tuple[int, int]]],
    measurements: RendezvousSet,
    options: SolverOptions | None = None,
    initial_poses: Mapping[int, Array] | None = None,
    initial_features: Mapping[int, Array] | None = None,
) -> JointSolution:
    """Build and solve the joint problem of the aligned ``robots`` (module docs).

    ``robots`` lists the aligned robot indices, the reference (index 0) first;
    ``base_nodes[r]`` places ``G_r`` in the reference frame; each cluster lists the
    ``(robot, label)`` members of one associated feature. Cold start: each robot's local map
    moved by its base node (an associated feature at the mean of its members). Warm start:
    robot ``r``'s poses (N, 3) and features (F, 2) in the reference frame from
    ``initial_poses[r]`` and ``initial_features[r]`` where given, taken only when it costs
    less than the cold start (maps that changed much since can make it the worse start, and
    the robust cost has more than one minimum).
    """
    initial_poses = initial_poses or {}
    initial_features = initial_features or {}
    robots = list(robots)
    if not robots or robots[0] != 0:
        raise ValueError("joint_solve: the reference robot (index 0) must come first")
    problem = Problem()
    pose_ids: dict[int, IntArray] = {}
    cold_poses: dict[int, Array] = {}
    for r in robots:
        m = maps[r]
        cold_poses[r] = se2.compose(np.broadcast_to(base_nodes[r], (len(m.pose_ids), 3)), m.poses)
        pose_ids[r] = problem.add_variables(
            POSE,
            [(m.name, "pose", i) for i in range(len(m.pose_ids))],
            initial_poses.get(r, cold_poses[r]),
        )

    # features: one unknown per cluster, then one per remaining feature, robot by robot
    label_index = {r: {int(lab): k for k, lab in enumerate(maps[r].feature_labels)} for r in robots}
    cold_xy = {
        r: se2.transform_point(
            np.broadcast_to(base_nodes[r], (len(maps[r].feature_ids), 3)),
            maps[r].feature_positions,
        )
        for r in robots
    }
    owner: dict[int, IntArray] = {r: np.full(len(maps[r].feature_ids), -1) for r in robots}
    members: list[list[tuple[int, int]]] = []
    cluster_index: list[list[tuple[int, int]]] = []  # (robot, local index) of the members
    aligned = set(robots)
    for cluster in clusters:
        inside = [(r, lab) for r, lab in cluster if r in aligned]
        if not inside:
            continue
        k = len(members)
        for r, lab in inside:
            if lab not in label_index[r]:
                raise ValueError(f"association names unknown feature {maps[r].name}/{lab}")
            if owner[r][label_index[r][lab]] >= 0:
                raise ValueError(f"feature {maps[r].name}/{lab} is in two associations")
            owner[r][label_index[r][lab]] = k
        members.append(sorted(inside))
        cluster_index.append([(r, label_index[r][lab]) for r, lab in inside])
    free: dict[int, IntArray] = {}
    for r in robots:
        free[r] = np.flatnonzero(owner[r] < 0)
        owner[r][free[r]] = len(members) + np.arange(len(free[r]))
        members.extend([(r, int(maps[r].feature_labels[i]))] for i in free[r])

    def feature_starts(xy: Mapping[int, Array]) -> Array:
        """Each joint feature's start: its member's position, or the mean of its members'."""
        clustered = [np.mean([xy[r][i] for r, i in index], axis=0) for index in cluster_index]
        return np.concatenate(
            [np.reshape(clustered, (-1, 2)), *(np.reshape(xy[r][free[r]], (-1, 2)) for r in robots)]
        )

    keys = [
        ("feature",) + tuple(x for rl in mem for x in (maps[rl[0]].name, rl[1])) for mem in members
    ]
    feature_var_ids = (
        problem.add_variables(POINT, keys, feature_starts({**cold_xy, **initial_features}))
        if members
        else np.zeros(0, dtype=np.int64)
    )
    feature_ids = {r: feature_var_ids[owner[r]] for r in robots}

    # every local factor, with its variables renamed; non-reference gauges dropped
    for r in robots:
        m = maps[r]
        id_map = np.full(m.problem.num_variables, -1, dtype=np.int64)
        id_map[m.pose_ids] = pose_ids[r]
        id_map[m.feature_ids] = feature_ids[r]
        for i, factor in enumerate(m.problem.factors):
            if i == m.gauge_factor and r != 0:
                continue
            renamed = copy.copy(factor)
            renamed.variables = id_map[factor.variables]
            if np.any(renamed.variables < 0):
                raise ValueError(
                    f"robot {m.name!r}: factor {factor.name!r} uses a variable that is neither "
                    "a pose nor a feature of the map"
                )
            problem.add_factor(renamed)

    inside = np.isin(measurements.observer, robots) & np.isin(measurements.observed, robots)
    rows = measurements.subset(inside)
    if len(rows):
        observer = np.empty(len(rows), dtype=np.int64)
        observed = np.empty(len(rows), dtype=np.int64)
        for r in robots:
            sel = rows.observer == r
            observer[sel] = pose_ids[r][rows.observer_pose[sel]]
            sel = rows.observed == r
            observed[sel] = pose_ids[r][rows.observed_pose[sel]]
        problem.add_factor(
            RelativePosition(
                observer, observed, rows.position, covariance=rows.covariance, name="rendezvous"
            )
        )
    warm_start = False
    if initial_poses or initial_features:
        warm = problem.values.copy()
        for r in robots:
            problem.set_values(pose_ids[r], cold_poses[r])
        if members:
            problem.set_values(feature_var_ids, feature_starts(cold_xy))
        warm_start = problem.take_if_cheaper(warm)
    report = problem.solve(options or SolverOptions())
    return JointSolution(
        problem, robots, pose_ids, feature_ids, members, feature_var_ids, report, warm_start
    )


def covariance_columns(system: NormalEquations, scalar_indices: IntArray) -> Array:
    """Columns ``(A^T A)^-1 e_j`` (n, k) for the given scalar positions, one solve each."""
    cols = np.asarray(scalar_indices, dtype=np.int64)
    out = np.empty((system.n, len(cols)))
    unit = np.zeros(system.n)
    for j, c in enumerate(cols):
        unit[c] = 1.0
        out[:, j] = system.solve(unit)
        unit[c] = 0.0
    return out


def heading_sigmas(
    problem: Problem,
    system: NormalEquations,
    pose_ids: IntArray,
    inverse: SelectedInverse | None = None,
) -> tuple[Array, Array]:
    """Heading standard deviation of each pose, in the problem's frame and relative to the
    first of ``pose_ids`` (the robot's own frame), both (N,).

    The variances come from ``inverse`` (or one solve per pose without it); the covariances
    with the first heading from one solve.
    """
    heading = problem.scalar_indices(pose_ids).reshape(-1, 3)[:, 2]
    if inverse is not None:
        var = inverse.entries(heading, heading)
        cross = covariance_columns(system, heading[:1])[heading, 0]
    else:
        sub = covariance_columns(system, heading)[heading]
        var = np.diag(sub).copy()
        cross = sub[:, 0]
    relative = var + var[0] - 2.0 * cross
    return np.sqrt(np.maximum(var, 0.0)), np.sqrt(np.maximum(relative, 0.0))


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


class SelectedInverse:
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
        indptr = lower.indptr.astype(np.int64)
        indices = lower.indices.astype(np.int64)
        data = lower.data
        d = np.asarray(d, dtype=float)
        self._keys = np.repeat(np.arange(n, dtype=np.int64), np.diff(indptr)) * n + indices
        nnz = len(data)
        # Z on the pattern, then its diagonal: one array, so Z_SS is one gather
        store = np.zeros(nnz + n)
        begins, ends, depth = _supernodes(indptr, indices, n)
        widths = ends - begins + 1
        below_counts = indptr[ends + 1] - indptr[ends]
        groups = self._by_shape(widths, below_counts, depth)
        shapes = [
            _SupernodeShape(self._keys, indptr, indices, data, d, begins[members], ends[members])
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
        keys = lo[off] * self.n + hi[off]
        pos = np.clip(np.searchsorted(self._keys, keys), 0, max(len(self._keys) - 1, 0))
        if np.any(self._keys[pos] != keys):
            raise ValueError("requested covariance entries are not on the factor's pattern")
        out[off] = self._values[pos]
        return out

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


class _SupernodeShape:
    """Supernodes of one shape (width ``w``, ``ms`` rows below), ordered by depth, with what
    :class:`SelectedInverse` needs of them that depends on the factor only: ``Z_JJ``'s first
    term ``L_JJ^-T D_J^-1 L_JJ^-1``, ``U = L_SJ L_JJ^-1`` and where ``Z_SS``, ``Z_SJ`` and
    ``Z_JJ`` are in the store (pattern entries, then the diagonal)."""

    def __init__(
        self,
        keys: IntArray,
        indptr: IntArray,
        indices: IntArray,
        data: Array,
        d: Array,
        begins: IntArray,
        ends: IntArray,
    ) -> None:
        nnz, n = len(keys), len(d)
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
                found = np.searchsorted(keys, below[:, ia] * n + below[:, ib])
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
