"""Odometry stress: scales applied where driving / on the spot, resampling keeps the motion,
bad options are named; a simulated robot's reported odometry is stressed, its truth not."""

import dataclasses

import numpy as np
import pytest

from csam_ros.core.model import motion
from csam_ros.core.model.log import OdometryLog
from csam_ros.datasets.odometry_stress import (
    OdometryStress,
    parse_odometry_stress,
    stress_odometry,
)
from csam_ros.datasets.scenario import load_scenario, scenario_from_dict
from csam_ros.datasets.simulation import simulate


def odometry(count=800, seed=0):
    rng = np.random.default_rng(seed)
    t = np.cumsum(rng.uniform(0.012, 0.018, count))
    u = np.column_stack([np.full(count, 0.3), np.zeros(count), rng.normal(0.1, 0.2, count)])
    u[300:400, 0] = 0.0
    return OdometryLog(t, u, np.tile([0.03, 0.01, 0.05], (count, 1)))


def test_scales_and_resampling():
    o = odometry()
    stressed = stress_odometry(o, parse_odometry_stress("turn_driving=1.5,distance=0.9"))
    np.testing.assert_allclose(stressed.inputs[:300, 2], 1.5 * o.inputs[:300, 2])
    np.testing.assert_allclose(stressed.inputs[300:400, 2], o.inputs[300:400, 2])
    np.testing.assert_allclose(stressed.inputs[:, 0], 0.9 * o.inputs[:, 0])
    resampled = stress_odometry(o, OdometryStress(resample_hz=8))
    assert len(resampled.stamps) == pytest.approx((o.stamps[-1] - o.stamps[0]) * 8, abs=2)
    assert np.all(np.isin(resampled.stamps, o.stamps))
    end = motion.odometry_poses(o.stamps, o.inputs)[-1]
    again = motion.odometry_poses(resampled.stamps, resampled.inputs)[-1]
    np.testing.assert_allclose(again, end, atol=0.05)  # piecewise-constant commands


@pytest.mark.parametrize("text", ["turn_driving=0", "speed=2", "distance=x", "turn_driving"])
def test_bad_options_are_named(text):
    with pytest.raises(ValueError):
        parse_odometry_stress(text)


def test_a_scenario_robot_reports_miscalibrated_odometry():
    scenario = load_scenario("map_joining")
    stress = OdometryStress(turn_driving=1.5, distance=0.9)
    robots = tuple(dataclasses.replace(r, odometry_stress=stress) for r in scenario.robots)
    plain, stressed = simulate(scenario), simulate(dataclasses.replace(scenario, robots=robots))
    for name in plain.robots:
        a, b = plain.robots[name].odometry, stressed.robots[name].odometry
        np.testing.assert_allclose(b.inputs[:, 0], 0.9 * a.inputs[:, 0])
        np.testing.assert_array_equal(
            plain.truth.trajectories[name], stressed.truth.trajectories[name]
        )


def test_scenario_file_key_is_checked():
    document = {
        "scenario": {
            "name": "s",
            "sample_time": 0.5,
            "world": {"points": [[1.0, 1.0]]},
            "defaults": {"odometry_sigma": {"v": 0.02, "v_lat": 0.01, "omega_deg": 0.5}},
            "robots": [
                {
                    "name": "r1",
                    "start": {"x": 0.0, "y": 0.0, "phi_deg": 0.0},
                    "program": [{"duration": 2.0, "v": 0.3}],
                    "odometry_stress": {"turn_driving": 1.5, "resample_hz": 8},
                }
            ],
        }
    }
    scenario = scenario_from_dict(document)
    assert scenario.robots[0].odometry_stress == OdometryStress(turn_driving=1.5, resample_hz=8)
    document["scenario"]["robots"][0]["odometry_stress"] = {"turn": 1.5}
    with pytest.raises(ValueError, match="odometry_stress"):
        scenario_from_dict(document)
