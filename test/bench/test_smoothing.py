"""The smoothing benchmark runs end to end on a small problem (numbers are printed, not
asserted)."""

import numpy as np

from csam_ros.bench import smoothing
from csam_ros.core.factors import Cauchy
from csam_ros.core.local_map import LocalMapOptions


def test_benchmark_runs_and_reports_each_solver(capsys):
    smoothing.main(
        [
            "--poses", "300", "--landmarks", "12", "--observations", "400",
            "--no-identical", "--no-victoria", "--no-online",
        ]
    )  # fmt: skip
    out = capsys.readouterr().out
    assert "== simulated: 300 poses, 12 landmarks" in out
    assert "ours " in out and "ours-splu" in out
    try:
        import gtsam  # noqa: F401
    except ImportError:
        return
    assert "gtsam-native" in out and "ratio ours / GTSAM native" in out


def test_incremental_policy_reaches_the_batch_optimum_on_a_simulated_problem():
    sim = smoothing.simulate_landmark_problem(200, 10, 300, seed=2, area=8.0)
    batch = smoothing.build_problem(sim)
    batch.solve()
    problem, iterations, _ = smoothing.solve_incremental(sim.graph(), 50, 1e-10, 50)
    assert iterations > 0
    np.testing.assert_allclose(problem.values, batch.values, atol=1e-7)


def test_graph_round_trip(tmp_path):
    g = smoothing.simulate_landmark_problem(50, 5, 60, seed=1, area=5.0).graph()
    smoothing.save_graph(g, tmp_path / "g.npz")
    h = smoothing.read_graph(tmp_path / "g.npz")
    assert h.name == g.name
    np.testing.assert_array_equal(h.obs_landmark, g.obs_landmark)
    np.testing.assert_array_equal(h.odometry_covariance, g.odometry_covariance)


def test_online_policy_ends_at_the_offline_map_and_times_the_message_work():
    log = smoothing.simulate_robot_log(duration=60.0, landmarks=10, scan_rate=5.0)[0]
    r = smoothing.online_rate(log, LocalMapOptions(robust=Cauchy()))
    assert r["updates"] > 0
    assert r["max_position_difference"] < 1e-6
    assert r["max_heading_difference"] < 1e-6
    assert r["max_landmark_difference"] < 1e-6
    assert r["rendezvous_poses"] == 2
    assert r["publish_covariances"] > 0 and r["publish_sqrt_information"] > 0
