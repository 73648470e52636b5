"""Checks on measurements at the system boundary: bad input is dropped and counted, never fatal.

Nodes (and offline replay, which must give the same result) run every incoming message through
these checks before it reaches a smoother or the merger. A dropped item is counted under a
reason that shows in ``/csam/status``; accepted data is never touched by a later bad message.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

# Reasons, as they appear in /csam/status and summary.json.
NOT_FINITE = "not_finite"
NON_POSITIVE_RANGE = "non_positive_range"
NON_POSITIVE_SIGMA = "non_positive_sigma"
OUTSIDE_FIELD_OF_VIEW = "outside_field_of_view"
UNKNOWN_ROBOT = "unknown_robot"
SELF_OBSERVATION = "self_observation"
STAMP_BACKWARDS = "stamp_backwards"
DUPLICATE = "duplicate"
EMPTY = "empty"
CALLBACK_ERROR = "callback_error"  # a node callback failed unexpectedly on this message

# A noisy bearing may fall a little outside the field of view: allow this many sigmas.
BEARING_MARGIN_SIGMAS = 5.0


@dataclass
class DropCounter:
    """Counts of dropped items by reason."""

    counts: Counter[str] = field(default_factory=Counter)

    def add(self, reason: str, n: int = 1) -> None:
        if n > 0:
            self.counts[reason] += n

    @property
    def total(self) -> int:
        return sum(self.counts.values())

    def as_dict(self) -> dict[str, int]:
        return dict(sorted(self.counts.items()))


@dataclass
class StampGuard:
    """Rejects a message whose stamp goes backwards or repeats on one stream (topic).

    Only accepted messages move the guard, so a rejected message (say, a garbage stamp far in
    the future with invalid content) cannot block the stream.
    """

    last_stamp: float = -np.inf

    def reason(self, stamp: float) -> str | None:
        """The drop reason for a message at ``stamp``, or None if its stamp is acceptable."""
        if not np.isfinite(stamp):
            return NOT_FINITE
        if stamp < self.last_stamp:
            return STAMP_BACKWARDS
        if stamp == self.last_stamp:
            return DUPLICATE
        return None

    def accept(self, stamp: float) -> None:
        self.last_stamp = stamp


def range_bearing_mask(
    ranges: ArrayLike,
    bearings: ArrayLike,
    sigma_range: ArrayLike,
    sigma_bearing: ArrayLike,
    field_of_view: float,
    drops: DropCounter,
) -> NDArray[np.bool_]:
    """Which range-bearing observations are valid; counts the others by their first fault.

    ``field_of_view`` is the sensor's full opening angle in radians (2 pi: no limit).
    """
    r = np.asarray(ranges, dtype=float)
    b = np.asarray(bearings, dtype=float)
    sr = np.asarray(sigma_range, dtype=float)
    sb = np.asarray(sigma_bearing, dtype=float)
    keep = np.ones(r.shape, dtype=bool)
    for reason, bad in (
        (NOT_FINITE, ~(np.isfinite(r) & np.isfinite(b) & np.isfinite(sr) & np.isfinite(sb))),
        (NON_POSITIVE_RANGE, r <= 0),
        (NON_POSITIVE_SIGMA, (sr <= 0) | (sb <= 0)),
        (OUTSIDE_FIELD_OF_VIEW, np.abs(b) > 0.5 * field_of_view + BEARING_MARGIN_SIGMAS * sb),
    ):
        fault = keep & bad
        drops.add(reason, int(fault.sum()))
        keep &= ~fault
    return keep


def odometry_ok(inputs: ArrayLike, sigmas: ArrayLike, drops: DropCounter) -> bool:
    """Whether one odometry sample (input and its sigmas) is usable; counts it if not."""
    u = np.asarray(inputs, dtype=float)
    s = np.asarray(sigmas, dtype=float)
    if not (np.all(np.isfinite(u)) and np.all(np.isfinite(s))):
        drops.add(NOT_FINITE)
        return False
    if np.any(s <= 0):
        drops.add(NON_POSITIVE_SIGMA)
        return False
    return True


class MeasurementFilter:
    """Validates every robot's measurement streams as they arrive, counting drops per robot.

    ``robots`` lists the known robot names (None: any name is accepted as a robot, but a
    rendezvous must still name another robot). Each (robot, stream) pair has its own
    :class:`StampGuard`. Within a message, single bad observations are dropped and the rest kept;
    a message that arrives with no observation is dropped as ``empty``.
    """

    def __init__(self, robots: list[str] | None = None, field_of_view: float = 2 * np.pi) -> None:
        self.robots = None if robots is None else list(robots)
        self.field_of_view = float(field_of_view)
        self.drops: dict[str, DropCounter] = {}
        self._guards: dict[tuple[str, str], StampGuard] = {}

    def counter(self, robot: str) -> DropCounter:
        """The drop counter of ``robot`` (unknown robots are counted under their own name)."""
        return self.drops.setdefault(robot, DropCounter())

    def _stamp_fault(self, robot: str, stream: str, stamp: float) -> str | None:
        if self.robots is not None and robot not in self.robots:
            return UNKNOWN_ROBOT
        return self._guards.setdefault((robot, stream), StampGuard()).reason(stamp)

    def _accept(self, robot: str, stream: str, stamp: float) -> None:
        self._guards[(robot, stream)].accept(stamp)

    def odometry(self, robot: str, stamp: float, inputs: ArrayLike, sigmas: ArrayLike) -> bool:
        """Whether an odometry sample is accepted."""
        fault = self._stamp_fault(robot, "odometry", stamp)
        if fault is not None:
            self.counter(robot).add(fault)
            return False
        if not odometry_ok(inputs, sigmas, self.counter(robot)):
            return False
        self._accept(robot, "odometry", stamp)
        return True

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
        if r.size == 0:
            if self.robots is None or robot in self.robots:
                drops.add(EMPTY)
            else:
                drops.add(UNKNOWN_ROBOT)
            return None
        fault = self._stamp_fault(robot, stream, stamp)
        if fault is not None:
            drops.add(fault)
            return None
        keep = range_bearing_mask(
            r, bearings, sigma_range, sigma_bearing, self.field_of_view, drops
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
        if not keep.any():  # every observation was counted under its own fault
            return None
        self._accept(robot, stream, stamp)
        return keep
