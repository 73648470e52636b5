"""Local map: online feeding equals the offline batch, late rendezvous poses, outputs."""

import numpy as np
import pytest

from csam_ros.core.model import motion, se2
from csam_ros.core.model.log import OdometryLog, RobotLog
from csam_ros.core.sam.factors import PointObservation, RelativePose
from csam_ros.core.smoothing.local_map import LocalMap
from csam_ros.core.smoothing.local_map_build import build_local_map
from csam_ros.core.smoothing.local_map_config import LocalMapOptions
from csam_ros.datasets.simulation import simulate_robot_log


def make_log(duration=40.0, rate=67.0, seed=0, landmarks=12, scan_rate=2.0):
    return simulate_robot_log(duration, rate, seed, landmarks, scan_rate)


def feed_online(log, late_stamps=(), chunk=1.0, options=None):
    """Feed a log in stamp order in chunks of ``chunk`` seconds, updating after each chunk."""
    local = LocalMap(log.name, options)
    local.inserted = 0
    odo, f = log.odometry, log.features
    t0, t1 = odo.stamps[0], odo.stamps[-1]
    edges = np.arange(t0, t1 + chunk, chunk)
    for a, b in zip(edges[:-1], edges[1:], strict=True):
        o = (odo.stamps >= a) & (odo.stamps < b) if a > t0 else odo.stamps < b
        local.add_log_part(log, o, (f.stamps >= a) & (f.stamps < b))
        local.request_poses(
            log.rendezvous.stamps[(log.rendezvous.stamps >= a) & (log.rendezvous.stamps < b)]
        )
        if b > t0 + 0.6 * (t1 - t0):
            # another robot's observation of this robot, reported late, stamped in the past
            local.request_poses([s for s in late_stamps])
            late_stamps = ()
        local.inserted += local.update().inserted_poses
    local.add_log_part(log, odo.stamps >= edges[-1], [])
    local.update(converge=True)
    return local


def test_log_parts_in_any_order_and_selection_give_the_whole_log():
    log, _, _, _ = make_log(duration=10.0, seed=3)
    whole = LocalMap("r")
    whole.add_log(log)
    whole.update(converge=True)
    parts = LocalMap("r")
    n, k = len(log.odometry.stamps), len(log.features.stamps)
    first_features = np.zeros(k, dtype=bool)
    first_features[: k // 2] = True
    parts.add_log_part(log, slice(0, n // 2), first_features)
    parts.add_log_part(log, np.arange(n // 2, n), np.flatnonzero(~first_features)[::-1])
    parts.request_poses(log.rendezvous.stamps)
    parts.update(converge=True)
    np.testing.assert_array_equal(parts.stamps, whole.stamps)
    np.testing.assert_array_equal(parts.landmark_labels, whole.landmark_labels)
    np.testing.assert_allclose(parts.poses, whole.poses, atol=1e-9)
    np.testing.assert_allclose(parts.landmarks, whole.landmarks, atol=1e-9)


def test_online_equals_offline_batch_with_late_pose_insertion():
    log, _, stamps, _ = make_log()
    late = [stamps[0] + 3.3337, stamps[0] + 12.5]
    offline = build_local_map(log, extra_pose_stamps=late)
    online = feed_online(log, late_stamps=late)
    assert online.last_report is not None
    np.testing.assert_array_equal(online.stamps, offline.stamps)
    np.testing.assert_allclose(online.poses[:, :2], offline.poses[:, :2], atol=1e-7)
    np.testing.assert_allclose(
        se2.wrap_angle(online.poses[:, 2] - offline.poses[:, 2]), 0, atol=1e-8
    )
    np.testing.assert_array_equal(online.landmark_labels, offline.landmark_labels)
    np.testing.assert_allclose(online.landmarks, offline.landmarks, atol=1e-7)
    assert online.problem.cost() == pytest.approx(offline.problem.cost(), rel=1e-9)
    for s in late:
        assert np.min(np.abs(online.stamps - s)) == 0.0
    assert online.inserted == 2


def test_offline_windows_and_one_batch_give_the_same_map():
    log, _, _, _ = make_log(seed=5)
    batch = build_local_map(log, window=None)
    reports = []
    windowed = build_local_map(log, window=7.0, on_update=reports.append)
    span = log.odometry.stamps[-1] - log.odometry.stamps[0]
    assert len(reports) == int(np.ceil(span / 7.0))  # a window's update each, the last converged
    assert sum(r.new_poses for r in reports) == len(windowed.stamps)
    np.testing.assert_array_equal(batch.stamps, windowed.stamps)
    np.testing.assert_allclose(batch.poses[:, :2], windowed.poses[:, :2], atol=1e-7)
    np.testing.assert_allclose(batch.landmarks, windowed.landmarks, atol=1e-7)


def test_online_updates_stay_near_the_optimum_of_the_data_so_far():
    log, _, stamps, _ = make_log(seed=6)
    local = LocalMap("r")
    odo, f = log.odometry, log.features
    worst = 0.0
    for end in stamps[0] + np.arange(2.0, 40.0, 2.0):
        o = (odo.stamps > end - 2.0) & (odo.stamps <= end)
        local.add_log_part(log, o, (f.stamps > end - 2.0) & (f.stamps <= end))
        local.update()
        converged = local._build_problem()
        converged.solve()
        worst = max(worst, float(np.abs(converged.values - local.problem.values).max()))
    assert worst < 1e-4


def test_local_map_is_in_robot_frame_and_close_to_truth():
    log, truth, stamps, lm = make_log(seed=1)
    local = build_local_map(log)
    np.testing.assert_allclose(local.poses[0], 0.0, atol=1e-9)
    assert local.stamps[0] == stamps[0]
    # key poses at every feature stamp and rendezvous stamp, regular keys every second
    for s in np.concatenate([log.features.stamps, log.rendezvous.stamps]):
        assert np.min(np.abs(local.stamps - s)) <= 1e-6
    assert np.max(np.diff(local.stamps)) <= 1.0 + 1e-9
    # landmarks near the truth (robot frame = truth frame here: both start at the origin)
    truth_lm = lm[local.landmark_labels - 10]
    assert np.max(np.linalg.norm(local.landmarks - truth_lm, axis=1)) < 0.3
    i = np.searchsorted(stamps, local.stamps[-1])
    assert np.linalg.norm(local.poses[-1, :2] - truth[i, :2]) < 0.5


def test_marginal_outputs():
    log, _, _, _ = make_log(duration=25.0, seed=2)
    local = build_local_map(log)
    covs = local.pose_covariances()
    assert covs.shape == (len(local.stamps), 3, 3)
    assert np.all(np.linalg.eigvalsh(covs)[:, 0] > 0)
    assert covs[0, 2, 2] < 1e-10 < covs[-1, 2, 2]  # gauge-fixed first pose
    lm_cov = local.landmark_covariances()
    assert lm_cov.shape == (len(local.landmark_labels), 2, 2)
    stamps = log.rendezvous.stamps[:1]
    joint = local.covariance(stamps, local.landmark_labels[:2])
    assert joint.shape == (7, 7)
    idx = local.pose_index(stamps)[0]
    np.testing.assert_allclose(joint[:3, :3], covs[idx], rtol=1e-9)
    r, key_stamps, poses = local.sqrt_information(log.rendezvous.stamps)
    assert r.shape == (6, 6) and np.allclose(np.tril(r, -1), 0)
    cov = local.covariance(key_stamps)
    np.testing.assert_allclose(r.T @ r, np.linalg.inv(cov), rtol=1e-6)
    np.testing.assert_allclose(poses, local.poses[local.pose_index(key_stamps)])


def test_features_before_odometry_are_dropped_and_counted():
    log, _, stamps, _ = make_log(duration=10.0, seed=3)
    local = LocalMap("r")
    local.add_features([stamps[0] - 1.0], [99], [1.0], [0.0], [0.01], [0.01])
    local.add_log(log)
    local.update()
    assert local.dropped_features == 1
    assert 99 not in local.landmark_labels


def test_stamps_closer_than_the_tolerance_in_a_row_each_have_a_key_pose_within_it():
    # 0.6 tol apart, each within the tolerance of the one before: one key for all of them
    # would leave the last 1.2 tol from it
    local = LocalMap("r")
    tol = local.options.stamp_tolerance
    local.add_odometry([0.0, 1.0], np.ones((2, 3)), np.ones((2, 3)))
    stamps = 0.5 + tol * np.array([0.0, 0.6, 1.2])
    local.add_features(stamps, [1, 2, 3], np.ones(3), np.zeros(3), np.ones(3), np.ones(3))
    local.update()
    keys = local.stamps[local.pose_index(stamps)]
    assert np.all(np.abs(keys - stamps) <= tol)
    assert len(np.unique(keys)) == 2


def test_a_feature_just_past_the_odometry_waits_for_a_key_pose():
    # the last odometry sample is within the tolerance of a key, the feature within it of the
    # sample, but not of the key: it waits for the odometry to reach it
    local = LocalMap("r")
    local.add_odometry([12.0, 12.000000001], np.ones((2, 3)), np.ones((2, 3)))
    local.add_features([12.000001001], [7], [1.0], [1.0], [1.0], [1.0])
    local.update()
    assert 7 not in local.landmark_labels
    local.add_odometry([12.5], np.ones((1, 3)), np.ones((1, 3)))
    local.update()
    assert 7 in local.landmark_labels


def test_bad_odometry_is_named():
    local = LocalMap("r")
    with pytest.raises(ValueError, match="odometry sample 1 has a non-positive sigma"):
        local.add_odometry([0.0, 0.1], np.ones((2, 3)), [[1, 1, 1], [1, 0, 1]])
    with pytest.raises(ValueError, match="odometry sample 1: correlations"):
        local.add_odometry([0.0, 0.1], np.ones((2, 3)), np.ones((2, 3)), [[0, 0, 0], [1, 0, 0]])
    local.add_odometry([0.0, 0.1], np.ones((2, 3)), np.ones((2, 3)))
    with pytest.raises(ValueError, match="does not follow"):
        local.add_odometry([0.05], np.ones((1, 3)), np.ones((1, 3)))


def test_maybe_update_follows_the_update_period():
    log, _, stamps, _ = make_log(duration=5.0, seed=4)
    local = LocalMap("r", LocalMapOptions(update_period=2.0))
    odo = log.odometry
    solved = 0
    for k in range(len(odo.stamps)):
        local.add_odometry(odo.stamps[k : k + 1], odo.inputs[k : k + 1], odo.sigmas[k : k + 1])
        if local.maybe_update() is not None:
            solved += 1
    assert 2 <= solved <= 4


def miscalibrated(log, distance, turn_driving, turn_spot=1.0, driving_speed=0.02):
    """The log with its odometry reporting ``distance`` x the distance and the turn rate
    scaled while driving and on the spot (the truth unchanged)."""
    o = log.odometry
    u = o.inputs.copy()
    driving = np.abs(u[:, 0]) > driving_speed
    u[:, 2] *= np.where(driving, turn_driving, turn_spot)
    u[:, :2] *= distance
    return RobotLog(log.name, OdometryLog(o.stamps, u, o.sigmas), log.features, log.rendezvous)


def test_odometry_calibration_recovers_the_scales_online():
    log, truth, stamps, _ = make_log(duration=90.0, seed=1)
    bad = miscalibrated(log, distance=0.9, turn_driving=1.5)
    local = feed_online(bad, chunk=3.0, options=LocalMapOptions(odometry_calibration=True))
    cal = local.odometry_calibration
    applied = np.array([1 / 0.9, 1 / 1.5])
    np.testing.assert_allclose(cal.scale[:2], applied, rtol=0.03)
    assert np.all(np.abs(cal.scale[:2] - applied) < 4 * cal.sigma[:2])
    spot_prior = LocalMapOptions().calibration_sigmas[2]
    assert cal.sigma[2] == pytest.approx(spot_prior, rel=1e-3)  # never on the spot: the prior
    # the published problem carries the odometry at the estimate: plain relative poses
    at_estimate = motion.calibrated_odometry_between(
        bad.odometry.stamps,
        bad.odometry.inputs,
        bad.odometry.sigmas,
        local.stamps,
        cal.scale,
        0.02,
    )
    published = [f for f in local.problem.factors if isinstance(f, RelativePose)][0]
    np.testing.assert_allclose(published.measured, at_estimate.relative_poses, atol=1e-6)
    heading = se2.wrap_angle(local.poses[:, 2] - truth[np.searchsorted(stamps, local.stamps), 2])
    assert np.abs(heading).max() < 0.1
    # the landmarks are the solve's: their observations fit (whitened errors within the gate)
    observed = [f for f in local.problem.factors if isinstance(f, PointObservation)][0]
    blocks = [local.problem.values_of(ids) for ids in observed.variables.T]
    whitened, _, _ = observed.whitened(blocks, jacobians=False)
    assert np.median(np.linalg.norm(whitened, axis=1)) < 3.0
    # saved and restored: the same estimate, the same published odometry
    again = LocalMap.from_state("r", local.state(), LocalMapOptions(odometry_calibration=True))
    np.testing.assert_array_equal(again.odometry_calibration.scale, cal.scale)
    restored = [f for f in again.problem.factors if isinstance(f, RelativePose)][0]
    np.testing.assert_allclose(restored.measured, published.measured, atol=1e-6)


def test_odometry_calibration_off_leaves_the_map_as_before():
    log = miscalibrated(make_log(duration=30.0, seed=2)[0], distance=0.95, turn_driving=1.3)
    before = feed_online(log, chunk=2.0)
    off = feed_online(log, chunk=2.0, options=LocalMapOptions(odometry_calibration=False))
    on = feed_online(log, chunk=2.0, options=LocalMapOptions(odometry_calibration=True))
    np.testing.assert_allclose(off.poses, before.poses, atol=1e-12, rtol=0)
    np.testing.assert_allclose(off.landmarks, before.landmarks, atol=1e-12, rtol=0)
    assert off.odometry_calibration is None and len(off.state().odometry_calibration) == 0
    assert np.abs(on.poses - off.poses).max() > 1e-3
