"""The joint solve: equal to the centralised MAP of all measurements of all robots with the
same associations (GTSAM, written independently from the raw log), and the bookkeeping of
:class:`RobotMap` and of heading sigmas."""

from __future__ import annotations

import numpy as np
import pytest
from sam_problems import dense_inverse_at_estimate

from csam_ros.core.joining.joint_solve import heading_sigmas
from csam_ros.core.joining.pipeline import robot_map_from_local_map, run_csam
from csam_ros.core.joining.result import CsamResult
from csam_ros.core.model import motion, se2, sensor
from csam_ros.core.model.log import MultiRobotLog
from csam_ros.core.sam.factors import POSE, PosePrior, RelativePose
from csam_ros.core.sam.selected_inverse import SelectedInverse
from csam_ros.core.sam.solver import GAUGE_SIGMA, Problem
from csam_ros.core.smoothing.local_map_build import build_local_map
from csam_ros.core.smoothing.robot_map import RobotMap
from csam_ros.datasets.scenario import load_scenario
from csam_ros.datasets.simulation import simulate


@pytest.fixture(scope="module", params=["map_joining", "chain"])
def joined(request) -> tuple[MultiRobotLog, CsamResult]:
    """Two robots, and four robots with measurements between non-reference robots."""
    log = simulate(load_scenario(request.param), 2)
    return log, run_csam(log)


def _tangent_to_global(theta: float) -> np.ndarray:
    """d(x, y, phi) / d(GTSAM Pose2 local tangent) at the pose."""
    j = np.eye(3)
    j[:2, :2] = se2.rotation(theta)
    return j


def _centralised_gtsam(log: MultiRobotLog, result: CsamResult):
    """MAP of every measurement of every robot, in robot1's frame, written from the log."""
    gtsam = pytest.importorskip("gtsam")
    names = list(log.robots)
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    pose_key = {n: (lambda i, k=k: gtsam.symbol(chr(ord("a") + k), i)) for k, n in enumerate(names)}
    feature_of = {}  # "robot/label" -> feature index
    for j, f in enumerate(result.features):
        for m in f.members:
            feature_of[m] = j
    truth = log.truth
    ref_start = truth.trajectories[names[0]][0]

    def pose_of(v, key):
        p = v.atPose2(key)
        return np.array([p.x(), p.y(), p.theta()])

    def add(keys, dim, error_fn, cov):
        noise = gtsam.noiseModel.Gaussian.Covariance(np.asarray(cov, dtype=float).reshape(dim, dim))
        graph.add(gtsam.CustomFactor(noise, keys, error_fn))

    def odometry(z):
        def error(this, v, jac):
            a, b = pose_of(v, this.keys()[0]), pose_of(v, this.keys()[1])
            ra = se2.rotation(a[2])
            d = b[:2] - a[:2]
            local = ra.T @ d
            e = np.array([local[0] - z[0], local[1] - z[1], se2.wrap_angle(b[2] - a[2] - z[2])])
            if jac is not None:
                ja = np.zeros((3, 3))
                ja[:2, :2] = -ra.T
                ja[:2, 2] = [local[1], -local[0]]
                ja[2, 2] = -1
                jb = np.zeros((3, 3))
                jb[:2, :2] = ra.T
                jb[2, 2] = 1
                jac[0] = ja @ _tangent_to_global(a[2])
                jac[1] = jb @ _tangent_to_global(b[2])
            return e

        return error

    def relative_position(z, point_is_pose):
        def error(this, v, jac):
            a = pose_of(v, this.keys()[0])
            if point_is_pose:
                b = pose_of(v, this.keys()[1])
                t = b[:2]
            else:
                t = np.asarray(v.atPoint2(this.keys()[1]), dtype=float)
            ra = se2.rotation(a[2])
            local = ra.T @ (t - a[:2])
            if jac is not None:
                ja = np.zeros((2, 3))
                ja[:, :2] = -ra.T
                ja[:, 2] = [local[1], -local[0]]
                jac[0] = ja @ _tangent_to_global(a[2])
                if point_is_pose:
                    jb = np.zeros((2, 3))
                    jb[:, :2] = ra.T
                    jac[1] = jb @ _tangent_to_global(b[2])
                else:
                    jac[1] = ra.T
            return local - z

        return error

    def gauge(this, v, jac):
        a = pose_of(v, this.keys()[0])
        if jac is not None:
            jac[0] = _tangent_to_global(a[2])
        return np.array([a[0], a[1], se2.wrap_angle(a[2])])

    add([pose_key[names[0]](0)], 3, gauge, np.eye(3) * GAUGE_SIGMA**2)
    for name in names:
        robot = log.robots[name]
        stamps = result.robots[name].stamps
        odo = robot.odometry
        f = motion.odometry_between(odo.stamps, odo.inputs, odo.sigmas, stamps)
        for i in range(len(stamps) - 1):
            add(
                [pose_key[name](i), pose_key[name](i + 1)],
                3,
                odometry(f.relative_poses[i]),
                f.covariances[i],
            )
        # independent initial values: the true trajectory in robot1's frame
        true_t = truth.trajectory_stamps[name]
        idx = np.searchsorted(true_t, stamps)
        for i, p in enumerate(se2.between(ref_start, truth.trajectories[name][idx])):
            values.insert(pose_key[name](i), gtsam.Pose2(*p))
        fe = robot.features
        z, cov = sensor.polar_to_cartesian(fe.ranges, fe.bearings, fe.sigma_range, fe.sigma_bearing)
        pose_idx = np.searchsorted(stamps, fe.stamps)
        for k in range(len(z)):
            j = feature_of[f"{name}/{int(fe.labels[k])}"]
            add(
                [pose_key[name](int(pose_idx[k])), gtsam.symbol("l", j)],
                2,
                relative_position(z[k], False),
                cov[k],
            )
        rv = robot.rendezvous
        z, cov = sensor.polar_to_cartesian(rv.ranges, rv.bearings, rv.sigma_range, rv.sigma_bearing)
        for k in range(len(z)):
            other = rv.observed[k]
            i = int(np.searchsorted(stamps, rv.stamps[k]))
            j = int(np.searchsorted(result.robots[other].stamps, rv.stamps[k]))
            add(
                [pose_key[name](i), pose_key[other](j)],
                2,
                relative_position(z[k], True),
                cov[k],
            )
    world_features = {}
    for name in names:
        for label, fid in truth.label_to_feature[name].items():
            world_features[f"{name}/{label}"] = truth.feature_positions[fid]
    for j, f in enumerate(result.features):
        xy = se2.inverse_transform_point(ref_start, world_features[f.members[0]])
        values.insert(gtsam.symbol("l", j), np.asarray(xy, dtype=float))
    params = gtsam.GaussNewtonParams()
    params.setRelativeErrorTol(1e-15)
    params.setAbsoluteErrorTol(1e-15)
    params.setMaxIterations(50)
    estimate = gtsam.GaussNewtonOptimizer(graph, values, params).optimize()
    return gtsam, graph, estimate, pose_key, pose_of


def test_joint_solve_is_the_centralised_map(joined) -> None:
    log, result = joined
    assert all(r.alignment in ("reference", "aligned") for r in result.robots.values())
    assert len(result.associations) > 10
    gtsam, graph, estimate, pose_key, pose_of = _centralised_gtsam(log, result)
    for name, robot in result.robots.items():
        theirs = np.array([pose_of(estimate, pose_key[name](i)) for i in range(len(robot.stamps))])
        diff = robot.poses_joined - theirs
        diff[:, 2] = se2.wrap_angle(diff[:, 2])
        scale = np.maximum(1.0, np.abs(theirs))
        assert np.max(np.abs(diff) / scale) < 1e-6, name
    theirs = np.array(
        [np.asarray(estimate.atPoint2(gtsam.symbol("l", j))) for j in range(len(result.features))]
    )
    ours = np.array([f.xy for f in result.features])
    assert np.max(np.abs(ours - theirs) / np.maximum(1.0, np.abs(theirs))) < 1e-6
    # each base node covariance is the marginal of that robot's first pose
    marginals = gtsam.Marginals(graph, estimate)
    for name in list(result.robots)[1:]:
        first = estimate.atPose2(pose_key[name](0))
        j = _tangent_to_global(first.theta())
        cov = j @ marginals.marginalCovariance(pose_key[name](0)) @ j.T
        np.testing.assert_allclose(result.robots[name].base_node_cov, cov, rtol=1e-4, atol=1e-12)


def test_heading_sigmas_against_dense_covariance() -> None:
    rng = np.random.default_rng(0)
    problem = Problem()
    n = 12
    truth = np.column_stack([np.arange(n) * 0.5, np.zeros(n), rng.normal(0, 0.1, n)])
    ids = problem.add_variables(POSE, [("x", i) for i in range(n)], truth)
    problem.add_factor(PosePrior(ids[:1], truth[:1], covariance=np.eye(3) * 1e-2))
    rel = se2.between(truth[:-1], truth[1:])
    problem.add_factor(RelativePose(ids[:-1], ids[1:], rel, covariance=np.diag([1e-3, 2e-3, 3e-3])))
    problem.solve()
    system = problem.normal_equations()
    system.linearize(problem.values)
    system.factorize()
    absolute, relative = heading_sigmas(problem, system, ids)
    full = np.linalg.inv(system.matrix().toarray() + np.triu(system.matrix().toarray(), 1).T)
    h = 3 * np.arange(n) + 2
    np.testing.assert_allclose(absolute, np.sqrt(full[h, h]), rtol=1e-9)
    expected = np.sqrt(full[h, h] + full[h[0], h[0]] - 2 * full[h, h[0]])
    np.testing.assert_allclose(relative, expected, rtol=1e-9, atol=1e-12)


def test_robot_map_checks_its_gauge() -> None:
    log = simulate(load_scenario("map_joining"), 0)
    local = build_local_map(log.robots["robot1"])
    good = robot_map_from_local_map(local)
    assert good.gauge_factor == 0
    with pytest.raises(ValueError, match="not the gauge prior"):
        RobotMap(
            good.name,
            good.problem,
            good.stamps,
            good.pose_ids,
            good.feature_labels,
            good.feature_ids,
            gauge_factor=1,
        )
    with pytest.raises(ValueError, match="stamps"):
        RobotMap(
            good.name,
            good.problem,
            good.stamps[:-1],
            good.pose_ids,
            good.feature_labels,
            good.feature_ids,
            0,
        )


def test_selected_inverse_matches_the_dense_inverse() -> None:
    log = simulate(load_scenario("map_joining"), 0)
    local = robot_map_from_local_map(build_local_map(log.robots["robot2"]))
    problem = local.problem
    system, dense = dense_inverse_at_estimate(problem)
    inverse = SelectedInverse(system)
    # the dense inverse's own rounding, relative to its largest entry (CPU dependent)
    atol = 1e-11 * np.abs(dense).max()
    for ids in (local.pose_ids, local.feature_ids):
        blocks = inverse.blocks(problem, ids)
        scalars = problem.scalar_indices(ids).reshape(len(ids), -1)
        expected = np.array([dense[np.ix_(s, s)] for s in scalars])
        np.testing.assert_allclose(blocks, expected, rtol=1e-8, atol=atol)
    # every entry on the factor's (filled) pattern
    pattern = system._factorization.factors()[0].tocoo()
    rows, cols = inverse.perm[pattern.row], inverse.perm[pattern.col]
    np.testing.assert_allclose(inverse.entries(rows, cols), dense[rows, cols], rtol=1e-8, atol=atol)
    # entries off the factor's pattern are refused, not invented
    far = problem.scalar_indices(local.pose_ids[[0, -1]])
    with pytest.raises(ValueError, match="pattern"):
        inverse.entries(np.array([far[0]]), np.array([far[-1]]))
