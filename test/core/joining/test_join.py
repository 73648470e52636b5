"""C-SAM's join end to end on simulated runs (the paper's two experiments, base-node
consistency over many seeds, pending robots, chains and repeated meetings, the summary
structure) and its steps one by one: the rendezvous filters, the notes, the step times."""

from __future__ import annotations

import copy
import json

import numpy as np
import pytest
from sam_problems import dense_inverse_at_estimate
from scipy.stats import chi2

from csam_ros.core.joining.config import CsamConfig
from csam_ros.core.joining.join import (
    StepTimes,
    filter_rendezvous,
    join_maps,
    local_map_notes,
    rendezvous_measurements,
    rendezvous_poses,
)
from csam_ros.core.joining.notes import NOT_CONVERGED, NoteKind
from csam_ros.core.joining.pipeline import build_robot_maps, run_csam
from csam_ros.core.joining.result import CsamResult, LocalMapCheck
from csam_ros.core.model import se2
from csam_ros.core.model.log import RendezvousLog
from csam_ros.core.truth.evaluation import evaluate
from csam_ros.datasets.scenario import load_document, load_scenario, scenario_from_dict
from csam_ros.datasets.simulation import simulate


@pytest.fixture(scope="module")
def map_joining():
    log = simulate(load_scenario("map_joining"), 1)
    return log, run_csam(log)


def test_map_joining_lowers_heading_uncertainty_everywhere(map_joining) -> None:
    log, result = map_joining
    first_meeting = min(r.rendezvous.stamps.min() for r in log.robots.values())
    for name, robot in result.robots.items():
        before, after = robot.sigma_phi_local, robot.sigma_phi_joined
        assert robot.alignment in ("reference", "aligned"), name
        # at or below at every pose (up to the two linearisation points)
        assert np.all(after <= before * (1 + 1e-6) + 1e-9), name
        later = robot.stamps >= first_meeting
        assert np.mean(after[later] / before[later]) < 0.8, name
        # before the rendezvous too, through the associated duplicate features
        earlier = ~later & (before > 1e-3)
        assert np.mean(after[earlier] / before[earlier]) < 0.9, name


def test_map_joining_associations_are_right(map_joining) -> None:
    log, result = map_joining
    metrics = evaluate(result, log.truth)["association"]
    assert metrics["true_pairs"] > 30
    assert metrics["precision"] == 1.0
    assert metrics["recall"] >= 0.9
    assert all(0 <= a.mahalanobis < 9.21 for a in result.associations)


def test_sensor_extension_q_inherits_p_heading_certainty() -> None:
    result = run_csam(simulate(load_scenario("sensor_extension"), 1))
    p, q = result.robots["robot1"], result.robots["robot2"]
    assert q.alignment == "aligned"
    assert q.sigma_phi_local.mean() > 1.5 * p.sigma_phi_local.mean()  # the scenario's point
    assert q.sigma_phi_joined.mean() <= 1.5 * p.sigma_phi_joined.mean()
    assert q.sigma_phi_joined_reference.mean() <= 1.5 * p.sigma_phi_joined.mean()
    assert q.sigma_phi_joined.mean() < 0.5 * q.sigma_phi_local.mean()


SMALL = {
    "scenario": {
        "name": "small_meeting",
        "sample_time": 1.0,
        "world": {
            "seed": 3,
            "areas": [{"center": [0.0, 0.0], "size": [8.0, 5.0], "spacing": 1.5, "jitter": 0.2}],
        },
        "defaults": {"odometry_sigma": {"v": 0.03, "v_lat": 0.015, "omega_deg": 2.0}},
        "robots": [
            {
                "name": "robot1",
                "start": {"x": -4.0, "y": -1.0, "phi_deg": 0.0},
                "program": [{"duration": 8.0, "v": 1.0}],
            },
            {
                "name": "robot2",
                "start": {"x": 4.0, "y": 1.0, "phi_deg": 180.0},
                "program": [{"duration": 8.0, "v": 1.0}],
            },
        ],
    }
}


def _base_error(log, result: CsamResult, name: str) -> np.ndarray:
    truth = log.truth.trajectories
    true_base = se2.between(truth["robot1"][0], truth[name][0])
    err = result.robots[name].base_node - true_base
    err[2] = se2.wrap_angle(err[2])
    return err


def test_base_node_is_consistent_over_seeds() -> None:
    scenario = scenario_from_dict(SMALL)
    nees = []
    for seed in range(50):
        log = simulate(scenario, seed)
        result = run_csam(log)
        robot = result.robots["robot2"]
        assert robot.alignment == "aligned"
        err = _base_error(log, result, "robot2")
        nees.append(err @ np.linalg.solve(robot.base_node_cov, err))
    n = len(nees)
    # sum of n NEES values of 3 dof is chi-square with 3n dof when the estimate is consistent
    low, high = chi2.ppf([0.025, 0.975], 3 * n) / n
    assert low <= np.mean(nees) <= high, (np.mean(nees), low, high)


def _one_measurement(log):
    out = copy.deepcopy(log)
    for robot in out.robots.values():
        rv = robot.rendezvous
        keep = slice(0, 1) if robot.name == "robot1" else slice(0, 0)
        robot.rendezvous = RendezvousLog(
            rv.stamps[keep],
            rv.observed[keep],
            rv.ranges[keep],
            rv.bearings[keep],
            rv.sigma_range[keep],
            rv.sigma_bearing[keep],
        )
    return out


def test_one_rendezvous_measurement_leaves_the_robot_pending() -> None:
    log = _one_measurement(simulate(scenario_from_dict(SMALL), 0))
    result = run_csam(log)
    robot = result.robots["robot2"]
    assert robot.alignment.startswith("pending: ")
    assert "one rendezvous measurement" in robot.alignment
    assert robot.poses_joined is None and robot.base_node is None
    summary = result.to_dict()
    entry = summary["robots"]["robot2"]
    assert entry["base_node"] is None and entry["poses_joined"] == []
    assert len(entry["poses_local"]) == len(entry["stamps"]) == len(entry["sigma_phi_local"])
    assert all(m.startswith("robot1/") for f in summary["features"] for m in f["members"])
    assert summary["associations"] == []


def test_chain_of_four_and_a_robot_that_never_meets() -> None:
    document = load_document("chain")
    document["scenario"]["robots"].append(
        {
            "name": "robot5",
            "start": {"x": 40.0, "y": 40.0, "phi_deg": 0.0},
            "program": [{"duration": 10.0, "v": 0.5}],
        }
    )
    document["scenario"]["world"]["areas"].append(
        {"center": [42.0, 40.0], "size": [4.0, 4.0], "spacing": 1.5, "jitter": 0.2}
    )
    log = simulate(scenario_from_dict(document), 0)
    result = run_csam(log)
    status = {n: r.alignment for n, r in result.robots.items()}
    assert status["robot1"] == "reference"
    assert all(status[f"robot{k}"] == "aligned" for k in (2, 3, 4))
    assert status["robot5"] == "pending: no rendezvous with any robot"
    for k in (2, 3, 4):
        err = _base_error(log, result, f"robot{k}")
        cov = result.robots[f"robot{k}"].base_node_cov
        assert err @ np.linalg.solve(cov, err) < chi2.ppf(0.999, 3)
    metrics = evaluate(result, log.truth)["association"]
    assert metrics["precision"] == 1.0 and metrics["recall_aligned"] >= 0.9
    # clusters over three and four robots
    assert max(len(f.members) for f in result.features) >= 3


def _repeated_meetings_log():
    document = copy.deepcopy(SMALL)
    robots = document["scenario"]["robots"]
    # robot1 drives back and forth past robot2, which waits: three separate meetings
    robots[0]["start"] = {"x": -6.0, "y": 0.0, "phi_deg": 0.0}
    robots[0]["program"] = [
        {"duration": 12.0, "v": 1.0},
        {"duration": 2.0, "v": 0.0, "omega_deg": 90.0},
        {"duration": 12.0, "v": 1.0},
        {"duration": 2.0, "v": 0.0, "omega_deg": -90.0},
        {"duration": 12.0, "v": 1.0},
    ]
    robots[1]["start"] = {"x": 0.0, "y": 3.0, "phi_deg": 0.0}
    robots[1]["program"] = [{"duration": 40.0, "v": 0.01}]
    document["scenario"]["world"]["areas"] = [
        {"center": [0.0, 1.5], "size": [14.0, 6.0], "spacing": 2.0, "jitter": 0.2}
    ]
    return simulate(scenario_from_dict(document), 0)


def test_repeated_meetings_add_rows_to_one_connector() -> None:
    log = _repeated_meetings_log()
    stamps = np.sort(np.concatenate([r.rendezvous.stamps for r in log.robots.values()]))
    meetings = 1 + int(np.sum(np.diff(stamps) > 3.0))
    assert meetings == 3
    result = run_csam(log)
    assert result.robots["robot2"].alignment == "aligned"
    assert result.statistics["rendezvous_measurements"] == len(stamps)
    err = _base_error(log, result, "robot2")
    assert err @ np.linalg.solve(result.robots["robot2"].base_node_cov, err) < chi2.ppf(0.999, 3)


def test_summary_structure(map_joining) -> None:
    _, result = map_joining
    summary = json.loads(json.dumps(result.to_dict()))
    assert summary["reference_frame"] == "robot1/map"
    ref = summary["robots"]["robot1"]
    assert ref["alignment"] == "reference" and ref["base_node"] == [0.0, 0.0, 0.0]
    for entry in summary["robots"].values():
        n = len(entry["stamps"])
        for key in ("poses_local", "poses_joined", "sigma_phi_local", "sigma_phi_joined"):
            assert len(entry[key]) == n, key
        assert np.shape(entry["base_node_cov"]) == (3, 3)
    members = [m for f in summary["features"] for m in f["members"]]
    assert len(members) == len(set(members))
    assert all(np.shape(f["cov"]) == (2, 2) and len(f["xy"]) == 2 for f in summary["features"])
    assert {"a", "b", "mahalanobis"} <= set(summary["associations"][0])
    assert {"alignment", "association", "joint_solve", "total"} <= set(summary["timing_s"])
    # every associated pair is inside one feature
    by_member = {m: i for i, f in enumerate(summary["features"]) for m in f["members"]}
    assert all(by_member[a["a"]] == by_member[a["b"]] for a in summary["associations"])


def test_rendezvous_filters_drop_a_wrong_measurement_and_thin_the_rest() -> None:
    log = _repeated_meetings_log()
    wrong = copy.deepcopy(log)
    rv = wrong.robots["robot1"].rendezvous
    rv.ranges[len(rv.ranges) // 2] += 1.5  # a misread: 1.5 m too far
    n_measured = sum(r.rendezvous.stamps.size for r in log.robots.values())

    def nees(result: CsamResult) -> float:
        err = _base_error(log, result, "robot2")
        return float(err @ np.linalg.solve(result.robots["robot2"].base_node_cov, err))

    trusting = run_csam(wrong)
    checked = run_csam(wrong, CsamConfig(rendezvous_consistency=True, consistency_drift=0.2))
    report = checked.rendezvous_filter["consistency"]
    assert report.dropped == {"robot1": {"inconsistent": 1}}
    assert checked.statistics["rendezvous_measurements"] == n_measured - 1
    assert nees(checked) < chi2.ppf(0.999, 3) < nees(trusting)

    thinned = run_csam(log, CsamConfig(rendezvous_min_interval=1.0, rendezvous_max_per_pair=4))
    kept = thinned.statistics["rendezvous_measurements"]
    assert 2 <= kept <= 8 < n_measured  # two ordered pairs, at most 4 each
    report = thinned.rendezvous_filter["thinning"]
    assert sum(report.kept.values()) == kept
    assert kept + sum(sum(d.values()) for d in report.dropped.values()) == n_measured
    assert thinned.robots["robot2"].alignment == "aligned"
    assert nees(thinned) < chi2.ppf(0.999, 3)


def test_an_unconverged_solve_is_reported_never_silent(map_joining) -> None:
    log, converged = map_joining
    assert converged.converged
    assert converged.statistics["joint_converged"] == 1.0
    assert converged.notes == [] and not converged.notes_of(*NOT_CONVERGED)

    config = CsamConfig(max_iterations=1)
    result = run_csam(log, config)
    assert not result.converged
    assert result.statistics["joint_converged"] == 0.0
    kinds = [n.kind for n in result.notes]
    assert kinds == [NoteKind.NOT_CONVERGED_ALIGNMENT, NoteKind.NOT_CONVERGED_JOINT]
    assert all(n.not_converged for n in result.notes)
    (note,) = result.notes_of(NoteKind.NOT_CONVERGED_JOINT)
    assert note.text.startswith("joint solve not converged: maximum iterations reached after 1 ")
    again = CsamResult.from_dict(json.loads(json.dumps(result.to_dict())))
    assert not again.converged and again.notes == result.notes


def test_one_robot_alone_has_the_marginals_of_its_dense_information(map_joining) -> None:
    """A robot joined alone: its joint problem is its local problem, and the reported
    marginals (heading sigmas, feature covariances) are those of the dense inverse of its
    information matrix at the joined estimate."""
    log, _ = map_joining
    alone = copy.copy(log)
    alone.robots = {"robot1": log.robots["robot1"]}
    built = build_robot_maps(alone)
    (m,) = built.maps
    joined = join_maps(built.maps, built.rendezvous_logs)
    robot = joined.robots["robot1"]
    by_label = {int(f.members[0].split("/")[1]): f for f in joined.features}
    features = [by_label[int(label)] for label in m.feature_labels]
    m.problem.values[:] = np.nan  # the joined estimate goes in, nothing of the local one
    m.problem.set_values(m.pose_ids, robot.poses_joined)
    m.problem.set_values(m.feature_ids, np.array([f.xy for f in features]))
    _, covariance = dense_inverse_at_estimate(m.problem)
    headings = m.problem.scalar_indices(m.pose_ids)[2::3]
    first = headings[0]
    np.testing.assert_allclose(
        robot.sigma_phi_joined_reference, np.sqrt(covariance[headings, headings]), rtol=1e-6
    )
    relative = covariance[headings, headings] + covariance[first, first]
    relative -= 2 * covariance[headings, first]
    np.testing.assert_allclose(
        robot.sigma_phi_joined, np.sqrt(np.maximum(relative, 0.0)), rtol=1e-6, atol=1e-9
    )
    xy = m.problem.scalar_indices(m.feature_ids).reshape(-1, 2)
    expected = covariance[xy[:, :, None], xy[:, None, :]]
    np.testing.assert_allclose(np.array([f.cov for f in features]), expected, rtol=1e-6)


def test_the_steps_are_timed_in_their_order(map_joining) -> None:
    """``timing_s`` names the steps in the order they ran (summary.json keeps that order);
    Algorithm 2 is timed only when it runs."""
    log, result = map_joining
    steps = [
        "local_map_checks",
        "local_rendezvous_parts",
        "alignment",
        "local_marginals",
        "association",
        "joint_solve",
        "joint_base_node_covariance",
        "joint_marginals",
    ]
    assert list(result.timing_s) == [*steps, "total", "local_maps"]
    built = build_robot_maps(log)
    alone = join_maps(built.maps, built.rendezvous_logs, CsamConfig(associate=False))
    assert list(alone.timing_s) == [s for s in steps if s != "association"] + ["total"]
    assert alone.timing_s["total"] == pytest.approx(sum(list(alone.timing_s.values())[:-1]))
    clock = StepTimes()
    clock.lap("a")
    clock.lap("b")
    clock.lap("a")
    times = clock.with_total()
    assert list(times) == ["a", "b", "total"] and times["total"] == times["a"] + times["b"]


def test_join_maps_needs_maps_of_distinct_robots() -> None:
    built = build_robot_maps(simulate(scenario_from_dict(SMALL), 0))
    with pytest.raises(ValueError, match="no local maps"):
        join_maps([], built.rendezvous_logs)
    with pytest.raises(ValueError, match="duplicate robot names"):
        join_maps([built.maps[0], built.maps[0]], built.rendezvous_logs)


def test_a_measurement_outside_a_maps_time_span_is_left_out_and_counted() -> None:
    built = build_robot_maps(simulate(scenario_from_dict(SMALL), 0))
    config = CsamConfig()
    logs, reports = filter_rendezvous(built.maps, built.rendezvous_logs, config)
    assert reports == {} and logs is built.rendezvous_logs
    rv = built.rendezvous_logs["robot1"]
    late = copy.copy(rv)
    late.stamps = rv.stamps.copy()
    late.stamps[-1] = built.maps[1].stamps[-1] + 1.0  # after robot2's last pose
    logs, reports = filter_rendezvous(built.maps, {**built.rendezvous_logs, "robot1": late}, config)
    assert reports["trajectory_span"].dropped == {"robot1": {"outside_trajectory": 1}}
    np.testing.assert_array_equal(logs["robot1"].stamps, rv.stamps[:-1])
    assert logs["robot2"] is built.rendezvous_logs["robot2"]


def test_rendezvous_poses_are_the_poses_of_the_measurements(map_joining) -> None:
    log, result = map_joining
    built = build_robot_maps(log)
    measurements, notes = rendezvous_measurements(built.maps, built.rendezvous_logs, CsamConfig())
    assert notes == []
    poses = rendezvous_poses(measurements)
    for r, m in enumerate(built.maps):
        stamps = np.concatenate(
            [
                measurements.stamps[measurements.observer == r],
                measurements.stamps[measurements.observed == r],
            ]
        )
        np.testing.assert_array_equal(np.asarray(m.stamps)[poses[r]], np.unique(stamps))
        np.testing.assert_array_equal(result.robots[m.name].rendezvous_stamps, np.unique(stamps))


def test_rendezvous_of_a_robot_without_a_map_are_a_typed_note(map_joining) -> None:
    log, _ = map_joining
    alone = copy.copy(log)
    alone.robots = {"robot1": log.robots["robot1"]}
    result = run_csam(alone)
    (note,) = result.notes
    assert note.kind is NoteKind.RENDEZVOUS_LEFT_OUT
    assert note.text.endswith(
        "rendezvous measurement(s) of 'robot2' by 'robot1' ignored: no map of 'robot2'"
    )


def test_the_local_map_checks_are_typed_notes() -> None:
    failed = LocalMapCheck(10, 9, 20, 1, [], "inconsistent local map: 9 of 10 factors")
    features = LocalMapCheck(10, 0, 20, 1, [4, 7])
    notes = local_map_notes(["robot1", "robot2", "robot3"], {0: failed, 1: features, 2: failed})
    assert [(n.kind, n.text) for n in notes] == [
        (
            NoteKind.LOCAL_MAP_INCONSISTENT,
            "robot1: inconsistent local map: 9 of 10 factors (reference kept)",
        ),
        (
            NoteKind.FEATURES_NOT_ASSOCIATED,
            "robot2: features [4, 7] not associated: their observations disagree",
        ),
        (
            NoteKind.LOCAL_MAP_INCONSISTENT,
            "robot3: inconsistent local map: 9 of 10 factors (pending)",
        ),
    ]
