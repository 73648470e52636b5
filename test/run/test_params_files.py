"""The params files config/<setup>.params.yaml: the committed ones are what the nodes'
declarations write, their values are the setups', and real nodes started with them take every
value and declare nothing the files leave out."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest
import yaml

from csam_ros.core.model.config_file import load_document
from csam_ros.run.params import merger_params, smoother_params
from csam_ros.run.params_files import (
    CONFIG_DIR,
    NODES,
    SETUPS,
    main,
    node_parameters,
    render,
    yaml_value,
)

RCLPY_OWN = {"start_type_description_service"}  # declared by rclpy, left at its default


def _sections(path: Path) -> dict[str, dict[str, Any]]:
    """node -> its ros__parameters in the params file at ``path`` (read as YAML)."""
    document = yaml.safe_load(path.read_text())
    keys = {key: node for node, (key, _) in NODES.items()}
    assert set(document) <= set(keys), sorted(document)
    return {keys[key]: section["ros__parameters"] for key, section in document.items()}


def test_the_committed_params_files_are_what_the_declarations_write(
    capsys: pytest.CaptureFixture[str],
) -> None:
    for setup in SETUPS:
        committed = (CONFIG_DIR / setup.file_name).read_text()
        assert committed == render(setup), (
            f"config/{setup.file_name} is out of step with the nodes' declarations: "
            "python -m csam_ros.run.params_files --write"
        )
    assert main([]) == 0
    assert "3 params files in" in capsys.readouterr().out


def test_write_writes_every_file_and_the_check_names_a_stale_one(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["--dir", str(tmp_path)]) == 1  # none written yet
    assert main(["--write", "--dir", str(tmp_path)]) == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(s.file_name for s in SETUPS)
    for setup in SETUPS:
        assert (tmp_path / setup.file_name).read_text() == render(setup)
    team = tmp_path / "team.params.yaml"
    team.write_text(team.read_text().replace("solve_period: 0.5", "solve_period: 0.7"))
    capsys.readouterr()
    assert main(["--dir", str(tmp_path)]) == 1
    assert capsys.readouterr().out == (
        f"{team}: differs from the declarations (--write writes it)\n"
    )


@pytest.mark.parametrize(
    "value", [0.0, 1.0, 9.21, 1e-6, 1e-10, 1e6, 2.5e-300, -3.0, 7, -1, True, "", "a'b\"c"]
)
def test_values_are_written_so_that_they_read_back_with_their_type(value: Any) -> None:
    text = yaml_value(value)
    back = yaml.safe_load(f"x: {text}")["x"]
    assert back == value and type(back) is type(value), text
    assert yaml.safe_load(yaml_value([value, value])) == [value, value]


def test_a_float_is_written_to_twelve_significant_digits() -> None:
    assert yaml_value(239.99999999999997) == "240.0"  # 240 deg to radians and back
    with pytest.raises(ValueError, match="cannot be a ROS parameter"):
        yaml_value(float("inf"))


def test_each_file_holds_its_setups_values_and_every_other_parameter_at_its_default() -> None:
    for setup in SETUPS:
        sections = _sections(CONFIG_DIR / setup.file_name)
        values = setup.values()
        assert set(sections) == set(values), setup.name
        for node, given in values.items():
            section = sections[node]
            for parameter in node_parameters(node):
                if parameter.name in given:
                    expected = given[parameter.name]
                    if isinstance(expected, float):  # to 12 significant digits
                        expected = pytest.approx(expected, rel=1e-12)
                    elif isinstance(expected, tuple):
                        expected = list(expected)
                    assert section[parameter.name] == expected, (setup.name, parameter.name)
                elif parameter.made_at_start or parameter.default is None:
                    assert parameter.name not in section, parameter.name
                else:
                    assert section[parameter.name] == parameter.default, parameter.name


def test_the_mrclam_and_demo_files_take_what_their_runs_give_the_nodes() -> None:
    """MR.CLAM: config/mrclam.yaml's sections as `csam replay --config` splits them; the demo:
    the scenario's robots, its sensors' field of view, its seed."""
    mrclam = _sections(CONFIG_DIR / "mrclam.params.yaml")
    document = load_document("mrclam")
    for name, value in merger_params(document).items():
        assert mrclam["merger"][name] == value, name
    for name, value in smoother_params(document).items():
        assert mrclam["smoother"][name] == value, name
    assert mrclam["merger"]["chi2_gate"] == 30.0 and mrclam["smoother"]["publish_period"] == 5.0
    robots = [f"robot{n}" for n in range(1, 6)]
    assert mrclam["merger"]["robots"] == robots == mrclam["smoother"]["robots"]
    demo = _sections(CONFIG_DIR / "map_joining.params.yaml")
    assert demo["smoother"]["field_of_view_deg"] == 240.0
    assert demo["simulator"]["scenario"] == "map_joining" and demo["simulator"]["seed"] == 1
    assert demo["merger"]["robots"] == ["robot1", "robot2"]
    assert {s["use_sim_time"] for s in demo.values()} == {True}
    team = _sections(CONFIG_DIR / "team.params.yaml")
    assert team["merger"]["robots"] == ["robot1", "robot2"] == team["smoother"]["robots"]
    assert team["detections"]["robot_tags"] == ["1:robot1", "2:robot2"]
    assert team["detections"]["sigma_range_base"] == 0.02  # the default sigmas
    assert {s["use_sim_time"] for s in team.values()} == {False}


@contextmanager
def _node_with_file(node: str, path: Path, *extra: str) -> Iterator[Any]:
    """``node`` made in a context of its own started with ``--ros-args --params-file path``."""
    import rclpy
    from rclpy.context import Context

    from csam_ros.nodes.detections import Detections
    from csam_ros.nodes.merger import Merger
    from csam_ros.nodes.simulator import Simulator
    from csam_ros.nodes.smoother import Smoother

    context = Context()
    rclpy.init(args=["csam", "--ros-args", "--params-file", str(path), *extra], context=context)
    made = None
    try:
        if node == "smoother":
            made = Smoother(context=context, namespace="robot1")
        elif node == "merger":
            made = Merger(context=context)
        elif node == "detections":
            made = Detections(context=context, namespace="robot1")
        else:
            made = Simulator(context=context)
        yield made
    finally:
        if made is not None:
            made.destroy_node()
        rclpy.try_shutdown(context=context)


@pytest.mark.parametrize("setup", SETUPS, ids=lambda s: s.name)
def test_real_nodes_take_every_value_of_their_section(setup: Any, ros_domain: int) -> None:
    """Each node of the file, made with ``--params-file``, holds each value of its section,
    declares no parameter the section leaves out (but those made at start), and is given
    none it does not declare."""
    from csam_ros.nodes.common import UNKNOWN_PARAMETER, given_parameters

    path = CONFIG_DIR / setup.file_name
    for node, section in _sections(path).items():
        made_at_start = {p.name for p in node_parameters(node) if p.made_at_start}
        with _node_with_file(node, path) as made:
            declared = set(made.get_parameters_by_prefix("")) - RCLPY_OWN
            assert declared == set(section) | (made_at_start - set(section)), node
            for name, value in section.items():
                assert made.get_parameter(name).value == value, (node, name)
            assert set(given_parameters(made)) == set(section), node
            drops = getattr(made, "drops", None)
            assert drops is None or UNKNOWN_PARAMETER not in drops.as_dict()
            if node == "smoother":
                assert made.robot == "robot1" and made.publish_period == section["publish_period"]
            if node == "detections":
                assert made.robot == "robot1" and made.model.sigma_bearing == 0.01
                assert made.robot_tags == {1: "robot1", 2: "robot2"}
            if node == "merger":
                assert made.config.chi2_gate == section["chi2_gate"]
                assert made.policy.settings.robots == tuple(section["robots"])
