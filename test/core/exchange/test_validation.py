"""Input checks at the boundary: physical bounds on every field, and the stamp rule of a stream
(an outlier never blocks a stream nor adds poses; a real gap is accepted after it)."""

from __future__ import annotations

import numpy as np
import pytest

from csam_ros.core.exchange.measurement_filter import MeasurementFilter
from csam_ros.core.exchange.validation import (
    DUPLICATE,
    GAP_SIGMA,
    RANGE_OUT_OF_BOUNDS,
    SIGMA_OUT_OF_BOUNDS,
    SPEED_OUT_OF_BOUNDS,
    STAMP_BACKWARDS,
    STAMP_GAP,
    STAMP_JUMP,
    TOO_MANY_OBSERVATIONS,
    InputBounds,
)
from csam_ros.core.smoothing.local_map import LocalMap
from csam_ros.core.smoothing.local_map_config import LocalMapOptions

U, S = np.array([0.5, 0.0, 0.1]), np.array([0.02, 0.01, 0.01])


def _odometry(checks: MeasurementFilter, stamps, inputs=U, robot: str = "r") -> list[float]:
    """Stamps of the samples accepted for odometry messages at ``stamps``."""
    return [t for stamp in stamps for t, *_ in checks.odometry(robot, stamp, inputs, S)]


def _scan(checks: MeasurementFilter, stamp: float, r=3.0, sr=0.01, sb=0.01):
    return checks.features("r", stamp, [r], [0.1], [sr], [sb])


@pytest.mark.parametrize(
    ("r", "sr", "sb", "reason"),
    [
        (1e8, 0.01, 0.01, RANGE_OUT_OF_BOUNDS),  # issue 15 case 2: each raised in add_features
        (1e300, 0.01, 0.01, RANGE_OUT_OF_BOUNDS),
        (3.0, 1e-10, 0.01, SIGMA_OUT_OF_BOUNDS),
        (3.0, 1e-300, 1e-300, SIGMA_OUT_OF_BOUNDS),
    ],
)
def test_feature_beyond_the_bounds_is_dropped_and_would_break_the_map(r, sr, sb, reason) -> None:
    checks = MeasurementFilter(["r"])
    assert _scan(checks, 1.0, r, sr, sb) is None
    assert checks.counter("r").as_dict() == {reason: 1}
    with pytest.raises(ValueError), np.errstate(over="ignore"):  # the map itself refuses it
        LocalMap("r").add_features([1.0], [1], [r], [0.1], [sr], [sb])


def test_odometry_beyond_the_speed_or_sigma_bounds_is_dropped() -> None:
    checks = MeasurementFilter(["r"])
    for u, s in (([1e300, 0, 0], S), ([0, -31.0, 0], S), ([0, 0, 1e3], S)):
        assert checks.odometry("r", 1.0, u, s) == []
    for s in ([1e-300, 0.01, 0.01], [2e3, 1, 1], [1e-5, 100.0, 1.0]):
        assert checks.odometry("r", 1.0, U, s) == []
    assert checks.counter("r").as_dict() == {SPEED_OUT_OF_BOUNDS: 3, SIGMA_OUT_OF_BOUNDS: 3}


def test_message_with_too_many_observations_is_dropped_whole() -> None:
    checks = MeasurementFilter(["r"], bounds=InputBounds(max_observations=3))
    assert checks.features("r", 1.0, *np.full((4, 4), 0.5)) is None
    assert checks.features("r", 1.0, *np.full((4, 3), 0.5)) is not None
    assert checks.counter("r").as_dict() == {TOO_MANY_OBSERVATIONS: 1}


def test_odometry_outlier_stamp_is_dropped_and_the_stream_goes_on() -> None:
    """Issue 15 case 3: one sample stamped 1e6 s blocked the stream for good."""
    checks = MeasurementFilter(["r"])
    assert _odometry(checks, [0.0, 0.1, 0.2]) == [0.0, 0.1, 0.2]
    assert _odometry(checks, [1e6]) == []
    assert _odometry(checks, [0.3, 0.4]) == [0.3, 0.4]
    assert _odometry(checks, [-1e6, 0.5]) == [0.5]  # a backward outlier blocks nothing either
    assert checks.counter("r").as_dict() == {STAMP_JUMP: 1, STAMP_BACKWARDS: 1}


def test_odometry_outlier_as_the_first_sample_cannot_become_the_start() -> None:
    checks = MeasurementFilter(["r"])
    assert _odometry(checks, [1e6, 0.0, 0.0, 0.1, 0.2]) == [0.0, 0.1, 0.2]
    assert checks.counter("r").as_dict() == {STAMP_JUMP: 1, DUPLICATE: 1}


def test_real_gap_in_odometry_is_accepted_after_it_as_one_weak_factor() -> None:
    checks = MeasurementFilter(["r"])
    good = _odometry(checks, np.arange(0.0, 5.05, 0.1))
    samples = [checks.odometry("r", t, U, S) for t in (1e6, 1e6 + 0.1, 1e6 + 0.2)]
    assert samples[0] == [] and [len(s) for s in samples[1:]] == [2, 1]
    (t_gap, u_gap, s_gap, rho_gap), (t_next, *_) = samples[1]
    assert (t_gap, t_next) == (1e6, 1e6 + 0.1)
    np.testing.assert_array_equal(u_gap, 0.0)  # unknown motion: zero input, sigma GAP_SIGMA
    np.testing.assert_array_equal(rho_gap, 0.0)  # and independent inputs
    np.testing.assert_allclose(s_gap * (1e6 - good[-1]), GAP_SIGMA)
    assert checks.counter("r").as_dict() == {STAMP_GAP: 1}
    # the local map bridges it with one factor: no million regular key poses, and it solves
    local = LocalMap("r", LocalMapOptions(key_interval=1.0))
    local.add_odometry(good, np.tile(U, (len(good), 1)), np.tile(S, (len(good), 1)))
    local.add_features([2.0], [7], [3.0], [0.2], [0.01], [0.01])
    local.update(converge=True)
    before = local.poses.copy()
    for batch in samples[1:]:
        stamps, inputs, sigmas, _ = zip(*batch, strict=True)
        local.add_odometry(stamps, np.stack(inputs), np.stack(sigmas))
    local.add_features([1e6 + 0.2], [7], [3.0], [0.2], [0.01], [0.01])
    local.update(converge=True)
    assert len(local.stamps) == len(before) + 2  # at 1e6 and at the scan
    np.testing.assert_allclose(local.poses[: len(before)], before, atol=1e-6)


def test_features_far_from_the_robots_clock_are_dropped_but_never_block() -> None:
    checks = MeasurementFilter(["r"])
    assert _scan(checks, 1e6) is not None  # no clock yet: it may even be right
    _odometry(checks, [0.0, 0.1])
    assert _scan(checks, 0.05) is not None  # the early outlier does not block the stream
    assert _scan(checks, 0.05) is None  # but a repeat is still a duplicate
    assert _scan(checks, 1e6 + 1) is None and _scan(checks, -500.0) is None
    assert _scan(checks, 0.1) is not None
    assert checks.counter("r").as_dict() == {DUPLICATE: 1, STAMP_JUMP: 2}


def test_peer_streams_follow_the_reference_clock() -> None:
    own = MeasurementFilter(["r", "p"])
    peers = MeasurementFilter(["r", "p"], reference=lambda: own.clock("r"))
    _odometry(own, [10.0, 10.1])
    assert peers.rendezvous("p", 1e6, ["r"], [2.0], [0.1], [0.01], [0.01]) is None
    assert peers.rendezvous("p", 10.2, ["r"], [2.0], [0.1], [0.01], [0.01]) is not None
    assert peers.counter("p").as_dict() == {STAMP_JUMP: 1}


def test_bounds_from_a_file_section_are_checked() -> None:
    assert InputBounds.from_dict({"max_range": 20, "max_observations": 50}).max_range == 20.0
    for section, words in (
        ({"max_rang": 1.0}, "unknown key"),
        ({"max_range": 0.0}, "greater than 0"),
        ({"max_observations": 2.5}, "whole number"),
        ({"min_sigma": 2.0, "max_sigma": 1.0}, "exceeds max_sigma"),
    ):
        with pytest.raises(ValueError, match=words):
            InputBounds.from_dict(section, "input")
