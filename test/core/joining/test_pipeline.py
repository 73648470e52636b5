"""C-SAM from logs: each robot's local map as its smoother builds it, a robot without one left
out with a typed note, the smoothers' thinning reported, C-SAM's view of a local map."""

from __future__ import annotations

import numpy as np
import pytest
from sam_problems import dense_inverse_at_estimate
from straight_logs import straight_robot

from csam_ros.core.joining.config import CsamConfig
from csam_ros.core.joining.notes import NoteKind
from csam_ros.core.joining.pipeline import build_robot_maps, robot_map_from_local_map, run_csam
from csam_ros.core.joining.result import RunSummary
from csam_ros.core.model.log import (
    MultiRobotLog,
)
from csam_ros.core.smoothing.local_map_build import build_local_map
from csam_ros.core.smoothing.local_map_config import LocalMapConfig
from csam_ros.datasets.scenario import load_scenario
from csam_ros.datasets.simulation import simulate


def test_a_robot_without_a_local_map_is_left_out_with_a_typed_note() -> None:
    log = MultiRobotLog(
        {"robot1": straight_robot("robot1", 5, 0.1), "robot2": straight_robot("robot2", 1, 0.1)}
        | {"robot3": straight_robot("robot3", 5, 1e305)}
    )
    built = build_robot_maps(log)
    assert [m.name for m in built.maps] == ["robot1"]
    assert [n.kind for n in built.left_out] == [NoteKind.NO_LOCAL_MAP] * 2
    assert built.left_out[0].text == (
        "robot2: no local map: 1 usable odometry sample(s), a map needs two"
    )
    assert built.left_out[1].text.startswith("robot3: no local map: its solve failed (")
    result = run_csam(log)
    assert list(result.robots) == ["robot1"]
    assert result.notes_of(NoteKind.NO_LOCAL_MAP) == built.left_out == result.notes[:2]
    with pytest.raises(ValueError, match="^no robot has a local map: robot2: no local map: 1 "):
        run_csam(MultiRobotLog({"robot2": straight_robot("robot2", 1, 0.1)}))


def test_the_thinning_is_reported_when_it_thins_and_the_maps_are_timed() -> None:
    log = simulate(load_scenario("map_joining"), 1)
    plain = run_csam(log)
    assert "thinning" not in plain.rendezvous_filter
    assert plain.timing_s["local_maps"] > 0.0
    thinned = run_csam(log, CsamConfig(rendezvous_max_per_pair=3))
    report = thinned.rendezvous_filter["thinning"]
    assert sum(report.kept.values()) == thinned.statistics["rendezvous_measurements"]
    assert thinned.statistics["rendezvous_measurements"] <= 6
    assert plain.statistics["rendezvous_measurements"] > 6


def test_csams_view_of_a_local_map_has_its_poses_features_and_their_covariances() -> None:
    log = simulate(load_scenario("map_joining"), 1)
    local = build_local_map(log.robots["robot2"])
    m = robot_map_from_local_map(local, with_covariances=True)
    assert m.name == "robot2" and m.gauge_factor is not None
    np.testing.assert_array_equal(m.poses, local.poses)
    np.testing.assert_array_equal(m.feature_labels, local.landmark_labels)
    np.testing.assert_array_equal(m.feature_positions, local.landmarks)
    _, dense = dense_inverse_at_estimate(m.problem)
    xy = m.problem.scalar_indices(m.feature_ids).reshape(-1, 2)
    expected = dense[xy[:, :, None], xy[:, None, :]]
    np.testing.assert_allclose(m.feature_covariances, expected, rtol=1e-6, atol=1e-12)
    assert robot_map_from_local_map(local).feature_covariances is None


def test_a_calibrated_local_map_reports_its_odometry_calibration_in_the_result() -> None:
    import dataclasses

    from csam_ros.datasets.odometry_stress import OdometryStress

    scenario = load_scenario("map_joining")
    stress = OdometryStress(turn_driving=1.5, distance=0.9)
    robots = tuple(dataclasses.replace(r, odometry_stress=stress) for r in scenario.robots)
    log = simulate(dataclasses.replace(scenario, robots=robots), seed=1)
    calibrated = run_csam(log, local_map=LocalMapConfig(odometry_calibration=True))
    for robot in calibrated.robots.values():
        assert robot.joined
        scale, sigma = robot.odometry_calibration
        assert np.all(sigma > 0)
        # true = scale * reported: the distance scale undoes 0.9
        assert abs(scale[0] * 0.9 - 1.0) < 0.03
    plain = run_csam(log)
    assert all(r.odometry_calibration is None for r in plain.robots.values())
    again = RunSummary.from_dict(RunSummary(calibrated).to_dict()).result
    np.testing.assert_array_equal(
        again.robots["robot1"].odometry_calibration,
        calibrated.robots["robot1"].odometry_calibration,
    )
