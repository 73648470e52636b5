"""Checks on measurements at the system boundary: bad input is dropped and counted, never fatal.

Nodes (and offline replay, which must give the same result) run every incoming message through
these checks before it reaches a smoother or the merger. A dropped item is counted under a
reason that shows in ``/csam/status``; accepted data is never touched by a later bad message.
The local maps and rendezvous rows at the merger are checked by
:mod:`csam_ros.core.exchange.local_map_checks`, with the reasons and errors here.
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from csam_ros.core.model.config_file import Section, setting
from csam_ros.core.model.log import correlation_minors
from csam_ros.core.smoothing.local_map_config import SMOOTHER

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
# Beyond the physical bounds of InputBounds.
RANGE_OUT_OF_BOUNDS = "range_out_of_bounds"
SIGMA_OUT_OF_BOUNDS = "sigma_out_of_bounds"  # a sigma, or the ratio of a measurement's sigmas
SPEED_OUT_OF_BOUNDS = "speed_out_of_bounds"
TOO_MANY_OBSERVATIONS = "too_many_observations"
STAMP_JUMP = "stamp_jump"  # more than max_stamp_jump away from its stream
STAMP_GAP = "stamp_gap"  # odometry resumed after a gap (the sample that started it)
# The merger's boundary: local maps and rendezvous poses from the smoothers.
MALFORMED_LOCAL_MAP = "malformed_local_map"
MALFORMED_RENDEZVOUS_POSES = "malformed_rendezvous_poses"
ROBOT_MISMATCH = "robot_mismatch"  # a message naming another robot than the one of its topic
NO_POSE_AT_STAMP = "no_pose_at_stamp"  # a rendezvous row inside the map's span but at no pose
FAILED_SOLVE = "failed_solve"  # a merger solve that raised or gave non-finite numbers

# A noisy bearing may fall a little outside the field of view: allow this many sigmas.
BEARING_MARGIN_SIGMAS = 5.0
# The sigma (m, m, rad) of the unknown motion across a gap in a robot's odometry.
GAP_SIGMA = 1000.0


class RefusedMessageError(ValueError):
    """A message refused at the merger's boundary, with the reason its drop is counted under."""

    def __init__(self, detail: str, reason: str) -> None:
        super().__init__(detail)
        self.reason = reason


class LocalMapError(RefusedMessageError):
    """A local map that cannot be turned into a local problem (or a map that has no
    message form)."""

    def __init__(self, detail: str, reason: str = MALFORMED_LOCAL_MAP) -> None:
        super().__init__(detail, reason)


# the rule of most input bounds: positive, and a parameter of the smoother node
_POSITIVE = {"minimum": 0.0, "exclusive": True, "node": SMOOTHER}


@dataclass(frozen=True)
class InputBounds(Section):
    """The ``input:`` section of a parameter file, and the smoother node's parameters of the
    same names: physical bounds on every field of an incoming sensor message.

    A value beyond them is dropped and counted, since the core would either raise on it (a
    covariance that is not positive definite) or be left stuck with it (an odometry factor
    that no later update can whiten), or, for a stamp, build a million poses.
    """

    section = "input"

    max_range: float = setting(
        1000.0,
        "m: largest range of a feature or robot observation",
        **_POSITIVE,
    )
    min_sigma: float = setting(
        1e-6,
        "smallest sigma of any measurement (m, rad, m/s or rad/s)",
        **_POSITIVE,
    )
    max_sigma: float = setting(
        1000.0,
        "largest sigma of any measurement (m, rad, m/s or rad/s)",
        **_POSITIVE,
    )
    max_sigma_ratio: float = setting(
        1e6,
        "largest ratio between the sigmas of one measurement (a range-bearing observation: "
        "range * sigma_bearing over sigma_range; odometry: its largest over its smallest)",
        minimum=1.0,
        node=SMOOTHER,
    )
    max_speed: float = setting(
        30.0,
        "m/s: largest |v| and |v_lat| of odometry",
        **_POSITIVE,
    )
    max_turn_rate: float = setting(30.0, "rad/s: largest |omega| of odometry", **_POSITIVE)
    max_stamp_jump: float = setting(
        60.0,
        "s: largest step of a stream's stamps taken as continuous (beyond: a gap)",
        **_POSITIVE,
    )
    max_observations: int = setting(
        1000,
        "most observations in one features or rendezvous message",
        minimum=1,
        node=SMOOTHER,
    )

    def __post_init__(self) -> None:
        if not self.min_sigma <= self.max_sigma:
            raise ValueError(
                f"input: min_sigma {self.min_sigma:g} exceeds max_sigma {self.max_sigma:g}"
            )


@dataclass
class DropCounter:
    """Counts of dropped items by reason."""

    counts: Counter[str] = field(default_factory=Counter)

    def add(self, reason: str, n: int = 1) -> None:
        if n > 0:
            self.counts[reason] += n

    def reclassify(self, old: str, new: str) -> None:
        """Count one item under ``new`` that was counted under ``old``."""
        if self.counts[old] > 0:
            self.counts[old] -= 1
            if self.counts[old] == 0:
                del self.counts[old]
        self.counts[new] += 1

    @property
    def total(self) -> int:
        return sum(self.counts.values())

    def as_dict(self) -> dict[str, int]:
        return dict(sorted(self.counts.items()))


def _sigma_fault(
    sigmas: NDArray[np.float64], ratios: NDArray[np.float64], bounds: InputBounds
) -> NDArray[np.bool_]:
    """Measurements (rows) whose sigmas leave [min_sigma, max_sigma] or whose ``ratios`` (of
    their covariance's axes) exceed ``max_sigma_ratio``."""
    out = ((sigmas < bounds.min_sigma) | (sigmas > bounds.max_sigma)).any(axis=-1)
    return out | ~(ratios <= bounds.max_sigma_ratio)


def range_bearing_mask(
    ranges: ArrayLike,
    bearings: ArrayLike,
    sigma_range: ArrayLike,
    sigma_bearing: ArrayLike,
    field_of_view: float,
    drops: DropCounter,
    bounds: InputBounds | None = None,
) -> NDArray[np.bool_]:
    """Which range-bearing observations are valid; counts the others by their first fault.

    ``field_of_view`` is the sensor's full opening angle in radians (2 pi: no limit).
    """
    bounds = bounds or InputBounds()
    r = np.asarray(ranges, dtype=float)
    b = np.asarray(bearings, dtype=float)
    sr = np.asarray(sigma_range, dtype=float)
    sb = np.asarray(sigma_bearing, dtype=float)
    keep = np.ones(r.shape, dtype=bool)
    with np.errstate(all="ignore"):
        sigmas = np.stack([sr, sb], axis=-1)
        # the observation's covariance axes: the map floors the tangential one against the
        # radial one (core.sensor), not the other way round
        spread = r * sb / sr
        faults = (
            (NOT_FINITE, ~(np.isfinite(r) & np.isfinite(b) & np.isfinite(sr) & np.isfinite(sb))),
            (NON_POSITIVE_RANGE, r <= 0),
            (NON_POSITIVE_SIGMA, (sr <= 0) | (sb <= 0)),
            (RANGE_OUT_OF_BOUNDS, r > bounds.max_range),
            (SIGMA_OUT_OF_BOUNDS, _sigma_fault(sigmas, spread, bounds)),
            (OUTSIDE_FIELD_OF_VIEW, np.abs(b) > 0.5 * field_of_view + BEARING_MARGIN_SIGMAS * sb),
        )
    for reason, bad in faults:
        fault = keep & bad
        drops.add(reason, int(fault.sum()))
        keep &= ~fault
    return keep


def point_mask(
    points: ArrayLike,
    covariances: ArrayLike,
    field_of_view: float,
    drops: DropCounter,
    bounds: InputBounds | None = None,
) -> NDArray[np.bool_]:
    """Which Cartesian observations ``(K, 2)`` with covariances ``(K, 2, 2)`` are valid; counts
    the others by their first fault. The covariance's axes are its sigmas (bounded as a
    range-bearing observation's; their ratio by ``max_sigma_ratio``); a point at the robot
    centre has no bearing and passes any field of view."""
    bounds = bounds or InputBounds()
    p = np.asarray(points, dtype=float).reshape(-1, 2).tolist()
    c = np.asarray(covariances, dtype=float).reshape(-1, 4).tolist()
    keep = np.ones(len(p), dtype=bool)
    # plain floats: a message holds a few observations, and there is one per stamp
    for k, ((x, y), (cxx, cxy, cyx, cyy)) in enumerate(zip(p, c, strict=True)):
        reason = _point_fault(x, y, cxx, cxy, cyx, cyy, field_of_view, bounds)
        if reason is not None:
            drops.add(reason)
            keep[k] = False
    return keep


def _point_fault(
    x: float,
    y: float,
    cxx: float,
    cxy: float,
    cyx: float,
    cyy: float,
    field_of_view: float,
    bounds: InputBounds,
) -> str | None:
    """Why one Cartesian observation is unusable (its first fault), or None."""
    if not all(math.isfinite(v) for v in (x, y, cxx, cxy, cyx, cyy)):
        return NOT_FINITE
    scale = max(abs(cxx), abs(cxy), abs(cyx), abs(cyy))
    # the covariance's eigenvalues (its axes squared), smallest by det / largest
    mean, radius = 0.5 * (cxx + cyy), math.hypot(0.5 * (cxx - cyy), 0.5 * (cxy + cyx))
    largest = mean + radius
    smallest = (cxx * cyy - cxy * cyx) / largest if largest > 0 else -1.0
    if abs(cxy - cyx) > 1e-9 * scale or not smallest > 0:
        return NON_POSITIVE_SIGMA
    r = math.hypot(x, y)
    if r > bounds.max_range:
        return RANGE_OUT_OF_BOUNDS
    low, high = math.sqrt(smallest), math.sqrt(largest)
    if (
        low < bounds.min_sigma
        or high > bounds.max_sigma
        or not high / low <= bounds.max_sigma_ratio
    ):
        return SIGMA_OUT_OF_BOUNDS
    margin = BEARING_MARGIN_SIGMAS * high / r if r > 0 else math.inf
    if abs(math.atan2(y, x)) > 0.5 * field_of_view + margin:
        return OUTSIDE_FIELD_OF_VIEW
    return None


def odometry_fault(inputs: ArrayLike, sigmas: ArrayLike, bounds: InputBounds) -> str | None:
    """Why one odometry sample (input and its sigmas) is unusable, or None."""
    # plain floats: called once per odometry message (tens of thousands in a replay)
    u = np.asarray(inputs, dtype=float).reshape(3).tolist()
    s = np.asarray(sigmas, dtype=float).reshape(3).tolist()
    if not all(math.isfinite(v) for v in (*u, *s)):
        return NOT_FINITE
    if min(s) <= 0:
        return NON_POSITIVE_SIGMA
    if max(abs(u[0]), abs(u[1])) > bounds.max_speed or abs(u[2]) > bounds.max_turn_rate:
        return SPEED_OUT_OF_BOUNDS
    ratio = max(s) / min(s)  # inf beyond floating point range
    if (
        min(s) < bounds.min_sigma
        or max(s) > bounds.max_sigma
        or not ratio <= bounds.max_sigma_ratio
    ):
        return SIGMA_OUT_OF_BOUNDS
    return None


# stamp, input, sigmas, correlations of the input noise (log.CORRELATION_PAIRS; zeros: none)
def correlation_fault(correlations: ArrayLike) -> str | None:
    """Why an odometry sample's input correlations (3,) are unusable, or None."""
    a, b, d = np.asarray(correlations, dtype=float).reshape(3).tolist()
    if not (math.isfinite(a) and math.isfinite(b) and math.isfinite(d)):
        return NOT_FINITE
    first, det = correlation_minors(a, b, d)
    return None if first > 0 and det > 0 else SIGMA_OUT_OF_BOUNDS


OdometrySample = tuple[float, NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]


@dataclass
class _Stream:
    """One (robot, stream)'s stamps: the last accepted one, and an odometry sample held back
    until the next one shows whether it starts the stream or ends a gap."""

    last: float = -np.inf
    held: OdometrySample | None = None


class MeasurementFilter:
    """Validates every robot's measurement streams as they arrive, counting drops per robot.

    ``robots`` lists the known robot names (None: any name is accepted as a robot, but a
    rendezvous must still name another robot). Every field is checked against ``bounds``.
    Within a message, single bad observations are dropped and the rest kept; a message that
    arrives with no observation is dropped as ``empty``, one with more than
    ``max_observations`` as ``too_many_observations``.

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
        self._streams: dict[tuple[str, str], _Stream] = {}

    def counter(self, robot: str) -> DropCounter:
        """The drop counter of ``robot`` (unknown robots are counted under their own name)."""
        return self.drops.setdefault(robot, DropCounter())

    def clock(self, robot: str) -> float:
        """``robot``'s last accepted odometry stamp, else ``reference()`` (-inf: none)."""
        last = self._stream(robot, "odometry").last
        if np.isfinite(last) or self.reference is None:
            return last
        return self.reference()

    def _stream(self, robot: str, stream: str) -> _Stream:
        return self._streams.setdefault((robot, stream), _Stream())

    def stream_state(self) -> dict[tuple[str, str], tuple[float, OdometrySample | None]]:
        """Each (robot, stream)'s last accepted stamp and held-back odometry sample (copies):
        what :meth:`restore_streams` puts back."""
        return {
            key: (s.last, None if s.held is None else (s.held[0], *(a.copy() for a in s.held[1:])))
            for key, s in self._streams.items()
        }

    def restore_streams(
        self, streams: Mapping[tuple[str, str], tuple[float, OdometrySample | None]]
    ) -> None:
        """Continue from :meth:`stream_state` of an earlier filter."""
        self._streams = {key: _Stream(last, held) for key, (last, held) in streams.items()}

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
        s, jump = self._stream(robot, "odometry"), self.bounds.max_stamp_jump
        held = s.held
        follows_held = held is not None and 0 < stamp - held[0] <= jump
        if not np.isfinite(s.last):  # not started: the first of two close samples
            if follows_held:
                s.last, s.held = sample[0], None
                return [held, sample]  # type: ignore[list-item]
            if held is not None and stamp == held[0]:
                drops.add(DUPLICATE)
                return []
            if held is not None:
                drops.add(STAMP_JUMP)  # the held sample: nothing close followed it
            s.held = sample
            return []
        if stamp <= s.last:
            drops.add(DUPLICATE if stamp == s.last else STAMP_BACKWARDS)
            return []
        if stamp - s.last <= jump:
            s.last, s.held = sample[0], None
            return [sample]
        if follows_held:
            assert held is not None
            drops.reclassify(STAMP_JUMP, STAMP_GAP)
            gap = held[0] - s.last
            unknown = (held[0], np.zeros(3), np.full(3, GAP_SIGMA / gap), np.zeros(3))
            s.last, s.held = sample[0], None
            return [unknown, sample]
        drops.add(STAMP_JUMP)
        s.held = sample
        return []

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
