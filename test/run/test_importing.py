"""Data sets into bags: robot numbers, a small MR.CLAM data set and a 2D SLAM file written as
new bags, and what an import refuses."""

from __future__ import annotations

from pathlib import Path

import pytest
from mrclam_files import PLAIN_CONFIG, small_dataset

from csam_ros.run.errors import RunError
from csam_ros.run.importing import import_dataset, robot_numbers
from csam_ros.run.offline import bag_contents


def test_robot_numbers_are_positive_integers() -> None:
    assert robot_numbers(None) is None and robot_numbers("") is None
    assert robot_numbers("1,3") == [1, 3]
    with pytest.raises(RunError, match="--robots: expected robot numbers such as 1,2,3"):
        robot_numbers("1,b")
    with pytest.raises(RunError, match="--robots: robot numbers start at 1, got '0,1'"):
        robot_numbers("0,1")


def test_an_mrclam_data_set_becomes_a_bag_with_its_report(tmp_path: Path) -> None:
    config = tmp_path / "plain.yaml"
    config.write_text(PLAIN_CONFIG)
    said: list[str] = []
    source = small_dataset(tmp_path / "dataset")
    count, robots = import_dataset(
        "mrclam", source, tmp_path / "bag", config=config, progress=said.append
    )
    assert robots == 2 and count > 0 and len(said) == 1
    assert bag_contents(tmp_path / "bag")[0] == ["robot1", "robot2"]
    with pytest.raises(RunError, match="bag exists: an import never overwrites a bag"):
        import_dataset("mrclam", source, tmp_path / "bag", config=config)
    with pytest.raises(RunError, match="^--config: "):
        import_dataset("mrclam", source, tmp_path / "other", config=tmp_path / "none.yaml")
    with pytest.raises(RunError, match="^--occlude: "):
        import_dataset("mrclam", source, tmp_path / "other", config=config, occlude="x")
    assert not (tmp_path / "other").exists()


def test_a_2d_slam_file_becomes_a_bag_and_takes_no_occlusion(tmp_path: Path) -> None:
    source = tmp_path / "data.txt"
    source.write_text("ODOMETRY 0 1 1 0 0 1 0 0 1 0 1\nLANDMARK 0 7 2 1 0.01 0 0.01\n")
    with pytest.raises(RunError, match="--occlude is an option of import mrclam"):
        import_dataset("slam2d", source, tmp_path / "bag", occlude="stress")
    count, robots = import_dataset("slam2d", source, tmp_path / "bag")
    assert robots == 1 and count > 0
    source.write_text("EDGE_SE2_XY 0 1 1 0 1 0 1\n")
    with pytest.raises(RunError, match="no odometry record"):
        import_dataset("slam2d", source, tmp_path / "other")
