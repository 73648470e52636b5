"""Relative camera range scales from mutual rendezvous (csam_ros.core.truth.range_scale)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from noise_models import noise_model

from csam_ros.core.truth.range_scale import (
    MutualPairs,
    map_range_scales,
    meeting_jackknife,
    meetings,
    mutual_pairs,
    mutual_range_scales,
    reference_from_joined_map,
)


def _relative(scales: dict[str, float]) -> dict[str, float]:
    """Scales divided by their geometric mean."""
    mean = np.exp(np.mean(np.log(list(scales.values()))))
    return {k: v / mean for k, v in scales.items()}


def _meeting(
    rng: np.random.Generator,
    scale_a: float,
    scale_b: float,
    exponent: float,
    noise: float,
    outliers: float,
    duration: float = 200.0,
) -> tuple[np.ndarray, ...]:
    """Two robots measuring each other asynchronously (about 4 Hz each, own clocks) while
    their distance and bearings change smoothly; log-normal range noise and a fraction of
    gross outliers."""
    t_a = np.sort(rng.uniform(0.0, duration, int(4 * duration)))
    t_b = np.sort(rng.uniform(0.0, duration, int(4 * duration)))
    phase = rng.uniform(0, 2 * np.pi, 3)

    def distance(t: np.ndarray) -> np.ndarray:
        return 2.5 + 1.5 * np.sin(0.05 * t + phase[0])

    def bearing(t: np.ndarray, k: int) -> np.ndarray:
        return 0.5 * np.sin(0.07 * t + phase[k])

    def measure(t: np.ndarray, scale: float, k: int) -> tuple[np.ndarray, np.ndarray]:
        b = bearing(t, k)
        r = scale * distance(t) * np.cos(b) ** exponent * np.exp(noise * rng.normal(size=t.size))
        bad = rng.random(t.size) < outliers
        r[bad] *= rng.uniform(0.5, 1.6, bad.sum())
        return r, b

    r_a, b_a = measure(t_a, scale_a, 1)
    r_b, b_b = measure(t_b, scale_b, 2)
    return t_a, r_a, b_a, t_b, r_b, b_b


def test_exact_pairs_give_the_scales_in_closed_form() -> None:
    truth = {"r1": 0.99, "r2": 1.004, "r3": 0.986, "r4": 1.01}
    names = list(truth)
    rng = np.random.default_rng(0)
    pairs = {}
    for a, b in [("r1", "r2"), ("r2", "r3"), ("r3", "r4"), ("r4", "r1"), ("r1", "r3")]:
        d = rng.uniform(1.0, 5.0, 7)
        y = np.log(truth[a] * d) - np.log(truth[b] * d)
        pairs[(a, b)] = MutualPairs(np.arange(7.0), y, np.zeros(7))
    result = mutual_range_scales(names, pairs)
    expected = _relative(truth)
    for name in names:
        assert result.scales[name] == pytest.approx(expected[name], abs=1e-9)
    assert np.prod(list(result.scales.values())) == pytest.approx(1.0, abs=1e-12)
    assert result.pairs[("r1", "r2")] == 7
    assert result.pair_log_ratio[("r1", "r2")] == pytest.approx(np.log(0.99 / 1.004), abs=1e-9)
    assert result.unpaired == []
    # the relative part re-scaled to another gauge is the truth itself
    rescaled = result.rescaled(truth)
    for name in names:
        assert rescaled[name] == pytest.approx(truth[name], abs=1e-9)


def test_simulated_meetings_recover_scales_and_depth_exponent_despite_noise_and_outliers() -> None:
    rng = np.random.default_rng(3)
    truth = {"r1": 0.9927, "r2": 0.9997, "r3": 0.9860, "r4": 1.0041, "r5": 0.9914}
    names = list(truth)
    pairs = {}
    for k, a in enumerate(names):
        for b in names[k + 1 :]:
            t_a, r_a, b_a, t_b, r_b, b_b = _meeting(rng, truth[a], truth[b], 1.0, 0.01, 0.05)
            pairs[(a, b)] = mutual_pairs(t_a, r_a, t_b, r_b, b_a, b_b, max_gap=0.5)
            assert len(pairs[(a, b)]) > 300
    fitted = mutual_range_scales(names, pairs, exponent=None)
    assert fitted.exponent == pytest.approx(1.0, abs=0.05)
    assert 0 < fitted.exponent_sigma < 0.05
    given = mutual_range_scales(names, pairs, exponent=1.0)
    expected = _relative(truth)
    for result in (fitted, given):
        for name in names:
            assert result.scales[name] == pytest.approx(expected[name], rel=1.5e-3)
            assert 0 < result.log_sigma[name] < 2e-3
        assert result.sigma == pytest.approx(np.sqrt(2) * 0.01, rel=0.3)
        assert result.outliers > 0
    # without the depth term the residuals spread far more
    plain = mutual_range_scales(names, pairs, exponent=0.0)
    assert plain.sigma > 3 * given.sigma


def test_robot_without_mutual_pair_is_reported_not_invented() -> None:
    rng = np.random.default_rng(5)
    names = ["r1", "r2", "r3", "r4"]
    t_a, r_a, _, t_b, r_b, _ = _meeting(rng, 0.98, 1.02, 0.0, 0.005, 0.0)
    far = np.array([1000.0, 1001.0])  # r3 and r4 measured each other, never at the same time
    pairs = {
        ("r2", "r1"): mutual_pairs(t_b, r_b, t_a, r_a),
        ("r3", "r4"): mutual_pairs(far, np.ones(2), far + 10.0, np.ones(2)),
    }
    assert len(pairs[("r3", "r4")]) == 0
    result = mutual_range_scales(names, pairs)
    assert set(result.scales) == {"r1", "r2"}
    assert result.unpaired == ["r3", "r4"]
    assert result.components == [["r1", "r2"]]
    assert result.scales["r1"] / result.scales["r2"] == pytest.approx(0.98 / 1.02, rel=2e-3)
    assert result.scales["r1"] * result.scales["r2"] == pytest.approx(1.0, abs=1e-12)


def test_separate_groups_each_get_their_own_gauge() -> None:
    names = ["r1", "r2", "r3", "r4"]
    one = MutualPairs(np.zeros(3), np.full(3, np.log(1.02)), np.zeros(3))
    two = MutualPairs(np.zeros(3), np.full(3, np.log(0.97)), np.zeros(3))
    result = mutual_range_scales(names, {("r1", "r2"): one, ("r4", "r3"): two})
    assert result.components == [["r1", "r2"], ["r3", "r4"]]
    assert result.scales["r1"] * result.scales["r2"] == pytest.approx(1.0)
    assert result.scales["r3"] * result.scales["r4"] == pytest.approx(1.0)
    assert result.scales["r4"] / result.scales["r3"] == pytest.approx(0.97)
    assert result.pair_log_ratio[("r3", "r4")] == pytest.approx(-np.log(0.97))


def test_mutual_pairs_interpolate_bracketing_ranges_and_respect_the_gaps() -> None:
    # b's log range grows linearly: interpolation at a's stamps is exact
    t_b = np.array([0.0, 0.4, 0.8, 5.0])
    r_b = np.exp(0.1 * t_b) * 2.0
    t_a = np.array([0.2, 0.8, 3.0, 5.03, 9.0])
    r_a = np.exp(0.1 * t_a) * 2.0 * 1.01
    pairs = mutual_pairs(t_a, r_a, t_b, r_b, max_gap=0.5, tolerance=0.05, both_directions=False)
    # 0.2: bracketed (0.0, 0.4); 0.8: exact; 3.0: gap 4.2 s, nearest 2.2 s away; 5.03:
    # nearest within the tolerance; 9.0: after b's last
    np.testing.assert_allclose(pairs.stamps, [0.2, 0.8, 5.03])
    np.testing.assert_allclose(pairs.log_ratio[:2], np.log(1.01), atol=1e-12)
    assert pairs.log_ratio[2] == pytest.approx(np.log(1.01) + 0.1 * 0.03, abs=1e-12)
    np.testing.assert_allclose(pairs.log_cos_ratio, 0.0)
    both = mutual_pairs(t_a, r_a, t_b, r_b, max_gap=0.5, tolerance=0.05)
    assert len(both) > len(pairs)
    assert np.all(np.diff(both.stamps) >= 0)
    inner = (both.stamps > 0.1) & (both.stamps < 0.9)
    np.testing.assert_allclose(both.log_ratio[inner], np.log(1.01), atol=1e-12)


def test_mutual_pairs_depth_term_from_bearings() -> None:
    t = np.array([0.0, 1.0])
    pairs = mutual_pairs(
        t,
        np.ones(2),
        t,
        np.ones(2),
        np.array([0.3, 0.3]),
        np.array([0.1, -0.1]),
        both_directions=False,
    )
    np.testing.assert_allclose(pairs.log_cos_ratio, np.log(np.cos(0.3) / np.cos(0.1)))
    with pytest.raises(ValueError, match="both robots"):
        mutual_pairs(t, np.ones(2), t, np.ones(2), np.zeros(2), None)
    with pytest.raises(ValueError, match="needs bearings"):
        mutual_range_scales(
            ["a", "b"], {("a", "b"): mutual_pairs(t, np.ones(2), t, np.ones(2))}, exponent=None
        )


def test_bad_pairs_are_rejected() -> None:
    empty = MutualPairs(np.zeros(1), np.zeros(1), np.zeros(1))
    with pytest.raises(ValueError, match="not in"):
        mutual_range_scales(["a", "b"], {("a", "c"): empty})
    with pytest.raises(ValueError, match="itself"):
        mutual_range_scales(["a", "b"], {("a", "a"): empty})


def test_meetings_split_at_pauses() -> None:
    stamps = np.array([0.0, 0.3, 10.0, 0.6, 10.2, 30.0])
    np.testing.assert_array_equal(meetings(stamps, gap=5.0), [0, 0, 1, 0, 1, 2])
    assert meetings(np.zeros(0), 5.0).size == 0


def test_jackknife_over_meetings_sees_errors_shared_within_a_meeting() -> None:
    """Each meeting carries its own offset (shared geometry): the pairs' own standard errors
    miss it, the delete-one-meeting jackknife does not."""
    rng = np.random.default_rng(11)
    truth = {"r1": 0.99, "r2": 1.01, "r3": 1.0}
    names = list(truth)
    pairs = {}
    for k, a in enumerate(names):
        for b in names[k + 1 :]:
            stamps, ratios = [], []
            for m in range(8):
                t = 100.0 * m + np.arange(40) * 0.25
                offset = 0.01 * rng.normal()
                stamps.append(t)
                ratios.append(
                    np.log(truth[a] / truth[b]) + offset + 0.005 * rng.normal(size=t.size)
                )
            y = np.concatenate(ratios)
            pairs[(a, b)] = MutualPairs(np.concatenate(stamps), y, np.zeros(y.size))
    result = mutual_range_scales(names, pairs)
    jackknife = meeting_jackknife(names, pairs, gap=5.0)
    assert jackknife.meetings == {("r1", "r2"): 8, ("r1", "r3"): 8, ("r2", "r3"): 8}
    assert jackknife.skipped == 0
    for name in names:
        assert jackknife.log_sigma[name] > 2 * result.log_sigma[name]
        assert jackknife.log_sigma[name] < 0.01


def test_scales_against_a_map_of_its_own_scale_and_frame_are_the_relative_scales() -> None:
    from csam_ros.datasets.scenario import load_scenario
    from csam_ros.datasets.simulation import simulate

    log = simulate(load_scenario("five_robots"), 1)
    assert log.truth is not None
    names = sorted(log.robots)
    truth = dict(zip(names, [0.985, 1.01, 0.995, 1.02, 0.99], strict=True))
    robots = {
        n: replace(r, features=replace(r.features, ranges=r.features.ranges * truth[n]))
        for n, r in log.robots.items()
    }
    # the map: the true landmarks scaled by 1.01, rotated and shifted (a joined map's own
    # scale and frame)
    c, s = np.cos(0.3), np.sin(0.3)
    moved = 1.01 * log.truth.feature_positions @ np.array([[c, -s], [s, c]]).T + [3.0, -2.0]
    reference = replace(log.truth, feature_positions=moved)
    noise = noise_model((0.01, 0.03, 0.012), (0.1, 0.1, 0.1))
    result = map_range_scales(replace(log, robots=robots), reference, noise)
    expected = _relative(truth)
    assert sorted(result) == names
    for name in names:
        assert result[name].scale == pytest.approx(expected[name], abs=3e-3)
        assert result[name].observations == log.robots[name].features.ranges.size
    assert np.prod([m.scale for m in result.values()]) == pytest.approx(1.0)


def test_reference_from_joined_map_keeps_shared_landmarks_and_their_members() -> None:
    features = [
        (["robot1/4", "robot2/7"], [1.0, 2.0]),
        (["robot1/5"], [3.0, 4.0]),  # one robot only: compares nothing
        (["robot2/1", "robot3/9", "robot1/2"], [5.0, 6.0]),
    ]
    reference = reference_from_joined_map(["robot1", "robot2", "robot3"], features)
    np.testing.assert_array_equal(reference.feature_ids, [0, 1])
    np.testing.assert_allclose(reference.feature_positions, [[1.0, 2.0], [5.0, 6.0]])
    assert reference.label_to_feature == {
        "robot1": {4: 0, 2: 1},
        "robot2": {7: 0, 1: 1},
        "robot3": {9: 1},
    }
