"""The noise model and its robust spread."""

from __future__ import annotations

import numpy as np
import pytest

from csam_ros.core.truth.noise_model import NEUTRAL_START, NoiseModel, robust_sigma


def test_robust_sigma_of_a_normal_sample() -> None:
    values = np.random.default_rng(0).normal(scale=0.3, size=20000)
    values[:500] = 50.0  # 2.5% gross outliers barely move it
    assert abs(robust_sigma(values) - 0.3) < 0.02


def test_noise_model_from_a_mapping_and_its_checks() -> None:
    start = NEUTRAL_START  # q = (0.02, 0.01, 0.04)
    changed = NoiseModel.from_dict({"q_v": 0.5, "sigma_bearing": "0.03"}, start)
    assert (changed.q_v, changed.sigma_bearing, changed.q_omega) == (0.5, 0.03, 0.04)
    assert changed.densities().tolist() == [0.5, 0.01, 0.04]
    with pytest.raises(ValueError, match="unknown noise keys"):
        NoiseModel.from_dict({"q_x": 1.0}, start)
    with pytest.raises(TypeError):
        NoiseModel.from_dict({"q_v": 1.0})  # no defaults: every value is required
    with pytest.raises(ValueError, match="sigma_range_per_m must be finite and >= 0"):
        NoiseModel.from_dict({"sigma_range_per_m": -0.1}, start)
    with pytest.raises(ValueError, match="q_omega must be finite and > 0"):
        NoiseModel.from_dict({"q_omega": float("nan")}, start)
