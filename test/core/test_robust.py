"""Robust pre-filters of rendezvous measurements on synthetic cases with known answers."""

from __future__ import annotations

import numpy as np
import pytest

from csam_ros.core import se2
from csam_ros.core.log import (
    MultiRobotLog,
    OdometryLog,
    RendezvousLog,
    RobotLog,
    empty_features,
    empty_rendezvous,
)
from csam_ros.core.robust import consistent_rendezvous, thin_rendezvous


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
    log = MultiRobotLog(
        {"robot1": robot("robot1", rv), "robot2": robot("robot2", empty_rendezvous())}
    )
    thinned, report = thin_rendezvous(log, min_interval=1.0)
    kept = thinned.robots["robot1"].rendezvous
    assert kept.stamps.size == 40  # 20 per pair
    for other in ("robot2", "robot3"):
        t = kept.stamps[np.array(kept.observed) == other]
        assert np.all(np.diff(t) >= 1.0 - 1e-12)
    assert report.dropped["robot1"]["thinned_interval"] == 120
    assert report.kept == {"robot1": 40, "robot2": 0}
    capped, report = thin_rendezvous(log, min_interval=1.0, max_per_pair=5)
    kept = capped.robots["robot1"].rendezvous
    t2 = kept.stamps[np.array(kept.observed) == "robot2"]
    assert t2.size == 5 and t2[0] == 0.0 and t2[-1] == 19.0  # spread over the whole run
    assert report.dropped["robot1"]["thinned_cap"] == 30
    assert thinned.robots["robot2"] is not log.robots["robot2"]  # a new log, input untouched
    assert log.robots["robot1"].rendezvous.stamps.size == 160
    with pytest.raises(ValueError, match="max_per_pair"):
        thin_rendezvous(log, max_per_pair=0)


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
    log = MultiRobotLog(
        {
            "p": robot("p", rendezvous(t_meas, ["q"] * 30, r_pq, b_pq)),
            "q": robot("q", rendezvous(t_meas[:10], ["p"] * 10, r_qp, b_qp)),
        }
    )
    trajectories = {"p": (stamps, poses_p), "q": (stamps, poses_q)}
    filtered, report = consistent_rendezvous(log, trajectories, drift=0.1)
    assert report.dropped == {"p": {"inconsistent": 2}, "q": {"inconsistent": 1}}
    kept_p = filtered.robots["p"].rendezvous
    assert kept_p.stamps.size == 28
    assert t_meas[3] not in kept_p.stamps and t_meas[17] not in kept_p.stamps
    assert filtered.robots["q"].rendezvous.stamps.size == 9
    pair = report.pairs["p|q"]
    assert pair["verified"] and pair["inliers"] == 37
    np.testing.assert_allclose(pair["base_node"], base, atol=0.05)


def test_consistent_rendezvous_leaves_unverifiable_pairs_alone() -> None:
    stamps = np.array([0.0, 1.0])
    poses = np.zeros((2, 3))
    rv = rendezvous(np.array([0.5]), ["q"], np.array([2.0]), np.array([0.1]))
    log = MultiRobotLog({"p": robot("p", rv), "q": robot("q", empty_rendezvous())})
    filtered, report = consistent_rendezvous(log, {"p": (stamps, poses), "q": (stamps, poses)})
    assert filtered.robots["p"].rendezvous.stamps.size == 1
    assert report.pairs["p|q"]["verified"] is False


def test_odometry_scales_recover_a_known_scale() -> None:
    from csam_ros.bench.mrclam import dead_reckoning
    from csam_ros.core.robust import OdometryScale, odometry_scales, scale_odometry

    n = 2001
    stamps = np.linspace(0.0, 100.0, n)
    inputs = np.column_stack(
        [0.1 + 0.05 * np.sin(stamps / 7), np.zeros(n), 0.3 * np.sin(stamps / 5)]
    )
    true_log = OdometryLog(stamps, inputs, np.full((n, 3), 0.01))
    true_poses = dead_reckoning(true_log)
    reported = OdometryLog(stamps, inputs / np.array([1.05, 1.0, 1.2]), true_log.sigmas)
    log = MultiRobotLog({"r": RobotLog("r", reported, empty_features(), empty_rendezvous())})
    keys = np.arange(0, n, 20)
    scales = odometry_scales(log, {"r": (stamps[keys], true_poses[keys])})
    assert scales["r"].forward == pytest.approx(1.05, rel=5e-3)  # first order in the arcs
    assert scales["r"].turn == pytest.approx(1.2, rel=2e-3)
    corrected = scale_odometry(log, {"r": OdometryScale(1.05, 1.2)})
    np.testing.assert_allclose(corrected.robots["r"].odometry.inputs, inputs)
