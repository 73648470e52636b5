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
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from csam_ros.core.model import motion
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
# A whole local map of another session than the one held, its smoother's answer to a resync
# naming another (another publisher's, not a restart), and an update older than the one held.
FOREIGN_SESSION = "foreign_session"
REPLAYED_UPDATE = "replayed_update"
TOO_MANY_ROBOTS = "too_many_robots"  # a robot found when the merger joins max_robots already
UNAUTHENTICATED = "unauthenticated"  # with a team key: a message whose signature did not come

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
