"""Params files in the ROS 2 form, one per setup, generated from the nodes' own declarations.

``config/<setup>.params.yaml`` holds a ``ros__parameters`` section for each node of a setup
(``/**/smoother`` for every robot's smoother, whatever its namespace; ``merger``;
``simulator``; ``/**/detections``), so that every node starts as ROS users start theirs::

    smoother --ros-args -r __ns:=/robot1 --params-file config/team.params.yaml
    merger --ros-args --params-file config/team.params.yaml

Each section lists every parameter its node declares, with the declaration's description
above it: the node's own table (:data:`~csam_ros.nodes.smoother.SMOOTHER_PARAMETERS`,
:data:`~csam_ros.nodes.merger_parameters.MERGER_PARAMETERS`,
:data:`~csam_ros.nodes.simulator.SIMULATOR_PARAMETERS`,
:data:`~csam_ros.nodes.detections.DETECTIONS_PARAMETERS`) and the fields of the settings
dataclasses whose Setting names the node. The setup's values come from where its runs take
them (:func:`setup_values`); a value other than the default says so. The files are written by
``python -m csam_ros.run.params_files --write`` and test/run/test_params_files.py checks that
the committed ones are what it writes.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import textwrap
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import yaml

from csam_ros.core.model import yaml_text

CONFIG_DIR = Path(__file__).resolve().parents[2] / "config"
SUFFIX = ".params.yaml"
WIDTH = 100  # the longest line written
# rclpy's own parameter of every node that the files set (TimeSource declares it)
USE_SIM_TIME = "use_sim_time"
USE_SIM_TIME_DESCRIPTION = "take the time from /clock (a simulator or a bag player publishes it)"


@dataclass(frozen=True)
class FileParameter:
    """One parameter of a node as a params file lists it."""

    name: str
    default: Any  # None: unset, of any type
    description: str
    made_at_start: str = ""  # the default is made at start from this


def _smoother() -> tuple[str, list[FileParameter]]:
    from csam_ros.core.exchange.validation import InputBounds
    from csam_ros.core.joining.config import CsamConfig
    from csam_ros.core.smoothing.local_map_config import SMOOTHER, LocalMapConfig
    from csam_ros.nodes.smoother import SMOOTHER_PARAMETERS
    from csam_ros.nodes.smoother_frames import FRAME_PARAMETERS

    own = _own(SMOOTHER_PARAMETERS + FRAME_PARAMETERS)
    return SMOOTHER, own + _settings(SMOOTHER, LocalMapConfig(), CsamConfig(), InputBounds())


def _merger() -> tuple[str, list[FileParameter]]:
    from csam_ros.core.joining.config import MERGER
    from csam_ros.nodes.merger_parameters import MERGER_CSAM_DEFAULTS, MERGER_PARAMETERS

    return MERGER, _own(MERGER_PARAMETERS) + _settings(MERGER, MERGER_CSAM_DEFAULTS)


def _simulator() -> tuple[str, list[FileParameter]]:
    from csam_ros.nodes.simulator import SIMULATOR_NODE, SIMULATOR_PARAMETERS

    return SIMULATOR_NODE, _own(SIMULATOR_PARAMETERS)


def _detections() -> tuple[str, list[FileParameter]]:
    from csam_ros.core.model.detections import DETECTIONS_NODE, DetectionModel
    from csam_ros.nodes.detections import DETECTIONS_PARAMETERS

    return DETECTIONS_NODE, _own(DETECTIONS_PARAMETERS) + _settings(
        DETECTIONS_NODE, DetectionModel()
    )


def _own(table: Sequence[Any]) -> list[FileParameter]:
    """A node's own parameters (a table of :class:`~csam_ros.nodes.common.Declared`)."""
    return [FileParameter(d.name, d.default, d.description, d.made_at_start) for d in table]


def _settings(node: str, *defaults: Any) -> list[FileParameter]:
    """The fields of settings dataclasses (their instances give the node's defaults) whose
    Setting names ``node``, as the node declares them."""
    from csam_ros.core.model.config_file import SETTING

    return [
        FileParameter(f.name, getattr(instance, f.name), f.metadata[SETTING].description)
        for instance in defaults
        for f in fields(instance)
        if f.metadata[SETTING].node == node
    ]


# each node a file may hold: its section's key (a smoother runs in its robot's namespace)
NODES: dict[str, tuple[str, Callable[[], tuple[str, list[FileParameter]]]]] = {
    "smoother": ("/**/smoother", _smoother),
    "merger": ("merger", _merger),
    "simulator": ("simulator", _simulator),
    "detections": ("/**/detections", _detections),
}


def node_parameters(node: str) -> list[FileParameter]:
    """Every parameter ``node`` declares, in its order, ``use_sim_time`` first."""
    name, parameters = NODES[node][1]()
    if name != node:
        raise ValueError(f"node {node!r} is named {name!r}")
    return [FileParameter(USE_SIM_TIME, False, USE_SIM_TIME_DESCRIPTION), *parameters]


# -- the setups ---------------------------------------------------------------------------------

DEMO_SCENARIO = "map_joining"
TEAM_ROBOTS = ["robot1", "robot2"]
TEAM_ROBOT_TAGS = ["1:robot1", "2:robot2"]  # the tag each robot carries (docs/DETECTIONS.md)


@dataclass(frozen=True)
class Setup:
    """One params file: what it is for, how its nodes start, and where its values come from."""

    name: str  # the file is config/<name>.params.yaml
    title: str
    usage: tuple[str, ...]
    values: Callable[[], dict[str, dict[str, Any]]]  # node -> parameter -> value

    @property
    def file_name(self) -> str:
        return f"{self.name}{SUFFIX}"


def _demo_values() -> dict[str, dict[str, Any]]:
    """What ``csam demo`` gives its nodes (run.demo.demo_live_run), at real time."""
    from csam_ros.datasets.scenario import load_scenario
    from csam_ros.run.demo import demo_live_run

    scenario = load_scenario(DEMO_SCENARIO)
    run = demo_live_run(DEMO_SCENARIO, Path("runs") / "demo", scenario.seed, 1.0)
    flags, values = run.source_ros_args[::2], run.source_ros_args[1::2]
    if set(flags) != {"-p"}:
        raise ValueError(f"the demo's simulator arguments are not all -p: {flags}")
    simulator = {}
    for value in values:
        name, _, text = value.partition(":=")
        simulator[name] = yaml_text.safe_load(text)
    sim_time = {USE_SIM_TIME: True}
    return {
        "simulator": {**sim_time, **simulator},
        "smoother": {**sim_time, "robots": run.robots, **run.smoother_params},
        "merger": {**sim_time, "robots": run.robots, **run.merger_params},
    }


def _mrclam_values() -> dict[str, dict[str, Any]]:
    """What ``csam replay BAG --config config/mrclam.yaml`` gives its nodes."""
    from csam_ros.core.model.config_file import load_document
    from csam_ros.datasets.mrclam import load_config
    from csam_ros.run.params import merger_params, smoother_params

    document = load_document("mrclam")
    robots = [f"robot{number}" for number in load_config("mrclam")["robots"]]
    sim_time = {USE_SIM_TIME: True}
    return {
        "smoother": {**sim_time, "robots": robots, **smoother_params(document)},
        "merger": {**sim_time, "robots": robots, **merger_params(document)},
    }


def _team_values() -> dict[str, dict[str, Any]]:
    """A real team: its robots' names and the tags they carry, every other parameter (the
    detections' sigmas among them) at its default."""
    from csam_ros.run.params import merger_params

    return {
        "detections": {"robot_tags": TEAM_ROBOT_TAGS},
        "smoother": {"robots": TEAM_ROBOTS},
        "merger": {"robots": TEAM_ROBOTS, **merger_params({})},
    }


SETUPS: tuple[Setup, ...] = (
    Setup(
        DEMO_SCENARIO,
        "The demo (config/map_joining.yaml: two robots meet between two feature areas) as "
        "`csam demo` runs it, at real time, its nodes started by hand.",
        (
            "simulator --ros-args --params-file config/map_joining.params.yaml",
            "smoother --ros-args -r __ns:=/robot1 --params-file config/map_joining.params.yaml",
            "smoother --ros-args -r __ns:=/robot2 --params-file config/map_joining.params.yaml",
            "merger --ros-args --params-file config/map_joining.params.yaml",
            "recorder -o BAG_DIR --all   (the simulator starts once it subscribes)",
        ),
        _demo_values,
    ),
    Setup(
        "mrclam",
        "UTIAS MR.CLAM Dataset 1 replayed from its bag (`csam import mrclam`), with "
        "config/mrclam.yaml's settings, as `csam replay BAG --config config/mrclam.yaml` runs it.",
        (
            "smoother --ros-args -r __ns:=/robot1 --params-file config/mrclam.params.yaml",
            "(and robot2 to robot5)",
            "merger --ros-args --params-file config/mrclam.params.yaml",
            "player BAG --rate 1",
        ),
        _mrclam_values,
    ),
    Setup(
        "team",
        "A real two-robot team, robot1 and robot2 (carrying tags 1 and 2), each on its own "
        "computer with a camera whose tag detections the detections node turns into "
        "observations, the merger on a base station: a starting point (every value but the "
        "robots' names and tags is the default; the detections' sigmas are placeholders). Copy "
        "it, then give your robots' names, tags, camera mountings, sigmas and sensors' bounds.",
        (
            "on robot1: detections --ros-args -r __ns:=/robot1 --params-file team.params.yaml",
            "           smoother --ros-args -r __ns:=/robot1 --params-file team.params.yaml",
            "on robot2: the same in /robot2",
            "on the base station: merger --ros-args --params-file team.params.yaml",
            "or: ros2 launch csam_ros robot.launch.py namespace:=robot1 (base_station.launch.py)",
        ),
        _team_values,
    ),
)


# -- writing ------------------------------------------------------------------------------------


def yaml_value(value: Any) -> str:
    """``value`` as the ROS params file parser (and YAML) reads it back with its type: floats
    always with a point (to 12 significant digits), strings quoted."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if not math.isfinite(value):
            raise ValueError(f"{value!r} cannot be a ROS parameter in a file")
        text = repr(float(f"{value:.12g}"))  # 239.99999999999997 (240 deg in rad and back): 240.0
        if "e" in text and "." not in text.split("e")[0]:
            mantissa, exponent = text.split("e")
            text = f"{mantissa}.0e{exponent}"
        return text
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, list | tuple):
        return "[" + ", ".join(yaml_value(v) for v in value) + "]"
    raise ValueError(f"{value!r}: not a ROS parameter value")


def _typed(value: Any, default: Any) -> Any:
    """``value`` with the type of the declared default (seconds given as whole numbers)."""
    if isinstance(default, float) and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    if isinstance(value, tuple):
        return list(value)
    return value


def _comment(text: str, indent: str) -> list[str]:
    return textwrap.wrap(text, WIDTH, initial_indent=f"{indent}# ", subsequent_indent=f"{indent}# ")


def node_section(node: str, values: dict[str, Any]) -> list[str]:
    """The lines of ``node``'s section: each of its parameters with its description, the
    setup's value or the default; one it has none of is an error."""
    parameters = node_parameters(node)
    unknown = sorted(set(values) - {p.name for p in parameters})
    if unknown:
        raise ValueError(f"{node} has no parameter(s) {unknown}")
    indent = "    "
    lines = [f"{NODES[node][0]}:", "  ros__parameters:"]
    for parameter in parameters:
        lines += _comment(parameter.description, indent)
        if parameter.name not in values:
            if parameter.made_at_start:
                lines.append(f"{indent}# {parameter.name}: by default {parameter.made_at_start}")
                continue
            if parameter.default is None:
                lines.append(f"{indent}# {parameter.name}: unset")
                continue
        default = parameter.default
        value = _typed(values.get(parameter.name, default), default)
        line = f"{indent}{parameter.name}: {yaml_value(value)}"
        if parameter.name in values and value != default and not parameter.made_at_start:
            shown = "unset" if default is None else yaml_value(default)
            line += f"  # default {shown}"
        lines.append(line)
    return lines


def render(setup: Setup) -> str:
    """The text of ``setup``'s params file."""
    lines = _comment(setup.title, "")
    lines += ["#"] + [f"#   {line}" for line in setup.usage] + ["#"]
    lines += _comment(
        "Generated from the nodes' parameter declarations by `python -m "
        "csam_ros.run.params_files --write` (the setups are in csam_ros/run/params_files.py): "
        "each node's every parameter, its description above it.",
        "",
    )
    for node, values in setup.values().items():
        lines += ["", *node_section(node, values)]
    return "\n".join(lines) + "\n"


def stale_files(directory: Path = CONFIG_DIR) -> list[str]:
    """The params files in ``directory`` that differ from what :func:`render` writes."""
    return [
        setup.file_name
        for setup in SETUPS
        if not (directory / setup.file_name).is_file()
        or (directory / setup.file_name).read_text() != render(setup)
    ]


def write_files(directory: Path = CONFIG_DIR) -> list[Path]:
    """Write every setup's params file into ``directory``; their paths."""
    written = []
    for setup in SETUPS:
        path = directory / setup.file_name
        path.write_text(render(setup))
        written.append(path)
    return written


# -- the launch files' use ---------------------------------------------------------------------


def merger_robots(params_file: str | Path) -> list[str]:
    """The merger's ``robots`` in a params file (its ``merger`` or ``/merger`` section; none:
    an empty list); a file that cannot be read is a ValueError naming it."""
    path = Path(params_file)
    try:
        document = yaml_text.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as error:
        raise ValueError(f"{path}: cannot read it as a params file: {error}") from None
    key = NODES["merger"][0]
    for name in (key, f"/{key}"):
        section = document.get(name) if isinstance(document, dict) else None
        if isinstance(section, dict) and isinstance(section.get("ros__parameters"), dict):
            robots = section["ros__parameters"].get("robots") or []
            if isinstance(robots, list) and all(isinstance(r, str) and r for r in robots):
                return list(robots)
            raise ValueError(f"{path}: merger robots: expected a list of names, got {robots!r}")
    return []


def base_station_recorder_arguments(
    params_file: str | Path, robots: str = "", bag: str = ""
) -> list[str]:
    """The base station recorder's arguments (launch/base_station.launch.py): ``-o BAG --topics
    ...`` of what reaches the base station from ``robots`` (comma-separated; '': the params
    file's merger robots) into ``bag`` ('': runs/base_station-<time>)."""
    from csam_ros.ros.topics import base_station_topics

    names = [r.strip() for r in robots.split(",") if r.strip()] or merger_robots(params_file)
    if not names:
        raise ValueError(
            f"{params_file} names no merger robots: give them as robots:=robot1,robot2"
        )
    out = bag or str(Path("runs") / f"base_station-{time.strftime('%Y%m%d-%H%M%S')}")
    return ["-o", out, "--topics", *base_station_topics(names)]


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m csam_ros.run.params_files",
        description="Write (--write) or check the params files config/<setup>.params.yaml "
        "from the nodes' parameter declarations.",
    )
    parser.add_argument("--write", action="store_true", help="write the files")
    parser.add_argument("--dir", type=Path, default=CONFIG_DIR, help="default: config/")
    args = parser.parse_args(argv)
    if args.write:
        for path in write_files(args.dir):
            print(f"wrote {path}")
        return 0
    stale = stale_files(args.dir)
    for name in stale:
        print(f"{args.dir / name}: differs from the declarations (--write writes it)")
    if not stale:
        print(f"{len(SETUPS)} params files in {args.dir} agree with the declarations")
    return 1 if stale else 0


if __name__ == "__main__":
    sys.exit(main())
