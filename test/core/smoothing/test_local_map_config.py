"""A local map's settings, checked against the fields' rules."""

import pytest

from csam_ros.core.joining.config import CsamConfig
from csam_ros.core.smoothing.local_map_config import LocalMapConfig


def test_config_values_are_checked_against_the_field_settings() -> None:
    config = LocalMapConfig.from_dict({"key_interval": 2, "robust_kernel": "huber"})
    assert config.key_interval == 2.0 and isinstance(config.key_interval, float)
    with pytest.raises(ValueError, match=r"local_map: unknown key\(s\) \['key_intervall'\]"):
        LocalMapConfig.from_dict({"key_intervall": 1.0})
    with pytest.raises(ValueError, match="local_map.batch_window: must be at least 0, got -1"):
        LocalMapConfig.from_dict({"batch_window": -1.0})
    with pytest.raises(ValueError, match="publish_period: must be greater than 0, got 0"):
        LocalMapConfig.from_dict({"publish_period": 0})
    with pytest.raises(ValueError, match="key_interval: must be finite"):
        LocalMapConfig.from_dict({"key_interval": float("inf")})
    with pytest.raises(ValueError, match="robust_kernel: 'tukey' is not one of '', 'huber'"):
        LocalMapConfig.from_dict({"robust_kernel": "tukey"})
    with pytest.raises(ValueError, match="csam.rendezvous_max_per_pair: expected a whole number"):
        CsamConfig.from_dict({"rendezvous_max_per_pair": 2.5})
    assert CsamConfig.from_dict({"rendezvous_max_per_pair": 20.0}).rendezvous_max_per_pair == 20


def test_the_converged_solves_take_the_converged_settings() -> None:
    """The converged solves (a flush, an offline build's last) take both converged settings;
    the capped online updates neither."""
    config = LocalMapConfig.from_dict(
        {"converged_step_scale": 64.0, "converged_cost_tolerance": 0.5}
    )
    options = config.options()
    assert (options.solver.max_step_scale, options.solver.cost_tolerance) == (64.0, 0.5)
    assert (options.online_solver.max_step_scale, options.online_solver.cost_tolerance) == (1, 0)
    assert LocalMapConfig().options().solver.cost_tolerance == 0.0
    with pytest.raises(ValueError, match="converged_cost_tolerance: must be at least 0"):
        LocalMapConfig.from_dict({"converged_cost_tolerance": -0.5})
