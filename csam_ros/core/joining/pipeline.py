"""C-SAM from robots' logs: each robot's local map (as its smoother builds it), then the join.

:func:`run_csam` is the offline counterpart of the live system: :func:`build_robot_maps` solves
every robot's local map with a pose at every kept rendezvous stamp (the rendezvous thinned as the
smoothers thin them), :func:`robot_map_from_local_map` gives C-SAM's view of each, and
:func:`~csam_ros.core.joining.join.join_maps` joins them (docs/METHOD.md sections 4.4 and 5-9).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace

import numpy as np

from csam_ros.core.joining.config import CsamConfig
from csam_ros.core.joining.join import join_maps
from csam_ros.core.joining.notes import Note
from csam_ros.core.joining.rendezvous_filters import FilterReport, thin_rendezvous
from csam_ros.core.joining.result import CsamResult
from csam_ros.core.model.log import MultiRobotLog, RendezvousLog
from csam_ros.core.model.rendezvous import required_stamps
from csam_ros.core.sam.covariance import factorize_at_estimate
from csam_ros.core.sam.selected_inverse import SelectedInverse
from csam_ros.core.smoothing.local_map import LocalMap
from csam_ros.core.smoothing.local_map_build import build_local_map
from csam_ros.core.smoothing.local_map_config import LocalMapConfig
from csam_ros.core.smoothing.robot_map import RobotMap, find_gauge_factor


def robot_map_from_local_map(local: LocalMap, with_covariances: bool = False) -> RobotMap:
    """C-SAM's view of a solved :class:`~csam_ros.core.smoothing.local_map.LocalMap` (with its
    feature covariances when ``with_covariances``)."""
    problem = local.problem
    pose_ids = problem.indices([("x", i) for i in range(len(local.stamps))])
    labels = local.landmark_labels
    feature_ids = problem.indices([("l", int(lab)) for lab in labels])
    calibration = local.odometry_calibration
    return RobotMap(
        name=local.name,
        problem=problem,
        stamps=local.stamps,
        pose_ids=pose_ids,
        feature_labels=labels,
        feature_ids=feature_ids,
        gauge_factor=find_gauge_factor(problem, int(pose_ids[0])),
        feature_covariances=(
            SelectedInverse(factorize_at_estimate(problem)).blocks(problem, feature_ids)
            if with_covariances
            else None
        ),
        odometry_calibration=(
            None if calibration is None else np.stack([calibration.scale, calibration.sigma])
        ),
    )


@dataclass
class RobotMaps:
    """The solved local maps :func:`run_csam` joins, with the rendezvous logs after thinning
    and what was left out."""

    maps: list[RobotMap]
    rendezvous_logs: dict[str, RendezvousLog]
    left_out: list[Note]  # robots without a local map, and why
    thinned: FilterReport
    seconds: float  # building time


def thinned_rendezvous(
    log: MultiRobotLog, config: CsamConfig
) -> tuple[dict[str, RendezvousLog], FilterReport]:
    """Every robot's rendezvous measurements as its smoother keeps them (``config``'s
    thinning), and what the thinning left out."""
    thinning = config.thinning()
    return thin_rendezvous(
        {n: r.rendezvous for n, r in log.robots.items()},
        thinning.min_interval,
        thinning.max_per_pair,
    )


def build_robot_maps(
    log: MultiRobotLog,
    config: CsamConfig | None = None,
    local_map: LocalMapConfig | None = None,
) -> RobotMaps:
    """Every robot's local map from its log, with a pose at the stamp of every kept
    rendezvous measurement that involves it (thinning as the smoothers do).

    A robot with fewer than two odometry samples, or whose local solve fails or is not
    finite, gets no local map: it is named in ``left_out``."""
    config = config or CsamConfig()
    local_map = local_map or LocalMapConfig()
    start = time.perf_counter()
    logs, thinned = thinned_rendezvous(log, config)
    stamps = required_stamps(logs)
    maps: list[RobotMap] = []
    left_out: list[Note] = []
    for name, robot in log.robots.items():
        samples = len(robot.odometry.stamps)
        if samples < 2:
            left_out.append(
                Note.no_local_map(name, f"{samples} usable odometry sample(s), a map needs two")
            )
            continue
        try:
            # values beyond floating point range end here as an error, not as warnings
            with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
                local = build_local_map(
                    replace(robot, rendezvous=logs[name]),
                    stamps[name],
                    local_map.options(),
                    window=local_map.window,
                )
            if not (np.isfinite(local.poses).all() and np.isfinite(local.landmarks).all()):
                raise FloatingPointError("the solution is not finite")
        except (ValueError, FloatingPointError, np.linalg.LinAlgError) as err:
            left_out.append(Note.no_local_map(name, f"its solve failed ({err})"))
            continue
        maps.append(robot_map_from_local_map(local))
    return RobotMaps(maps, dict(logs), left_out, thinned, time.perf_counter() - start)


def run_csam(
    log: MultiRobotLog,
    config: CsamConfig | None = None,
    local_map: LocalMapConfig | None = None,
) -> CsamResult:
    """:func:`build_robot_maps` then :func:`~csam_ros.core.joining.join.join_maps`;
    ``timing_s["local_maps"]`` is the building time. A robot without a local map is left out
    of the joining, as the merger leaves out a robot whose local map never arrives, and named
    in the result's ``notes``. ValueError when no robot is left."""
    config = config or CsamConfig()
    built = build_robot_maps(log, config, local_map)
    if not built.maps:
        raise ValueError("no robot has a local map: " + "; ".join(n.text for n in built.left_out))
    result = join_maps(built.maps, built.rendezvous_logs, config)
    result.notes[:0] = built.left_out
    thinning = config.thinning()
    if thinning.min_interval > 0 or thinning.max_per_pair is not None:
        result.rendezvous_filter["thinning"] = built.thinned
    result.timing_s["local_maps"] = built.seconds
    result.timing_s["total"] += built.seconds
    return result
