"""Rendezvous model (eq. 22-24): values against se2 compounding, Jacobians against central
finite differences."""

from __future__ import annotations

import numpy as np
import pytest
from jacobians import numeric_block_jacobians

from csam_ros.core.model import rendezvous, se2, sensor
from csam_ros.core.model.log import RendezvousLog


def _random_poses(rng: np.random.Generator, k: int) -> np.ndarray:
    return np.column_stack([rng.uniform(-5, 5, (k, 2)), rng.uniform(-np.pi, np.pi, k)])


def test_predict_matches_compounding() -> None:
    rng = np.random.default_rng(1)
    x_o, b_o, x_t, b_t = (_random_poses(rng, 20) for _ in range(4))
    pred = rendezvous.predict(x_o, b_o, x_t[:, :2], b_t)
    expected = se2.between(se2.compose(b_o, x_o), se2.compose(b_t, x_t))[:, :2]
    np.testing.assert_allclose(pred.position, expected, atol=1e-12)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_predict_jacobians_finite_difference(seed: int) -> None:
    rng = np.random.default_rng(seed)
    x_o, b_o, b_t = (_random_poses(rng, 15) for _ in range(3))
    t = rng.uniform(-3, 3, (15, 2))
    pred = rendezvous.predict(x_o, b_o, t, b_t)
    analytic = (pred.d_observer_pose, pred.d_observer_base, pred.d_observed_position)
    numeric = numeric_block_jacobians(lambda a: rendezvous.predict(*a).position, [x_o, b_o, t, b_t])
    for got, expected in zip((*analytic, pred.d_observed_base), numeric, strict=True):
        np.testing.assert_allclose(got, expected, atol=1e-7)


def test_pair_directions_match_paper_equations() -> None:
    rng = np.random.default_rng(3)
    x_p, b, x_q = (_random_poses(rng, 10) for _ in range(3))
    forward = np.arange(10) % 2 == 0
    pos, d_p, d_b, d_q = rendezvous.predict_pair(x_p, b, x_q, forward)
    p_sees_q = se2.compose(se2.compose(se2.inverse(x_p), b), x_q)[:, :2]
    q_sees_p = se2.compose(se2.compose(se2.inverse(x_q), se2.inverse(b)), x_p)[:, :2]
    np.testing.assert_allclose(pos, np.where(forward[:, None], p_sees_q, q_sees_p), atol=1e-12)
    numeric = numeric_block_jacobians(
        lambda a: rendezvous.predict_pair(a[0], a[1], a[2], forward)[0], [x_p, b, x_q]
    )
    for analytic, expected in zip((d_p, d_b, d_q), numeric, strict=True):
        np.testing.assert_allclose(analytic, expected, atol=1e-7)
    # the observed robot's heading never enters the prediction
    assert np.all(d_q[forward][:, :, 2] == 0.0)
    assert np.all(d_p[~forward][:, :, 2] == 0.0)


def test_point_difference_and_jacobians() -> None:
    rng = np.random.default_rng(4)
    b_a, b_c = _random_poses(rng, 12), _random_poses(rng, 12)
    l_a, l_c = rng.uniform(-4, 4, (12, 2)), rng.uniform(-4, 4, (12, 2))
    r, d_la, d_ba, d_lc, d_bc = rendezvous.point_difference(l_a, b_a, l_c, b_c)
    np.testing.assert_allclose(
        r, se2.transform_point(b_a, l_a) - se2.transform_point(b_c, l_c), atol=1e-12
    )
    numeric = numeric_block_jacobians(
        lambda a: rendezvous.point_difference(*a)[0], [l_a, b_a, l_c, b_c]
    )
    for analytic, expected in zip((d_la, d_ba, d_lc, d_bc), numeric, strict=True):
        np.testing.assert_allclose(analytic, expected, atol=1e-7)


def _logs():
    z = np.array
    return {
        "a": RendezvousLog(
            z([1.0, 2.0, 3.0]),
            ["b", "b", "ghost"],
            z([1.0, 2.0, 3.0]),
            z([0.1, 0.2, 0.3]),
            z([0.01] * 3),
            z([0.012] * 3),
        ),
        "b": RendezvousLog(z([2.0]), ["a"], z([2.0]), z([-0.1]), z([0.01]), z([0.012])),
    }


def test_required_stamps_cover_both_directions() -> None:
    stamps = rendezvous.required_stamps(_logs())
    np.testing.assert_array_equal(stamps["a"], [1.0, 2.0, 3.0])
    np.testing.assert_array_equal(stamps["b"], [1.0, 2.0])


def test_collect_pairs_stamps_with_poses_and_explains_what_it_leaves_out() -> None:
    poses = {"a": np.array([0.0, 1.0, 2.0, 3.0]), "b": np.array([1.0, 2.0])}
    meas, notes = rendezvous.collect(_logs(), poses)
    assert len(meas) == 3 and meas.robots == ["a", "b"]
    np.testing.assert_array_equal(meas.stamps, [1.0, 2.0, 2.0])
    np.testing.assert_array_equal(meas.observer_pose, [1, 2, 1])
    np.testing.assert_array_equal(meas.observed_pose, [0, 1, 2])
    assert any("ghost" in n for n in notes)
    z, _ = sensor.polar_to_cartesian(1.0, 0.1, 0.01, 0.012)
    np.testing.assert_allclose(meas.position[0], z[0])
    with pytest.raises(ValueError, match=r"robot 'b' has no pose at rendezvous stamp 2\.0"):
        rendezvous.collect(_logs(), {"a": poses["a"], "b": np.array([1.0])})
    meas, notes = rendezvous.collect(
        _logs(), {"a": poses["a"], "b": np.array([1.0])}, skip_missing_poses=True
    )
    assert len(meas) == 1 and any("no pose" in n for n in notes)
