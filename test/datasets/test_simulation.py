"""Simulation core and scenario files: reproducibility, noise statistics, sensor limits,
per-robot labels, rendezvous visibility and clear errors on bad scenario files."""

from __future__ import annotations

import copy

import numpy as np
import pytest

from csam_ros.core.model import se2
from csam_ros.core.model.config_file import ConfigFileError
from csam_ros.datasets.scenario import (
    ScenarioError,
    load_document,
    load_scenario,
    scenario_from_dict,
)
from csam_ros.datasets.simulation import (
    RangeBearingSensor,
    RobotSpec,
    Scenario,
    Segment,
    simulate,
    true_trajectory,
)


@pytest.fixture(scope="module")
def map_joining():
    return load_scenario("map_joining")


def test_same_seed_same_log_and_paths_independent_of_seed(map_joining: Scenario) -> None:
    a, b, c = simulate(map_joining, 3), simulate(map_joining, 3), simulate(map_joining, 4)
    for name in a.robots:
        np.testing.assert_array_equal(
            a.robots[name].features.ranges, b.robots[name].features.ranges
        )
        np.testing.assert_array_equal(
            a.robots[name].odometry.inputs, b.robots[name].odometry.inputs
        )
        assert not np.array_equal(a.robots[name].odometry.inputs, c.robots[name].odometry.inputs)
        np.testing.assert_array_equal(a.truth.trajectories[name], c.truth.trajectories[name])


def test_constant_turn_closes_a_circle() -> None:
    robot = RobotSpec("r", (1.0, 2.0, 0.3), (Segment(20.0, 0.5, 2 * np.pi / 20.0),))
    poses = true_trajectory(robot, 0.5)
    np.testing.assert_allclose(poses[-1], poses[0], atol=1e-9)
    radius = 0.5 / (2 * np.pi / 20.0)
    center = poses[0, :2] + radius * np.array([-np.sin(0.3), np.cos(0.3)])
    np.testing.assert_allclose(np.hypot(*(poses[:, :2] - center).T), radius, atol=1e-9)
    straight = true_trajectory(RobotSpec("s", (0, 0, 0), (Segment(2.0, 1.0, 0.0),)), 0.5)
    np.testing.assert_allclose(straight[:, 0], [0, 0.5, 1.0, 1.5, 2.0], atol=1e-12)


def _truth_relative(log, name):
    """True range/bearing of each logged feature observation."""
    robot = log.robots[name]
    truth = log.truth
    idx = np.searchsorted(truth.trajectory_stamps[name], robot.features.stamps)
    feature = np.array([truth.label_to_feature[name][int(lab)] for lab in robot.features.labels])
    rel = se2.inverse_transform_point(
        truth.trajectories[name][idx], truth.feature_positions[feature]
    )
    return np.hypot(rel[:, 0], rel[:, 1]), np.arctan2(rel[:, 1], rel[:, 0])


def test_feature_noise_and_sensor_limits(map_joining: Scenario) -> None:
    log = simulate(map_joining, 0)
    sensor = map_joining.robots[0].feature_sensor
    errs_r, errs_b = [], []
    for name, robot in log.robots.items():
        r, b = _truth_relative(log, name)
        assert np.all(r <= sensor.max_range) and np.all(np.abs(b) <= sensor.field_of_view / 2)
        errs_r.append(robot.features.ranges - r)
        errs_b.append(se2.wrap_angle(robot.features.bearings - b))
        # one scan per pose: every pose that sees a feature reports it exactly once
        keys = set(zip(robot.features.stamps.tolist(), robot.features.labels.tolist(), strict=True))
        assert len(keys) == len(robot.features.stamps)
    er, eb = np.concatenate(errs_r), np.concatenate(errs_b)
    n = len(er)
    assert n > 1000
    # sample std within 4 standard errors of the configured sigma
    assert abs(er.std() / sensor.sigma_range - 1) < 4 / np.sqrt(2 * n)
    assert abs(eb.std() / sensor.sigma_bearing - 1) < 4 / np.sqrt(2 * n)
    assert abs(er.mean()) < 4 * sensor.sigma_range / np.sqrt(n)


def test_every_visible_feature_is_observed(map_joining: Scenario) -> None:
    log = simulate(map_joining, 0)
    robot = log.robots["robot1"]
    poses = log.truth.trajectories["robot1"]
    rel = se2.inverse_transform_point(poses[:, None], map_joining.features[None])
    r = np.hypot(rel[..., 0], rel[..., 1])
    b = np.arctan2(rel[..., 1], rel[..., 0])
    expected = map_joining.robots[0].feature_sensor.visible(r, b).sum()
    assert len(robot.features.stamps) == expected


def test_odometry_noise_statistics() -> None:
    scenario = load_scenario("map_joining")
    sigma = np.array(scenario.robots[0].odometry_sigma)
    errors = []
    for seed in range(5):
        log = simulate(scenario, seed)
        odo = log.robots["robot1"].odometry
        errors.append(odo.inputs[1:] - np.array([0.5, 0.0, 0.0]))
        np.testing.assert_allclose(odo.sigmas, np.tile(sigma, (len(odo.stamps), 1)))
        np.testing.assert_allclose(np.diff(odo.stamps), scenario.sample_time)
    e = np.concatenate(errors)
    ratio = e.std(axis=0) / sigma
    assert np.all(np.abs(ratio - 1) < 4 / np.sqrt(2 * len(e)))


def test_labels_are_local_to_each_robot(map_joining: Scenario) -> None:
    log = simulate(map_joining, 0)
    truth = log.truth
    label_sets = [set(truth.label_to_feature[n]) for n in log.robots]
    assert not label_sets[0] & label_sets[1]
    f1 = truth.label_to_feature["robot1"]
    f2 = truth.label_to_feature["robot2"]
    # the same feature has different labels, and the label order is not the feature order
    inv2 = {f: lab for lab, f in f2.items()}
    assert all(inv2[f] != lab for lab, f in f1.items())
    labels1 = sorted(f1)
    assert [f1[lab] for lab in labels1] != sorted(f1.values())


def test_rendezvous_visibility_and_direction() -> None:
    scenario = load_scenario("sensor_extension")
    log = simulate(scenario, 0)
    p, q = log.robots["robot1"], log.robots["robot2"]
    assert len(q.rendezvous.stamps) == 0
    # P sees Q at every sample (the scenario's point)
    np.testing.assert_array_equal(p.rendezvous.stamps, p.odometry.stamps)
    assert set(p.rendezvous.observed) == {"robot2"}
    traj = log.truth.trajectories
    idx = np.searchsorted(log.truth.trajectory_stamps["robot1"], p.rendezvous.stamps)
    rel = se2.inverse_transform_point(traj["robot1"][idx], traj["robot2"][idx, :2])
    r_err = p.rendezvous.ranges - np.hypot(rel[:, 0], rel[:, 1])
    assert np.all(np.abs(r_err) < 5 * scenario.robots[0].rendezvous_sensor.sigma_range)
    assert np.all(np.abs(np.arctan2(rel[:, 1], rel[:, 0])) <= np.pi / 2)


def test_chain_meets_only_neighbours() -> None:
    log = simulate(load_scenario("chain"), 0)
    pairs = {
        tuple(sorted((name, other)))
        for name, robot in log.robots.items()
        for other in robot.rendezvous.observed
    }
    assert pairs == {("robot1", "robot2"), ("robot2", "robot3"), ("robot3", "robot4")}


def test_sensor_visibility_edges() -> None:
    sensor = RangeBearingSensor(max_range=4.0, field_of_view=np.pi)
    seen = sensor.visible(
        np.array([4.0, 4.01, 1.0, 1.0, 0.05]), np.array([0.0, 0.0, np.pi / 2, 1.6, 0.0])
    )
    np.testing.assert_array_equal(seen, [True, False, True, False, False])


def test_bad_segment_duration_is_named() -> None:
    robot = RobotSpec("r7", (0, 0, 0), (Segment(1.3, 0.5, 0.0),))
    with pytest.raises(ValueError, match="r7.*segment 0"):
        true_trajectory(robot, 0.5)


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda d: d["scenario"]["robots"][0].update(speed=1.0), r"robots\[0\].*speed"),
        (lambda d: d["scenario"].pop("sample_time"), "sample_time"),
        (lambda d: d["scenario"]["robots"][1].update(name="robot1"), "duplicate"),
        (lambda d: d["scenario"]["robots"][0]["program"][0].update(v="fast"), r"program\[0\]\.v"),
        (lambda d: d["scenario"]["robots"][0].update(observes=["robot9"]), "robot9"),
        (lambda d: d["scenario"]["world"].update(areas=[], points=[]), "no features"),
        (lambda d: d["scenario"]["defaults"]["feature_sensor"].update(sigma_range=0), "sigma"),
        (lambda d: d.pop("scenario"), "scenario"),
    ],
)
def test_scenario_errors_name_the_key(edit, message) -> None:
    document = copy.deepcopy(load_document("map_joining"))
    edit(document)
    with pytest.raises(ScenarioError, match=message):
        scenario_from_dict(document, "test.yaml")


def test_scenario_file_values() -> None:
    scenario = load_scenario("sensor_extension")
    p, q = scenario.robots
    np.testing.assert_allclose(np.array(q.odometry_sigma) / np.array(p.odometry_sigma), 5.0)
    assert p.feature_sensor.field_of_view == pytest.approx(np.pi)
    assert q.rendezvous_sensor is None and p.observes == ("robot2",)
    with pytest.raises(ConfigFileError, match="no such file"):
        load_scenario("no_such_scenario")
