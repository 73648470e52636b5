"""A fold cannot persist: a local map whose odometry reported a turn never made finds that
odometry and distrusts it (``fold_recovery``), and a map that does not fold is left alone."""

from __future__ import annotations

import numpy as np

from csam_ros.core.model.log import RobotLog
from csam_ros.core.sam.factors import Cauchy
from csam_ros.core.smoothing.fold_check import ConsistencyOptions, factor_outliers
from csam_ros.core.smoothing.fold_recovery import slipped_sample_scale
from csam_ros.core.smoothing.local_map_build import build_local_map
from csam_ros.core.smoothing.local_map_config import LocalMapOptions
from csam_ros.datasets.odometry_stress import OdometryStress
from csam_ros.datasets.scenario import load_scenario
from csam_ros.datasets.simulation import arcs_scenario, simulate

LIMITS = ConsistencyOptions()


def test_the_samples_of_an_interval_beyond_the_gate_are_scaled_to_its_expected_error() -> None:
    keys = np.array([0.0, 1.0, 2.0, 3.0])
    squared = np.array([1.0, 48.0, 2.0])  # the gate of 3 dof at 99.9 %: 16.27
    samples = np.array([0.0, 0.5, 1.0, 1.5, 2.0, 2.5, 3.0])  # sample i holds (t[i-1], t[i]]
    scale = slipped_sample_scale(samples, keys, squared, LIMITS.gate_probability)
    np.testing.assert_array_equal(scale, [1.0, 1.0, 1.0, 4.0, 4.0, 1.0, 1.0])
    straddling = np.array([0.0, 0.5, 1.5, 3.0])  # (0.5, 1.5] and (1.5, 3] reach into 1..2
    scale = slipped_sample_scale(straddling, keys, squared, LIMITS.gate_probability)
    np.testing.assert_array_equal(scale, [1.0, 1.0, 4.0, 4.0])


def _local_map(log: RobotLog, recover: bool):
    options = LocalMapOptions(robust=Cauchy(1.0), odometry_calibration=True, fold_recovery=recover)
    return build_local_map(log, options=options, window=5.0)


def _reasons(local) -> list[str]:
    return factor_outliers(local.problem, LIMITS.gate_probability).reasons(LIMITS)


def test_a_slip_folds_the_map_without_recovery_and_not_with_it() -> None:
    """(``python -m csam_ros.bench.odometry_calibration`` runs three slips on two robots.)"""
    stress = OdometryStress(turn_driving=1.5, resample_hz=8, slip_at=50.0, slip_turn=-0.8)
    log = simulate(arcs_scenario(stress)).robots["robot1"]
    folded = _local_map(log, recover=False)
    assert _reasons(folded) and folded.fold_recoveries == 0
    recovered = _local_map(log, recover=True)
    assert not _reasons(recovered) and recovered.fold_recoveries >= 1
    counts = factor_outliers(recovered.problem, LIMITS.gate_probability)
    assert counts.observation_outliers < 0.01 * counts.observation_factors
    k_d = recovered.odometry_calibration.scale[1]
    assert abs(k_d / stress.applied[1] - 1.0) < 0.01  # the slip no longer bends it


def test_a_map_that_does_not_fold_is_left_as_it_is() -> None:
    log = simulate(load_scenario("map_joining"), seed=2).robots["robot1"]
    plain, watched = (_local_map(log, recover) for recover in (False, True))
    assert not _reasons(plain) and watched.fold_recoveries == 0
    np.testing.assert_array_equal(watched.poses, plain.poses)
    np.testing.assert_array_equal(watched.landmarks, plain.landmarks)
