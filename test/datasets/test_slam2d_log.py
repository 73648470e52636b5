"""2D SLAM file to measurement log: exact odometry inputs and covariances, Cartesian
observations with their covariance, chain errors, and the converted file through
write_log_bag and ``csam replay --offline``."""

import json
import subprocess
import sys
from dataclasses import dataclass

import numpy as np
import pytest

from csam_ros.core.model import se2
from csam_ros.core.model.motion import increment, increment_and_jacobian
from csam_ros.core.model.sensor import polar_to_cartesian
from csam_ros.core.smoothing.local_map_build import build_local_map
from csam_ros.datasets.slam2d import Slam2dFormatError, build_problem, read_slam2d
from csam_ros.datasets.slam2d_log import (
    convert_slam2d,
    input_covariances,
    inputs_from_relative_poses,
    read_slam2d_log,
)


def upper(m):
    return " ".join(f"{v:.17g}" for v in m[np.triu_indices(len(m))])


def numbers(values):
    return " ".join(f"{v:.17g}" for v in values)


@dataclass
class SimulatedFile:
    odometry: np.ndarray  # (N-1, 3) measured relative poses
    odometry_covariance: np.ndarray
    obs_pose: np.ndarray
    obs_landmark: np.ndarray
    obs_xy: np.ndarray
    obs_covariance: np.ndarray

    def write_text(self, path, pose_ids=None, landmark_ids=None):
        n = len(self.odometry) + 1
        pose_ids = np.arange(n) if pose_ids is None else pose_ids
        landmark_ids = np.arange(100) if landmark_ids is None else landmark_ids
        lines = ["# simulated single-robot run"]
        for i, (z, c) in enumerate(zip(self.odometry, self.odometry_covariance, strict=True)):
            lines.append(f"ODOMETRY {pose_ids[i]} {pose_ids[i + 1]} {numbers(z)} {upper(c)}")
        for p, lm, z, c in zip(
            self.obs_pose, self.obs_landmark, self.obs_xy, self.obs_covariance, strict=True
        ):
            lines.append(f"LANDMARK {pose_ids[p]} {landmark_ids[lm]} {numbers(z)} {upper(c)}")
        path.write_text("\n".join(lines) + "\n")

    def write_g2o(self, path, pose_ids, landmark_ids):
        lines = []
        for i, (z, c) in enumerate(zip(self.odometry, self.odometry_covariance, strict=True)):
            m = np.eye(3)
            m[:2, :2] = se2.rotation(z[2]).T  # g2o's error is M (between - z)
            info = np.linalg.inv(m @ c @ m.T)
            lines.append(f"EDGE_SE2 {pose_ids[i]} {pose_ids[i + 1]} {numbers(z)} {upper(info)}")
        for p, lm, z, c in zip(
            self.obs_pose, self.obs_landmark, self.obs_xy, self.obs_covariance, strict=True
        ):
            lines.append(
                f"EDGE_SE2_XY {pose_ids[p]} {landmark_ids[lm]} {numbers(z)} "
                f"{upper(np.linalg.inv(c))}"
            )
        path.write_text("\n".join(lines) + "\n")


def simulate(
    n_poses=40, n_landmarks=10, seed=3, odometry_cov="correlated", observation_cov="correlated"
):
    """A robot driving a loop among landmarks, measured with small noise (sample time 1 s).

    Covariances: "representable" (of the form the log carries exactly, ``G diag(q^2) G^T`` and
    ``R diag(s_r^2, r^2 s_b^2) R^T`` at the measured values), "isotropic" (observations only,
    also exact), "diagonal" (diagonal in the pose frame, as in common data sets) or
    "correlated" (random correlations).
    """
    T = 1.0
    rng = np.random.default_rng(seed)
    m = n_poses - 1
    u_true = np.column_stack(
        [
            0.5 + 0.1 * rng.standard_normal(m),
            0.05 * rng.standard_normal(m),
            2 * np.pi / (n_poses * T) + 0.1 * rng.standard_normal(m),
        ]
    )
    steps = increment(u_true, np.full(m, T))
    poses = [np.zeros(3)]
    for s in steps:
        poses.append(se2.compose(poses[-1], s))
    poses = np.array(poses)
    centre = poses[:, :2].mean(axis=0)
    angle = rng.uniform(-np.pi, np.pi, n_landmarks)
    radius = rng.uniform(1.0, 4.0, n_landmarks)
    landmarks = centre + radius[:, None] * np.column_stack([np.cos(angle), np.sin(angle)])

    if odometry_cov == "representable":
        q = np.array([0.02, 0.01, 0.01])
        u_measured = u_true + q * rng.standard_normal((m, 3))
        odometry, g = increment_and_jacobian(u_measured, np.full(m, T))
        odo_cov = np.einsum("kij,j,klj->kil", g, q**2, g)
    else:
        if odometry_cov == "diagonal":
            odo_cov = np.tile(np.diag([0.02, 0.01, 0.01]) ** 2, (m, 1, 1))
        else:
            a = 0.01 * rng.standard_normal((m, 3, 3))
            odo_cov = np.einsum("kij,klj->kil", a, a) + np.diag([2e-4, 1e-4, 1e-4])
        odometry = np.array(
            [rng.multivariate_normal(s, c) for s, c in zip(steps, odo_cov, strict=True)]
        )

    obs_pose, obs_landmark, obs_xy, obs_cov = [], [], [], []
    for k, x in enumerate(poses):
        local = se2.inverse_transform_point(x, landmarks)
        r = np.hypot(local[:, 0], local[:, 1])
        for j in np.flatnonzero(r < 4.0):
            if observation_cov == "representable":
                rb = np.array([r[j], np.arctan2(local[j, 1], local[j, 0])])
                rb += [0.03, 0.01] * rng.standard_normal(2)
                z, c = polar_to_cartesian(rb[0], rb[1], 0.03, 0.01)
                z, c = z[0], c[0]
            else:
                if observation_cov == "isotropic":
                    c = 0.02**2 * np.eye(2)
                elif observation_cov == "diagonal":
                    c = np.diag([0.03, 0.01]) ** 2
                else:
                    b = 0.02 * rng.standard_normal((2, 2))
                    c = b @ b.T + np.diag([4e-4, 1e-4])
                z = rng.multivariate_normal(local[j], c)
            obs_pose.append(k)
            obs_landmark.append(j)
            obs_xy.append(z)
            obs_cov.append(c)
    return SimulatedFile(
        odometry,
        odo_cov,
        np.array(obs_pose),
        np.array(obs_landmark),
        np.array(obs_xy),
        np.array(obs_cov),
    )


def local_map_against_file_optimum(path):
    """Solve the file as it is and the converted log's local map; both in the first pose frame."""
    data = read_slam2d(path)
    problem = build_problem(data)
    problem.solve()
    log = read_slam2d_log(path)
    local = build_local_map(log.robots["robot1"])
    pose_ids = data.pose_ids
    file_poses = problem.values_of(problem.indices([("x", int(p)) for p in pose_ids]))
    file_landmarks = problem.values_of(
        problem.indices([("l", int(m)) for m in local.landmark_labels])
    )
    return local, file_poses.reshape(-1, 3), file_landmarks.reshape(-1, 2)


def test_inputs_reproduce_relative_poses_and_covariances():
    rng = np.random.default_rng(0)
    z = np.column_stack(
        [rng.uniform(-3, 3, 300), rng.uniform(-3, 3, 300), rng.uniform(-np.pi, np.pi, 300)]
    )
    z[:20, 2] = 0.0
    z[20:40, 2] = rng.uniform(-1e-6, 1e-6, 20)  # the series branch of motion.py
    z[40, 2] = np.pi
    a = rng.standard_normal((300, 3, 3))
    lam = np.einsum("kij,klj->kil", a, a) + 0.1 * np.eye(3)
    for T in (1.0, 0.1, 2.5):
        u = inputs_from_relative_poses(z, T)
        assert u[:20, 2].tolist() == [0.0] * 20
        np.testing.assert_allclose(increment(u, np.full(300, T)), z, rtol=0, atol=1e-12)
        q = input_covariances(u, T, lam)
        _, g = increment_and_jacobian(u, np.full(300, T))
        np.testing.assert_allclose(g @ q @ g.transpose(0, 2, 1), lam, rtol=1e-10, atol=1e-12)
        assert np.all(np.linalg.eigvalsh(q) > 0)


def test_heading_is_wrapped_before_solving():
    z = np.array([[1.0, 0.5, 2 * np.pi + 0.3], [0.2, -0.1, -3 * np.pi]])
    u = inputs_from_relative_poses(z, 1.0)
    back = increment(u, np.ones(2))
    np.testing.assert_allclose(back[:, :2], z[:, :2], atol=1e-12)
    np.testing.assert_allclose(se2.wrap_angle(back[:, 2] - z[:, 2]), 0.0, atol=1e-12)
    assert np.all(np.abs(u[:, 2]) <= np.pi)


def test_representable_g2o_file_gives_the_file_optimum(tmp_path):
    sim = simulate(30, 8, seed=5, odometry_cov="representable", observation_cov="representable")
    # g2o: poses and landmarks share one id space, here interleaved
    pose_ids = 2 * np.arange(30) + 10
    landmark_ids = 2 * np.arange(8) + 11
    sim.write_g2o(tmp_path / "run.g2o", pose_ids, landmark_ids)
    local, file_poses, file_landmarks = local_map_against_file_optimum(tmp_path / "run.g2o")
    np.testing.assert_array_equal(local.stamps, np.arange(30.0))
    assert sorted(local.landmark_labels.tolist()) == sorted(set(landmark_ids[sim.obs_landmark]))
    np.testing.assert_allclose(local.poses, file_poses, atol=1e-7)
    np.testing.assert_allclose(local.landmarks, file_landmarks, atol=1e-7)


@pytest.mark.parametrize(
    ("odometry_cov", "observation_cov"),
    [("diagonal", "isotropic"), ("representable", "diagonal"), ("correlated", "correlated")],
)
def test_any_covariance_gives_the_file_optimum(tmp_path, odometry_cov, observation_cov):
    """The log carries the odometry's input covariance and the observations' 2x2 covariance
    whole (before, their correlations were dropped and the map moved by up to 1.6 sigma)."""
    sim = simulate(40, 10, seed=7, odometry_cov=odometry_cov, observation_cov=observation_cov)
    sim.write_text(tmp_path / "run.txt")
    local, file_poses, file_landmarks = local_map_against_file_optimum(tmp_path / "run.txt")
    np.testing.assert_allclose(local.poses[:, :2], file_poses[:, :2], atol=1e-7)
    np.testing.assert_allclose(se2.wrap_angle(local.poses[:, 2] - file_poses[:, 2]), 0, atol=1e-8)
    np.testing.assert_allclose(local.landmarks, file_landmarks, atol=1e-7)
    robot = read_slam2d_log(tmp_path / "run.txt").robots["robot1"]
    points = robot.points
    order = np.argsort(sim.obs_pose, kind="stable")
    np.testing.assert_array_equal(points.points, sim.obs_xy[order])
    np.testing.assert_array_equal(points.covariances, sim.obs_covariance[order])
    assert len(robot.features.stamps) == 0
    # G Q G^T of the carried input covariance gives the file's odometry covariance back
    _, g = increment_and_jacobian(robot.odometry.inputs[1:], np.ones(39))
    q = robot.odometry.covariances()[1:]
    np.testing.assert_allclose(
        g @ q @ g.transpose(0, 2, 1), sim.odometry_covariance, rtol=1e-9, atol=1e-15
    )


def test_sample_time_sets_stamps_and_inputs(tmp_path):
    sim = simulate(6, 4, seed=2)
    sim.write_text(tmp_path / "run.txt", pose_ids=np.arange(6) * 3)
    log = read_slam2d_log(tmp_path / "run.txt", robot="walker", sample_time=0.5)
    robot = log.robots["walker"]
    assert log.truth is None
    np.testing.assert_array_equal(robot.odometry.stamps, 0.5 * np.arange(6))
    np.testing.assert_allclose(
        increment(robot.odometry.inputs[1:], np.full(5, 0.5)), sim.odometry, atol=1e-12
    )
    assert np.all(robot.odometry.sigmas > 0)
    order = np.argsort(sim.obs_pose, kind="stable")
    np.testing.assert_array_equal(robot.points.stamps, 0.5 * sim.obs_pose[order])
    np.testing.assert_array_equal(robot.points.labels, sim.obs_landmark[order])


def test_observation_at_the_robot_is_kept(tmp_path):
    """A Cartesian observation needs no bearing: one at the robot centre is a factor like any."""
    path = tmp_path / "close.txt"
    c3, c2 = upper(0.01 * np.eye(3)), upper(0.01 * np.eye(2))
    path.write_text(
        f"ODOMETRY 0 1 1 0 0 {c3}\n"
        f"LANDMARK 0 7 2 0 {c2}\n"
        f"LANDMARK 1 7 0 0 {c2}\n"
        f"LANDMARK 1 8 0 -3 {c2}\n"
    )
    result = convert_slam2d(read_slam2d(path))
    assert (result.poses, result.observations) == (2, 3)
    points = result.log.robots["robot1"].points
    assert points.labels.tolist() == [7, 7, 8]
    np.testing.assert_array_equal(points.points, [[2, 0], [0, 0], [0, -3]])
    local = build_local_map(result.log.robots["robot1"])
    np.testing.assert_allclose(local.landmarks[0], [5 / 3, 0.0], atol=1e-6)  # equal weights


@pytest.mark.parametrize(
    ("records", "message"),
    [
        (["ODOMETRY 0 1", "ODOMETRY 1 2", "ODOMETRY 0 2"], r":3: odometry 0 -> 2 is not between"),
        (["ODOMETRY 0 1", "ODOMETRY 2 1"], r":2: odometry 2 -> 1 runs backwards"),
        (["ODOMETRY 0 1", "ODOMETRY 0 1"], r":2: second odometry edge 0 -> 1 .*:1\)"),
        (["ODOMETRY 0 1", "ODOMETRY 2 3"], r"no odometry from pose 1 to pose 2"),
        (["ODOMETRY 0 1", "LANDMARK 5 1"], r"no odometry from pose 1 to pose 5"),
    ],
)
def test_chain_errors_name_the_edge(tmp_path, records, message):
    c3, c2 = upper(0.01 * np.eye(3)), upper(0.01 * np.eye(2))
    lines = [f"{r} 1 0 0 {c3}" if r.startswith("ODOMETRY") else f"{r} 1 1 {c2}" for r in records]
    path = tmp_path / "bad.txt"
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(Slam2dFormatError, match=message):
        read_slam2d_log(path)


def test_bad_arguments(tmp_path):
    with pytest.raises(Slam2dFormatError, match="no such file"):
        read_slam2d_log(tmp_path / "missing.txt")
    path = tmp_path / "one.txt"
    path.write_text(f"ODOMETRY 0 1 1 0 0 {upper(np.eye(3))}\n")
    with pytest.raises(ValueError, match="sample_time"):
        read_slam2d_log(path, sample_time=0.0)


def csam(*args):
    return subprocess.run(
        [sys.executable, "-m", "csam_ros.cli", *map(str, args)],
        capture_output=True,
        text=True,
        timeout=120,
    )


def test_converted_file_replays_offline(tmp_path):
    from csam_ros.run.bag_io import write_log_bag

    sim = simulate(30, 8, seed=11)
    sim.write_text(tmp_path / "run.txt", landmark_ids=np.arange(8) + 40)
    log = read_slam2d_log(tmp_path / "run.txt")
    write_log_bag(log, tmp_path / "bag")
    run = csam("replay", tmp_path / "bag", "--offline", "--out", tmp_path / "run")
    assert run.returncode == 0, run.stderr
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert list(summary["robots"]) == ["robot1"]
    assert summary["robots"]["robot1"]["alignment"] == "reference"
    assert len(summary["robots"]["robot1"]["stamps"]) == 30
    observed = sorted({f"robot1/{lm + 40}" for lm in sim.obs_landmark})
    assert sorted(m for f in summary["features"] for m in f["members"]) == observed
    assert sum(summary["dropped"].get("robot1", {}).values()) == 0


def test_cli_import_errors_are_one_line(tmp_path):
    bad = tmp_path / "bad.txt"
    bad.write_text(f"ODOMETRY 0 1 1 0 0 {upper(np.eye(3))}\nODOMETRY 0 1 nan\n")
    run = csam("import", "slam2d", bad, "--out", tmp_path / "bag")
    assert run.returncode == 2
    assert "Traceback" not in run.stderr
    assert run.stderr.strip().count("\n") == 0
    assert f"{bad}:2" in run.stderr
    assert not (tmp_path / "bag").exists()


def test_import_keeps_the_file_covariances_in_the_bag(tmp_path):
    from csam_ros.bag import read_bag_messages
    from csam_ros.ros.conversions import LogBuilder

    sim = simulate(20, 6, seed=9)  # correlated odometry and observation covariances
    sim.write_text(tmp_path / "run.txt")
    done = csam("import", "slam2d", tmp_path / "run.txt", "--out", tmp_path / "bag")
    assert done.returncode == 0, done.stderr
    builder = LogBuilder()
    for m in read_bag_messages(tmp_path / "bag", ["/robot1/odom", "/robot1/feature_points"]):
        builder.add(m.topic, m.message)
    robot = builder.build().robots["robot1"]
    order = np.argsort(sim.obs_pose, kind="stable")
    np.testing.assert_array_equal(robot.points.points, sim.obs_xy[order])
    np.testing.assert_allclose(robot.points.covariances, sim.obs_covariance[order], rtol=1e-15)
    _, g = increment_and_jacobian(robot.odometry.inputs[1:], np.ones(19))
    q = robot.odometry.covariances()[1:]
    np.testing.assert_allclose(g @ q @ g.transpose(0, 2, 1), sim.odometry_covariance, rtol=1e-9)


def victoria_park_cut(path, poses):
    """GTSAM's Victoria Park file up to pose id ``poses`` (948 poses below 1,000) with their
    observations."""
    gtsam = pytest.importorskip("gtsam")
    source = gtsam.findExampleDataFile("victoria_park.txt")
    lines = []
    with open(source) as stream:
        for line in stream:
            fields = line.split()
            if fields and int(fields[2] if fields[0] == "ODOMETRY" else fields[1]) < poses:
                lines.append(line)
    path.write_text("".join(lines))
    return path


def test_victoria_park_cut_replays_to_gtsam_optimum(tmp_path):
    """`csam import slam2d` then `csam replay --offline` on Victoria Park up to pose id 1,000
    against GTSAM's optimum of the file's model (this project's errors written with GTSAM's
    geometry), GTSAM's Gauss-Newton started from dead reckoning: on this cut both reach the
    same minimum (measured: 3e-6 m apart); on the cut up to pose 2,000 GTSAM diverges."""
    from csam_ros.bench.smoothing import graph_from_slam2d
    from csam_ros.testing.gtsam_oracle import build_gtsam, gauss_newton, gtsam_estimate

    cut = victoria_park_cut(tmp_path / "vp.txt", 1000)
    done = csam("import", "slam2d", cut, "--out", tmp_path / "bag")
    assert done.returncode == 0, done.stderr
    done = csam("replay", tmp_path / "bag", "--offline", "--out", tmp_path / "run")
    assert done.returncode == 0, done.stderr
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    poses = np.array(summary["robots"]["robot1"]["poses_joined"])
    features = {int(f["members"][0].split("/")[1]): f["xy"] for f in summary["features"]}

    data = read_slam2d(cut)
    graph, values = build_gtsam(graph_from_slam2d(data), identical=True)
    result, iterations = gauss_newton(graph, values)
    assert iterations < 50
    gtsam_poses, gtsam_landmarks = gtsam_estimate(graph_from_slam2d(data), result)
    assert poses.shape == (len(data.pose_ids), 3)
    assert sorted(features) == data.landmark_ids.tolist()
    landmarks = np.array([features[int(i)] for i in data.landmark_ids])
    assert np.hypot(*(poses[:, :2] - gtsam_poses[:, :2]).T).max() < 1e-4
    assert np.abs(se2.wrap_angle(poses[:, 2] - gtsam_poses[:, 2])).max() < 1e-5
    assert np.hypot(*(landmarks - gtsam_landmarks).T).max() < 1e-4
