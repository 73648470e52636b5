"""Field checks of what a checkpoint or state file holds, against what each field means, before
any of it is used (:mod:`csam_ros.core.exchange.checkpoint` reads with them).

A file whose bytes are whole (its CRCs match) may still hold numbers no run could have
written: a stamp of 10^30 ns that no ROS time holds, stamps out of order, a sigma of zero or
NaN, a scalar where an array belongs. Each check raises :class:`StateFieldError` naming the field
and the first bad value; the reader adds the file's name (a ``CheckpointError``).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
from numpy.typing import NDArray

from csam_ros.core.exchange.local_map_checks import MAX_COORDINATE, MAX_SQRT_INFORMATION
from csam_ros.core.model.log import (
    FeatureLog,
    FeaturePointLog,
    OdometryLog,
    RendezvousLog,
    correlations_valid,
)
from csam_ros.core.sam.factors import singular_sqrt_information
from csam_ros.core.smoothing.local_map_state import LocalMapState, check_state

# A stamp in seconds is at most what a ROS time holds (its ``sec`` is an int32), one in
# nanoseconds (a message stamp: -1 for none yet) as well; a count is exact in a JSON number.
MAX_STAMP_S = float(2**31 - 1)
MAX_STAMP_NS = (2**31 - 1) * 10**9 + 999_999_999
MAX_COUNT = 2**53


class StateFieldError(ValueError):
    """A field of a state that no run could have written; the message names the field."""


def check_integer(name: str, value: Any, low: int, high: int) -> int:
    """``value`` as an int within ``[low, high]`` (a JSON integer, not a bool)."""
    if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
        raise StateFieldError(f"{name}: {value!r:.40} is not an integer in [{low}, {high}]")
    return value


def check_number(name: str, value: Any, low: float, high: float) -> float:
    """``value`` as a finite float within ``[low, high]``."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise StateFieldError(f"{name}: {value!r:.40} is not a number")
    if not low <= float(value) <= high:  # NaN fails too
        raise StateFieldError(f"{name}: {value!r:.40} is not a number in [{low:g}, {high:g}]")
    return float(value)


def check_counts(name: str, node: Any) -> dict[str, int]:
    """A mapping of names to counts (integers in ``[0, MAX_COUNT]``)."""
    if not isinstance(node, Mapping):
        raise StateFieldError(f"{name}: expected counts by name, got {type(node).__name__}")
    return {str(k): check_integer(f"{name}/{k}", v, 0, MAX_COUNT) for k, v in node.items()}


def _first(mask: NDArray[np.bool_]) -> int | None:
    bad = np.flatnonzero(~mask.reshape(len(mask), -1).all(axis=1)) if len(mask) else []
    return int(bad[0]) if len(bad) else None


def check_values(
    name: str, values: NDArray[Any], bound: float = np.inf, positive: bool = False
) -> None:
    """Every value finite, of magnitude at most ``bound`` (and above 0 when ``positive``)."""
    v = np.asarray(values, dtype=float)
    ok = np.isfinite(v) & (np.abs(v) <= bound)
    if positive:
        ok &= v > 0
    row = _first(ok)
    if row is not None:
        what = "positive " if positive else ""
        raise StateFieldError(
            f"{name}: row {row} ({v[row].tolist()!r:.60}) is not {what}finite numbers "
            f"within {bound:g}"
        )


def check_stamps(name: str, stamps: NDArray[Any], order: str = "") -> None:
    """Finite stamps in seconds within a ROS time's range; ``order``: "increasing" (strictly)
    or "sorted" (non-decreasing)."""
    check_values(name, stamps, MAX_STAMP_S)
    steps = np.diff(np.asarray(stamps, dtype=float))
    bad = np.flatnonzero(steps <= 0 if order == "increasing" else steps < 0) if order else []
    if len(bad):
        i = int(bad[0]) + 1
        raise StateFieldError(
            f"{name}: stamp {i} ({stamps[i]!r}) does not follow stamp {i - 1} "
            f"({stamps[i - 1]!r}); stamps must be {order}"
        )


def _check_sqrt_information(name: str, rows: NDArray[Any]) -> None:
    if len(rows) == 0:
        return
    check_values(name, rows.reshape(len(rows), -1), MAX_SQRT_INFORMATION)
    singular = singular_sqrt_information(rows)
    if len(singular):
        raise StateFieldError(f"{name}: row {int(singular[0])} is singular")


def check_correlations(name: str, correlations: NDArray[Any]) -> None:
    row = _first(correlations_valid(correlations))
    if row is not None:
        raise StateFieldError(
            f"{name}: row {row} ({correlations[row].tolist()!r:.60}) gives no positive "
            "definite covariance"
        )


def check_local_map_state(name: str, s: LocalMapState) -> None:
    """A smoother's local map state (``name``: where it is, e.g. ``map``), field by field."""
    try:
        check_state(name, s)
    except ValueError as err:
        raise StateFieldError(str(err)) from None
    check_stamps(f"{name}/odometry_stamps", s.odometry_stamps, "increasing")
    check_values(f"{name}/odometry_inputs", s.odometry_inputs, MAX_COORDINATE)
    check_values(f"{name}/odometry_sigmas", s.odometry_sigmas, positive=True)
    check_correlations(f"{name}/odometry_correlations", s.odometry_correlations)
    # the integrated ones come first, each run sorted; those still to integrate are sorted
    check_stamps(f"{name}/feature_stamps", s.feature_stamps)
    check_stamps(f"{name}/feature_stamps", s.feature_stamps[s.integrated_features :], "sorted")
    check_values(f"{name}/feature_points", s.feature_points, MAX_COORDINATE)
    _check_sqrt_information(f"{name}/feature_sqrt_information", s.feature_sqrt_information)
    check_stamps(f"{name}/requested", s.requested)
    check_stamps(f"{name}/keys", s.keys, "increasing")
    check_values(f"{name}/key_values", s.key_values, MAX_COORDINATE)
    check_values(f"{name}/relative", s.relative, MAX_COORDINATE)
    _check_sqrt_information(f"{name}/relative_sqrt_information", s.relative_sqrt_information)
    labels, counts = np.unique(s.landmark_labels, return_counts=True)
    if np.any(counts > 1):
        raise StateFieldError(f"{name}/landmark_labels: {int(labels[counts > 1][0])} appears twice")
    check_values(f"{name}/landmark_values", s.landmark_values, MAX_COORDINATE)
    integrated = np.asarray(s.feature_labels[: s.integrated_features])
    unknown = integrated[~np.isin(integrated, s.landmark_labels)]
    if len(unknown):
        raise StateFieldError(
            f"{name}/feature_labels: integrated feature {int(unknown[0])} is no landmark"
        )
    check_integer(f"{name}/dropped_features", s.dropped_features, 0, MAX_COUNT)
    if s.last_solved_odometry != -np.inf:
        check_number(
            f"{name}/last_solved_odometry", s.last_solved_odometry, -MAX_STAMP_S, MAX_STAMP_S
        )
    if np.shape(s.odometry_calibration) not in ((0,), (3,)):
        shape = np.shape(s.odometry_calibration)
        raise StateFieldError(f"{name}/odometry_calibration: shape {shape}, not (0,) or (3,)")
    check_values(f"{name}/odometry_calibration", s.odometry_calibration, MAX_COORDINATE)


def check_odometry_log(name: str, log: OdometryLog) -> None:
    check_stamps(f"{name}/stamps", log.stamps, "increasing")
    check_values(f"{name}/inputs", log.inputs, MAX_COORDINATE)
    check_values(f"{name}/sigmas", log.sigmas, positive=True)
    if log.correlations is not None:
        check_correlations(f"{name}/correlations", log.correlations)


def check_range_bearing_log(name: str, log: FeatureLog | RendezvousLog) -> None:
    """Range-bearing measurements (of features or of robots): sorted stamps, positive ranges
    and sigmas, finite bearings."""
    check_stamps(f"{name}/stamps", log.stamps, "sorted")
    check_values(f"{name}/ranges", log.ranges, MAX_COORDINATE, positive=True)
    check_values(f"{name}/bearings", log.bearings, MAX_COORDINATE)
    check_values(f"{name}/sigma_range", log.sigma_range, positive=True)
    check_values(f"{name}/sigma_bearing", log.sigma_bearing, positive=True)


def check_point_log(name: str, log: FeaturePointLog) -> None:
    check_stamps(f"{name}/stamps", log.stamps, "sorted")
    check_values(f"{name}/points", log.points, MAX_COORDINATE)
    cov = np.asarray(log.covariances, dtype=float).reshape(-1, 2, 2)
    check_values(f"{name}/covariances", cov.reshape(len(cov), 4))
    scale = np.abs(cov).max(axis=(1, 2)) if len(cov) else np.zeros(0)
    symmetric = np.abs(cov[:, 0, 1] - cov[:, 1, 0]) <= 1e-9 * scale
    definite = (cov[:, 0, 0] > 0) & (cov[:, 0, 0] * cov[:, 1, 1] - cov[:, 0, 1] ** 2 > 0)
    row = _first(symmetric & definite)
    if row is not None:
        raise StateFieldError(f"{name}/covariances: row {row} is not symmetric positive definite")
