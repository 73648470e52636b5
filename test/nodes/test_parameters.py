"""Node parameters derived from the parameter dataclasses: each field is a parameter of the node
its Setting names, with its description and range, and a YAML file reaches the nodes intact."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import pytest
from rclpy.exceptions import InvalidParameterValueException
from rclpy.node import Node
from rclpy.parameter import Parameter

from csam_ros.core.joining.config import CsamConfig
from csam_ros.core.model.config_file import load_document, settings
from csam_ros.core.smoothing.local_map_config import LocalMapConfig
from csam_ros.run.params import merger_params, smoother_params


@contextmanager
def _nodes(context: Any, merger: dict | None = None, smoother: dict | None = None) -> Iterator:
    from csam_ros.nodes.merger import Merger
    from csam_ros.nodes.smoother import Smoother

    def overrides(values: dict | None) -> list[Parameter]:
        return [Parameter(k, value=v) for k, v in (values or {}).items()]

    made: list[Node] = []
    try:
        made.append(
            Smoother(context=context, namespace="robot1", parameter_overrides=overrides(smoother))
        )
        made.append(Merger(context=context, parameter_overrides=overrides(merger)))
        yield {n.get_name(): n for n in made}
    finally:
        for node in made:
            node.destroy_node()


def test_every_config_field_is_a_parameter_of_its_node(ros_context: Any) -> None:
    with _nodes(ros_context) as nodes:
        for cls in (CsamConfig, LocalMapConfig):
            for name, (rule, default) in settings(cls).items():
                owners = [n for n, node in nodes.items() if node.has_parameter(name)]
                assert owners == ([rule.node] if rule.node else []), name
                if rule.node is None:
                    continue
                node = nodes[rule.node]
                descriptor = node.describe_parameter(name)
                assert descriptor.description == rule.description
                value = node.get_parameter(name).value
                assert type(value) is type(default), name
                if rule.minimum is not None:
                    ranges = [*descriptor.floating_point_range, *descriptor.integer_range]
                    assert [r.from_value for r in ranges] == [rule.minimum], name
        assert nodes["merger"].config == CsamConfig(skip_missing_poses=True)


def test_a_yaml_config_reaches_the_nodes_parameters(ros_context: Any) -> None:
    document = load_document("mrclam")
    csam = CsamConfig.from_dict(document["csam"])
    local_map = LocalMapConfig.from_dict(document["local_map"])
    with _nodes(ros_context, merger_params(document), smoother_params(document)) as nodes:
        merger, smoother = nodes["merger"], nodes["smoother"]
        for section, config in (("csam", csam), ("local_map", local_map)):
            for name, (rule, _) in settings(type(config)).items():
                if rule.node is not None and name in document[section]:
                    node = nodes[rule.node]
                    assert node.get_parameter(name).value == getattr(config, name), name
        # the nodes' own use of them: the merger's config and the smoother's update policy
        assert merger.config.chi2_gate == 30.0 and merger.config.rendezvous_consistency
        assert smoother.publish_period == 5.0
        assert (smoother.thinning.min_interval, smoother.thinning.max_per_pair) == (5.0, 20)
        assert smoother.map.options.robust.scale == local_map.options().robust.scale


def test_out_of_range_parameters_are_errors_naming_them(ros_context: Any) -> None:
    cases = [
        (InvalidParameterValueException, "key_interval", {"smoother": {"key_interval": -1.0}}),
        (ValueError, "chi2_gate: must be greater than 0", {"merger": {"chi2_gate": 0.0}}),
        (
            ValueError,
            "robust_kernel: 'tukey' is not one of",
            {"smoother": {"robust_kernel": "tukey"}},
        ),
    ]
    for error, message, values in cases:
        with pytest.raises(error, match=message), _nodes(ros_context, **values):
            pass
