"""Isolated DDS discovery for tests and demo runs.

DDS discovery reaches every process on the machine that uses the same ROS_DOMAIN_ID. A test
session or a demo run keeps to itself by (1) restricting discovery to this host
(``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``, ROS 2 Jazzy) and (2) using a domain nobody else
uses. :func:`reserve_domain_id` picks such a domain and holds it for as long as the returned
reservation is open, by binding TCP port ``32768 + id`` (the scheme of ROS 2's
``domain_coordinator``, so it also coordinates with ROS tooling that uses it). Domains whose
DDS ports are already bound on this machine (a participant from any other program) are
skipped. No ROS import here: this runs before rclpy is initialised.

Usage::

    with reserve_domain_id() as reservation:
        env = isolated_environment(reservation.domain_id)
        subprocess.run(["smoother", ...], env=env)
"""

from __future__ import annotations

import os
import random
import socket
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

from csam_ros.closing import Closing

COORDINATION_PORT_BASE = 32768  # domain_coordinator's scheme: hold port base + domain id
DOMAIN_IDS = range(1, 101)  # domain_coordinator's range; all valid DDS domains on Linux
# RTPS well-known ports (DDSI-RTPS 2.x, sec. 9.6.1.1): PB + DG * domain + offsets < DG
RTPS_PORT_BASE = 7400
RTPS_DOMAIN_GAIN = 250


@dataclass
class DomainReservation(Closing):
    """A ROS domain id held for this process until :meth:`release` (or the end of ``with``)."""

    domain_id: int
    _socket: socket.socket | None = field(default=None, repr=False)

    def release(self) -> None:
        """Give the domain id back."""
        if self._socket is not None:
            self._socket.close()
            self._socket = None

    close = release


def _bound_udp_ports() -> set[int]:
    """Local UDP ports bound on this machine (Linux /proc), empty where unavailable."""
    ports: set[int] = set()
    for table in ("/proc/net/udp", "/proc/net/udp6"):
        try:
            lines = Path(table).read_text().splitlines()[1:]
        except OSError:
            continue
        for line in lines:
            local = line.split()[1]  # "ADDR:PORT" in hex
            ports.add(int(local.rsplit(":", 1)[1], 16))
    return ports


def domain_in_use(domain_id: int, bound_ports: set[int] | None = None) -> bool:
    """Whether any DDS participant on this machine has bound a port of ``domain_id``."""
    ports = _bound_udp_ports() if bound_ports is None else bound_ports
    first = RTPS_PORT_BASE + RTPS_DOMAIN_GAIN * domain_id
    return any(first <= port < first + RTPS_DOMAIN_GAIN for port in ports)


def reserve_domain_id(rng: random.Random | None = None) -> DomainReservation:
    """Reserve a ROS_DOMAIN_ID in 1..100 that no other reservation and no DDS participant on
    this machine uses. Raises RuntimeError when all are taken."""
    candidates = list(DOMAIN_IDS)
    (rng or random.Random()).shuffle(candidates)
    bound = _bound_udp_ports()
    for domain_id in candidates:
        if domain_in_use(domain_id, bound):
            continue
        sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        try:
            sock.bind(("", COORDINATION_PORT_BASE + domain_id))
        except OSError:
            sock.close()
            continue
        return DomainReservation(domain_id, sock)
    raise RuntimeError(
        f"no free ROS_DOMAIN_ID in {DOMAIN_IDS.start}..{DOMAIN_IDS.stop - 1}: all are reserved "
        "or have DDS participants on this machine"
    )


def isolated_environment(domain_id: int, base: Mapping[str, str] | None = None) -> dict[str, str]:
    """A copy of ``base`` (default: os.environ) with discovery limited to this host and to
    ``domain_id``; pass it as ``env=`` to node subprocesses."""
    if not 0 <= domain_id <= 232:
        raise ValueError(f"domain_id must be in 0..232 (DDS port range), got {domain_id}")
    env = dict(os.environ if base is None else base)
    env["ROS_DOMAIN_ID"] = str(domain_id)
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    env.pop("ROS_STATIC_PEERS", None)
    env.pop("ROS_LOCALHOST_ONLY", None)  # deprecated in Jazzy; conflicts with the range above
    return env


def isolate_this_process(domain_id: int) -> None:
    """Set the isolation variables in os.environ; call before rclpy.init()."""
    isolated = isolated_environment(domain_id)
    for key in set(os.environ) - set(isolated):
        del os.environ[key]
    os.environ.update(isolated)


# The Fast DDS transport live runs use (see the file): datagrams below the path MTU, so that a
# lost packet costs one resent fragment, not the whole sample
DDS_PROFILE = Path(__file__).with_name("fastdds_profile.xml")
DDS_PROFILE_VARIABLES = ("FASTRTPS_DEFAULT_PROFILES_FILE", "FASTDDS_DEFAULT_PROFILES_FILE")
DDS_PROFILE_SWITCH = "CSAM_DDS_PROFILE"  # "off": Fast DDS's defaults; a path: that profile


def with_dds_profile(env: Mapping[str, str]) -> dict[str, str]:
    """A copy of ``env`` for node processes, with the shipped Fast DDS profile: unless
    ``CSAM_DDS_PROFILE=off``, or a profile is already named there (kept as it is);
    ``CSAM_DDS_PROFILE=FILE`` names another one."""
    out = dict(env)
    choice = out.get(DDS_PROFILE_SWITCH, "").strip()
    if choice.lower() == "off" or any(out.get(v) for v in DDS_PROFILE_VARIABLES):
        return out
    profile = Path(choice) if choice else DDS_PROFILE
    if not profile.is_file():
        raise FileNotFoundError(f"{DDS_PROFILE_SWITCH}: no such profile file {profile}")
    for variable in DDS_PROFILE_VARIABLES:
        out[variable] = str(profile.resolve())
    return out


def subnet_environment(domain_id: int, base: Mapping[str, str] | None = None) -> dict[str, str]:
    """A copy of ``base`` (default: os.environ) on ``domain_id`` with discovery over the
    subnet: nodes on several hosts (or network namespaces) find each other by multicast."""
    env = isolated_environment(domain_id, base)
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "SUBNET"
    return env
