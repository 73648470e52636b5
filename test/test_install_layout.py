"""The environment is laid out as colcon lays out an ament_python package, so that
``ros2 run csam_ros <exe>`` and the ament index work where ROS 2 is installed."""

from __future__ import annotations

import os
import subprocess
import sys
import xml.etree.ElementTree as ElementTree
from pathlib import Path

import pytest

PREFIX = Path(sys.prefix)
REPO = Path(__file__).resolve().parents[1]
EXECUTABLES = [
    "simulator",
    "smoother",
    "merger",
    "recorder",
    "player",
    "foxglove_bridge",
    "detections",
    "csam",
]


def _succeeds(command: list[str]) -> None:
    """Run ``command`` in the source tree; it must exit 0."""
    result = subprocess.run(
        command, cwd=REPO, capture_output=True, text=True, timeout=120, check=False
    )
    assert result.returncode == 0, result.stderr


@pytest.fixture
def ament_prefix(monkeypatch: pytest.MonkeyPatch) -> Path:
    """AMENT_PREFIX_PATH as a ROS setup script would set it for this environment."""
    monkeypatch.setenv("AMENT_PREFIX_PATH", str(PREFIX))
    return PREFIX


def test_ament_index_finds_csam_ros_and_csam_msgs(ament_prefix: Path) -> None:
    from ament_index_python.packages import (
        get_package_prefix,
        get_package_share_directory,
        get_packages_with_prefixes,
    )

    assert Path(get_package_prefix("csam_ros")) == ament_prefix
    share = Path(get_package_share_directory("csam_ros"))
    assert share == ament_prefix / "share" / "csam_ros"
    manifest = ElementTree.parse(share / "package.xml").getroot()
    assert manifest.findtext("name") == "csam_ros"
    assert (share / "package.xml").read_text() == (REPO / "package.xml").read_text()
    packages = get_packages_with_prefixes()
    assert Path(packages["csam_msgs"]) == ament_prefix
    assert (ament_prefix / "share" / "csam_msgs" / "msg" / "LocalMap.msg").is_file()


@pytest.mark.parametrize("name", EXECUTABLES)
def test_executable_is_installed_where_ros2_run_looks(name: str) -> None:
    installed = PREFIX / "lib" / "csam_ros" / name
    assert installed.is_file(), f"{installed} is missing"
    assert os.access(installed, os.X_OK), f"{installed} is not executable"
    on_path = PREFIX / "bin" / name
    assert on_path.resolve() == installed.resolve()
    result = subprocess.run(
        [str(installed), "--help"], capture_output=True, text=True, timeout=10, check=False
    )
    assert result.returncode == 0, result.stderr
    assert "usage" in result.stdout.lower()
    assert "Traceback" not in result.stderr


def _same_files(installed: Path, source: Path, pattern: str) -> None:
    names = sorted(p.name for p in source.glob(pattern))
    assert names and sorted(p.name for p in installed.glob(pattern)) == names, installed
    for name in names:
        assert (installed / name).read_text() == (source / name).read_text(), name


def test_setup_py_installs_the_params_and_launch_files_to_the_share_folder(
    tmp_path: Path,
) -> None:
    """What colcon installs from setup.py's data_files: config/ (params files among them) and
    launch/ in share/csam_ros, where `ros2 launch csam_ros FILE` looks."""
    _succeeds([sys.executable, "setup.py", "-q", "install_data", f"--install-dir={tmp_path}"])
    share = tmp_path / "share" / "csam_ros"
    _same_files(share / "launch", REPO / "launch", "*.launch.py")
    _same_files(share / "config", REPO / "config", "*.yaml")
    assert (share / "config" / "team.params.yaml").is_file()


def test_install_layout_puts_the_config_and_launch_folders_in_the_share_folder(
    tmp_path: Path,
) -> None:
    """scripts/install_layout.sh on an environment whose executables are installed (links to
    this one's): share/csam_ros/config and share/csam_ros/launch are the source tree's."""
    venv = tmp_path / "venv"
    (venv / "lib" / "csam_ros").mkdir(parents=True)
    (venv / "bin").mkdir()
    for name in EXECUTABLES:
        (venv / "lib" / "csam_ros" / name).symlink_to(PREFIX / "lib" / "csam_ros" / name)
    _succeeds(["bash", str(REPO / "scripts" / "install_layout.sh"), str(venv)])
    share = venv / "share" / "csam_ros"
    assert (share / "launch").resolve() == REPO / "launch"
    assert (share / "config").resolve() == REPO / "config"
    _same_files(share / "launch", REPO / "launch", "*.launch.py")
    assert (share / "package.xml").read_text() == (REPO / "package.xml").read_text()
    for name in EXECUTABLES:
        assert (venv / "bin" / name).resolve() == (PREFIX / "lib" / "csam_ros" / name).resolve()
