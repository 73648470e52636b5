"""Robust pre-filters of rendezvous measurements on synthetic cases with known answers."""

from __future__ import annotations

import numpy as np
import pytest

from csam_ros.core.joining.rendezvous_filters import (
    RendezvousThinning,
    consistent_rendezvous,
    thin_rendezvous,
)
from csam_ros.core.model import se2
from csam_ros.core.model.log import (
    MultiRobotLog,
    OdometryLog,
    RendezvousLog,
    RobotLog,
    empty_features,
    empty_rendezvous,
)


def robot(name: str, rendezvous: RendezvousLog) -> RobotLog:
    odometry = OdometryLog(np.array([0.0, 100.0]), np.zeros((2, 3)), np.ones((2, 3)))
    return RobotLog(name, odometry, empty_features(), rendezvous)


def rendezvous(stamps: np.ndarray, observed: list[str], ranges: np.ndarray, bearings: np.ndarray):
    n = len(stamps)
    return RendezvousLog(
        np.asarray(stamps, float), observed, ranges, bearings, np.full(n, 0.05), np.full(n, 0.01)
    )


def test_thin_rendezvous_interval_and_cap() -> None:
    stamps = np.arange(0.0, 20.0, 0.25)  # 80 per pair
    n = stamps.size
    observed = ["robot2"] * n
    stamps_all = np.concatenate([stamps, stamps + 0.1])
    observed_all = observed + ["robot3"] * n
    order = np.argsort(stamps_all, kind="stable")
    rv = rendezvous(
        stamps_all[order],
        [observed_all[i] for i in order],
        np.ones(2 * n),
        np.zeros(2 * n),
    )
    logs = {"robot1": rv, "robot2": empty_rendezvous()}
    thinned, report = thin_rendezvous(logs, min_interval=1.0)
    kept = thinned["robot1"]
    assert kept.stamps.size == 40  # 20 per pair
    for other in ("robot2", "robot3"):
        t = kept.stamps[np.array(kept.observed) == other]
        assert np.all(np.diff(t) >= 1.0 - 1e-12)
    assert report.dropped["robot1"]["thinned_interval"] == 120
    assert report.kept == {"robot1": 40, "robot2": 0}
    capped, report = thin_rendezvous(logs, min_interval=1.0, max_per_pair=5)
    t2 = capped["robot1"].stamps[np.array(capped["robot1"].observed) == "robot2"]
    # 0..5 offered, halved to 1, 3, 5 (the newest stays; interval 2); 7, 9, 11 offered, halved
    # to 3, 7, 11 (interval 4); 15, 19 offered: 11 offered in all, 5 kept
    np.testing.assert_array_equal(t2, [3.0, 7.0, 11.0, 15.0, 19.0])  # spread over the run
    assert report.dropped["robot1"]["thinned_cap"] == 2 * (11 - 5)
    assert report.dropped["robot1"]["thinned_interval"] == 2 * (80 - 11)
    assert logs["robot1"].stamps.size == 160  # input untouched
    with pytest.raises(ValueError, match="max_per_pair"):
        thin_rendezvous(logs, max_per_pair=0)


def test_thinning_streams_as_the_offline_filter() -> None:
    """The smoothers' streaming decisions reach the offline filter's kept set, and the filter
    is idempotent (the merger applies it again to already thinned logs)."""
    rng = np.random.default_rng(3)
    stamps = np.sort(rng.uniform(0.0, 500.0, 400))
    observed = list(rng.choice(["b", "c"], 400))
    rv = rendezvous(stamps, observed, np.ones(400), np.zeros(400))
    thinned, _ = thin_rendezvous({"a": rv}, min_interval=2.0, max_per_pair=7)
    streaming = RendezvousThinning(2.0, 7)
    for t, o in zip(stamps, observed, strict=True):
        streaming.offer("a", o, t)
    for other in ("b", "c"):
        kept = thinned["a"].stamps[np.array(thinned["a"].observed) == other]
        assert 4 <= kept.size <= 7
        np.testing.assert_array_equal(kept, streaming.kept_stamps("a", other))
    again, report = thin_rendezvous(thinned, min_interval=2.0, max_per_pair=7)
    np.testing.assert_array_equal(again["a"].stamps, thinned["a"].stamps)
    assert report.dropped == {}


def test_consistent_rendezvous_drops_wrong_measurements() -> None:
    rng = np.random.default_rng(4)
    stamps = np.linspace(0.0, 99.0, 100)
    # trajectories in their own frames
    poses_p = np.stack([np.cos(stamps / 15), np.sin(stamps / 20), stamps / 30], -1)
    poses_q = np.stack([2 * np.sin(stamps / 25), np.cos(stamps / 10), -stamps / 40], -1)
    base = np.array([3.0, -1.0, 0.7])  # G_q in G_p
    world_p, world_q = poses_p, se2.compose(base, poses_q)
    t_meas = np.sort(rng.uniform(0, 99, 30))

    def at(poses: np.ndarray, t: np.ndarray) -> np.ndarray:
        return np.stack([np.interp(t, stamps, poses[:, k]) for k in range(3)], -1)

    def measure(observer: np.ndarray, target: np.ndarray):
        local = se2.inverse_transform_point(observer, target[:, :2])
        r = np.linalg.norm(local, axis=1) + rng.normal(scale=0.02, size=len(local))
        b = np.arctan2(local[:, 1], local[:, 0]) + rng.normal(scale=0.005, size=len(local))
        return r, b

    r_pq, b_pq = measure(at(world_p, t_meas), at(world_q, t_meas))
    r_qp, b_qp = measure(at(world_q, t_meas[:10]), at(world_p, t_meas[:10]))
    r_pq[[3, 17]] += 1.5  # two wrong measurements by p
    b_qp[5] += 0.8  # and one by q
    logs = {
        "p": rendezvous(t_meas, ["q"] * 30, r_pq, b_pq),
        "q": rendezvous(t_meas[:10], ["p"] * 10, r_qp, b_qp),
    }
    trajectories = {"p": (stamps, poses_p), "q": (stamps, poses_q)}
    filtered, report = consistent_rendezvous(logs, trajectories, drift=0.1)
    assert report.dropped == {"p": {"inconsistent": 2}, "q": {"inconsistent": 1}}
    kept_p = filtered["p"]
    assert kept_p.stamps.size == 28
    assert t_meas[3] not in kept_p.stamps and t_meas[17] not in kept_p.stamps
    assert filtered["q"].stamps.size == 9
    pair = report.pairs["p|q"]
    assert pair["verified"] and pair["inliers"] == 37
    np.testing.assert_allclose(pair["base_node"], base, atol=0.05)


def test_consistent_rendezvous_leaves_unverifiable_pairs_alone() -> None:
    stamps = np.array([0.0, 1.0])
    poses = np.zeros((2, 3))
    rv = rendezvous(np.array([0.5]), ["q"], np.array([2.0]), np.array([0.1]))
    logs = {"p": rv, "q": empty_rendezvous()}
    filtered, report = consistent_rendezvous(logs, {"p": (stamps, poses), "q": (stamps, poses)})
    assert filtered["p"].stamps.size == 1
    assert report.pairs["p|q"]["verified"] is False


def test_odometry_scales_recover_a_known_scale() -> None:
    from csam_ros.core.joining.rendezvous_filters import (
        OdometryScale,
        odometry_scales,
        scale_odometry,
    )
    from csam_ros.core.model.motion import odometry_poses

    n = 2001
    stamps = np.linspace(0.0, 100.0, n)
    inputs = np.column_stack(
        [0.1 + 0.05 * np.sin(stamps / 7), np.zeros(n), 0.3 * np.sin(stamps / 5)]
    )
    true_log = OdometryLog(stamps, inputs, np.full((n, 3), 0.01))
    true_poses = odometry_poses(stamps, inputs)
    reported = OdometryLog(stamps, inputs / np.array([1.05, 1.0, 1.2]), true_log.sigmas)
    log = MultiRobotLog({"r": RobotLog("r", reported, empty_features(), empty_rendezvous())})
    keys = np.arange(0, n, 20)
    scales = odometry_scales(log, {"r": (stamps[keys], true_poses[keys])})
    assert scales["r"].forward == pytest.approx(1.05, rel=5e-3)  # first order in the arcs
    assert scales["r"].turn == pytest.approx(1.2, rel=2e-3)
    corrected = scale_odometry(log, {"r": OdometryScale(1.05, 1.2)})
    np.testing.assert_allclose(corrected.robots["r"].odometry.inputs, inputs)
