"""2D SLAM file readers: text and g2o formats give the same problem; malformed lines."""

import numpy as np
import pytest

from csam_ros.core.model import se2
from csam_ros.datasets.slam2d import Slam2dFormatError, build_problem, initial_values, read_slam2d
from csam_ros.testing.landmark_problem import build_problem as build_sim_problem
from csam_ros.testing.landmark_problem import simulate_landmark_problem


def upper(m):
    return " ".join(f"{v:.17g}" for v in m[np.triu_indices(len(m))])


def write_text(sim, path):
    lines = ["# simulated test problem"]
    for i, (z, c) in enumerate(zip(sim.odometry, sim.odometry_covariance, strict=True)):
        lines.append(f"ODOMETRY {i} {i + 1} " + " ".join(f"{v:.17g}" for v in z) + " " + upper(c))
    for p, lm, z, c in zip(
        sim.obs_pose, sim.obs_landmark, sim.obs_xy, sim.obs_covariance, strict=True
    ):
        lines.append(f"LANDMARK {p} {lm} {z[0]:.17g} {z[1]:.17g} " + upper(c))
    path.write_text("\n".join(lines) + "\n")


def write_g2o(sim, path):
    n = len(sim.initial_poses)
    lines = []
    for i, x in enumerate(sim.initial_poses):
        lines.append(f"VERTEX_SE2 {i} {x[0]:.17g} {x[1]:.17g} {x[2]:.17g}")
    for j, lm in enumerate(sim.initial_landmarks):
        lines.append(f"VERTEX_XY {n + j} {lm[0]:.17g} {lm[1]:.17g}")
    for i, (z, c) in enumerate(zip(sim.odometry, sim.odometry_covariance, strict=True)):
        m = np.eye(3)
        m[:2, :2] = se2.rotation(z[2]).T  # g2o error = M (between - z)
        info = np.linalg.inv(m @ c @ m.T)
        lines.append(
            f"EDGE_SE2 {i} {i + 1} " + " ".join(f"{v:.17g}" for v in z) + " " + upper(info)
        )
    for p, lm, z, c in zip(
        sim.obs_pose, sim.obs_landmark, sim.obs_xy, sim.obs_covariance, strict=True
    ):
        lines.append(f"EDGE_SE2_XY {p} {n + lm} {z[0]:.17g} {z[1]:.17g} " + upper(np.linalg.inv(c)))
    path.write_text("\n".join(lines) + "\n")


@pytest.fixture(scope="module")
def sim():
    return simulate_landmark_problem(80, 8, 150, seed=4, area=6.0)


def test_text_format_gives_the_simulated_problem(sim, tmp_path):
    write_text(sim, tmp_path / "sim.txt")
    data = read_slam2d(tmp_path / "sim.txt")
    assert data.format == "text"
    np.testing.assert_allclose(data.odometry, sim.odometry)
    np.testing.assert_allclose(data.observation_covariance, sim.obs_covariance)
    poses, landmarks = initial_values(data)
    # without vertices the first pose is the origin; the simulation starts at x0
    x0 = sim.initial_poses[0]
    assert x0[2] == 0.0
    np.testing.assert_allclose(poses[79], sim.initial_poses[79] - [x0[0], x0[1], 0], atol=1e-9)
    problem = build_problem(data)
    reference = build_sim_problem(sim)
    assert problem.cost() == pytest.approx(reference.cost(), rel=1e-9)
    problem.solve()
    reference.solve()
    shift = np.concatenate([np.tile([x0[0], x0[1], 0.0], 80), np.tile(x0[:2], 8)])
    np.testing.assert_allclose(problem.values, reference.values - shift, atol=1e-8)


def test_g2o_format_gives_the_same_optimum(sim, tmp_path):
    write_g2o(sim, tmp_path / "sim.g2o")
    data = read_slam2d(tmp_path / "sim.g2o")
    assert data.format == "g2o"
    assert len(data.pose_vertices) == 80 and len(data.landmark_vertices) == 8
    problem = build_problem(data)
    problem.solve()
    reference = build_sim_problem(sim)
    reference.solve()
    assert problem.cost() == pytest.approx(reference.cost(), rel=1e-9)
    n = 80
    np.testing.assert_allclose(problem.values[: 3 * n], reference.values[: 3 * n], atol=1e-8)
    lms = problem.values_of(problem.indices([("l", n + j) for j in range(8)]))
    np.testing.assert_allclose(lms, reference.values[3 * n :].reshape(-1, 2), atol=1e-8)


def test_odometry_given_backwards_initialises_by_inverse(tmp_path):
    (tmp_path / "b.txt").write_text(
        "ODOMETRY 1 0 -1 0 0 0.01 0 0 0.01 0 0.01\n"
        "ODOMETRY 1 2 1 0 1.5707963267948966 0.01 0 0 0.01 0 0.01\n"
    )
    poses, _ = initial_values(read_slam2d(tmp_path / "b.txt"))
    np.testing.assert_allclose(poses[1], [1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(poses[2], [2, 0, np.pi / 2], atol=1e-12)


@pytest.mark.parametrize(
    ("content", "message"),
    [
        ("ODOMETRY 0 1 1 0 0 1 0 0 1 0\n", r"bad.txt:1: ODOMETRY needs 11 values, got 10"),
        ("# c\n\nLANDMARK 0 3 1 x 1 0 1\n", r"bad.txt:3: LANDMARK has a non-numeric field"),
        ("ODOMETRY 0 1 1 0 0 1 0 0 1 0 -1\n", r"bad.txt:1: covariance is not positive definite"),
        ("FOO 1 2\n", r"bad.txt:1: unknown record 'FOO'"),
        ("ODOMETRY 0 1 1 0 0 1 0 0 1 0 1\nVERTEX_XY 3 0 0\n", r"bad.txt:2: VERTEX_XY mixes"),
        ("VERTEX_XY 1 0 0\nEDGE_SE2_XY 1 2 1 1 1 0 1\n", r"bad.txt:2: vertex 1 used as a pose"),
        ("LANDMARK 0 1 nan 0 1 0 1\n", r"bad.txt:1: LANDMARK has a non-finite value"),
        ("ODOMETRY 2 2 1 0 0 1 0 0 1 0 1\n", r"bad.txt:1: ODOMETRY connects pose 2 to itself"),
        ("", r"bad.txt: no records"),
        (  # beyond 64 bits: a traceback where the ids became arrays
            "ODOMETRY 0 1 1 0 0 1 0 0 1 0 1\nODOMETRY 1 100000000000000000000 1 0 0 1 0 0 1 0 1\n",
            r"bad.txt:2: ODOMETRY has an id beyond",
        ),
    ],
)
def test_malformed_lines_name_file_and_line(tmp_path, content, message):
    (tmp_path / "bad.txt").write_text(content)
    with pytest.raises(Slam2dFormatError, match=message):
        read_slam2d(tmp_path / "bad.txt")


def test_disconnected_pose_is_reported(tmp_path):
    (tmp_path / "d.txt").write_text("ODOMETRY 0 1 1 0 0 1 0 0 1 0 1\nLANDMARK 5 0 1 1 1 0 1\n")
    with pytest.raises(ValueError, match="pose 5 is not connected"):
        initial_values(read_slam2d(tmp_path / "d.txt"))


@pytest.mark.parametrize("kind", ["mcap bag", "gzip of a valid file", "text then NUL bytes"])
def test_import_of_a_binary_file_is_one_line(kind, tmp_path, capsys):
    """`csam import slam2d` given a binary file (it once ended in a UnicodeDecodeError
    traceback): one line naming the file and line, exit code 2, no bag."""
    import gzip
    from pathlib import Path

    from csam_ros.cli import main

    good = "ODOMETRY 0 1 1 0 0 1 0 0 1 0 1\nLANDMARK 0 7 2 1 0.01 0 0.01\n"
    path = tmp_path / "data.txt"
    if kind == "mcap bag":
        repo = Path(__file__).resolve().parents[2]
        path.write_bytes((repo / "bags" / "map_joining" / "bag_0.mcap").read_bytes()[:4096])
        expected = f"{path}:1: not UTF-8 text (byte 0x89 at column 1): a 2D SLAM file is text"
    elif kind == "gzip of a valid file":
        path.write_bytes(gzip.compress(good.encode()))
        expected = f"{path}:1: not UTF-8 text (byte 0x8b at column 2)"
    else:
        path.write_bytes(good.encode() + b"\x00\x00\x00\x00\n")
        expected = f"{path}:3: unknown record"
    code = main(["import", "slam2d", str(path), "--out", str(tmp_path / "bag")])
    err = capsys.readouterr().err
    assert code == 2
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
    assert err.startswith(f"csam import: {expected}"), err
    assert not (tmp_path / "bag").exists()
