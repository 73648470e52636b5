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

from csam_ros.core.model import motion, se2
from csam_ros.core.model.config_file import Section, setting
from csam_ros.core.model.log import CORRELATION_PAIRS, correlation_minors
from csam_ros.core.model.odometry_frame import QUATERNION_TOLERANCE
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
# Odometry read from its pose (OdometryReading): a pose difference implying a speed beyond the
# bounds (the next difference starts from the new pose), an orientation that is no rotation
# (tf2's tolerance), a pose marked unknown where odometry_source is "pose".
ODOMETRY_JUMP = "odometry_jump"
QUATERNION_NOT_NORMALISED = "quaternion_not_normalised"
POSE_UNKNOWN = "pose_unknown"
# Not a drop: odometry samples that came without sigmas and were given the default ones.
ODOMETRY_DEFAULT_SIGMAS = "odometry_default_sigmas"
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


# where odometry's motion is read (InputBounds.odometry_source)
ODOMETRY_SOURCES = ("auto", "twist", "pose")

# the rule of most input bounds: positive, and a parameter of the smoother node
_POSITIVE = {"minimum": 0.0, "exclusive": True, "node": SMOOTHER}


@dataclass(frozen=True)
class InputBounds(Section):
    """The ``input:`` section of a parameter file, and the smoother node's parameters of the
    same names: physical bounds on every field of an incoming sensor message.

    A value beyond them is dropped and counted, since the core would either raise on it (a
    covariance that is not positive definite) or be left stuck with it (an odometry factor
    that no later update can whiten), or, for a stamp, build a million poses. The ``odometry_``
    settings say how odometry as robot drivers publish it is read (:class:`OdometryReading`).
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
    odometry_source: str = setting(
        "auto",
        "where odometry's motion is read: 'twist' (v, v_lat, omega), 'pose' (differences of "
        "consecutive integrated poses), 'auto' (the twist where it is nonzero, else the pose)",
        choices=ODOMETRY_SOURCES,
        node=SMOOTHER,
    )
    odometry_sigma_per_m: float = setting(
        0.05,
        "m: sigma of odometry's position after 1 m travelled, where its covariance is zero or "
        "unknown (growing with the square root of the distance)",
        **_POSITIVE,
    )
    odometry_sigma_per_rad: float = setting(
        0.05,
        "rad: sigma of odometry's heading after 1 rad turned, where its covariance is zero or "
        "unknown (growing with the square root of the turn)",
        **_POSITIVE,
    )
    odometry_sigma_floor: float = setting(
        0.001,
        "m and rad: least sigma of those defaults' position and heading after 1 s (at rest)",
        **_POSITIVE,
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
Pose = tuple[float, float, float]  # x, y, yaw in the odometry frame


@dataclass(frozen=True)
class OdometryReading:
    """One odometry message (nav_msgs/Odometry) as the core reads it, without ROS types.

    ``twist``: v, v_lat, omega in the body frame; ``twist_covariance``: the variances of v,
    v_lat and omega, then the covariances of their pairs (log.CORRELATION_PAIRS), or None
    when the message marks it unknown (-1 first); ``pose``: x, y and yaw of the integrated
    pose in the odometry frame, or None when the message marks it unknown (-1 first in the
    pose covariance); ``quaternion_error``: ``| |q|^2 - 1 |`` of the pose's orientation.
    """

    stamp: float
    twist: tuple[float, float, float]
    twist_covariance: tuple[float, ...] | None
    pose: Pose | None = None
    quaternion_error: float = 0.0


_PAIR_I, _PAIR_J = np.array(CORRELATION_PAIRS).T


def odometry_noise(
    covariance: tuple[float, ...] | None,
    inputs: ArrayLike,
    dt: float,
    bounds: InputBounds,
) -> tuple[NDArray[np.float64], NDArray[np.float64] | None, bool]:
    """The sigmas ``(3,)`` of one odometry sample's input, the correlations of their pairs
    ``(3,)`` (None: independent), and whether defaults were used.

    ``covariance`` is :attr:`OdometryReading.twist_covariance`. Where it is unknown or all
    zero, and for each variance that is zero, the sigmas are the defaults of ``bounds``
    (:func:`~csam_ros.core.model.motion.default_input_sigmas` of the input held over ``dt``,
    1 s when ``dt`` is unknown). A negative variance gives a NaN sigma."""
    if covariance is None or not any(covariance):
        return _default_sigmas(inputs, dt, bounds), None, True
    v0, v1, v2, *upper = covariance
    variances = [v0, v1, v2]
    sigmas = np.array([math.sqrt(v) if v >= 0 else math.nan for v in variances])
    defaulted = v0 == 0 or v1 == 0 or v2 == 0
    if defaulted:
        default = _default_sigmas(inputs, dt, bounds)
        for k, v in enumerate(variances):
            if v == 0:
                sigmas[k] = default[k]
                variances[k] = float(default[k]) ** 2
    if not any(upper):
        return sigmas, None, defaulted
    var = np.array(variances)
    with np.errstate(invalid="ignore", divide="ignore"):
        return sigmas, np.array(upper) / np.sqrt(var[_PAIR_I] * var[_PAIR_J]), defaulted


def _default_sigmas(inputs: ArrayLike, dt: float, bounds: InputBounds) -> NDArray[np.float64]:
    T = dt if math.isfinite(dt) and dt > 0 else 1.0
    return motion.default_input_sigmas(
        np.asarray(inputs, dtype=float).reshape(1, 3),
        [T],
        bounds.odometry_sigma_per_m,
        bounds.odometry_sigma_per_rad,
        bounds.odometry_sigma_floor,
    )[0]


def pose_fault(reading: OdometryReading) -> str | None:
    """Why an odometry message's pose is unusable, or None (also when it has none)."""
    if reading.pose is None:
        return None
    if not all(math.isfinite(v) for v in reading.pose):
        return NOT_FINITE
    if not reading.quaternion_error <= QUATERNION_TOLERANCE:
        return QUATERNION_NOT_NORMALISED
    return None


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
