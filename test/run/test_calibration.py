"""Calibration's checks before any estimate: it never overwrites a file, needs a data set
directory, at least one round and a readable config; data it cannot estimate from is named
(the estimate itself: test_cli and test/datasets with MR.CLAM Dataset 1)."""

from __future__ import annotations

from pathlib import Path

import pytest

from csam_ros.run.calibration import calibrate_dataset
from csam_ros.run.errors import RunError


def test_what_calibrate_refuses_is_one_run_error(tmp_path: Path) -> None:
    taken = tmp_path / "taken.yaml"
    taken.write_text("mine")
    said: list[str] = []
    for args, message in (
        ((tmp_path, taken), "taken.yaml exists: calibrate never overwrites a file"),
        ((tmp_path / "nowhere", tmp_path / "c.yaml"), "nowhere: no such data set directory"),
    ):
        with pytest.raises(RunError, match=message):
            calibrate_dataset(*args, progress=said.append)
    with pytest.raises(RunError, match="--rounds must be at least 1, got 0"):
        calibrate_dataset(tmp_path, tmp_path / "c.yaml", rounds=0)
    with pytest.raises(RunError, match="^--config: "):
        calibrate_dataset(tmp_path, tmp_path / "c.yaml", config=tmp_path / "none.yaml")
    with pytest.raises(RunError, match="^--robots: "):
        calibrate_dataset(tmp_path, tmp_path / "c.yaml", robots="a")
    assert taken.read_text() == "mine" and not (tmp_path / "c.yaml").exists() and not said


def test_data_the_estimate_cannot_use_is_one_run_error_naming_the_data_set(
    tmp_path: Path,
) -> None:
    """Too little data for an estimate (numbers the noise model refuses, or a singular
    system): the error names the data set, not only the numbers."""
    from mrclam_files import small_dataset

    source = small_dataset(tmp_path / "small")
    with pytest.raises(RunError, match=f"^{source}: no calibration from this data "):
        calibrate_dataset(source, tmp_path / "c.yaml", progress=lambda line: None)
    assert not (tmp_path / "c.yaml").exists()
