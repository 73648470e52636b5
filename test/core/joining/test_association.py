"""Algorithm 2: the k-d tree gate loses no pair a brute-force search would accept, the
Mahalanobis distances of true matches follow chi-square(2), conflicts are resolved by global
assignment and clusters keep one feature per robot."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.linalg import block_diag

from csam_ros.core.joining.alignment import align
from csam_ros.core.joining.association import (
    AssociationOptions,
    _assign,
    _candidates,
    _cluster,
    _Free,
    _global_features,
    _joined_with,
    _pair_distances,
    associate,
)
from csam_ros.core.joining.local_views import local_view, map_features
from csam_ros.core.joining.match_conditioning import (
    SparseConditioning,
    StateInformation,
    condition_dense,
    low_rank_rows,
    stack_dense,
    stacked_congruence,
    stacked_product,
)
from csam_ros.core.joining.pipeline import robot_map_from_local_map
from csam_ros.core.model.rendezvous import collect, required_stamps
from csam_ros.core.smoothing.local_map_build import build_local_map
from csam_ros.datasets.scenario import load_scenario
from csam_ros.datasets.simulation import simulate


def _stage(scenario: str, seed: int):
    """Local maps, Algorithm 1 and the association inputs of a simulated run."""
    log = simulate(load_scenario(scenario), seed)
    logs = {n: r.rendezvous for n, r in log.robots.items()}
    stamps = required_stamps(logs)
    maps = [robot_map_from_local_map(build_local_map(r, stamps[n])) for n, r in log.robots.items()]
    meas, _ = collect(logs, {m.name: m.stamps for m in maps})
    parts, feats = [], []
    for r, m in enumerate(maps):
        idx = np.unique(
            np.concatenate(
                [meas.observer_pose[meas.observer == r], meas.observed_pose[meas.observed == r]]
            )
        )
        view = local_view(m, idx)
        parts.append(view.part)
        feats.append(map_features(m, view))
    alignment = align(parts, meas)
    roots = [p.sqrt_information for p in parts]
    return log, maps, alignment, feats, roots


def _truth_pairs(log, maps, a, c):
    l2f = log.truth.label_to_feature
    fa = {l2f[maps[a].name][int(lab)]: int(lab) for lab in maps[a].feature_labels}
    fc = {l2f[maps[c].name][int(lab)]: int(lab) for lab in maps[c].feature_labels}
    return {(fa[f], fc[f]) for f in set(fa) & set(fc)}


def test_spatial_gate_loses_nothing_and_true_pairs_are_chi_square() -> None:
    gate = 9.21
    distances = []
    for seed in range(6):
        log, maps, alignment, feats, roots = _stage("map_joining", seed)
        inv = [np.linalg.inv(r) for r in roots]
        g = {r: _global_features(r, feats[r], alignment, inv[r] @ inv[r].T) for r in (0, 1)}
        state, _ = condition_dense(alignment.covariance, g, [])
        everything = [np.arange(len(g[r].labels)) for r in (0, 1)]
        free = [_Free.of(g[r], everything[r], state) for r in (0, 1)]
        ia, ic = _candidates(*free, np.sqrt(gate))
        ja, jc = (x.ravel() for x in np.meshgrid(*everything, indexing="ij"))
        d_all = _pair_distances(g[0], g[1], ja, jc, state)
        brute = set(zip(ja[d_all < gate].tolist(), jc[d_all < gate].tolist(), strict=True))
        assert brute <= set(zip(ia.tolist(), ic.tolist(), strict=True))  # k-d tree lost none
        assert len(ia) < len(d_all) / 5  # ... while looking at few pairs
        truth = _truth_pairs(log, maps, 0, 1)
        label_d = {
            (int(g[0].labels[i]), int(g[1].labels[j])): dd
            for i, j, dd in zip(ja, jc, d_all, strict=True)
        }
        distances += [label_d[p] for p in truth]
        result = associate(feats, alignment, roots, AssociationOptions(chi2_gate=gate))
        found = {(m.label_a, m.label_c) for m in result.matches}
        assert found == truth  # precision and recall 1 on this scenario
    # D of true pairs before any match is chi-square with 2 degrees of freedom (mean 2); per
    # seed the values share one alignment error, so the bound is loose
    assert 1.3 < np.mean(distances) < 3.0


def test_leave_one_out_distance_is_the_deleted_innovation() -> None:
    _, _, alignment, feats, roots = _stage("map_joining", 0)
    inv = [np.linalg.inv(r) for r in roots]
    g = {r: _global_features(r, feats[r], alignment, inv[r] @ inv[r].T) for r in (0, 1)}
    prior = alignment.covariance
    result = associate(feats, alignment, roots)
    index = [{int(lab): k for k, lab in enumerate(g[r].labels)} for r in (0, 1)]
    every = [(0, index[0][m.label_a], 1, index[1][m.label_c]) for m in result.matches]
    pairs = every[:12]
    state, loo = condition_dense(prior, g, pairs)
    # the Kalman-form update equals the information form: (P^-1 + H^T N^-1 H)^-1
    nu, h, noise = stack_dense(g, pairs, len(prior))
    rows = h.reshape(-1, h.shape[2])
    weight = block_diag(*np.linalg.inv(noise))
    information = np.linalg.inv(prior) + rows.T @ weight @ rows
    covariance = np.linalg.inv(information)
    scale = np.abs(covariance).max()
    np.testing.assert_allclose(state.covariance, covariance, atol=1e-9 * scale)
    # the blocks the candidates use are those of the whole posterior covariance
    a, c = g[0].columns, g[1].columns
    np.testing.assert_allclose(state.block(a, c), covariance[np.ix_(a, c)], atol=1e-9 * scale)
    np.testing.assert_allclose(state.block(c, c), covariance[np.ix_(c, c)], atol=1e-9 * scale)
    shift = -covariance @ rows.T @ weight @ nu.reshape(-1)
    np.testing.assert_allclose(state.shift, shift, atol=1e-8 * np.abs(shift).max())
    for k in (0, 5, 11):
        others, _ = condition_dense(prior, g, pairs[:k] + pairs[k + 1 :])
        _, i, _, j = pairs[k]
        direct = _pair_distances(g[0], g[1], np.array([i]), np.array([j]), others)[0]
        assert loo[k] == pytest.approx(direct, rel=1e-6)
    # the information form on Algorithm 1's block factor: the same state and distances
    conditioning = SparseConditioning(StateInformation(alignment.state_covariance), g)
    sparse, sparse_loo = conditioning(pairs)
    for rows, cols in ((a, c), (c, c), (a, a)):
        np.testing.assert_allclose(
            sparse.block(rows, cols), covariance[np.ix_(rows, cols)], atol=1e-9 * scale
        )
    np.testing.assert_allclose(sparse.shift, shift, atol=1e-8 * np.abs(shift).max())
    np.testing.assert_allclose(sparse_loo, loo, rtol=1e-6)
    # matches removed and added since the factorisation: a low-rank correction, the same
    # state as the Kalman form's
    for changed in (pairs[:-3], pairs[2:-3] + pairs[-2:]):
        corrected, corrected_loo = conditioning(changed)
        oracle, oracle_loo = condition_dense(prior, g, changed)
        assert conditioning.factorisations == 1
        for rows, cols in ((a, c), (c, c), (a, a)):
            np.testing.assert_allclose(
                corrected.block(rows, cols), oracle.block(rows, cols), atol=1e-9 * scale
            )
        np.testing.assert_allclose(corrected.shift, oracle.shift, atol=1e-8 * np.abs(shift).max())
        np.testing.assert_allclose(corrected_loo, oracle_loo, rtol=1e-6)
    # more rows changed than the factor's multiply-adds per nonzero: factored again
    limit = low_rank_rows(conditioning._current_factor)
    assert 0 < limit < 2 * (len(every) - len(pairs))
    conditioning(every)
    assert conditioning.factorisations == 2
    conditioning(every[: len(every) - int(limit // 2)])  # 2 * int(limit // 2) rows
    assert conditioning.factorisations == 2


def test_global_assignment_prefers_the_best_set() -> None:
    # a0-c0 is the single best pair, but {a0-c1, a1-c0} fits better as a whole
    ia = np.array([0, 0, 1])
    ic = np.array([0, 1, 0])
    d = np.array([1.0, 2.0, 1.5])
    np.testing.assert_array_equal(_assign(ia, ic, d, 9.21), [False, True, True])
    # an isolated pair is kept; a feature never gets two partners
    ia = np.array([0, 0, 5])
    ic = np.array([0, 1, 7])
    d = np.array([3.0, 1.0, 8.0])
    np.testing.assert_array_equal(_assign(ia, ic, d, 9.21), [False, True, True])


def test_clusters_keep_one_feature_per_robot() -> None:
    found = [
        (1.0, 0, 10, 1, 20),  # r0/10 ~ r1/20
        (2.0, 1, 20, 2, 30),  # r1/20 ~ r2/30 -> cluster of three
        (3.0, 0, 11, 2, 30),  # would put r0/10 and r0/11 together: rejected
        (4.0, 0, 12, 2, 31),
    ]
    result = _cluster(found, 4, 9)
    assert result.clusters == [[(0, 10), (1, 20), (2, 30)], [(0, 12), (2, 31)]]
    assert result.rejected_conflicts == 1
    assert [m.mahalanobis for m in result.matches] == [1.0, 2.0, 4.0]


def test_stacked_products_are_matmuls_of_each_matrix() -> None:
    rng = np.random.default_rng(3)
    stack, matrix, vector = rng.normal(size=(4, 2, 5)), rng.normal(size=(5, 3)), rng.normal(size=5)
    np.testing.assert_allclose(stacked_product(stack, matrix), stack @ matrix, atol=1e-14)
    np.testing.assert_allclose(stacked_product(stack, vector), stack @ vector, atol=1e-14)
    square = rng.normal(size=(5, 5))
    expected = stack @ square @ stack.transpose(0, 2, 1)
    np.testing.assert_allclose(stacked_congruence(stack, square), expected, atol=1e-13)


def test_gate_must_be_positive() -> None:
    with pytest.raises(ValueError, match="chi2_gate"):
        associate([], None, [], AssociationOptions(chi2_gate=0.0))  # type: ignore[arg-type]


def test_chain_clusters_span_robots() -> None:
    log, maps, alignment, feats, roots = _stage("chain", 0)
    result = associate(feats, alignment, roots)
    l2f = log.truth.label_to_feature
    for cluster in result.clusters:
        truth = {l2f[maps[r].name][lab] for r, lab in cluster}
        assert len(truth) == 1  # every cluster is one true feature
        assert len({r for r, _ in cluster}) == len(cluster)
    assert max(len(c) for c in result.clusters) >= 3


def test_features_tied_through_clusters_are_not_compared_again() -> None:
    # r0/0 ~ r1/5 ~ r2/7: r0/0 is tied to robot 2 through robot 1, r2/7 to robot 0
    tied = _joined_with({(0, 0, 1, 5): 1.0, (1, 5, 2, 7): 2.0, (0, 3, 1, 4): 1.0})
    assert sorted(tied[0, 2]) == [0] and sorted(tied[2, 0]) == [7]
    assert sorted(tied[0, 1]) == [0, 3] and sorted(tied[1, 2]) == [5]
    assert (2, 1) in tied and (0, 3) not in tied


def test_robots_that_met_are_compared_first() -> None:
    """Robot pairs that never met are compared from the second pass on: on the chain (robots
    meet their neighbours only) the clusters are those of comparing every pair at once, and
    each is one true feature."""
    log, maps, alignment, feats, roots = _stage("chain", 0)
    index = {m.name: r for r, m in enumerate(maps)}
    met = {
        (min(index[n], index[o]), max(index[n], index[o]))
        for n, robot in log.robots.items()
        for o in robot.rendezvous.observed
    }
    assert len(met) < len(maps) * (len(maps) - 1) // 2  # some pairs never met
    first = associate(feats, alignment, roots)
    later = associate(feats, alignment, roots, met=met)
    l2f = log.truth.label_to_feature
    for cluster in later.clusters:
        assert len({l2f[maps[r].name][lab] for r, lab in cluster}) == 1
    assert later.clusters == first.clusters
