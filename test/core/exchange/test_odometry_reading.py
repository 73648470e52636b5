"""Odometry as robot drivers publish it: pose differences as inputs, default sigmas where the
covariance is zero or unknown, pose jumps and bad poses dropped and counted."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from csam_ros.core.exchange.checkpoint import FilterState, SmootherCheckpoint, ThinningState
from csam_ros.core.exchange.measurement_filter import MeasurementFilter
from csam_ros.core.exchange.validation import (
    NOT_FINITE,
    ODOMETRY_JUMP,
    POSE_UNKNOWN,
    QUATERNION_NOT_NORMALISED,
    InputBounds,
    OdometryReading,
    odometry_noise,
)
from csam_ros.core.joining.rendezvous_filters import RendezvousThinning
from csam_ros.core.model import motion, se2
from csam_ros.core.model.log import empty_rendezvous
from csam_ros.core.smoothing.local_map import LocalMap

ZERO = (0.0,) * 6  # an all-zero twist covariance, as the stock diff-drive controller sends


def _drive(n: int = 120, seed: int = 2) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Stamps, twists and the poses a driver integrates from them (from an odometry origin
    that is not the robot's start)."""
    rng = np.random.default_rng(seed)
    stamps = 50.0 + np.cumsum(rng.uniform(0.02, 0.1, n))
    twist = np.c_[rng.uniform(0.0, 1.2, n), rng.uniform(-0.05, 0.05, n), rng.uniform(-1, 1, n)]
    twist[40:50] = 0.0  # at rest
    return stamps, twist, motion.odometry_poses(stamps, twist, start=(4.0, -1.0, 0.7))


def _twist_reading(t: float, u, covariance=ZERO, pose=None) -> OdometryReading:
    return OdometryReading(float(t), tuple(map(float, u)), covariance, pose)


def _pose_reading(t: float, pose, covariance=ZERO, error: float = 0.0) -> OdometryReading:
    return OdometryReading(float(t), (0.0, 0.0, 0.0), covariance, tuple(map(float, pose)), error)


def _feed(checks: MeasurementFilter, readings) -> list:
    return [pair for r in readings for pair in checks.odometry_reading("r", r)]


@pytest.mark.parametrize("source", ["auto", "pose"])
def test_pose_only_odometry_gives_the_twist_paths_samples(source: str) -> None:
    stamps, twist, poses = _drive()
    by_twist = MeasurementFilter(["r"])
    by_pose = MeasurementFilter(["r"], bounds=InputBounds(odometry_source=source))
    a = _feed(by_twist, [_twist_reading(t, u) for t, u in zip(stamps, twist, strict=True)])
    b = _feed(by_pose, [_pose_reading(t, p) for t, p in zip(stamps, poses, strict=True)])
    assert len(a) == len(b) == len(stamps)
    # the first sample only marks the start: its input is not used
    np.testing.assert_array_equal([s[0] for s, _ in a], [s[0] for s, _ in b])
    np.testing.assert_allclose([s[1] for s, _ in a][1:], [s[1] for s, _ in b][1:], atol=1e-9)
    np.testing.assert_allclose([s[2] for s, _ in a][1:], [s[2] for s, _ in b][1:], rtol=1e-6)
    assert by_twist.defaulted.as_dict() == by_pose.defaulted.as_dict() == {"r": len(stamps)}
    assert by_pose.counter("r").total == 0
    # each sample goes with the pose its message carried (none for the twist)
    assert [p for _, p in a] == [None] * len(stamps)
    np.testing.assert_array_equal([p for _, p in b], poses)


def test_auto_takes_the_twist_where_it_is_nonzero_and_the_pose_where_it_is_zero() -> None:
    stamps, twist, poses = _drive()
    drifted = poses.copy()
    drifted[:, 0] += 0.001 * np.arange(len(stamps))  # the driver's pose and twist disagree
    checks = MeasurementFilter(["r"])
    readings = [
        _twist_reading(t, u, pose=tuple(p)) for t, u, p in zip(stamps, twist, drifted, strict=True)
    ]
    got = np.array([s[1] for s, _ in _feed(checks, readings)])
    moving = np.flatnonzero(twist.any(axis=1))
    np.testing.assert_array_equal(got[moving], twist[moving])
    by_pose = motion.inputs_from_poses(stamps[39:50], drifted[39:50])  # from the last moving
    np.testing.assert_allclose(got[40:50], by_pose, atol=1e-9)
    assert np.abs(by_pose[:, :2]).min() > 0  # the pose moved: not the twist's zero
    twist_only = MeasurementFilter(["r"], bounds=InputBounds(odometry_source="twist"))
    got = np.array([s[1] for s, _ in _feed(twist_only, readings)])
    np.testing.assert_array_equal(got, twist)


def test_a_pose_jump_is_dropped_counted_and_the_next_difference_starts_after_it() -> None:
    stamps, twist, poses = _drive()
    k = 70
    jumped = poses.copy()
    jumped[k:] = se2.compose(np.array([3.0, -8.0, 1.0]), poses[k:])  # the driver reset its pose
    checks = MeasurementFilter(["r"])
    got = _feed(checks, [_pose_reading(t, p) for t, p in zip(stamps, jumped, strict=True)])
    assert checks.counter("r").as_dict() == {ODOMETRY_JUMP: 1}
    kept = np.array([s[0] for s, _ in got])
    np.testing.assert_array_equal(kept, np.delete(stamps, k))
    # every accepted increment is the robot's motion; the one after the jump spans both
    # intervals and holds the motion after the jump only (the jump's interval is lost)
    inputs = np.array([s[1] for s, _ in got])
    increments = motion.increment(inputs[1:], np.diff(kept))
    expected = se2.between(poses[:-1], poses[1:])
    np.testing.assert_allclose(
        np.delete(increments, k - 1, axis=0)[: k - 1], expected[: k - 1], atol=1e-9
    )
    np.testing.assert_allclose(increments[k - 1], expected[k], atol=1e-9)
    np.testing.assert_allclose(increments[k:], expected[k + 1 :], atol=1e-9)


def test_bad_poses_are_dropped_counted_and_block_nothing() -> None:
    stamps, twist, poses = _drive(20)
    checks = MeasurementFilter(["r"])
    good = [_pose_reading(t, p) for t, p in zip(stamps, poses, strict=True)]
    between = 0.5 * (stamps[9] + stamps[10])
    bad = [
        _pose_reading(between, (math.nan, 0.0, 0.0)),
        _pose_reading(between, (0.0, 0.0, math.inf)),
        _pose_reading(between, poses[9], error=0.5),  # |q|^2 = 1.5: no rotation
        _pose_reading(between, poses[9], error=math.nan),
        OdometryReading(between, (0.5, 0.0, 0.0), ZERO, None),  # pose unknown, source pose
    ]
    only_pose = MeasurementFilter(["r"], bounds=InputBounds(odometry_source="pose"))
    for f in (checks, only_pose):
        _feed(f, good[:10])
        assert _feed(f, bad[:4]) == []
        got = _feed(f, good[10:])
        assert [s[0] for s, _ in got] == list(stamps[10:])
    assert checks.counter("r").as_dict() == {NOT_FINITE: 2, QUATERNION_NOT_NORMALISED: 2}
    assert _feed(only_pose, bad[4:]) == []
    assert only_pose.counter("r").as_dict() == {
        NOT_FINITE: 2,
        QUATERNION_NOT_NORMALISED: 2,
        POSE_UNKNOWN: 1,
    }
    # the auto source takes a message with no pose by its twist
    assert len(_feed(checks, [OdometryReading(stamps[-1] + 0.1, (0.5, 0.0, 0.0), ZERO)])) == 1


def test_sigmas_from_the_covariance_or_defaults_where_it_is_zero_or_unknown() -> None:
    bounds = InputBounds(odometry_sigma_per_m=0.1, odometry_sigma_per_rad=0.2)
    u, dt = np.array([1.0, 0.0, 0.5]), 0.25
    default = motion.default_input_sigmas(u[None], [dt], 0.1, 0.2, bounds.odometry_sigma_floor)[0]
    for unknown in (None, ZERO):
        sigmas, rho, defaulted = odometry_noise(unknown, u, dt, bounds)
        np.testing.assert_array_equal(sigmas, default)
        assert rho is None and defaulted
    sigmas, rho, defaulted = odometry_noise((0.04, 0.0, 0.01, 0.0, 0.0, 0.0), u, dt, bounds)
    np.testing.assert_array_equal(sigmas, [0.2, default[1], 0.1])  # v_lat's variance is zero
    assert rho is None and defaulted
    sigmas, rho, defaulted = odometry_noise((0.04, 0.01, 0.09, 0.01, 0.0, -0.015), u, dt, bounds)
    np.testing.assert_array_equal(sigmas, [0.2, 0.1, 0.3])
    np.testing.assert_allclose(rho, [0.5, 0.0, -0.5])
    assert not defaulted
    sigmas, _, _ = odometry_noise((-0.04, 0.01, 0.09, 0.0, 0.0, 0.0), u, dt, bounds)
    assert math.isnan(sigmas[0])  # a negative variance: dropped as not finite downstream


def _restarted(checks: MeasurementFilter, path: Path) -> MeasurementFilter:
    """A new filter from ``checks``' state written to and read back from a checkpoint."""
    SmootherCheckpoint(
        robot="r",
        local_map=LocalMap("r").state(),
        filter=FilterState.of(checks),
        peer_filter=FilterState.of(MeasurementFilter(["r"])),
        thinning=ThinningState.of(RendezvousThinning(1.0, 4)),
        own_rendezvous=empty_rendezvous(),
        rendezvous_stamps=np.zeros(0),
        last_odometry_ns=0,
        published_ns=0,
        errors=0,
        restarts=0,
        lost_seconds=0.0,
    ).write(path)
    again = MeasurementFilter(["r"])
    SmootherCheckpoint.read(path, "r").filter.restore(again)
    return again


def test_the_poses_of_a_stream_survive_a_checkpoint(tmp_path: Path) -> None:
    """A smoother restarted from its checkpoint goes on differencing poses from the last one
    (and from a held one) as if it had never stopped."""
    stamps, twist, poses = _drive(30)
    readings = [_pose_reading(t, p) for t, p in zip(stamps, poses, strict=True)]
    gap = _pose_reading(stamps[-1] + 100.0, poses[-1])  # held back: a gap or an outlier
    after = _pose_reading(stamps[-1] + 100.1, se2.compose(poses[-1], [0.05, 0.0, 0.01]))
    whole = MeasurementFilter(["r"])
    expected = _feed(whole, [*readings, gap, after])
    first = MeasurementFilter(["r"])
    got = _feed(first, [*readings[:15]])
    again = _restarted(first, tmp_path / "a.npz")
    got += _feed(again, [*readings[15:], gap])
    got += _feed(_restarted(again, tmp_path / "b.npz"), [after])
    assert len(got) == len(expected) == len(readings) + 2
    for (a, pa), (b, pb) in zip(got, expected, strict=True):
        assert a[0] == b[0] and pa == pb
        for x, y in zip(a[1:], b[1:], strict=True):
            np.testing.assert_array_equal(x, y)
