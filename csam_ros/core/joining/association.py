"""Feature association between aligned maps (paper section IV-B, Algorithm 2; docs/METHOD.md
section 6).

The hypothesis "feature ``i`` of robot ``a`` and feature ``j`` of robot ``c`` are one" predicts
``r = B_a (+) l_i - B_c (+) l_j = 0`` (the paper's ``l_i^p - b_pq (+) l_j^q`` when ``a`` is the
reference). With ``H`` its Jacobian and ``P`` the joint covariance of ``(l_i, B_a, l_j, B_c)``,
cross terms included, ``S = H P H^T`` and ``D = r^T S^-1 r`` (eq. 26).

Joint covariance, recovered sparsely. Algorithm 1 gives the joint covariance ``Sigma`` of the
rendezvous poses ``rho`` of all robots and of the base nodes (the state ``s``). Inside one
local map a feature depends on the connector only through the rendezvous poses:
``l = l0 + K (rho - rho0) + eps`` with the gain ``K = P_l,rho P_rho,rho^-1`` and ``eps``
independent of everything outside that map, of covariance ``C = P_ll - K P_rho,rho K^T``
(the local map's marginals). So a feature's global position ``g = B_a (+) l`` is, to first
order, ``g0 + G (s - s0) + J_l eps`` (``G = [J_l K | J_B]`` on robot ``a``'s columns) and

    S_ij = (G_i - G_j) Sigma (G_i - G_j)^T + J_li C_i J_li^T + J_lj C_j J_lj^T.

Only the rendezvous columns of each local covariance are ever needed (``P_l,rho``), never the
full map covariance.

Candidates. Robot pairs whose features cannot meet are skipped (the boxes of their positions,
each grown by ``sqrt(xi)`` times its spread, do not overlap). Pairs are found with a k-d tree
on global positions (scipy ``cKDTree``): since ``D >= |r|^2 / lambda_max(S)`` and
``sqrt(lambda_max(S)) <= s_i + s_j`` with ``s`` the largest standard deviation of each global
position, a pair can pass the gate only if ``|r| <= sqrt(xi) (s_i + s_j)``: the search radius,
exact, not a heuristic.

Decision, in passes. (1) Pairs of features not yet tied, through the matches accepted, to a
feature of each other's robot with ``D < xi`` (chi-square, 2 dof; default 9.21, the 99 %
quantile) are made unique both ways by a global assignment that maximises ``sum(xi - D)`` over
the gated pairs of each robot pair (``linear_sum_assignment`` on each connected component of
the candidate graph): a conflict goes to the best-fitting set, not to the first pair found. (2)
Joint compatibility: every accepted match is a measurement ``r = 0`` of the state; the state is
conditioned on all of them (a linear update on Algorithm 1's sparse information:
:mod:`~csam_ros.core.joining.match_conditioning`) and each match is tested against all the
others by its leave-one-out distance ``e_k^T (N_k - H_k Sigma_post H_k^T)^-1 e_k`` (``e_k`` its
posterior residual); while the worst exceeds ``xi`` it is dropped for good and the update
redone. (3) The next pass gates the remaining features against the conditioned state, which is
now much tighter, so pairs that were ambiguous (or out of reach) before are decided; passes
stop when nothing changes.
With more than two robots, matches are merged into clusters (union-find) in increasing ``D``;
a match that would put two features of one robot into one cluster is rejected and counted.
Matches that share a feature (clusters over three or more robots) are treated as independent
in the update, a slight overconfidence of the test only.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray
from scipy.sparse.csgraph import connected_components

from csam_ros.core.joining.alignment import Alignment
from csam_ros.core.joining.match_conditioning import (
    ConditionedState,
    MatchIndex,
    SparseConditioning,
    StateInformation,
    condition_dense,
    stacked_congruence,
    stacked_product,
)
from csam_ros.core.joining.state_covariance import FactoredStateCovariance
from csam_ros.core.model import se2
from csam_ros.core.model.chi_square import CHI2_2DOF_99

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]


@dataclass
class MapFeatures:
    """One robot's local features as Algorithm 2 needs them.

    ``positions`` (F, 2) and ``covariances`` (F, 2, 2) are local estimates and marginal
    covariances in ``G_r``; ``rendezvous_gain`` (F, 2, 3n) is ``K = P_l,rho P_rho,rho^-1``
    with the columns of the robot's rendezvous part (:class:`~csam_ros.core.joining.alignment.
    RendezvousPart`).
    """

    labels: IntArray
    positions: Array
    covariances: Array
    rendezvous_gain: Array


@dataclass
class AssociationOptions:
    """Settings of Algorithm 2."""

    chi2_gate: float = CHI2_2DOF_99
    max_passes: int = 10  # association passes, each conditioned on the matches so far


@dataclass
class Match:
    """An accepted association: feature ``label_a`` of robot ``a`` is ``label_c`` of ``c``."""

    robot_a: int
    label_a: int
    robot_c: int
    label_c: int
    mahalanobis: float


@dataclass
class Associations:
    """The outcome of Algorithm 2."""

    matches: list[Match]
    clusters: list[list[tuple[int, int]]]  # (robot, label) members of each merged feature
    candidates: int = 0  # pairs inside the spatial search radius
    gated: int = 0  # pairs with D below the gate
    rejected_conflicts: int = 0  # matches dropped for one-feature-per-robot in clusters
    rejected_incompatible: int = 0  # matches dropped by the joint compatibility test


@dataclass
class _GlobalFeatures:
    """Global positions of one robot's features, linearised on the Algorithm 1 state ``s``.

    ``g = position + compact @ (s - s_bar)[columns] + J_l eps`` with ``Cov(J_l eps) = noise``.
    """

    robot: int
    labels: IntArray
    position: Array  # (F, 2) reference frame, at the Algorithm 1 estimate
    compact: Array  # (F, 2, m): the gain on the state columns ``columns``
    noise: Array  # (F, 2, 2)
    columns: IntArray  # (m,) the robot's rendezvous poses' and base node's state columns

    def moments(self, state: ConditionedState, idx: IntArray) -> tuple[Array, Array]:
        """Mean (K, 2) and covariance (K, 2, 2) of global positions ``idx`` given the state."""
        g = self.compact[idx]
        sub = state.block(self.columns, self.columns)
        pos = self.position[idx] + stacked_product(g, state.shift[self.columns])
        cov = stacked_congruence(g, sub) + self.noise[idx]
        return pos, 0.5 * (cov + cov.swapaxes(1, 2))


def _global_features(
    r: int, features: MapFeatures, alignment: Alignment, sigma_rho_prior: Array
) -> _GlobalFeatures:
    """Posterior global feature positions of robot ``r`` after Algorithm 1 (module docs)."""
    base = alignment.base_nodes[r]
    shift = alignment.rendezvous_shift[r].reshape(-1)
    gain = features.rendezvous_gain
    local = features.positions + np.einsum("fij,j->fi", gain, shift)
    f = len(local)
    c, s = np.cos(base[2]), np.sin(base[2])
    rot = np.array([[c, -s], [s, c]])
    position = se2.transform_point(np.broadcast_to(base, (f, 3)), local)
    j_l = np.broadcast_to(rot, (f, 2, 2))
    cond = features.covariances - gain @ sigma_rho_prior @ gain.transpose(0, 2, 1)
    noise = j_l @ cond @ j_l.transpose(0, 2, 1)
    columns = alignment.rho_columns(r)
    compact = j_l @ gain
    base_cols = alignment.base_columns(r)
    if base_cols is not None:
        j_b = np.zeros((f, 2, 3))
        j_b[:, 0, 0] = j_b[:, 1, 1] = 1.0
        j_b[:, 0, 2] = -s * local[:, 0] - c * local[:, 1]
        j_b[:, 1, 2] = c * local[:, 0] - s * local[:, 1]
        compact = np.concatenate([compact, j_b], axis=2)
        columns = np.concatenate([columns, base_cols])
    return _GlobalFeatures(
        r, features.labels, position, compact, 0.5 * (noise + noise.swapaxes(1, 2)), columns
    )


def _pair_distances(
    ga: _GlobalFeatures,
    gc: _GlobalFeatures,
    ia: IntArray,
    ic: IntArray,
    state: ConditionedState,
    chunk: int = 20000,
) -> Array:
    """Mahalanobis distances of candidate pairs ``(ia, ic)`` given the state (eq. 26).

    ``S = V_i + V_j - X_ij - X_ij^T`` with ``V`` each global position's covariance and
    ``X_ij = G_i Sigma G_j^T`` the cross term, computed on each robot's own state columns.
    """
    out = np.empty(len(ia))
    if len(ia) == 0:
        return out
    ua, inv_a = np.unique(ia, return_inverse=True)
    uc, inv_c = np.unique(ic, return_inverse=True)
    pa, va = ga.moments(state, ua)
    pc, vc = gc.moments(state, uc)
    sigma_ac = state.block(ga.columns, gc.columns)
    left = stacked_product(ga.compact[ua], sigma_ac)  # (A, 2, m_c)
    right = gc.compact[uc]  # (C, 2, m_c)
    for lo in range(0, len(ia), chunk):
        a, c = inv_a[lo : lo + chunk], inv_c[lo : lo + chunk]
        cross = left[a] @ right[c].transpose(0, 2, 1)
        s_mat = va[a] + vc[c] - cross - cross.transpose(0, 2, 1)
        r = pa[a] - pc[c]
        out[lo : lo + chunk] = np.einsum(
            "ki,ki->k", r, np.linalg.solve(s_mat, r[:, :, None])[:, :, 0]
        )
    return out


@dataclass
class _Free:
    """One robot's features in a pass (for a robot pair: those not matched with the other
    robot yet): their global positions given the state and the largest standard deviation of
    each."""

    index: IntArray
    position: Array  # (K, 2)
    sigma: Array  # (K,)

    @classmethod
    def of(cls, g: _GlobalFeatures, index: IntArray, state: ConditionedState) -> _Free:
        if len(index) == 0:
            return cls(index, np.zeros((0, 2)), np.zeros(0))
        pos, cov = g.moments(state, index)
        return cls(index, pos, np.sqrt(np.maximum(np.linalg.eigvalsh(cov)[:, -1], 0.0)))

    def without(self, index: list[int]) -> _Free:
        """These features but those of ``index`` (positions in the robot's features)."""
        if not index:
            return self
        keep = ~np.isin(self.index, index)
        return _Free(self.index[keep], self.position[keep], self.sigma[keep])

    def reach(self, root_gate: float) -> tuple[Array, Array]:
        """Corners of the box every gated partner of these features lies in, but for the
        partner's own spread."""
        grow = root_gate * self.sigma[:, None]
        return (self.position - grow).min(axis=0), (self.position + grow).max(axis=0)


def _meeting_pairs(
    robots: list[int], every: Mapping[int, _Free], root_gate: float
) -> list[tuple[int, int]]:
    """The robot pairs ``(a, c)``, ``a < c`` in ``robots``' order, whose features can meet:
    their boxes (:meth:`_Free.reach`, all of each robot's features) overlap, all at once."""
    boxes = np.array([np.concatenate(every[r].reach(root_gate)) for r in robots])  # lo, hi
    overlap = np.all(boxes[:, None, :2] <= boxes[None, :, 2:], axis=2)
    overlap &= overlap.T
    a, c = np.nonzero(np.triu(overlap, 1))
    return [(robots[i], robots[j]) for i, j in zip(a.tolist(), c.tolist(), strict=True)]


def _may_meet(fa: _Free, fc: _Free, root_gate: float) -> bool:
    """Whether any pair of ``fa`` and ``fc`` can be within the gate's radius: the boxes of
    positions, each grown by ``sqrt(xi)`` times its own spread, overlap (exact)."""
    if len(fa.index) == 0 or len(fc.index) == 0:
        return False
    lo_a, hi_a = fa.reach(root_gate)
    lo_c, hi_c = fc.reach(root_gate)
    return bool(np.all(lo_a <= hi_c) and np.all(lo_c <= hi_a))


def _candidates(fa: _Free, fc: _Free, root_gate: float) -> tuple[IntArray, IntArray]:
    """Pairs of free features whose distance can pass the gate (k-d tree, exact bound)."""
    from scipy.spatial import cKDTree  # on use: scipy.spatial loads slowly

    if len(fa.index) == 0 or len(fc.index) == 0:
        empty = np.zeros(0, dtype=np.int64)
        return empty, empty
    pa, sa, pc, sc = fa.position, fa.sigma, fc.position, fc.sigma
    lists = cKDTree(pc).query_ball_point(pa, root_gate * (sa + sc.max()))
    ia = np.repeat(np.arange(len(lists)), [len(x) for x in lists])
    ic = np.fromiter((j for x in lists for j in x), dtype=np.int64, count=len(ia))
    near = np.hypot(*(pa[ia] - pc[ic]).T) <= root_gate * (sa[ia] + sc[ic])
    return fa.index[ia[near]], fc.index[ic[near]]


def _assign(ia: IntArray, ic: IntArray, d: Array, gate: float) -> NDArray[np.bool_]:
    """Unique matches maximising ``sum(gate - D)``, per connected component of candidates."""
    from scipy.optimize import linear_sum_assignment  # on use: scipy.optimize loads slowly

    keep = np.zeros(len(d), dtype=bool)
    if len(d) == 0:
        return keep
    ua, ra = np.unique(ia, return_inverse=True)
    uc, rc = np.unique(ic, return_inverse=True)
    graph = sp.coo_matrix((np.ones(len(d)), (ra, len(ua) + rc)), shape=(len(ua) + len(uc),) * 2)
    _, comp = connected_components(graph, directed=False)
    pair_comp = comp[ra]
    order = np.argsort(pair_comp, kind="stable")
    bounds = np.flatnonzero(np.diff(np.concatenate([[-1], pair_comp[order], [-2]])))
    for lo, hi in zip(bounds[:-1], bounds[1:], strict=True):
        idx = order[lo:hi]
        if len(idx) == 1:
            keep[idx] = True
            continue
        rows, row_of = np.unique(ra[idx], return_inverse=True)
        cols, col_of = np.unique(rc[idx], return_inverse=True)
        benefit = np.zeros((len(rows), len(cols)))
        benefit[row_of, col_of] = gate - d[idx]
        pick_r, pick_c = linear_sum_assignment(benefit, maximize=True)
        lookup = {(int(a), int(b)): int(k) for k, a, b in zip(idx, row_of, col_of, strict=True)}
        for a, b in zip(pick_r, pick_c, strict=True):
            k = lookup.get((int(a), int(b)))
            if k is not None:
                keep[k] = True
    return keep


def associate(
    features: Sequence[MapFeatures | None],
    alignment: Alignment,
    parts_sqrt_information: Sequence[Array | None],
    options: AssociationOptions | None = None,
    met: set[tuple[int, int]] | None = None,
) -> Associations:
    """Algorithm 2 over every pair of aligned robots (index ``r`` follows the alignment).

    ``met`` (robot pairs ``(a, c)``, ``a < c``), when given, are the robots that measured each
    other: their features are compared first, the others' from the second pass on, against
    the state conditioned on the first matches (and with their joint covariance in the
    factor by then: the first pass needs no factorisation of its own).

    ``parts_sqrt_information[r]`` is robot ``r``'s rendezvous square-root information (the
    ``R`` of its :class:`~csam_ros.core.joining.alignment.RendezvousPart`), which gives the local
    covariance of its rendezvous poses ``P_rho,rho = R^-1 R^-T``. The state is conditioned on
    the matches in the information form on Algorithm 1's sparse factor, or in the Kalman form
    when Algorithm 1 was solved densely (:mod:`~csam_ros.core.joining.match_conditioning`).
    """
    options = options or AssociationOptions()
    gate = float(options.chi2_gate)
    if not gate > 0:
        raise ValueError(f"chi2_gate must be positive, got {gate}")
    glob: dict[int, _GlobalFeatures] = {}
    for r, feats in enumerate(features):
        if feats is None or not alignment.aligned(r) or len(feats.labels) == 0:
            continue
        if r not in alignment.rendezvous_shift:
            continue
        root = parts_sqrt_information[r]
        if root is None:
            raise ValueError(f"robot {alignment.robots[r]!r}: aligned but no rendezvous part")
        inv_root = np.linalg.inv(root)
        glob[r] = _global_features(r, feats, alignment, inv_root @ inv_root.T)
    robots = sorted(glob)
    robot_pairs = [(a, c) for k, a in enumerate(robots) for c in robots[k + 1 :]]
    if not robot_pairs:
        return Associations([], [])
    condition = _conditioning(alignment, glob)
    root_gate = float(np.sqrt(gate))
    accepted: dict[MatchIndex, float] = {}
    rejected: set[MatchIndex] = set()
    state, _ = condition([])
    candidates = gated = 0
    later: list[tuple[int, int]] = []  # robot pairs whose comparison waits for the next pass
    for number in range(options.max_passes):
        every = {r: _Free.of(g, np.arange(len(g.labels)), state) for r, g in glob.items()}
        matched = _joined_with(accepted)
        found: dict[tuple[int, int], tuple[IntArray, IntArray]] = {}
        for a, c in _meeting_pairs(robots, every, root_gate):
            free_a = every[a].without(matched.get((a, c), []))
            free_c = every[c].without(matched.get((c, a), []))
            if not _may_meet(free_a, free_c, root_gate):
                continue
            ia, ic = _candidates(free_a, free_c, root_gate)
            keep = np.array(
                [(a, i, c, j) not in rejected for i, j in zip(ia, ic, strict=True)], dtype=bool
            )
            if not keep.any():
                continue
            if number == 0 and met is not None and (a, c) not in met:
                later.append((a, c))
                continue
            found[a, c] = ia[keep].astype(np.int64), ic[keep].astype(np.int64)
        missing = [(a, c) for a, c in found if not state.covers(glob[a].columns, glob[c].columns)]
        if (
            missing
        ):  # robots never coupled before: their covariance block is made part of the factor's
            state, _ = condition(list(accepted), missing)
        new: dict[MatchIndex, float] = {}
        for (a, c), (ia, ic) in found.items():
            candidates += len(ia)
            d = _pair_distances(glob[a], glob[c], ia, ic, state)
            inside = d < gate
            ia, ic, d = ia[inside], ic[inside], d[inside]
            gated += len(d)
            pick = _assign(ia, ic, d, gate)
            new.update(
                ((a, int(i), c, int(j)), float(dd))
                for i, j, dd in zip(ia[pick], ic[pick], d[pick], strict=True)
            )
        couple = [(a, c) for a, c in later if not state.covers(glob[a].columns, glob[c].columns)]
        if not new and not later:
            break
        later = []
        accepted.update(new)
        while True:  # joint compatibility: drop the match least compatible with the others
            pairs = list(accepted)
            state, loo = condition(pairs, couple)
            worst = int(np.argmax(loo)) if len(loo) else -1
            if worst < 0 or loo[worst] < gate:
                break
            rejected.add(pairs[worst])
            del accepted[pairs[worst]]
    matched = [
        (d, a, int(glob[a].labels[i]), c, int(glob[c].labels[j]))
        for (a, i, c, j), d in accepted.items()
    ]
    result = _cluster(matched, gated, candidates)
    result.rejected_incompatible = len(rejected)
    return result


def _joined_with(accepted: Mapping[MatchIndex, float]) -> dict[tuple[int, int], list[int]]:
    """For each (robot, other robot): the robot's features already tied, through the matches
    accepted, to a feature of the other (a match between them would say again what the
    others say)."""
    parent: dict[tuple[int, int], tuple[int, int]] = {}

    def root(x: tuple[int, int]) -> tuple[int, int]:
        while parent.setdefault(x, x) != x:
            parent[x] = parent[parent[x]]
            x = parent[x]
        return x

    for a, i, c, j in accepted:
        parent[root((a, i))] = root((c, j))
    robots: dict[tuple[int, int], set[int]] = {}
    for x in parent:
        robots.setdefault(root(x), set()).add(x[0])
    out: dict[tuple[int, int], list[int]] = {}
    for r, i in parent:
        for other in robots[root((r, i))] - {r}:
            out.setdefault((r, other), []).append(i)
    return out


class _Conditioning(Protocol):
    def __call__(
        self, pairs: list[MatchIndex], couple: Sequence[tuple[int, int]] = ()
    ) -> tuple[ConditionedState, Array]: ...


def _conditioning(alignment: Alignment, glob: dict[int, _GlobalFeatures]) -> _Conditioning:
    """The state conditioned on a list of matches, and their leave-one-out distances, in the
    form that suits Algorithm 1's covariance (:mod:`~csam_ros.core.joining.
    match_conditioning`); ``couple`` (robot pairs) asks that the state cover their joint
    covariance."""
    covariance = alignment.state_covariance
    if isinstance(covariance, FactoredStateCovariance) and covariance.information is not None:
        return SparseConditioning(StateInformation(covariance), glob)
    prior = alignment.covariance
    return lambda pairs, couple=(): condition_dense(prior, glob, pairs)


def _cluster(
    found: list[tuple[float, int, int, int, int]], gated: int, candidates: int
) -> Associations:
    """Merge matches into clusters in increasing ``D``, one feature per robot per cluster."""
    parent: dict[tuple[int, int], tuple[int, int]] = {}
    members: dict[tuple[int, int], set[int]] = {}

    def root(x: tuple[int, int]) -> tuple[int, int]:
        parent.setdefault(x, x)
        members.setdefault(x, {x[0]})
        while parent[x] != x:
            parent[x] = parent[parent[x]]
            x = parent[x]
        return x

    matches: list[Match] = []
    rejected = 0
    for d, a, la, c, lc in sorted(found):
        ra, rc = root((a, la)), root((c, lc))
        if ra == rc:
            continue
        if members[ra] & members[rc]:
            rejected += 1
            continue
        parent[rc] = ra
        members[ra] |= members.pop(rc)
        matches.append(Match(a, la, c, lc, d))
    groups: dict[tuple[int, int], list[tuple[int, int]]] = {}
    for x in parent:
        groups.setdefault(root(x), []).append(x)
    clusters = [sorted(g) for g in groups.values() if len(g) > 1]
    clusters.sort()
    return Associations(matches, clusters, candidates, gated, rejected)
