"""The settings of C-SAM: read from scenario and parameter files, errors naming the key,
and the options of each step derived from them."""

from __future__ import annotations

import pytest

from csam_ros.core.joining.config import MERGER, CsamConfig
from csam_ros.core.model.config_file import settings
from csam_ros.core.sam.factors import Cauchy
from csam_ros.core.smoothing.local_map_config import SMOOTHER, LocalMapConfig
from csam_ros.datasets.scenario import load_document


def test_config_from_file_and_errors() -> None:
    config = CsamConfig.from_dict(load_document("map_joining")["csam"])
    assert config.chi2_gate == pytest.approx(9.21)
    with pytest.raises(ValueError, match="chi2_gat"):
        CsamConfig.from_dict({"chi2_gat": 9.0})
    with pytest.raises(ValueError, match="chi2_gate"):
        CsamConfig.from_dict({"chi2_gate": -1})
    with pytest.raises(ValueError, match="associate"):
        CsamConfig.from_dict({"associate": "yes"})


def test_real_data_settings_and_errors() -> None:
    document = load_document("mrclam")
    config = CsamConfig.from_dict(document["csam"])
    assert config.rendezvous_consistency and config.thinning().max_per_pair == 20
    assert config.solver_options().relative_tolerance == 1e-5  # the robust cost creeps
    assert CsamConfig.from_dict({"rendezvous_max_per_pair": 0}).thinning().max_per_pair is None
    with pytest.raises(ValueError, match="rendezvous_min_interval"):
        CsamConfig.from_dict({"rendezvous_min_interval": -1.0})
    with pytest.raises(ValueError, match="max_step_scale: must be at least 1"):
        CsamConfig.from_dict({"max_step_scale": 0.5})
    local = LocalMapConfig.from_dict(document["local_map"])
    assert isinstance(local.options().robust, Cauchy) and local.window == 10.0
    assert local.options().robust.scale == 1.0
    assert LocalMapConfig.from_dict({"batch_window": 0}).window is None
    with pytest.raises(ValueError, match="robust_kernel"):
        LocalMapConfig.from_dict({"robust_kernel": "tukey"})
    with pytest.raises(ValueError, match="key_intervall"):
        LocalMapConfig.from_dict({"key_intervall": 1.0})
    with pytest.raises(ValueError, match="batch_window"):
        LocalMapConfig.from_dict({"batch_window": "long"})


def test_each_step_takes_its_options_from_the_settings() -> None:
    config = CsamConfig(
        max_heading_sigma_deg=10.0,
        max_iterations=7,
        step_tolerance=1e-5,
        relative_tolerance=1e-4,
        max_step_scale=2.0,
        max_feature_outliers=0.5,
    )
    alignment = config.alignment_options()
    assert alignment.max_heading_sigma == pytest.approx(0.17453292519943295)
    assert (alignment.max_iterations, alignment.step_tolerance) == (7, 1e-5)
    assert alignment.relative_tolerance == 1e-4
    solver = config.solver_options()
    assert (solver.max_iterations, solver.step_tolerance, solver.max_step_scale) == (7, 1e-5, 2.0)
    assert config.consistency_options().max_feature_outliers == 0.5


def test_the_thinning_is_the_smoothers_and_the_rest_the_mergers() -> None:
    """The rendezvous thinning decides where the local maps hold poses: the smoothers take it;
    every other setting is a parameter of the merger."""
    nodes = {name: setting.node for name, (setting, _) in settings(CsamConfig).items()}
    assert {n for n, node in nodes.items() if node == SMOOTHER} == {
        "rendezvous_min_interval",
        "rendezvous_max_per_pair",
    }
    assert set(nodes.values()) == {SMOOTHER, MERGER}
