"""The odometry frame: message poses or dead reckoning, poses between samples, map -> odom."""

import numpy as np
import pytest

from csam_ros.core.model import motion, se2
from csam_ros.core.model.odometry_frame import (
    OdometryFrame,
    map_to_odom,
    quaternion_norm_error,
    quaternion_yaw,
)


def _odometry(rng: np.random.Generator, n: int = 50) -> tuple[np.ndarray, np.ndarray]:
    stamps = 5.0 + np.cumsum(rng.uniform(0.05, 0.2, n))
    inputs = np.c_[rng.uniform(0, 1, n), rng.uniform(-0.1, 0.1, n), rng.uniform(-1, 1, n)]
    return stamps, inputs


@pytest.mark.parametrize("yaw", [0.0, 0.3, -2.0, np.pi, -np.pi + 1e-9])
def test_quaternion_yaw_of_a_planar_rotation(yaw: float) -> None:
    z, w = np.sin(yaw / 2), np.cos(yaw / 2)
    assert abs(se2.wrap_angle(quaternion_yaw(0.0, 0.0, z, w) - yaw)) < 1e-12
    assert abs(se2.wrap_angle(quaternion_yaw(0.0, 0.0, 1.001 * z, 1.001 * w) - yaw)) < 1e-12
    assert quaternion_norm_error(0.0, 0.0, z, w) < 1e-15
    assert quaternion_norm_error(0.0, 0.0, 0.0, 0.0) == 1.0


def test_dead_reckoning_is_the_odometry_poses_and_between_samples_the_motion_model() -> None:
    stamps, inputs = _odometry(np.random.default_rng(3))
    frame = OdometryFrame()
    for t, u in zip(stamps, inputs, strict=True):
        frame.add(t, u)
    expected = motion.odometry_poses(stamps, inputs)
    for t, pose in zip(stamps, expected, strict=True):
        np.testing.assert_allclose(frame.pose_at(t), pose, atol=1e-12)
    query = 0.5 * (stamps[:-1] + stamps[1:])
    at = [frame.pose_at(t) for t in query]
    np.testing.assert_allclose(
        at, motion.odometry_poses_at(stamps, inputs, expected, query), atol=1e-12
    )
    assert frame.pose_at(stamps[0] - 1.0) is None and frame.pose_at(stamps[-1] + 1.0) is None


def test_message_poses_are_taken_as_they_are_and_dead_reckoning_goes_on_from_them() -> None:
    frame = OdometryFrame()
    frame.add(1.0, np.zeros(3), (10.0, 5.0, 1.0))
    frame.add(2.0, [1.0, 0.0, 0.0], (10.0, 7.0, 1.5))  # a driver's own integration
    reckoned = frame.add(3.0, [1.0, 0.0, 0.0])  # no pose in this message
    np.testing.assert_allclose(reckoned, [10.0 + np.cos(1.5), 7.0 + np.sin(1.5), 1.5], atol=1e-12)
    assert frame.add(2.5, [9.0, 0.0, 0.0]) is not None and len(frame) == 3  # out of order
    frame.forget_before(2.5)
    assert len(frame) == 2 and frame.pose_at(1.5) is None
    np.testing.assert_allclose(frame.pose_at(2.0), [10.0, 7.0, 1.5])
    bounded = OdometryFrame(keep=4)
    for k in range(10):
        bounded.add(float(k), np.zeros(3))
    assert len(bounded) == 4 and bounded.latest is not None and bounded.latest[0] == 9.0


def test_map_to_odom_puts_the_robot_at_its_key_pose() -> None:
    rng = np.random.default_rng(5)
    key, odometry = rng.uniform(-5, 5, 3), rng.uniform(-5, 5, 3)
    correction = map_to_odom(key, odometry)
    np.testing.assert_allclose(se2.compose(correction, odometry), se2.wrap_angle(key), atol=1e-12)
