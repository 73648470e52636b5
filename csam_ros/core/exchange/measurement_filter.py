"""The measurement filter of every node and of offline replay: each robot's streams
(odometry, features, points, rendezvous) checked as they arrive, with the field checks,
bounds and reasons of :mod:`csam_ros.core.exchange.validation`."""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from csam_ros.core.exchange.validation import (
    DUPLICATE,
    EMPTY,
    GAP_SIGMA,
    NOT_FINITE,
    ODOMETRY_JUMP,
    POSE_UNKNOWN,
    SELF_OBSERVATION,
    STAMP_BACKWARDS,
    STAMP_GAP,
    STAMP_JUMP,
    TOO_MANY_OBSERVATIONS,
    UNKNOWN_ROBOT,
    DropCounter,
    InputBounds,
    OdometryReading,
    OdometrySample,
    Pose,
    correlation_fault,
    odometry_fault,
    odometry_noise,
    point_mask,
    pose_fault,
    range_bearing_mask,
)
from csam_ros.core.model import motion, se2


@dataclass
class _Stream:
    """One (robot, stream)'s stamps: the last accepted one, and an odometry sample held back
    until the next one shows whether it starts the stream or ends a gap; for odometry, the
    poses (odometry frame) its messages carried at those two samples, which the next pose
    difference starts from."""

    last: float = -np.inf
    held: OdometrySample | None = None
    pose: Pose | None = None
    held_pose: Pose | None = None


# the stream-state entries of an odometry stream's poses (MeasurementFilter.stream_state)
_POSE, _HELD_POSE = "/pose", "/held_pose"


class MeasurementFilter:
    """Validates every robot's measurement streams as they arrive, counting drops per robot.

    ``robots`` lists the known robot names (None: any name is accepted as a robot, but a
    rendezvous must still name another robot). Every field is checked against ``bounds``.
    Within a message, single bad observations are dropped and the rest kept; a message that
    arrives with no observation is dropped as ``empty``, one with more than
    ``max_observations`` as ``too_many_observations``. Odometry comes as values
    (:meth:`odometry`) or as a message as drivers fill it (:meth:`odometry_reading`: the
    twist or pose differences, default sigmas, pose jumps).

    Stamps (``J`` = ``bounds.max_stamp_jump``). A robot's odometry is its clock:

    - Odometry starts with two samples less than ``J`` apart: the first is held back until
      the second confirms it (a lone first sample far off is replaced, counted
      ``stamp_jump``), so an outlier cannot become the start.
    - A sample at or before the last accepted one is dropped (``stamp_backwards``,
      ``duplicate``); it never moves the stream, so no backward outlier blocks it.
    - A sample more than ``J`` after the last accepted one is dropped (``stamp_jump``) and
      held. If the next sample follows it within ``J``, the stream has resumed after a real
      gap: that count becomes ``stamp_gap``, and both are accepted, the held one as a
      sample of unknown motion (zero input, sigmas ``GAP_SIGMA / gap``: the gap's motion
      has a sigma of ``GAP_SIGMA`` m, m, rad whatever its length), so the local map bridges
      the gap with one weak factor and no regular key poses. Any other next sample drops
      the held one for good, so a single outlier creates no pose and blocks nothing.
    - Features and rendezvous more than ``J`` away from the robot's clock (the observer's
      last accepted odometry stamp, else ``reference()``, e.g. the smoother's own robot for
      its peers) are dropped as ``stamp_jump``; each stream also drops a stamp at or before
      its last accepted one, unless that one lies more than ``J`` from the clock (or, with
      no clock yet, from the new stamp): an outlier accepted before the clock existed must
      not block the stream.
    """

    def __init__(
        self,
        robots: list[str] | None = None,
        field_of_view: float = 2 * np.pi,
        bounds: InputBounds | None = None,
        reference: Callable[[], float] | None = None,
    ) -> None:
        self.robots = None if robots is None else list(robots)
        self.field_of_view = float(field_of_view)
        self.bounds = bounds or InputBounds()
        self.reference = reference
        self.drops: dict[str, DropCounter] = {}
        # odometry samples of each robot given default sigmas (ODOMETRY_DEFAULT_SIGMAS; kept)
        self.defaulted = DropCounter()
        self._streams: dict[tuple[str, str], _Stream] = {}

    def counter(self, robot: str) -> DropCounter:
        """The drop counter of ``robot`` (unknown robots are counted under their own name)."""
        counter = self.drops.get(robot)
        if counter is None:  # not setdefault: one new counter per call (per message) otherwise
            counter = self.drops[robot] = DropCounter()
        return counter

    def clock(self, robot: str) -> float:
        """``robot``'s last accepted odometry stamp, else ``reference()`` (-inf: none)."""
        last = self._stream(robot, "odometry").last
        if np.isfinite(last) or self.reference is None:
            return last
        return self.reference()

    def _stream(self, robot: str, stream: str) -> _Stream:
        held = self._streams.get((robot, stream))
        if held is None:
            held = self._streams[(robot, stream)] = _Stream()
        return held

    def stream_state(self) -> dict[tuple[str, str], tuple[float, OdometrySample | None]]:
        """Each (robot, stream)'s last accepted stamp and held-back odometry sample (copies):
        what :meth:`restore_streams` puts back. The poses an odometry stream's messages
        carried go as entries of their own (``odometry/pose``, ``odometry/held_pose``), each
        a held sample whose input is the pose."""
        state: dict[tuple[str, str], tuple[float, OdometrySample | None]] = {}
        for (robot, stream), s in self._streams.items():
            held = s.held
            state[(robot, stream)] = (
                s.last,
                None if held is None else (held[0], *(a.copy() for a in held[1:])),
            )
            stamp = held[0] if held is not None else s.last
            for suffix, pose, at in ((_POSE, s.pose, s.last), (_HELD_POSE, s.held_pose, stamp)):
                if pose is not None:
                    zero = np.zeros(3)
                    state[(robot, stream + suffix)] = (at, (at, np.array(pose), zero, zero.copy()))
        return state

    def restore_streams(
        self, streams: Mapping[tuple[str, str], tuple[float, OdometrySample | None]]
    ) -> None:
        """Continue from :meth:`stream_state` of an earlier filter."""
        poses = {}
        self._streams = {}
        for (robot, stream), (last, held) in streams.items():
            if stream.endswith((_POSE, _HELD_POSE)) and held is not None:
                poses[(robot, stream)] = tuple(float(v) for v in held[1])
            else:
                self._streams[(robot, stream)] = _Stream(last, held)
        for (robot, stream), pose in poses.items():
            base, _, suffix = stream.rpartition("/")
            target = self._stream(robot, base)
            if "/" + suffix == _POSE:
                target.pose = pose  # type: ignore[assignment]
            else:
                target.held_pose = pose  # type: ignore[assignment]

    def _known(self, robot: str) -> bool:
        return self.robots is None or robot in self.robots

    def odometry(
        self,
        robot: str,
        stamp: float,
        inputs: ArrayLike,
        sigmas: ArrayLike,
        correlations: ArrayLike | None = None,
    ) -> list[OdometrySample]:
        """The samples to add for one odometry message, in stamp order: none (dropped or held
        back), the sample, or after a gap the held sample of unknown motion and this one.
        ``correlations`` of the input noise travel with the sample (zeros when None)."""
        drops = self.counter(robot)
        if not self._known(robot):
            drops.add(UNKNOWN_ROBOT)
            return []
        rho = np.zeros(3) if correlations is None else np.asarray(correlations, dtype=float)
        fault = (
            NOT_FINITE
            if not np.isfinite(stamp)
            else odometry_fault(inputs, sigmas, self.bounds)
            or (None if correlations is None else correlation_fault(rho))
        )
        if fault is not None:
            drops.add(fault)
            return []
        sample = (
            float(stamp),
            np.asarray(inputs, dtype=float),
            np.asarray(sigmas, dtype=float),
            rho.reshape(3),
        )
        return self._admit(robot, sample)[0]

    def _admit(self, robot: str, sample: OdometrySample) -> tuple[list[OdometrySample], bool]:
        """The stamp rules (class docstring) for a valid odometry sample: the samples to add,
        and whether ``sample`` is now held back."""
        drops = self.counter(robot)
        stamp = sample[0]
        s, jump = self._stream(robot, "odometry"), self.bounds.max_stamp_jump
        held = s.held
        follows_held = held is not None and 0 < stamp - held[0] <= jump
        if not np.isfinite(s.last):  # not started: the first of two close samples
            if follows_held:
                s.last, s.held = sample[0], None
                return [held, sample], False  # type: ignore[list-item]
            if held is not None and stamp == held[0]:
                drops.add(DUPLICATE)
                return [], False
            if held is not None:
                drops.add(STAMP_JUMP)  # the held sample: nothing close followed it
            s.held = sample
            return [], True
        if stamp <= s.last:
            drops.add(DUPLICATE if stamp == s.last else STAMP_BACKWARDS)
            return [], False
        if stamp - s.last <= jump:
            s.last, s.held = sample[0], None
            return [sample], False
        if follows_held:
            assert held is not None
            drops.reclassify(STAMP_JUMP, STAMP_GAP)
            gap = held[0] - s.last
            unknown = (held[0], np.zeros(3), np.full(3, GAP_SIGMA / gap), np.zeros(3))
            s.last, s.held = sample[0], None
            return [unknown, sample], False
        drops.add(STAMP_JUMP)
        s.held = sample
        return [], True

    def _before(self, s: _Stream, stamp: float) -> tuple[bool, float, Pose | None] | None:
        """The sample an odometry sample at ``stamp`` would follow under the stamp rules (as
        :meth:`_admit` will decide): (whether it is the held one, its stamp, its message's
        pose), or None when it would start the stream, be held back or be dropped."""
        jump, held = self.bounds.max_stamp_jump, s.held
        follows_held = held is not None and 0 < stamp - held[0] <= jump
        if np.isfinite(s.last) and s.last < stamp and stamp - s.last <= jump:
            return False, s.last, s.pose
        if follows_held and (not np.isfinite(s.last) or stamp > s.last):
            assert held is not None
            return True, held[0], s.held_pose
        return None

    def odometry_reading(
        self, robot: str, reading: OdometryReading
    ) -> list[tuple[OdometrySample, Pose | None]]:
        """The samples to add for one odometry message as drivers publish it (as
        :meth:`odometry`), each with the pose (odometry frame) its message carried, or None.

        The motion comes from the twist, or from the difference between this message's pose
        and the one of the sample it follows, as the constant input over the interval
        (``bounds.odometry_source``; ``auto``: the pose where the twist is all zero and both
        poses are known). A pose difference implying a speed beyond ``max_speed`` or
        ``max_turn_rate`` is a jump of the pose: dropped (``odometry_jump``), and the next
        difference starts from this pose, so the jump never enters the map. Where the
        covariance is zero or unknown the sigmas are ``bounds``' defaults
        (:func:`odometry_noise`), counted per robot in :attr:`defaulted`.
        """
        drops = self.counter(robot)
        if not self._known(robot):
            drops.add(UNKNOWN_ROBOT)
            return []
        stamp, pose, source = reading.stamp, reading.pose, self.bounds.odometry_source
        fault = (
            NOT_FINITE
            if not math.isfinite(stamp)
            else POSE_UNKNOWN
            if source == "pose" and pose is None
            else pose_fault(reading)
        )
        if fault is not None:
            drops.add(fault)
            return []
        s = self._stream(robot, "odometry")
        before = self._before(s, stamp)
        dt = stamp - before[1] if before is not None else math.nan
        known = before is not None and before[2] is not None
        from_pose = source == "pose" or (
            source == "auto" and pose is not None and known and not any(reading.twist)
        )
        inputs: NDArray[np.float64]
        if not from_pose:
            inputs = np.array(reading.twist, dtype=float)
        elif before is None:  # it starts the stream (its input is not used), or is dropped
            inputs = np.zeros(3)
        else:
            assert pose is not None
            inputs = np.full(3, np.inf)
            if before[2] is not None:  # else nothing to difference against: a jump
                increment = se2.between(np.array(before[2]), np.array(pose))
                inputs = motion.inputs_from_increments(increment[None], [dt])[0]
            b = self.bounds
            if not (
                max(abs(inputs[0]), abs(inputs[1])) <= b.max_speed
                and abs(inputs[2]) <= b.max_turn_rate
            ):
                drops.add(ODOMETRY_JUMP)
                if before[0]:
                    s.held_pose = pose
                else:
                    s.pose = pose
                return []
        sigmas, rho, defaulted = odometry_noise(reading.twist_covariance, inputs, dt, self.bounds)
        fault = odometry_fault(inputs, sigmas, self.bounds) or (
            None if rho is None else correlation_fault(rho)
        )
        if fault is not None:
            drops.add(fault)
            return []
        held_pose = s.held_pose
        sample = (float(stamp), inputs, sigmas, np.zeros(3) if rho is None else rho)
        samples, now_held = self._admit(robot, sample)
        if samples:
            s.pose, s.held_pose = pose, None
        elif now_held:
            s.held_pose = pose
        if defaulted and (samples or now_held):
            self.defaulted.add(robot)
        if not samples:
            return []
        poses = [held_pose, pose] if len(samples) == 2 else [pose]
        return list(zip(samples, poses, strict=True))

    def features(
        self,
        robot: str,
        stamp: float,
        ranges: ArrayLike,
        bearings: ArrayLike,
        sigma_range: ArrayLike,
        sigma_bearing: ArrayLike,
    ) -> NDArray[np.bool_] | None:
        """Mask of the accepted observations of one feature scan, or None if it is dropped."""
        return self._observations(
            robot, "features", stamp, ranges, bearings, sigma_range, sigma_bearing, None
        )

    def points(
        self, robot: str, stamp: float, points: ArrayLike, covariances: ArrayLike
    ) -> NDArray[np.bool_] | None:
        """Mask of the accepted Cartesian feature observations at one stamp (their own
        stream), or None if the message is dropped."""
        drops = self.counter(robot)
        count = len(np.asarray(points, dtype=float).reshape(-1, 2))
        fault = self._message_fault(robot, "points", stamp, count)
        if fault is not None:
            drops.add(fault)
            return None
        keep = point_mask(points, covariances, self.field_of_view, drops, self.bounds)
        return self._accepted(robot, "points", stamp, keep)

    def rendezvous(
        self,
        robot: str,
        stamp: float,
        observed: list[str],
        ranges: ArrayLike,
        bearings: ArrayLike,
        sigma_range: ArrayLike,
        sigma_bearing: ArrayLike,
    ) -> NDArray[np.bool_] | None:
        """Mask of the accepted observations of other robots, or None if the message is dropped."""
        return self._observations(
            robot, "rendezvous", stamp, ranges, bearings, sigma_range, sigma_bearing, observed
        )

    def _message_fault(self, robot: str, stream: str, stamp: float, count: int) -> str | None:
        """Why a features, points or rendezvous message of ``count`` observations at ``stamp``
        is dropped as a whole, or None."""
        if count == 0 or count > self.bounds.max_observations:
            if not self._known(robot):
                return UNKNOWN_ROBOT
            return EMPTY if count == 0 else TOO_MANY_OBSERVATIONS
        if not self._known(robot):
            return UNKNOWN_ROBOT
        if not np.isfinite(stamp):
            return NOT_FINITE
        jump = self.bounds.max_stamp_jump
        clock = self.clock(robot)
        if np.isfinite(clock) and abs(stamp - clock) > jump:
            return STAMP_JUMP
        last = self._stream(robot, stream).last
        anchor = clock if np.isfinite(clock) else stamp
        if np.isfinite(last) and abs(last - anchor) <= jump and stamp <= last:
            return DUPLICATE if stamp == last else STAMP_BACKWARDS
        return None

    def _observations(
        self,
        robot: str,
        stream: str,
        stamp: float,
        ranges: ArrayLike,
        bearings: ArrayLike,
        sigma_range: ArrayLike,
        sigma_bearing: ArrayLike,
        observed: list[str] | None,
    ) -> NDArray[np.bool_] | None:
        drops = self.counter(robot)
        r = np.asarray(ranges, dtype=float)
        fault = self._message_fault(robot, stream, stamp, r.size)
        if fault is not None:
            drops.add(fault)
            return None
        keep = range_bearing_mask(
            r, bearings, sigma_range, sigma_bearing, self.field_of_view, drops, self.bounds
        )
        if observed is not None:
            names = np.asarray(observed, dtype=object)
            own = keep & (names == robot)
            drops.add(SELF_OBSERVATION, int(own.sum()))
            keep &= ~own
            if self.robots is not None:
                unknown = keep & ~np.isin(names, self.robots)
                drops.add(UNKNOWN_ROBOT, int(unknown.sum()))
                keep &= ~unknown
        return self._accepted(robot, stream, stamp, keep)

    def _accepted(
        self, robot: str, stream: str, stamp: float, keep: NDArray[np.bool_]
    ) -> NDArray[np.bool_] | None:
        """``keep``, the stamp now the stream's last, or None (the message dropped) when no
        observation is left: each was counted under its own fault."""
        if not keep.any():
            return None
        self._stream(robot, stream).last = float(stamp)
        return keep
