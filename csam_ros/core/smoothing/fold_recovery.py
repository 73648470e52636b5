"""A local map that folds recovers by itself (docs/METHOD.md section 4.4.2).

A map fails its check (:mod:`~csam_ros.core.smoothing.fold_check`) when some of its odometry
reported motion the robot did not make (a wheel slip, a bump, a turn the calibration cannot
explain): the Gaussian odometry factors spread that error along the path, and the robust
observations give way instead, for good. The recovery solves the map once with a Cauchy kernel
on the odometry too, graduated from wide to narrow (:data:`ODOMETRY_GNC_SCALES`), so that the
error gathers in the intervals where it happened. The odometry samples of those intervals get
their sigmas scaled until their factor's whitened error has its expected size
(:func:`slipped_sample_scale`), and the map is solved again with its ordinary factors: what it
publishes says that the odometry there is not to be trusted.

Measured (``python -m csam_ros.bench.odometry_calibration``): a simulated robot with a turn
of 0.6-1.2 rad that its odometry reported and it never made.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from csam_ros.core.model.chi_square import chi2_quantile
from csam_ros.core.sam.factors import CalibratedRelativePose, Cauchy, RelativePose
from csam_ros.core.sam.solver import Problem, SolverOptions

Array = NDArray[np.float64]

ODOMETRY_GNC_SCALES = (16.0, 4.0, 1.0)  # Cauchy scales (whitened) of the robust odometry solve


def robust_odometry_solve(problem: Problem, options: SolverOptions) -> Array:
    """Solve ``problem`` with a graduated Cauchy kernel on its odometry factor; that factor's
    squared whitened errors at the solution (the problem's values are the solution)."""
    (odometry,) = [
        f for f in problem.factors if isinstance(f, RelativePose | CalibratedRelativePose)
    ]
    try:
        for scale in ODOMETRY_GNC_SCALES:
            odometry.robust = Cauchy(scale)
            problem.solve(replace(options, max_step_scale=1.0))
    finally:
        odometry.robust = None
    return problem.squared_errors()[problem.factors.index(odometry)]


def slipped_sample_scale(
    sample_stamps: Array, keys: Array, squared: Array, gate_probability: float
) -> Array:
    """Per odometry sample, the factor by which to scale its sigmas: ``sqrt(squared / 3)``
    for the samples that hold input in an interval between ``keys`` whose factor's squared
    error ``squared`` lies beyond the gate (its error then has its expected size), else 1.
    Sample ``i`` holds the input over ``(t[i-1], t[i]]``, which may reach into two intervals."""
    gate = chi2_quantile(gate_probability, 3)
    per_factor = np.where(squared > gate, np.sqrt(squared / 3.0), 1.0)
    last = len(per_factor) - 1
    starts = np.concatenate([sample_stamps[:1], sample_stamps[:-1]])
    first = np.clip(np.searchsorted(keys, starts, side="right") - 1, 0, last)
    through = np.clip(np.searchsorted(keys, sample_stamps, side="left") - 1, 0, last)
    return np.maximum(per_factor[first], per_factor[through])
