"""The launch files (launch/*.launch.py, for ``ros2 launch csam_ros FILE`` on a full ROS 2
install): valid Python with a launch description; the base station's recorder arguments; and,
where ROS 2's ``launch_ros`` is installed, each file launched as ``ros2 launch`` launches it,
its nodes answering with the params file's values."""

from __future__ import annotations

import ast
import os
import signal
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from parameter_services import Parameters, client_node

from csam_ros.ros.topics import base_station_topics
from csam_ros.run.params_files import (
    CONFIG_DIR,
    base_station_recorder_arguments,
    merger_robots,
)

REPO = Path(__file__).resolve().parents[1]
LAUNCH_DIR = REPO / "launch"
TEAM = CONFIG_DIR / "team.params.yaml"
NO_LAUNCH_ROS = (
    "ROS 2's launch_ros is not installed here (the pinned ROS 2 wheels have no launch "
    "packages; a full ROS 2 install has it): the launch files are not launched"
)


def test_the_launch_files_are_python_with_a_launch_description() -> None:
    files = sorted(LAUNCH_DIR.glob("*.launch.py"))
    assert [p.name for p in files] == ["base_station.launch.py", "robot.launch.py"]
    for path in files:
        tree = ast.parse(path.read_text(), str(path))
        compile(tree, str(path), "exec")
        functions = {node.name for node in tree.body if isinstance(node, ast.FunctionDef)}
        assert "generate_launch_description" in functions, path.name
        assert "ros2 launch csam_ros" in (ast.get_docstring(tree) or ""), path.name


def test_the_base_station_recorder_records_what_reaches_the_base_station(tmp_path: Path) -> None:
    bag = str(tmp_path / "bag")
    team = ["robot1", "robot2"]
    assert merger_robots(TEAM) == team
    assert base_station_recorder_arguments(TEAM, "", bag) == [
        "-o",
        bag,
        "--topics",
        *base_station_topics(team),
    ]
    given = base_station_recorder_arguments(TEAM, "robot3, robot4", bag)
    assert given[3:] == base_station_topics(["robot3", "robot4"])
    default = base_station_recorder_arguments(TEAM)
    assert default[1].startswith(str(Path("runs") / "base_station-"))

    empty = tmp_path / "empty.params.yaml"
    empty.write_text("/merger:\n  ros__parameters:\n    solve_period: 1.0\n")
    assert merger_robots(empty) == []
    with pytest.raises(ValueError, match="names no merger robots: give them as robots:="):
        base_station_recorder_arguments(empty)
    bad = tmp_path / "bad.params.yaml"
    bad.write_text("merger:\n  ros__parameters:\n    robots: robot1\n")
    with pytest.raises(ValueError, match="expected a list of names, got 'robot1'"):
        merger_robots(bad)
    with pytest.raises(ValueError, match="missing.params.yaml: cannot read it"):
        merger_robots(tmp_path / "missing.params.yaml")


# `ros2 launch FILE NAME:=VALUE...` without the ros2 command (ros2cli)
LAUNCH = """
import sys
from launch import LaunchService
from launch.actions import IncludeLaunchDescription
from launch.launch_description_sources import PythonLaunchDescriptionSource
path, *pairs = sys.argv[1:]
service = LaunchService(argv=pairs)
arguments = [tuple(pair.split(":=", 1)) for pair in pairs]
source = PythonLaunchDescriptionSource(path)
service.include_launch_description(IncludeLaunchDescription(source, launch_arguments=arguments))
sys.exit(service.run())
"""


class Launches:
    """Launch files launched as ``ros2 launch`` does, each in a process group of its own so
    that Ctrl-C reaches it and its nodes, as from a terminal."""

    def __init__(self, log_dir: Path) -> None:
        self.log_dir = log_dir
        self.started: list[subprocess.Popen[bytes]] = []
        # the ament index finds csam_ros's executables and share folder in this environment
        prefixes = [p for p in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p]
        self.env = {**os.environ, "AMENT_PREFIX_PATH": os.pathsep.join([sys.prefix, *prefixes])}

    def log(self, name: str) -> Path:
        return self.log_dir / f"{name}.log"

    def start(self, name: str, *arguments: str) -> subprocess.Popen[bytes]:
        """``ros2 launch csam_ros NAME ARGUMENT...`` (each argument NAME:=VALUE)."""
        with self.log(name).open("wb") as log:
            process = subprocess.Popen(
                [sys.executable, "-c", LAUNCH, str(LAUNCH_DIR / name), *arguments],
                stdout=log,
                stderr=subprocess.STDOUT,
                env=self.env,
                start_new_session=True,
            )
        self.started.append(process)
        return process

    def interrupt(self, process: subprocess.Popen[bytes]) -> int:
        """Ctrl-C to the launch and its nodes; its exit code."""
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGINT)
        return process.wait(timeout=30)

    def close(self) -> None:
        for process in self.started:
            try:
                self.interrupt(process)
            except subprocess.TimeoutExpired:
                os.killpg(process.pid, signal.SIGKILL)
                process.wait(timeout=10)


@pytest.fixture
def launches(tmp_path: Path) -> Iterator[Launches]:
    pytest.importorskip("launch_ros", reason=NO_LAUNCH_ROS)
    made = Launches(tmp_path)
    yield made
    made.close()


def _ended_cleanly(launches: Launches, name: str, process: subprocess.Popen[bytes]) -> None:
    code = launches.interrupt(process)
    log = launches.log(name).read_text(errors="replace")
    assert code == 0, log
    assert "process has finished cleanly" in log and "escalating" not in log, log


def test_the_robot_launch_file_starts_its_smoother_with_the_params_file(
    launches: Launches, ros_context: Any
) -> None:
    name = "robot.launch.py"
    process = launches.start(name, "namespace:=robot2", f"params_file:={TEAM}")
    with client_node(ros_context) as (node, executor):
        at_smoother = Parameters(node, executor, "/robot2/smoother")
        assert at_smoother.get("robot", "robots") == ["robot2", ["robot1", "robot2"]]
        at_detections = Parameters(node, executor, "/robot2/detections")
        assert at_detections.get("robot", "robot_tags") == ["robot2", ["1:robot1", "2:robot2"]]
    _ended_cleanly(launches, name, process)


def test_the_base_station_launch_file_starts_the_merger_and_its_recorder(
    launches: Launches, ros_context: Any, tmp_path: Path
) -> None:
    bag = tmp_path / "bag"
    name = "base_station.launch.py"
    process = launches.start(name, f"params_file:={TEAM}", f"bag:={bag}")
    with client_node(ros_context) as (node, executor):
        at_merger = Parameters(node, executor, "/merger")
        assert at_merger.get("robots", "solve_period") == [["robot1", "robot2"], 0.5]
        recording = Parameters(node, executor, "/recorder")
        assert recording.get("use_sim_time") == [False]
    _ended_cleanly(launches, name, process)
    assert (bag / "metadata.yaml").is_file()
