"""Tests of the MR.CLAM importer on small files written here (and a smoke test on the data)."""

from __future__ import annotations

import json
import re
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from mrclam_files import BARCODES, LANDMARKS, clean_odometry, write_dataset
from noise_models import noise_model

from csam_ros.datasets.mrclam import (
    AUTO,
    MRCLAM_NOISE,
    MrclamFormatError,
    default_dataset_dir,
    import_mrclam,
    load_config,
)

DATASET = default_dataset_dir()
ROOT = Path(__file__).resolve().parents[2]
SEEN = ["1000.5 72 2.0 0.1"]  # a robot's one measurement (a robot without any is refused)


def test_clean_import_labels_and_truth(tmp_path: Path) -> None:
    meas = {
        1: ["1001.0 72 2.0 0.1", "1001.5 27 3.0 -0.2", "1002.0 14 1.5 0.0", "1002.5 54 2.5 0.3"],
        2: ["1001.2 72 2.1 0.1", "1001.7 70 3.5 -0.2", "1002.2 5 1.4 0.05"],
        3: ["1001.3 27 2.2 0.0", "1003.0 54 1.0 0.2"],
    }
    d = write_dataset(tmp_path / "ds", {r: clean_odometry() for r in (1, 2, 3)}, meas)
    log, report = import_mrclam(d)
    assert list(log.robots) == ["robot1", "robot2", "robot3"]
    assert report.epoch == pytest.approx(1000.0)
    truth = log.truth
    assert truth is not None
    assert sorted(truth.feature_ids.tolist()) == [6, 7, 8, 9]
    np.testing.assert_allclose(
        truth.feature_positions[truth.feature_ids.tolist().index(7)], [3, -1]
    )
    code_to_subject = {b: s for s, b in BARCODES.items()}
    for number, rows in meas.items():
        name = f"robot{number}"
        labels = truth.label_to_feature[name]
        # per-robot numbering: robot k labels the 4 landmarks k..k+3
        assert sorted(labels) == list(range(number, number + 4))
        assert sorted(labels.values()) == [6, 7, 8, 9]
        features = log.robots[name].features
        expected = [
            (float(r.split()[0]) - 1000.0, code_to_subject[int(r.split()[1])])
            for r in rows
            if code_to_subject[int(r.split()[1])] >= 6
        ]
        assert features.stamps.tolist() == pytest.approx([e[0] for e in expected])
        assert [labels[int(lab)] for lab in features.labels] == [e[1] for e in expected]
    # labels are local: the same subject gets different labels on different robots
    inverse = {name: {s: lab for lab, s in m.items()} for name, m in truth.label_to_feature.items()}
    for subject in (6, 7, 8, 9):
        assert len({inverse[name][subject] for name in inverse}) > 1
    assert log.robots["robot1"].rendezvous.observed == ["robot2"]
    assert log.robots["robot2"].rendezvous.observed == ["robot1"]
    assert report.total("feature_measurements") == 7
    assert report.total("rendezvous_measurements") == 2
    json.dumps(report.to_dict())


def test_labels_differ_between_seeds_but_are_deterministic(tmp_path: Path) -> None:
    d = write_dataset(
        tmp_path / "ds", {1: clean_odometry(), 2: clean_odometry()}, {1: SEEN, 2: SEEN}
    )
    a, _ = import_mrclam(d, label_seed=0)
    b, _ = import_mrclam(d, label_seed=0)
    c, _ = import_mrclam(d, label_seed=1)
    assert a.truth.label_to_feature == b.truth.label_to_feature
    maps = [a.truth.label_to_feature, c.truth.label_to_feature]
    assert maps[0] != maps[1]


def test_malformed_odometry_rows_counted(tmp_path: Path) -> None:
    rows = clean_odometry(n=8)
    rows[1] = "1000.500 0.1"  # wrong column count
    rows[2] = "1001.000 abc 0.0"  # non-numeric
    rows[3] = "1001.500 nan 0.0"  # NaN
    rows[4] = "1002.000 0.1 inf"  # inf
    rows.insert(5, "")  # blank line: skipped, not counted
    d = write_dataset(tmp_path / "ds", {1: rows}, {1: SEEN})
    log, report = import_mrclam(d)
    counts = report.counts["robot1"]
    assert counts["odometry_wrong_columns"] == 1
    assert counts["odometry_non_numeric"] == 1
    assert counts["odometry_non_finite"] == 2
    assert counts["odometry_rows"] == 7  # rows with 3 columns
    assert log.robots["robot1"].odometry.stamps.tolist() == pytest.approx([0, 2.5, 3.0, 3.5])
    assert any("Robot1_Odometry.dat:4" in n and "columns" in n for n in report.notes)
    assert any("Robot1_Odometry.dat:5" in n and "non-numeric" in n for n in report.notes)


def test_malformed_measurement_rows_counted(tmp_path: Path) -> None:
    meas = [
        "1001.0 72 2.0 0.1",  # good
        "1001.1 72 2.0",  # wrong column count
        "1001.2 72 x 0.1",  # non-numeric
        "1001.3 72 nan 0.1",  # NaN
        "1001.4 72 -1.0 0.1",  # negative range
        "1001.5 72 0.0 0.1",  # zero range
        "1001.55 72 1e308 0.1",  # a range of no camera (its square overflows)
        "1001.6 72.5 2.0 0.1",  # barcode not an integer
        "1001.7 72 2.0 4.0",  # bearing beyond pi
        "1001.8 43 2.0 0.1",  # misread barcode (in no table)
        "1001.9 5 2.0 0.1",  # robot1 measuring itself
        "1002.0 41 2.0 0.1",  # robot3, not selected
        "1002.1 14 2.0 0.1",  # robot2: a rendezvous measurement
        "999.0 72 2.0 0.1",  # before robot1's odometry
    ]
    d = write_dataset(
        tmp_path / "ds",
        {1: clean_odometry(), 2: clean_odometry(), 3: clean_odometry()},
        {1: meas, 2: SEEN},  # robot3, not selected, has no measurement file
    )
    log, report = import_mrclam(d, robots=[1, 2])
    expected = {
        "measurement_wrong_columns": 1,
        "measurement_non_numeric": 1,
        "measurement_non_finite": 1,
        "measurement_non_positive_range": 2,
        "measurement_range_out_of_bounds": 1,
        "measurement_bad_barcode": 1,
        "measurement_bearing_out_of_range": 1,
        "measurement_unknown_barcode": 1,
        "measurement_self": 1,
        "measurement_unselected_robot": 1,
        "measurement_outside_window": 1,
        "feature_measurements": 1,
        "rendezvous_measurements": 1,
    }
    c = report.counts["robot1"]
    assert {key: c[key] for key in expected} == expected
    robot1 = log.robots["robot1"]
    assert robot1.features.ranges.tolist() == [2.0]
    assert robot1.rendezvous.observed == ["robot2"]
    assert "Robot1_Measurement.dat:9: range beyond 1000 m" in report.notes
    assert "robot3" not in log.robots
    # epoch counts the unselected robot's files too: the measurement at 999.0 of robot1
    assert report.epoch == pytest.approx(999.0)


def test_duplicate_odometry_stamps_keep_last(tmp_path: Path) -> None:
    rows = ["1000.0 0.1 0.0", "1001.0 0.2 0.0", "1001.0 0.3 0.0", "1002.0 0.4 0.0"]
    d = write_dataset(tmp_path / "ds", {1: rows}, {1: SEEN})
    log, report = import_mrclam(d)
    odo = log.robots["robot1"].odometry
    assert report.counts["robot1"]["odometry_duplicate_stamps"] == 1
    assert odo.stamps.tolist() == [0.0, 1.0, 2.0]
    # the row applied over (1, 2] is the last row stamped 1.0
    assert odo.inputs[1:, 0].tolist() == [0.1, 0.3]


def test_out_of_order_odometry_sorted_and_counted(tmp_path: Path) -> None:
    rows = ["1000.0 0.1 0.0", "1002.0 0.3 0.0", "1001.0 0.2 0.0", "1003.0 0.4 0.0"]
    meas = ["1002.5 72 2.0 0.1", "1001.5 27 2.0 0.1"]
    d = write_dataset(tmp_path / "ds", {1: rows}, {1: meas})
    log, report = import_mrclam(d)
    c = report.counts["robot1"]
    assert c["odometry_out_of_order"] == 1
    assert c["measurement_out_of_order"] == 1
    odo = log.robots["robot1"].odometry
    assert odo.stamps.tolist() == [0.0, 1.0, 2.0, 3.0]
    assert odo.inputs[1:, 0].tolist() == [0.1, 0.2, 0.3]
    assert log.robots["robot1"].features.stamps.tolist() == [1.5, 2.5]


def integrate_distance(stamps: np.ndarray, inputs: np.ndarray) -> float:
    return float(np.sum(inputs[1:, 0] * np.diff(stamps)))


def test_constant_velocity_straight_line_distance(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    stamps = 1000.0 + np.cumsum(rng.uniform(0.005, 0.05, 400))
    rows = [f"{t:.4f} 0.25 0.0" for t in stamps]
    d = write_dataset(tmp_path / "ds", {1: rows}, {1: SEEN})
    log, _ = import_mrclam(d, start=1.0, duration=3.0)
    odo = log.robots["robot1"].odometry
    assert odo.stamps[0] == pytest.approx(1.0)
    assert odo.stamps[-1] == pytest.approx(4.0)
    assert np.all(np.diff(odo.stamps) > 0)
    assert np.all(odo.inputs[:, 1] == 0.0)  # v_lat
    assert integrate_distance(odo.stamps, odo.inputs) == pytest.approx(0.25 * 3.0)


def test_piecewise_velocity_uses_the_row_active_before_each_sample(tmp_path: Path) -> None:
    rows = ["1000.0 1.0 0.1", "1001.0 2.0 0.2", "1003.0 5.0 0.3"]
    d = write_dataset(tmp_path / "ds", {1: rows}, {1: SEEN})
    log, _ = import_mrclam(d)
    odo = log.robots["robot1"].odometry
    # the last row has no end: not extrapolated
    assert odo.stamps.tolist() == [0.0, 1.0, 3.0]
    assert integrate_distance(odo.stamps, odo.inputs) == pytest.approx(1.0 * 1 + 2.0 * 2)
    assert float(np.sum(odo.inputs[1:, 2] * np.diff(odo.stamps))) == pytest.approx(0.1 + 0.4)
    log, _ = import_mrclam(d, start=0.5, duration=2.0)
    odo = log.robots["robot1"].odometry
    assert odo.stamps.tolist() == [0.5, 1.0, 2.5]
    assert integrate_distance(odo.stamps, odo.inputs) == pytest.approx(0.5 * 1 + 1.5 * 2)


def test_noise_sigmas(tmp_path: Path) -> None:
    rows = ["1000.0 0.1 0.0", "1000.25 0.1 0.0", "1001.25 0.1 0.0"]
    d = write_dataset(tmp_path / "ds", {1: rows}, {1: ["1000.5 72 2.0 0.1"]})
    noise = noise_model((0.05, 0.02, 0.01), (0.1, 0.2, 0.3))
    log, _ = import_mrclam(d, noise=noise)
    odo = log.robots["robot1"].odometry
    np.testing.assert_allclose(odo.sigmas[1], np.array([0.1, 0.2, 0.3]) / 0.5)
    np.testing.assert_allclose(odo.sigmas[2], [0.1, 0.2, 0.3])
    features = log.robots["robot1"].features
    assert features.sigma_range.tolist() == pytest.approx([0.05 + 0.02 * 2.0])
    assert features.sigma_bearing.tolist() == pytest.approx([0.01])
    with pytest.raises(ValueError, match="sigma_bearing"):
        replace(MRCLAM_NOISE, sigma_bearing=0.0)


def test_rendezvous_to_robot_without_odometry_then(tmp_path: Path) -> None:
    d = write_dataset(
        tmp_path / "ds",
        {1: clean_odometry(), 2: clean_odometry(t0=1003.0)},
        {1: ["1001.0 14 2.0 0.1", "1004.0 14 2.0 0.1"], 2: ["1004.0 72 2.0 0.1"]},
    )
    log, report = import_mrclam(d)
    assert report.counts["robot1"]["measurement_observed_outside_window"] == 1
    assert log.robots["robot1"].rendezvous.stamps.tolist() == [4.0]


def test_bad_requests_raise_clear_errors(tmp_path: Path) -> None:
    d = write_dataset(tmp_path / "ds", {1: clean_odometry()}, {1: SEEN})
    with pytest.raises(MrclamFormatError, match=r"robots \[4\]"):
        import_mrclam(d, robots=[1, 4])
    with pytest.raises(MrclamFormatError, match="no odometry in the window"):
        import_mrclam(d, start=100.0, duration=1.0)
    with pytest.raises(ValueError, match="duration"):
        import_mrclam(d, duration=-1.0)
    with pytest.raises(MrclamFormatError, match="does not exist"):
        import_mrclam(tmp_path / "nowhere")


def test_config_file_loads() -> None:
    config = load_config(ROOT / "config" / "mrclam.yaml")
    assert config["noise"] == MRCLAM_NOISE  # the importer's default is the config's model
    assert config["landmark_swaps"] == "auto"
    assert sorted(config["range_scale"]) == [1, 2, 3, 4, 5]
    assert all(0.95 < v < 1.05 for v in config["range_scale"].values())


def test_landmark_swaps_exchange_truth_positions(tmp_path: Path) -> None:
    d = write_dataset(tmp_path / "ds", {1: clean_odometry()}, {1: SEEN})
    log, report = import_mrclam(d, landmark_swaps=[(6, 8)])
    ids = log.truth.feature_ids.tolist()
    np.testing.assert_allclose(log.truth.feature_positions[ids.index(6)], LANDMARKS[8])
    np.testing.assert_allclose(log.truth.feature_positions[ids.index(8)], LANDMARKS[6])
    np.testing.assert_allclose(log.truth.feature_positions[ids.index(7)], LANDMARKS[7])
    assert report.truth_corrections == ["true positions of landmark subjects 6 and 8 exchanged"]
    _, plain = import_mrclam(d)
    assert plain.truth_corrections == []
    with pytest.raises(ValueError, match=r"\(6, 3\)"):
        import_mrclam(d, landmark_swaps=[(6, 3)])


def test_range_scale_divides_every_range_of_that_robot(tmp_path: Path) -> None:
    meas = {1: ["1001.0 72 2.0 0.1", "1002.0 14 1.5 0.0"], 2: ["1001.2 72 2.1 0.1"]}
    d = write_dataset(tmp_path / "ds", {1: clean_odometry(), 2: clean_odometry()}, meas)
    noise = replace(MRCLAM_NOISE, sigma_range=0.05, sigma_range_per_m=0.02)
    log, report = import_mrclam(d, noise=noise, range_scale={1: 0.98})
    robot1, robot2 = log.robots["robot1"], log.robots["robot2"]
    assert robot1.features.ranges.tolist() == pytest.approx([2.0 / 0.98])
    assert robot1.rendezvous.ranges.tolist() == pytest.approx([1.5 / 0.98])
    # the sigma follows the corrected range
    assert robot1.features.sigma_range.tolist() == pytest.approx([0.05 + 0.02 * 2.0 / 0.98])
    assert robot2.features.ranges.tolist() == pytest.approx([2.1])
    assert report.range_scale == {"robot1": 0.98}
    assert report.to_dict()["range_scale"] == {"robot1": 0.98}
    assert "0.9800   1.0000  range scale" in report.summary()
    for bad, match in (
        ({4: 1.0}, "robot 4 is not in the data set"),
        ({"robot1": 1.0}, "robot 'robot1' is not in the data set"),
        ({1: 0.0}, "range_scale of robot 1 must be finite and > 0"),
        ({2: float("nan")}, "range_scale of robot 2"),
    ):
        with pytest.raises(ValueError, match=match):
            import_mrclam(d, range_scale=bad)


@pytest.mark.skipif(DATASET is None or not DATASET.is_dir(), reason="MR.CLAM Dataset 1 not present")
def test_real_dataset_imports() -> None:
    log, report = import_mrclam(DATASET)
    assert list(log.robots) == [f"robot{k}" for k in range(1, 6)]
    assert report.total("odometry_rows") == 97890 + 94826 + 97351 + 100012 + 100726
    assert report.total("measurement_unknown_barcode") == 3
    assert report.total("odometry_duplicate_stamps") == 9 + 22 + 19 + 16
    for robot in log.robots.values():
        assert 3000 < robot.features.stamps.size < 7200
        assert 700 <= robot.rendezvous.stamps.size <= 2000
        assert np.all(np.diff(robot.odometry.stamps) > 0)
    assert report.end - report.start == pytest.approx(1490.6, abs=0.1)


# Each file kind of a data set, as `csam import mrclam` sees it (the robots' own ground truth,
# RobotN_Groundtruth.dat, is not read: the data sets here do not ship it).
FILE_KINDS = [
    "Barcodes.dat",
    "Landmark_Groundtruth.dat",
    "Robot1_Odometry.dat",
    "Robot1_Measurement.dat",
]


def _import(directory: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> tuple:
    """``csam import mrclam`` in this process: exit code, stdout, stderr."""
    return _import_with(directory, tmp_path, capsys)


@pytest.mark.parametrize("damage", ["missing", "empty", "comments only"])
@pytest.mark.parametrize("name", FILE_KINDS)
def test_a_missing_or_empty_file_is_refused_by_name(
    name: str, damage: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Every file the import reads, missing or without a data row: one line naming it, exit
    code 2, no bag (an empty odometry file once died in an IndexError; a missing or empty
    measurement file was imported as a robot that saw nothing)."""
    from mrclam_files import small_dataset

    directory = small_dataset(tmp_path / "ds")
    path = directory / name
    path.unlink()
    if damage != "missing":
        path.write_text("" if damage == "empty" else "# a comment only\n")
    code, out, err = _import(directory, tmp_path, capsys)
    assert code == 2, out + err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
    why = "missing" if damage == "missing" else "no valid "
    assert err.startswith(f"csam import: {path}: {why}"), err
    if damage != "missing":
        assert "(the file is empty or holds only comments)" in err
    assert not (tmp_path / "bag").exists()


@pytest.mark.parametrize("name", FILE_KINDS)
def test_a_file_cut_inside_a_line_drops_that_line_and_says_so(
    name: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A file cut inside its last line (no newline at its end): that line is dropped, counted
    and quoted in the import's printout, never silently taken with a cut number."""
    from mrclam_files import small_dataset

    directory = small_dataset(tmp_path / "ds")
    path = directory / name
    data = path.read_bytes()
    path.write_bytes(data[:-3])  # "...0.05\n" -> "...0." : still a number
    lines = data.decode().splitlines()
    code, out, err = _import(directory, tmp_path, capsys)
    assert code == 0, err
    prefix = {
        "Barcodes.dat": "barcode",
        "Landmark_Groundtruth.dat": "landmark",
        "Robot1_Odometry.dat": "odometry",
        "Robot1_Measurement.dat": "measurement",
    }[name]
    assert f"{name}:{len(lines)}: the file ends inside this line (cut short?): dropped" in out
    if name.startswith("Robot1"):
        assert re.search(rf"^\s+1\s+0\s+{prefix}_cut_last_line$", out, re.M), out
    else:
        assert f"1 {prefix}_cut_last_line" in out, out
    _, report = import_mrclam(directory)
    counts = report.counts["robot1"] if name.startswith("Robot1") else report.table_counts
    assert counts[f"{prefix}_cut_last_line"] == 1
    whole = small_dataset(tmp_path / "whole")
    _, complete = import_mrclam(whole)
    assert complete.total(f"{prefix}_cut_last_line") == 0 and not complete.table_counts.get(
        f"{prefix}_cut_last_line"
    )


@pytest.mark.parametrize("content", ["", "# x y theta\n", "1000.0 0.0 0.0 0.0\n1000"])
def test_robot_ground_truth_files_are_not_read_and_said_so(
    content: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """RobotN_Groundtruth.dat (in the original distribution, not used here) empty, with a
    comment only or cut: the import is the same as without it, and names it as not read."""
    from mrclam_files import small_dataset

    directory = small_dataset(tmp_path / "ds")
    plain, _ = import_mrclam(directory)
    (directory / "Robot1_Groundtruth.dat").write_text(content)
    code, out, err = _import(directory, tmp_path, capsys)
    assert code == 0, err
    assert "not read: Robot1_Groundtruth.dat" in out
    log, report = import_mrclam(directory)
    assert report.unread == ["Robot1_Groundtruth.dat"]
    for name, robot in log.robots.items():
        np.testing.assert_array_equal(robot.odometry.stamps, plain.robots[name].odometry.stamps)
        np.testing.assert_array_equal(robot.features.ranges, plain.robots[name].features.ranges)


def test_a_robot_with_only_one_of_its_files_is_refused_unless_left_out(tmp_path: Path) -> None:
    """A measurement file without its odometry file names the missing file; leaving the
    robot out with ``robots`` imports the others (its barcode still counts as a robot's)."""
    from mrclam_files import small_dataset

    directory = small_dataset(tmp_path / "ds")
    (directory / "Robot2_Odometry.dat").unlink()
    with pytest.raises(MrclamFormatError, match=r"Robot2_Odometry.dat: missing \(Robot2_Meas"):
        import_mrclam(directory)
    log, report = import_mrclam(directory, robots=[1])
    assert list(log.robots) == ["robot1"]
    assert report.counts["robot1"]["measurement_unselected_robot"] == 1  # robot1 saw robot2


def _long_dataset(directory: Path) -> Path:
    """Two robots driving 400 s: robot1 sees landmark 6 every second, robot2 every 2 s (so
    robot2 sees landmarks least often); each sees the other every 10 s."""
    meas = {
        1: [f"{1000 + t:.1f} 72 2.0 0.1" for t in range(1, 400)]
        + [f"{1000 + t + 0.5:.1f} 14 1.5 0.0" for t in range(5, 400, 10)],
        2: [f"{1000 + t:.1f} 27 2.0 0.1" for t in range(1, 400, 2)]
        + [f"{1000 + t + 0.5:.1f} 5 1.5 0.0" for t in range(5, 400, 10)],
    }
    meas = {r: sorted(rows) for r, rows in meas.items()}
    return write_dataset(directory, {r: clean_odometry(n=801) for r in (1, 2)}, meas)


def test_occlusion_drops_a_robots_landmark_observations_in_its_windows(tmp_path: Path) -> None:
    """Windows [start, end) of seconds after the data set's first stamp: the robot's feature
    observations inside them are dropped and counted, its rendezvous and the other robot's
    observations kept."""
    from csam_ros.datasets.mrclam import parse_occlusion

    d = _long_dataset(tmp_path / "ds")
    plain, _ = import_mrclam(d)
    windows = parse_occlusion("1:10-20, 1:100.5-150,2:0-5")
    assert windows == [(1, 10.0, 20.0), (1, 100.5, 150.0), (2, 0.0, 5.0)]
    log, report = import_mrclam(d, occlusion=windows)
    stamps = plain.robots["robot1"].features.stamps
    hidden = ((stamps >= 10) & (stamps < 20)) | ((stamps >= 100.5) & (stamps < 150))
    assert hidden.sum() == 10 + 49
    np.testing.assert_array_equal(log.robots["robot1"].features.stamps, stamps[~hidden])
    assert report.counts["robot1"]["measurement_occluded"] == 59
    assert report.counts["robot1"]["feature_measurements"] == stamps.size - 59
    assert report.counts["robot2"]["measurement_occluded"] == 2  # at 1 s and 3 s
    for name in ("robot1", "robot2"):
        np.testing.assert_array_equal(
            log.robots[name].rendezvous.stamps, plain.robots[name].rendezvous.stamps
        )
    assert report.occlusion == {"robot1": [[10.0, 20.0], [100.5, 150.0]], "robot2": [[0.0, 5.0]]}
    assert "occluded: robot1's landmark observations in [10, 20) [100, 150) s" in report.summary()
    with pytest.raises(ValueError, match="robot 3 is not imported"):
        import_mrclam(d, occlusion=[(3, 0.0, 1.0)])


def test_the_stress_case_occludes_half_of_the_least_seeing_robots_run(tmp_path: Path) -> None:
    """'stress': the robot with the fewest landmark observations per second loses them in
    every other 90 s window from 90 s after its start (400 s: [90, 180) and [270, 360))."""
    from csam_ros.datasets.mrclam import STRESS, parse_occlusion

    d = _long_dataset(tmp_path / "ds")
    assert parse_occlusion(" stress ") == STRESS
    log, report = import_mrclam(d, occlusion=STRESS)
    assert report.occlusion == {"robot2": [[90.0, 180.0], [270.0, 360.0]]}
    assert report.counts["robot2"]["measurement_occluded"] == 90  # every 2 s over 180 s
    assert "measurement_occluded" not in report.counts["robot1"]
    seen = log.robots["robot2"].features.stamps
    assert not np.any(((seen >= 90) & (seen < 180)) | ((seen >= 270) & (seen < 360)))


@pytest.mark.parametrize(
    ("value", "message"),
    [
        ("4", "'4' is not ROBOT:START-END"),
        ("4:200-100", "'4:200-100': the window must end after it starts"),
        ("1:0-10,x", "'x' is not ROBOT:START-END"),
        ("7:0-10", "robot 7 is not imported"),
    ],
)
def test_bad_occlusion_is_one_line(
    value: str, message: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from mrclam_files import small_dataset

    code, _, err = _import_with(
        small_dataset(tmp_path / "ds"), tmp_path, capsys, "--occlude", value
    )
    assert code == 2
    assert len(err.strip().splitlines()) == 1 and err.startswith("csam import: "), err
    assert message in err, err
    assert not (tmp_path / "bag").exists()


@pytest.mark.skipif(DATASET is None or not DATASET.is_dir(), reason="MR.CLAM Dataset 1 not present")
def test_stress_case_on_the_first_200_s_of_dataset_1() -> None:
    """On a cut of the real data: robot 4 sees landmarks least often (a third as often as the
    others); its observations in [90, 180) s are dropped, nothing else changes."""
    plain, _ = import_mrclam(DATASET, duration=200.0)
    log, report = import_mrclam(DATASET, duration=200.0, occlusion="stress")
    assert list(report.occlusion) == ["robot4"]
    [[begin, end]] = report.occlusion["robot4"]
    assert begin == pytest.approx(90.0, abs=0.1) and end == pytest.approx(180.0, abs=0.1)
    stamps = plain.robots["robot4"].features.stamps
    hidden = (stamps >= begin) & (stamps < end)
    assert report.counts["robot4"]["measurement_occluded"] == hidden.sum() > 100
    np.testing.assert_array_equal(log.robots["robot4"].features.stamps, stamps[~hidden])
    for name, robot in log.robots.items():
        np.testing.assert_array_equal(robot.rendezvous.ranges, plain.robots[name].rendezvous.ranges)
        if name != "robot4":
            np.testing.assert_array_equal(robot.features.ranges, plain.robots[name].features.ranges)


def test_import_command_occludes_and_says_so(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`csam import mrclam --occlude stress` prints the robot, its windows and the count, and
    the bag holds the observations left."""
    from csam_ros.bag import read_bag

    d = _long_dataset(tmp_path / "ds")
    code, out, err = _import_with(d, tmp_path, capsys, "--occlude", "stress")
    assert code == 0, err
    assert (
        "occluded: robot2's landmark observations in [90, 180) [270, 360) s (180 s; "
        "90 dropped, its rendezvous kept)" in out
    ), out
    assert re.search(r"^\s+0\s+90\s+measurement_occluded$", out, re.M), out
    features = [m for m in read_bag(tmp_path / "bag") if m.topic == "/robot2/features"]
    assert len(features) == 200 - 90


def _import_with(
    directory: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], *extra: str
) -> tuple:
    """``csam import mrclam DIR --config <plain> --out tmp/bag *extra`` in this process: exit
    code, stdout, stderr."""
    from mrclam_files import PLAIN_CONFIG

    from csam_ros.cli import main

    config = tmp_path / "plain.yaml"
    config.write_text(PLAIN_CONFIG)
    args = ["import", "mrclam", str(directory), "--config", str(config)]
    code = main([*args, "--out", str(tmp_path / "bag"), *extra])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


@pytest.mark.skipif(DATASET is None or not DATASET.is_dir(), reason="MR.CLAM Dataset 1 not present")
def test_auto_finds_dataset_1s_swap_and_none_in_datasets_2_and_4() -> None:
    _, report = import_mrclam(DATASET, landmark_swaps=AUTO)
    (line,) = report.truth_corrections
    assert line.startswith("true positions of landmark subjects 11 and 17 exchanged (detected")
    for other in ("MRCLAM_Dataset2", "MRCLAM_Dataset4"):  # beside Dataset 1, when there
        if (DATASET.parent / other).is_dir():
            _, report = import_mrclam(DATASET.parent / other, landmark_swaps=AUTO)
            assert report.truth_corrections == [], other
