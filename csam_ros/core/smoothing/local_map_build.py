"""Offline: the local map of a whole robot log (:func:`build_local_map`).

It builds the same problem as the online :class:`~csam_ros.core.smoothing.local_map.LocalMap`
and solves it to convergence, starting from the online policy run on windows of 60 s (one batch
solve from dead reckoning can end in a poor local minimum on long real runs: on MR.CLAM robot 1
with a Cauchy kernel it reached a cost of 24,701 against 3,634). Online and offline maps agree
to 1e-5 m without a kernel or with Huber (convex); with the redescending Cauchy kernel the two
paths can settle in different local minima (MR.CLAM robots 2-5: 0.1-0.2 m apart).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace

import numpy as np
from numpy.typing import ArrayLike

from csam_ros.core.model.log import RobotLog
from csam_ros.core.sam.solver import SolverOptions
from csam_ros.core.smoothing.local_map import LocalMap
from csam_ros.core.smoothing.local_map_config import LocalMapOptions
from csam_ros.core.smoothing.local_map_state import UpdateReport

# Offline, a 2D SLAM file's robot (Cartesian feature points only, no robust kernel; its stamps
# count poses, so a window of seconds means nothing there) is built in chunks of this many
# odometry samples, each solved to CHUNK_SOLVER's tolerance: the benchmark's incremental
# build (csam_ros.bench.smoothing). On Victoria Park (6,969 poses) it reaches the optimum of
# 60 s windows (cost 3,092; one batch solve from dead reckoning ends at 259,472) in 0.56 s
# instead of 4.0 s; chunks of 200, 500 and 2,000 samples reach it too, in 1.4, 0.8, 1.5 s.
FILE_CHUNK = 1000
CHUNK_SOLVER = SolverOptions(relative_tolerance=1e-6, max_iterations=200)


def build_local_map(
    log: RobotLog,
    extra_pose_stamps: ArrayLike = (),
    options: LocalMapOptions | None = None,
    window: float | None = 60.0,
    on_update: Callable[[UpdateReport], object] | None = None,
) -> LocalMap:
    """Offline: the local map of a whole robot log, solved to convergence.

    The problem is the same as online. Its initial values come from the online policy run
    on windows of ``window`` seconds of odometry (each window added and solved warm-started,
    as :meth:`LocalMap.update` does), which keeps long, drifting real runs (and robust
    kernels) out of the poor local minima that one batch solve from dead reckoning can end
    in; ``window=None`` starts the one batch solve from dead reckoning instead. A 2D SLAM
    file's robot is built in chunks of :data:`FILE_CHUNK` odometry samples instead, each
    solved to :data:`CHUNK_SOLVER`'s tolerance. ``on_update`` sees each update's report.
    """
    local = LocalMap(log.name, options)
    if window is None or len(log.odometry.stamps) == 0:
        local.add_log(log, extra_pose_stamps)
        local.update(converge=True)
        return local
    odo, f, p = log.odometry, log.features, log.points
    local.request_poses(log.rendezvous.stamps)
    local.request_poses(extra_pose_stamps)
    if not window > 0:
        raise ValueError(f"window must be positive or None, got {window}")
    chunked = len(p.stamps) > 0 and len(f.stamps) == 0 and local.options.robust is None
    own_options = local.options
    if chunked:
        edges = odo.stamps[FILE_CHUNK : len(odo.stamps) - 1 : FILE_CHUNK]
        local.options = replace(local.options, online_solver=CHUNK_SOLVER)
    else:
        # the window ends t0 + k * window after data (no empty windows across a gap)
        t0, last = odo.stamps[0], int((odo.stamps[-1] - odo.stamps[0]) // window)
        k = np.ceil((np.concatenate([odo.stamps, f.stamps, p.stamps]) - t0) / window)
        k = np.unique(np.concatenate([k, k + 1]))
        edges = t0 + window * k[(k >= 1) & (k <= last)]
    o_cut = [*np.searchsorted(odo.stamps, edges, side="right").tolist(), len(odo.stamps)]
    orders, cuts = [], []
    for stamps in (f.stamps, p.stamps):
        order = np.argsort(stamps, kind="stable")
        orders.append(order)
        cuts.append([*np.searchsorted(stamps[order], edges, side="right").tolist(), len(order)])
    o_start, f_start, p_start = 0, 0, 0
    for oc, fc, pc in zip(o_cut, *cuts, strict=True):
        local.add_log_part(log, slice(o_start, oc), orders[0][f_start:fc], orders[1][p_start:pc])
        o_start, f_start, p_start = oc, fc, pc
        if not (oc == len(odo.stamps) and fc == len(f.stamps) and pc == len(p.stamps)):
            report = local.update()
            if on_update is not None:
                on_update(report)
    local.options = own_options
    report = local.update(converge=True)
    if on_update is not None:
        on_update(report)
    return local
