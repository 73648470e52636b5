"""The config file written from a calibration: loads as config/mrclam.yaml does."""

from __future__ import annotations

from pathlib import Path

import pytest
from noise_models import noise_model

from csam_ros.core.model.config_file import load_document
from csam_ros.core.truth.calibration import NoiseEstimate
from csam_ros.core.truth.snapshots import OdometryNoiseEstimate, SensorNoiseEstimate
from csam_ros.datasets.mrclam import load_config
from csam_ros.datasets.mrclam_calibration import calibration_config, range_scales

BASE = Path(__file__).resolve().parents[2] / "config" / "mrclam.yaml"


def estimate() -> NoiseEstimate:
    noise = noise_model((0.0012345678, 0.0401, 0.0049), (0.025, 0.008, 0.061), (1.4, 2.1))
    return NoiseEstimate(
        noise=noise,
        first_estimate=noise,
        em={"rounds": [], "rendezvous": {"n": 10, "range_factor": 1.4, "bearing_factor": 2.1}},
        sensor=SensorNoiseEstimate(noise=noise, n_observations=100, n_snapshots=20),
        odometry=OdometryNoiseEstimate(
            q=[0.025, 0.008, 0.061], n_pairs=12, gated_fraction=0.0, median_gap_s=6.0
        ),
        landmarks={},
        seconds=1.0,
        range_scale={"robot2": (1.002, 1.001, 1.003), "robot1": (0.99, 0.98, 1.0)},
    )


def test_written_config_loads_with_the_estimate_and_the_base_sections(tmp_path: Path) -> None:
    result = estimate()
    assert range_scales(result) == {1: 0.99, 2: 1.002}
    path = tmp_path / "calibrated.yaml"
    path.write_text(calibration_config(result, BASE, "a test data set"))
    config, base = load_config(path), load_config(BASE)
    assert config["noise"].sigma_range == pytest.approx(0.0012345678, rel=1e-5)
    assert config["noise"].rendezvous_bearing_factor == 2.1
    assert config["range_scale"] == {1: 0.99, 2: 1.002}
    for key in ("robots", "start", "duration", "label_seed", "landmark_swaps"):
        assert config[key] == base[key]
    document, base_document = load_document(path), load_document(BASE)
    assert {k: v for k, v in document.items() if k != "mrclam"} == {
        k: v for k, v in base_document.items() if k != "mrclam"
    }
    text = path.read_text()
    assert "a test data set" in text
    assert "# How C-SAM runs on this data" in text  # the base's comments travel along
    assert max(len(line) for line in text.splitlines()) <= 100
