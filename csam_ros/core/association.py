"""Feature association between aligned maps (paper section IV-B, Algorithm 2; METHOD 6).

The hypothesis "feature ``i`` of robot ``a`` and feature ``j`` of robot ``c`` are one" predicts
``r = B_a (+) l_i - B_c (+) l_j = 0`` (the paper's ``l_i^p - b_pq (+) l_j^q`` when ``a`` is the
reference). With ``H`` its Jacobian and ``P`` the joint covariance of ``(l_i, B_a, l_j, B_c)``,
cross terms included, ``S = H P H^T`` and ``D = r^T S^-1 r`` (eq. 26).

Joint covariance, recovered sparsely. Algorithm 1 gives the joint covariance ``Sigma`` of the
rendezvous poses ``rho`` of all robots and of the base nodes. Inside one local map a feature
depends on the connector only through the rendezvous poses: ``l = l0 + K (rho - rho0) + eps``
with the gain ``K = P_l,rho P_rho,rho^-1`` and ``eps`` independent of everything outside that
map, of covariance ``C = P_ll - K P_rho,rho K^T`` (the local map's marginals). Hence after
Algorithm 1 a feature's mean is ``l0 + K (rho - rho0)`` and, writing its global position
``g = B_a (+) l`` to first order as ``G s + J_l eps`` (``s`` the Algorithm 1 state,
``G = [J_l K | J_B]`` on robot ``a``'s columns),

    S_ij = (G_i - G_j) Sigma (G_i - G_j)^T + J_li C_i J_li^T + J_lj C_j J_lj^T.

Only the rendezvous columns of each local covariance are ever needed (``P_l,rho``), never the
full map covariance.

Candidates. Pairs are found with a k-d tree on global positions (scipy ``cKDTree``): since
``D >= |r|^2 / lambda_max(S)`` and ``sqrt(lambda_max(S)) <= s_i + s_j`` with ``s`` the largest
standard deviation of each global position, a pair can pass the gate only if
``|r| <= sqrt(xi) (s_i + s_j)``: the search radius, exact, not a heuristic.

Decision. A pair is a match candidate when ``D < xi`` (chi-square, 2 dof; default 9.21, the
99 % quantile). Between two robots the matches are then made unique both ways by a global
assignment that maximises ``sum(xi - D)`` over the gated pairs (``linear_sum_assignment`` on
each connected component of the candidate graph), so a conflict is resolved in favour of the
overall best-fitting set rather than the first pair found. With more than two robots,
matches are merged into clusters (union-find) in increasing ``D``; a match that would put two
features of one robot into one cluster is rejected and counted.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray
from scipy.optimize import linear_sum_assignment
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from csam_ros.core import se2
from csam_ros.core.alignment import Alignment

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]

CHI2_2DOF_99 = 9.21


@dataclass
class MapFeatures:
    """One robot's local features as Algorithm 2 needs them.

    ``positions`` (F, 2) and ``covariances`` (F, 2, 2) are local estimates and marginal
    covariances in ``G_r``; ``rendezvous_gain`` (F, 2, 3n) is ``K = P_l,rho P_rho,rho^-1``
    with the columns of the robot's rendezvous part (:class:`~csam_ros.core.alignment.
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
    rejected_conflicts: int = 0  # gated pairs dropped for uniqueness across robots
    posterior_positions: dict[int, Array] = field(default_factory=dict)  # robot -> (F, 2) local


@dataclass
class _GlobalFeatures:
    """Global positions of one robot's features and their linearisation on the state."""

    robot: int
    labels: IntArray
    position: Array  # (F, 2) reference frame
    state_gain: Array  # (F, 2, m_r) on ``columns``
    columns: IntArray  # state columns of the robot (rho then base)
    noise: Array  # (F, 2, 2) J_l C J_l^T
    sigma_max: Array  # (F,) largest std of the global position


def _global_features(
    r: int, features: MapFeatures, alignment: Alignment, sigma_rho_prior: Array
) -> _GlobalFeatures:
    """Posterior global feature positions of robot ``r`` after Algorithm 1 (module docs)."""
    base = alignment.base_nodes[r]
    shift = alignment.rendezvous_shift[r].reshape(-1)
    gain = features.rendezvous_gain
    local = features.positions + np.einsum("fij,j->fi", gain, shift)
    f = len(local)
    base_rep = np.broadcast_to(base, (f, 3))
    c, s = np.cos(base[2]), np.sin(base[2])
    rot = np.array([[c, -s], [s, c]])
    position = se2.transform_point(base_rep, local)
    j_l = np.broadcast_to(rot, (f, 2, 2))
    cond = features.covariances - gain @ sigma_rho_prior @ gain.transpose(0, 2, 1)
    noise = j_l @ cond @ j_l.transpose(0, 2, 1)
    rho_cols = alignment.rho_columns(r)
    base_cols = alignment.base_columns(r)
    blocks = [j_l @ gain]
    columns = [rho_cols]
    if base_cols is not None:
        j_b = np.zeros((f, 2, 3))
        j_b[:, 0, 0] = j_b[:, 1, 1] = 1.0
        j_b[:, 0, 2] = -s * local[:, 0] - c * local[:, 1]
        j_b[:, 1, 2] = c * local[:, 0] - s * local[:, 1]
        blocks.append(j_b)
        columns.append(base_cols)
    state_gain = np.concatenate(blocks, axis=2)
    cols = np.concatenate(columns)
    sub = alignment.covariance[np.ix_(cols, cols)]
    total = state_gain @ sub @ state_gain.transpose(0, 2, 1) + noise
    sigma_max = np.sqrt(
        np.maximum(np.linalg.eigvalsh(0.5 * (total + total.transpose(0, 2, 1)))[:, -1], 0)
    )
    return _GlobalFeatures(r, features.labels, position, state_gain, cols, noise, sigma_max)


def _pair_distances(
    ga: _GlobalFeatures, gc: _GlobalFeatures, ia: IntArray, ic: IntArray, sigma: Array
) -> Array:
    """Mahalanobis distances of candidate pairs ``(ia, ic)`` (module docs, eq. 26)."""
    cols = np.concatenate([ga.columns, gc.columns])
    sub = sigma[np.ix_(cols, cols)]
    ma = len(ga.columns)
    m = len(cols)
    g = np.zeros((len(ia), 2, m))
    g[:, :, :ma] = ga.state_gain[ia]
    g[:, :, ma:] -= gc.state_gain[ic]
    s_mat = g @ sub @ g.transpose(0, 2, 1) + ga.noise[ia] + gc.noise[ic]
    r = ga.position[ia] - gc.position[ic]
    return np.einsum("ki,ki->k", r, np.linalg.solve(s_mat, r[:, :, None])[:, :, 0])


def _assign(ia: IntArray, ic: IntArray, d: Array, gate: float) -> NDArray[np.bool_]:
    """Unique matches maximising ``sum(gate - D)``, per connected component of candidates."""
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
) -> Associations:
    """Algorithm 2 over every pair of aligned robots (index ``r`` follows the alignment).

    ``parts_sqrt_information[r]`` is robot ``r``'s rendezvous square-root information (the
    ``R`` of its :class:`~csam_ros.core.alignment.RendezvousPart`), which gives the local
    covariance of its rendezvous poses ``P_rho,rho = R^-1 R^-T``.
    """
    options = options or AssociationOptions()
    gate = float(options.chi2_gate)
    if not gate > 0:
        raise ValueError(f"chi2_gate must be positive, got {gate}")
    glob: dict[int, _GlobalFeatures] = {}
    posterior: dict[int, Array] = {}
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
        posterior[r] = se2.inverse_transform_point(
            np.broadcast_to(alignment.base_nodes[r], (len(feats.labels), 3)), glob[r].position
        )
    robots = sorted(glob)
    found: list[tuple[float, int, int, int, int]] = []
    candidates = gated = 0
    root_gate = np.sqrt(gate)
    for i, a in enumerate(robots):
        for c in robots[i + 1 :]:
            ga, gc = glob[a], glob[c]
            tree = cKDTree(gc.position)
            radius = root_gate * (ga.sigma_max + gc.sigma_max.max())
            lists = tree.query_ball_point(ga.position, radius)
            ia = np.repeat(np.arange(len(lists)), [len(x) for x in lists])
            ic = np.fromiter((j for x in lists for j in x), dtype=np.int64, count=len(ia))
            dist = np.hypot(*(ga.position[ia] - gc.position[ic]).T)
            near = dist <= root_gate * (ga.sigma_max[ia] + gc.sigma_max[ic])
            ia, ic = ia[near], ic[near]
            candidates += len(ia)
            d = _pair_distances(ga, gc, ia, ic, alignment.covariance)
            inside = d < gate
            ia, ic, d = ia[inside], ic[inside], d[inside]
            gated += len(d)
            keep = _assign(ia, ic, d, gate)
            found.extend(
                (float(dd), a, int(ga.labels[x]), c, int(gc.labels[y]))
                for dd, x, y in zip(d[keep], ia[keep], ic[keep], strict=True)
            )
    return _cluster(found, gated, candidates, posterior)


def _cluster(
    found: list[tuple[float, int, int, int, int]],
    gated: int,
    candidates: int,
    posterior: dict[int, Array],
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
    return Associations(matches, clusters, candidates, gated, rejected, posterior)
