"""The Fast DDS profile of live runs: set for node processes in one place, with an opt-out, and
installed with the package."""

from __future__ import annotations

import subprocess
import sys
import xml.etree.ElementTree as ElementTree
from pathlib import Path

import pytest

from csam_ros.run.ros_env import (
    DDS_PROFILE,
    DDS_PROFILE_SWITCH,
    DDS_PROFILE_VARIABLES,
    subnet_environment,
    with_dds_profile,
)

REPO = Path(__file__).resolve().parents[2]
NS = "{http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles}"


def test_the_profile_keeps_datagrams_below_the_path_mtu() -> None:
    root = ElementTree.parse(DDS_PROFILE).getroot()
    sizes = [int(e.text or "0") for e in root.iter(f"{NS}maxMessageSize")]
    assert sizes and all(0 < s <= 1500 - 20 - 8 for s in sizes)  # Ethernet MTU - IP - UDP


def test_node_environment_names_the_profile_unless_opted_out(tmp_path: Path) -> None:
    env = with_dds_profile({"PATH": "/bin"})
    assert all(env[v] == str(DDS_PROFILE.resolve()) for v in DDS_PROFILE_VARIABLES)
    assert DDS_PROFILE_VARIABLES[0] not in with_dds_profile({DDS_PROFILE_SWITCH: "off"})
    own = tmp_path / "own.xml"
    own.write_text("<dds/>")
    kept = with_dds_profile({DDS_PROFILE_VARIABLES[0]: str(own)})
    assert kept[DDS_PROFILE_VARIABLES[0]] == str(own)  # the user's profile stays
    chosen = with_dds_profile({DDS_PROFILE_SWITCH: str(own)})
    assert chosen[DDS_PROFILE_VARIABLES[1]] == str(own.resolve())
    with pytest.raises(FileNotFoundError, match="no such profile file"):
        with_dds_profile({DDS_PROFILE_SWITCH: str(tmp_path / "missing.xml")})


def test_subnet_environment_discovers_beyond_this_host() -> None:
    env = subnet_environment(17, {"ROS_LOCALHOST_ONLY": "1", "ROS_STATIC_PEERS": "x"})
    assert env["ROS_DOMAIN_ID"] == "17"
    assert env["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "SUBNET"
    assert "ROS_LOCALHOST_ONLY" not in env and "ROS_STATIC_PEERS" not in env


def test_the_package_installs_the_profile(tmp_path: Path) -> None:
    # setup.py's own install steps for the package files and data files, into tmp_path
    subprocess.run(
        [sys.executable, "setup.py", "-q", "build_py", "-d", str(tmp_path / "lib")]
        + ["install_data", "-d", str(tmp_path / "data")],
        cwd=REPO,
        check=True,
        capture_output=True,
        timeout=120,
    )
    # beside ros_env.py, where runs find it; and in share/ for nodes started by hand
    installed = tmp_path / "lib" / "csam_ros" / "run" / "fastdds_profile.xml"
    shared = tmp_path / "data" / "share" / "csam_ros" / "fastdds_profile.xml"
    assert installed.read_bytes() == shared.read_bytes() == DDS_PROFILE.read_bytes()
