"""The odometry frame (REP-105 ``odom``): where a robot's odometry puts it, sample by sample.

A driver publishes its integrated pose in ``odom`` (and ``odom -> base_link`` on ``/tf``); a
source of body-frame velocities only (the simulator's odometry, older bags) has no such pose,
and its ``odom`` frame is the dead reckoning of its samples from the first one, at the origin.
:class:`OdometryFrame` holds either, for recent samples, and answers the odometry pose at any
stamp between them, moved on from the sample before by the exact increment of the input held
then (docs/METHOD.md section 2): the smoother's ``map -> odom`` transform corrects the pose
at its latest key stamp, and the simulator and player publish ``odom -> base_link`` from it.
"""

from __future__ import annotations

import bisect
import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from csam_ros.core.model import motion, se2

Array = NDArray[np.float64]

# tf2's tolerance on a quaternion's squared norm (|q|^2 - 1): beyond it tf2 refuses a transform
QUATERNION_TOLERANCE = 1e-2


def quaternion_yaw(x: float, y: float, z: float, w: float) -> float:
    """The heading (rotation about z) of the orientation ``(x, y, z, w)``; the quaternion's
    scale cancels, so one a little off unit norm gives the same yaw."""
    return math.atan2(2.0 * (w * z + x * y), w * w + x * x - y * y - z * z)


def quaternion_norm_error(x: float, y: float, z: float, w: float) -> float:
    """``| |q|^2 - 1 |`` (NaN for a non-finite quaternion)."""
    return abs(x * x + y * y + z * z + w * w - 1.0)


class OdometryFrame:
    """The odometry-frame poses of a robot's recent odometry samples (stamps increasing).

    :meth:`add` takes each sample with the pose its message carries, or None: the pose is then
    the dead reckoning of the sample's input from the previous pose (the origin for the first
    one). At most ``keep`` samples are held; :meth:`forget_before` drops older ones sooner.
    """

    def __init__(self, keep: int = 100_000) -> None:
        self.keep = keep
        self._stamps: list[float] = []
        self._inputs: list[Array] = []
        self._poses: list[Array] = []

    def __len__(self) -> int:
        return len(self._stamps)

    @property
    def latest(self) -> tuple[float, Array] | None:
        """The last sample's stamp and pose, or None before any."""
        return (self._stamps[-1], self._poses[-1].copy()) if self._stamps else None

    def add(self, stamp: float, inputs: ArrayLike, pose: ArrayLike | None = None) -> Array:
        """Take one odometry sample (its input held over the interval ending at ``stamp``) with
        its message's pose, or None to dead-reckon it; returns the sample's pose. A stamp at
        or before the last one is ignored (the last pose is returned)."""
        u = np.asarray(inputs, dtype=float).reshape(3)
        if self._stamps and stamp <= self._stamps[-1]:
            return self._poses[-1].copy()
        if pose is not None:
            at = np.asarray(pose, dtype=float).reshape(3).copy()
        elif self._stamps:
            at = _moved_on(self._poses[-1], u, stamp - self._stamps[-1])
        else:
            at = np.zeros(3)
        self._stamps.append(float(stamp))
        self._inputs.append(u)
        self._poses.append(at)
        if len(self._stamps) > self.keep:
            self._drop(len(self._stamps) - self.keep)
        return at.copy()

    def pose_at(self, stamp: float) -> Array | None:
        """The odometry pose at ``stamp``: a sample's own at its stamp, between two samples the
        earlier one's moved on by the later one's input; None outside the samples held."""
        i = bisect.bisect_right(self._stamps, stamp) - 1
        if i < 0:
            return None
        if self._stamps[i] == stamp:
            return self._poses[i].copy()
        if i + 1 >= len(self._stamps):
            return None
        return _moved_on(self._poses[i], self._inputs[i + 1], stamp - self._stamps[i])

    def forget_before(self, stamp: float) -> None:
        """Drop the samples before the last one at or before ``stamp`` (no later query asks
        for a pose before ``stamp``)."""
        i = bisect.bisect_right(self._stamps, stamp) - 1
        if i > 0:
            self._drop(i)

    def _drop(self, count: int) -> None:
        del self._stamps[:count], self._inputs[:count], self._poses[:count]


def _moved_on(pose: Array, inputs: Array, dt: float) -> Array:
    """``pose (+) U(inputs, dt)`` (docs/METHOD.md section 2), one sample in scalar arithmetic."""
    step = motion.increment_one(*inputs.tolist(), dt)
    return np.array(se2.compose_one(tuple(pose.tolist()), step))


def map_to_odom(key_pose: ArrayLike, odometry_pose: ArrayLike) -> Array:
    """REP-105's ``map -> odom``: the correction that takes the odometry pose at a key pose's
    stamp to the key pose (``key (+) (-)odometry``), so ``map -> odom -> base_link`` puts
    the robot at its key pose."""
    return se2.compose(key_pose, se2.inverse(odometry_pose))
