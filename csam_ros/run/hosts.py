"""Robots on their own hosts: ``csam demo --hosts``.

Each robot and the base station get a network namespace of their own (a "host"), joined by a
Linux bridge in a further namespace (the "switch"); nothing is added to the caller's network,
and deleting the namespaces removes everything. Every robot host runs a simulator of the same
scenario and seed that publishes only its robot's topics, the robot's smoother and a recorder
of its own topics (``bag_<robot>/``: its raw data never crosses the link); the base station
runs the merger, the recorder of what reaches it (the merger's inputs and the global topics,
``bag/``) and the run monitor. Nodes find each other by
multicast discovery over the subnet on one ROS domain.

Sim time has one source: the first robot's simulator publishes /clock (and the features'
truth); every other node follows it across the links. Several /clock publishers would each
pace their own timeline, and nodes would see time jump back and forth between them.

The run ends over ROS: when every simulator has published its data, the monitor (on the
base station) calls each smoother's ``~/flush`` across the links, then the merger's, waits for
the merger's joined map of those final local maps, and writes what it saw to ``hosts.json``.

Link faults (:class:`Links`): every IP packet a host receives over its link is dropped with
probability ``loss`` (iptables' ``statistic`` match in the raw table, before reassembly, so a
lost fragment is lost alone, as on a radio link); ``kbit_s`` caps each link's rate both ways
(a token bucket, ``tc qdisc tbf``, with 400 ms of queue), ``base_kbit_s`` the base station's
link alone (the one link every robot's data shares); ``cut`` takes one host's link
down (its bridge port) over a window of the run and restores it: what it sends meanwhile is
lost without an error, as out of radio range. In simulation the cut host also loses /clock,
so its nodes pause until the link returns (real robots keep their own clocks). Needs root,
``ip``, for loss ``iptables`` and for a rate ``tc``.

Discovery crosses the links too: every process tells every other of each of its endpoints.
So the nodes run without /rosout and the type description service, a robot's recorder
discovers only its own host, and where the base station's link has a rate limit the run's
Fast DDS profile (:func:`link_profile`, in the run folder) sends endpoint announcements and
/clock by multicast and repeats announcements less often.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import secrets
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path

from csam_ros.core.joining.result import RunSummary
from csam_ros.run.launch import ProcessGroup
from csam_ros.run.live import (
    LiveRun,
    LiveRunError,
    MarkersAfterJoined,
    end_of_data,
    joined_map_is_final,
    recorder_holds_results,
    ros_params,
    smoother_drops,
)
from csam_ros.run.ros_env import (
    DDS_PROFILE_VARIABLES,
    reserve_domain_id,
    subnet_environment,
    with_dds_profile,
)

BASE = "base"
PREFIX = "csam-"  # namespace names: csam-<pid>-<tag>-<host>
SUBNET = "10.231.0"  # each run has its own bridge, so runs never share this subnet
MONITOR_READY = "base_ready"  # file the monitor writes when it reaches every smoother
MONITOR_END = "end_of_data"  # file the run writes when every simulator is done
MONITOR_RESULT = "hosts.json"


class HostsError(RuntimeError):
    """Network namespaces cannot be made here (not root, or a tool is missing)."""


@dataclass(frozen=True)
class Links:
    """The faults of every host's link."""

    loss: float = 0.0  # probability that a packet is dropped on receipt
    kbit_s: float = 0.0  # rate limit each way (0: none)
    # (host, start, end): that host's link cut from start to end s after the data starts
    cut: tuple[str, float, float] | None = None
    # the base station's link alone (0: kbit_s): the link all the robots' data shares
    base_kbit_s: float = 0.0

    def __post_init__(self) -> None:
        if not 0.0 <= self.loss < 1.0:
            raise ValueError(f"loss must be in [0, 1), got {self.loss}")
        if not self.kbit_s >= 0:
            raise ValueError(f"the link rate must be >= 0 kbit/s, got {self.kbit_s}")
        if not self.base_kbit_s >= 0:
            raise ValueError(f"the base link rate must be >= 0 kbit/s, got {self.base_kbit_s}")
        if self.cut is not None and not 0 <= self.cut[1] < self.cut[2]:
            raise ValueError(f"a link cut needs 0 <= start < end, got {self.cut[1:]}")

    def rate_of(self, host: str) -> float:
        """The rate limit of ``host``'s link in kbit/s each way (0: none)."""
        return self.base_kbit_s if host == BASE and self.base_kbit_s else self.kbit_s

    def __str__(self) -> str:
        rate = f", {self.kbit_s:g} kbit/s each way" if self.kbit_s else ""
        if self.base_kbit_s:
            rate += f", the base station's link {self.base_kbit_s:g} kbit/s each way"
        cut = ""
        if self.cut is not None:
            host, start, end = self.cut
            cut = f", {host}'s link cut from {start:g} to {end:g} s after the data starts"
        return f"{self.loss:.0%} packet loss{rate}{cut}"


def missing_requirements(links: Links = Links()) -> str | None:
    """Why namespaces with these links cannot be made here, or None when they can."""
    if os.geteuid() != 0:
        return "network namespaces need root"
    if shutil.which("ip") is None:
        return "no `ip` command (iproute2)"
    if links.loss > 0 and shutil.which("iptables") is None:
        return "no `iptables` command for the link loss (Debian: apt-get install iptables)"
    if (links.kbit_s > 0 or links.base_kbit_s > 0) and shutil.which("tc") is None:
        return "no `tc` command for the link rate (iproute2)"
    return None


def _ip(*args: str, check: bool = True) -> subprocess.CompletedProcess[str]:
    result = subprocess.run(["ip", *args], capture_output=True, text=True, check=False)
    if check and result.returncode != 0:
        raise HostsError(f"ip {' '.join(args)}: {result.stderr.strip()}")
    return result


def _in(namespace: str, *argv: str) -> None:
    result = subprocess.run(
        ["ip", "netns", "exec", namespace, *argv], capture_output=True, text=True, check=False
    )
    if result.returncode != 0:
        raise HostsError(f"{namespace}: {' '.join(argv)}: {result.stderr.strip()}")


@dataclass
class Network:
    """Hosts (network namespaces) on one bridge; ``namespaces[host]``, ``addresses[host]``."""

    tag: str
    hosts: list[str]
    links: Links = Links()
    namespaces: dict[str, str] = field(default_factory=dict)
    addresses: dict[str, str] = field(default_factory=dict)
    ports: dict[str, str] = field(default_factory=dict)  # each host's port on the bridge

    def set_link(self, host: str, up: bool) -> None:
        """Connect or cut ``host``'s link (its bridge port up or down; what it sends
        meanwhile is lost without an error, as over a radio link out of range)."""
        _in(self.switch, "ip", "link", "set", self.ports[host], "up" if up else "down")

    @property
    def switch(self) -> str:
        return f"{PREFIX}{self.tag}-switch"

    def all_namespaces(self) -> list[str]:
        return [self.switch, *self.namespaces.values()]

    def command(self, host: str, argv: list[str]) -> list[str]:
        """``argv`` run on ``host`` (``ip netns exec`` replaces itself with the command)."""
        return ["ip", "netns", "exec", self.namespaces[host], *argv]


def remove_stale_namespaces() -> list[str]:
    """Delete the namespaces of runs whose process is gone (killed before cleaning up)."""
    listed = _ip("netns", "list", check=False).stdout.split()
    removed = []
    for name in listed:
        parts = name.split("-")
        if not name.startswith(PREFIX) or len(parts) < 4 or not parts[1].isdigit():
            continue
        if not Path(f"/proc/{parts[1]}").exists():
            _ip("netns", "delete", name, check=False)
            removed.append(name)
    return removed


def create_network(hosts: list[str], links: Links = Links()) -> Network:
    """Namespaces for ``hosts`` on one bridge, each with ``links``' faults on its link;
    :func:`delete_network` deletes it (this does when it fails)."""
    net = Network(f"{os.getpid()}-{secrets.token_hex(3)}", hosts, links)
    try:
        _connect(net)
    except BaseException:
        delete_network(net)
        raise
    return net


def _connect(net: Network) -> None:
    _ip("netns", "add", net.switch)
    _in(net.switch, "ip", "link", "add", "br0", "type", "bridge", "mcast_snooping", "0")
    _in(net.switch, "ip", "link", "set", "br0", "up")
    for k, host in enumerate(net.hosts):
        name = f"{PREFIX}{net.tag}-{host}"
        _ip("netns", "add", name)
        net.namespaces[host] = name
        net.addresses[host] = f"{SUBNET}.{k + 1}"
        port = net.ports[host] = f"port{k}"
        _in(net.switch, "ip", "link", "add", port, "type", "veth", "peer", "eth0", "netns", name)
        _in(net.switch, "ip", "link", "set", port, "master", "br0", "up")
        _in(name, "ip", "link", "set", "lo", "up")
        _in(name, "ip", "addr", "add", f"{net.addresses[host]}/24", "dev", "eth0")
        _in(name, "ip", "link", "set", "eth0", "up")
        _in(name, "ip", "route", "add", "default", "dev", "eth0")  # multicast needs a route
        if net.links.loss > 0:
            _in(
                name,
                *("iptables", "-t", "raw", "-A", "PREROUTING", "-i", "eth0"),
                *("-m", "statistic", "--mode", "random", "--probability", f"{net.links.loss:.4f}"),
                *("-j", "DROP"),
            )
        if (rate := net.links.rate_of(host)) > 0:  # both ways: the host's side and its port
            for namespace, device in ((name, "eth0"), (net.switch, port)):
                _in(
                    namespace,
                    *("tc", "qdisc", "add", "dev", device, "root", "tbf"),
                    *("rate", f"{rate:g}kbit", "burst", "4kb", "latency", "400ms"),
                )


def delete_network(net: Network) -> None:
    """Delete every namespace of ``net`` (their links and the bridge go with them)."""
    for name in net.all_namespaces():
        _ip("netns", "delete", name, check=False)


@contextmanager
def network(hosts: list[str], links: Links = Links()) -> Iterator[Network]:
    """:func:`create_network` for a ``with`` block, deleted at its end whatever happens
    (SIGTERM too: it raises KeyboardInterrupt here while the block runs)."""
    reason = missing_requirements(links)
    if reason is not None:
        raise HostsError(reason)
    remove_stale_namespaces()
    previous = signal.getsignal(signal.SIGTERM)

    def on_term(*_: object) -> None:
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, on_term)
    try:
        net = create_network(hosts, links)
        try:
            yield net
        finally:
            delete_network(net)
    finally:
        signal.signal(signal.SIGTERM, previous)


def run_hosts(
    run: LiveRun, links: Links = Links(), progress: Callable[[str], None] = print
) -> RunSummary:
    """``run`` (as :func:`csam_ros.run.demo.demo_live_run` makes it) with every robot and the
    base station on a host of its own; returns the merger's summary. ``hosts.json`` in
    ``run.out_dir`` holds the monitor's figures (joined maps during the run, seconds from
    the end of the data to the final joined map)."""
    run.out_dir.mkdir(parents=True, exist_ok=True)
    if run.isolated:
        with reserve_domain_id() as reservation:
            return _run_on(run, links, reservation.domain_id, progress)
    return _run_on(run, links, int(os.environ.get("ROS_DOMAIN_ID", "0")), progress)


def _run_on(run: LiveRun, links: Links, domain: int, progress: Callable[[str], None]) -> RunSummary:
    if BASE in run.robots:
        raise HostsError(f"a robot named {BASE!r} would share the base station's host name")
    hosts = [*run.robots, BASE]
    if links.cut is not None and links.cut[0] not in run.robots:
        raise HostsError(f"--cut names {links.cut[0]!r}, not one of the robots {run.robots}")
    env = with_dds_profile(subnet_environment(domain))
    shipped = env.get(DDS_PROFILE_VARIABLES[0])
    if links.rate_of(BASE) > 0 and shipped:
        path = run.out_dir / "fastdds_profile.xml"
        path.write_text(link_profile(Path(shipped).read_text(), links, domain, run.robots))
        env.update({v: str(path) for v in DDS_PROFILE_VARIABLES})
        # the profile's publication mode holds (asynchronous, paced, where it says so)
        env["RMW_FASTRTPS_PUBLICATION_MODE"] = "AUTO"
    profile = env.get(DDS_PROFILE_VARIABLES[0], "Fast DDS defaults")
    with network(hosts, links) as net:
        where = ", ".join(f"{h} {net.addresses[h]}" for h in hosts)
        progress(f"  hosts: {where}; ROS_DOMAIN_ID {domain}, discovery over the subnet")
        progress(f"  links: {links}; transport: {profile}")
        group = ProcessGroup(run.out_dir / "logs", env)
        try:
            return _run(run, net, group, progress)
        finally:
            if group.dead().keys() != group.processes.keys():  # failed or interrupted
                stop_nodes(group, progress)


LINK_SHARE = 0.8  # of a capped base link, paced among the robots' writers


def link_profile(shipped: str, links: Links, domain: int, robots: list[str]) -> str:
    """The Fast DDS profile ``shipped`` (XML text) for a run whose base station's link has a
    rate limit: what every process tells every other about itself crosses that link less
    often. Endpoint announcements go by multicast (one datagram for all hosts, not a unicast
    copy per process), a process announces itself every 10 s (not 3 s) and is held alive
    for 60 s, the graph announcements (ros_discovery_info) and /clock are heartbeated at
    Fast DDS's 3 s (not the 0.2 s of the map topics), and every reader of /clock listens on
    the domain's multicast address, where one datagram reaches all of them. Reliable writers
    announce unacknowledged data every 2 s, not 0.2 s. What the robots send the base (their
    map updates, rendezvous poses, /tf and status) is paced: each process sends at most its
    share of :data:`LINK_SHARE` of the link (a Fast DDS flow controller), so the link's queue
    does not overflow into a storm of repairs."""
    from csam_ros.ros.topics import LOCAL_MAP_UPDATES, RENDEZVOUS_POSES, STATUS, TF, robot_topics

    if links.rate_of(BASE) <= 0:
        return shipped
    pace = int(LINK_SHARE * links.rate_of(BASE) * 1000 / 8 / len(robots))  # bytes per s
    port = 7400 + 250 * domain + 1  # the RTPS user multicast port of the domain
    endpoints = (
        '<data_reader profile_name="/clock"><multicastLocatorList><locator><udpv4>'
        f"<address>239.255.0.1</address><port>{port}</port>"
        "</udpv4></locator></multicastLocatorList></data_reader>"
    )
    slow = "<times><heartbeatPeriod><sec>3</sec><nanosec>0</nanosec></heartbeatPeriod></times>"
    for topic in ("ros_discovery_info", "/clock"):
        endpoints += f'<data_writer profile_name="{topic}">{slow}</data_writer>'
    paced = (
        "<qos><publishMode><kind>ASYNCHRONOUS</kind>"
        "<flow_controller_name>csam_link_share</flow_controller_name></publishMode></qos>"
    )
    for topic in [*robot_topics(robots, [LOCAL_MAP_UPDATES, RENDEZVOUS_POSES]), TF.name]:
        endpoints += f'<data_writer profile_name="{topic}">{paced}</data_writer>'
    endpoints += f'<data_writer profile_name="{STATUS.name}">{paced}{slow}</data_writer>'
    builtin = (
        "<builtin><discovery_config>"
        "<leaseDuration><sec>60</sec><nanosec>0</nanosec></leaseDuration>"
        "<leaseAnnouncement><sec>10</sec><nanosec>0</nanosec></leaseAnnouncement>"
        "</discovery_config><avoid_builtin_multicast>false</avoid_builtin_multicast></builtin>"
        "<flow_controller_descriptor_list><flow_controller_descriptor>"
        f"<name>csam_link_share</name><max_bytes_per_period>{pace}</max_bytes_per_period>"
        "<period_ms>1000</period_ms></flow_controller_descriptor></flow_controller_descriptor_list>"
    )
    # a reliable writer announces unacknowledged data every 2 s, not 0.2 s: more than the
    # link's queue holds (0.4 s), so it does not ask for repairs of what is still queued
    shipped, replaced = re.subn(
        r"<heartbeatPeriod>\s*<sec>0</sec>\s*<nanosec>200000000</nanosec>\s*</heartbeatPeriod>",
        "<heartbeatPeriod><sec>2</sec><nanosec>0</nanosec></heartbeatPeriod>",
        shipped,
    )
    if replaced != 1:
        raise HostsError("the shipped Fast DDS profile has no 0.2 s writer heartbeat to slow")
    start = shipped.index("<rtps>", shipped.index('<participant profile_name="csam_participant"'))
    start += len("<rtps>")
    text = shipped[:start] + builtin + shipped[start:]
    end = text.index("</profiles>")
    return text[:end] + endpoints + text[end:]


HOSTS_CLOCK_PERIOD_S = 0.05  # wall-clock s between /clock messages across hosts
# every node on a host runs without a /rosout publisher (its log is its host's file) and
# without the ~/get_type_description service: three endpoints fewer per node, each of which
# every other process across the links would be told of
LEAN_NODE_ARGS = [
    "--ros-args",
    "--disable-rosout-logs",
    *("-p", "start_type_description_service:=false"),
]


def _node(argv: list[str]) -> list[str]:
    """``argv`` of a ROS node with :data:`LEAN_NODE_ARGS`."""
    return [*argv, *LEAN_NODE_ARGS]


def _run(
    run: LiveRun, net: Network, group: ProcessGroup, progress: Callable[[str], None]
) -> RunSummary:
    summary_path = run.summary_path
    for stale in (MONITOR_READY, MONITOR_END, MONITOR_RESULT, summary_path.name):
        (run.out_dir / stale).unlink(missing_ok=True)
    # the nodes of a single-host run, each on its host (checkpoints in the run folder here;
    # real hosts keep their own on their disks)
    from csam_ros.ros.topics import base_station_topics, robot_host_topics

    base_topics = base_station_topics(run.robots) + run.extra_topics
    group.start("recorder", net.command(BASE, _node(run.recorder_argv("bag", base_topics))))
    # a robot logs its own data: it never crosses the link, nor does its recorder's discovery
    # (it finds only the nodes of its own host, as every other host is spared its endpoints)
    local = {**group.env, "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}
    for robot in run.robots:
        argv = run.recorder_argv(f"bag_{robot}", robot_host_topics(robot))
        group.start(f"recorder_{robot}", net.command(robot, _node(argv)), local)
    group.start("merger", net.command(BASE, _node(run.merger_argv())))
    monitor = [sys.executable, "-m", "csam_ros.run.hosts", "--out", str(run.out_dir)]
    group.start("monitor", net.command(BASE, [*monitor, "--robots", *run.robots]))
    for robot in run.robots:
        group.start(f"smoother_{robot}", net.command(robot, _node(run.smoother_argv(robot))))
    start = time.monotonic()
    shown = 0

    def relay() -> None:  # the monitor's progress lines
        nonlocal shown
        lines = (run.out_dir / "logs" / "monitor.log").read_text(errors="replace").splitlines()
        for line in lines[shown:]:
            if line.startswith("  "):
                progress(line)
        shown = len(lines)

    def check(ignore: set[str]) -> None:
        for name, code in group.dead().items():
            if name not in ignore:
                raise LiveRunError(f"{name} exited with {code}:\n{group.log_tail(name)}")
        if time.monotonic() - start > run.timeout_s:
            raise LiveRunError(f"the run did not end within {run.timeout_s} s")

    # the data starts once the base station reaches every smoother (as a single-host run's
    # source starts once the smoothers answer): else, on a lossy link, discovery can take
    # longer than a short run
    while not (run.out_dir / MONITOR_READY).exists():
        check(set())
        relay()
        time.sleep(0.1)
    for k, robot in enumerate(run.robots):
        group.start(
            f"{run.source_name}_{robot}",
            net.command(
                robot,
                [
                    *run.source_argv,
                    *LEAN_NODE_ARGS,
                    "--ros-args",
                    *run.source_ros_args,
                    *ros_params(
                        {
                            "use_sim_time": True,
                            "emit_robots": [robot],
                            "publish_clock": k == 0,  # the one source of sim time
                            # every node of every host gets each /clock message: at 100 Hz
                            # they alone filled a 256 kbit/s link
                            "clock_period": HOSTS_CLOCK_PERIOD_S,
                        }
                    ),
                ],
            ),
        )
    sources = [f"{run.source_name}_{r}" for r in run.robots]
    cut_host = net.links.cut[0] if net.links.cut is not None else run.robots[0]
    cut = LinkCut(net, progress, run.out_dir / "logs" / f"{run.source_name}_{cut_host}.log")
    while any(group.processes[s].poll() is None for s in sources):
        check(set(sources))
        relay()
        cut.follow()
        time.sleep(0.1)
    for source in sources:
        code = group.processes[source].returncode
        if code != 0:
            raise LiveRunError(f"{source} exited with {code}:\n{group.log_tail(source)}")
    published = [_all_published_at(run.out_dir / "logs" / f"{s}.log") for s in sources]
    ends = [t for t in published if t is not None]
    # the end of the data: the last simulator's last message (wall clock of this machine)
    end = max(ends) if len(ends) == len(published) else time.time()
    (run.out_dir / MONITOR_END).write_text(f"{end!r}\n")
    progress(
        f"  every robot's data published and acknowledged ({time.time() - end:.1f} s after "
        "its end); the base station flushes the smoothers over ROS"
    )
    while group.processes["monitor"].poll() is None:
        check({*sources, "monitor"})
        relay()
        cut.follow()
        time.sleep(0.1)
    cut.restore()
    relay()
    if group.processes["monitor"].returncode != 0:
        raise LiveRunError(f"the monitor failed:\n{group.log_tail('monitor')}")
    stop_nodes(group, progress)
    if not summary_path.exists():
        raise LiveRunError(f"the merger wrote no summary:\n{group.log_tail('merger')}")
    dropped = smoother_drops(run.robots, run.state_dir)
    lost = "; ".join(f"{r} {d}" for r, d in dropped.items() if d) or "nothing"
    progress(f"  the smoothers dropped (from their checkpoints): {lost}")
    return replace(RunSummary.read(summary_path), dropped=dropped)


class LinkCut:
    """Cuts and restores the link of :attr:`Links.cut` as the run's wall clock passes its
    window, counted from the start of the data: when the cut host's simulator starts
    publishing (its log says so; it first waits for its subscribers, which can take seconds
    on a loaded machine)."""

    def __init__(self, net: Network, progress: Callable[[str], None], source_log: Path) -> None:
        self.net, self.progress, self.source_log = net, progress, source_log
        self.start: float | None = None
        self.state = "before"

    def follow(self) -> None:
        cut = self.net.links.cut
        if cut is None or self.state == "after":
            return
        if self.start is None:
            from csam_ros.nodes.simulator import LOG_PUBLISHING

            self.start = _logged_at(self.source_log, LOG_PUBLISHING)
            if self.start is None:
                return
        host, begin, end = cut
        elapsed = time.time() - self.start
        if self.state == "before" and elapsed >= begin:
            self.net.set_link(host, up=False)
            self.state = "cut"
            self.progress(f"  {host}'s link cut at {elapsed:.1f} s")
        if self.state == "cut" and elapsed >= end:
            self.restore()

    def restore(self) -> None:
        if self.state == "cut":
            host = self.net.links.cut[0]  # type: ignore[index]
            self.net.set_link(host, up=True)
            elapsed = time.time() - (self.start or time.time())
            self.progress(f"  {host}'s link restored at {elapsed:.1f} s")
        self.state = "after"


def stop_nodes(group: ProcessGroup, progress: Callable[[str], None]) -> None:
    """Stop every process (the recorder first: it finalises the bag), each by SIGINT and only
    if that fails by SIGTERM, then SIGKILL; say how long the slowest took."""
    times = {}
    for name in ["recorder", *reversed([n for n in group.processes if n != "recorder"])]:
        if name not in group.processes:
            continue
        began = time.monotonic()
        code = group.stop(name, timeout=20 if name.startswith("recorder") else 10)
        times[name] = (time.monotonic() - began, code)
    running = {n: t for n, (t, _) in times.items()}
    slowest = max(running, key=running.__getitem__)
    killed = sorted(n for n, (_, code) in times.items() if code is not None and code < 0)
    progress(
        f"  nodes stopped on SIGINT: the slowest, {slowest}, in {running[slowest]:.2f} s"
        + (f"; ended by a signal: {', '.join(killed)}" if killed else "")
    )


def _all_published_at(log: Path) -> float | None:
    """The wall-clock time of a simulator's "all messages published" log line."""
    from csam_ros.nodes.simulator import LOG_ALL_PUBLISHED

    return _logged_at(log, LOG_ALL_PUBLISHED)


def _logged_at(log: Path, text: str) -> float | None:
    """The wall-clock time of the first line of ``log`` that ends with ``text``."""
    if not log.exists():
        return None
    for line in log.read_text(errors="replace").splitlines():
        if line.endswith(text):
            try:
                return float(line.split("[")[2].split("]")[0])
            except (IndexError, ValueError):
                return None
    return None


# -- the monitor: on the base station, over ROS only -------------------------------------------


@dataclass
class MonitorReport:
    """What the base station saw of a run."""

    joined_before_end: int  # joined maps received before the data ended
    joined_total: int
    end_to_final_s: float  # seconds from the end of the data to the final joined map
    flush_calls: int
    final_stamps: dict[str, int]

    def write(self, path: Path) -> None:
        path.write_text(json.dumps(self.__dict__, indent=1))

    @staticmethod
    def read(path: Path) -> MonitorReport:
        return MonitorReport(**json.loads(path.read_text()))


def monitor(
    robots: list[str],
    data_end: Callable[[], float | None],
    ready: Callable[[], None] = lambda: None,
    timeout_s: float = 600.0,
    progress: Callable[[str], None] = print,
) -> MonitorReport:
    """Wait for the smoothers' ``~/flush`` services and local maps (then call ``ready``),
    count the joined maps while the data comes, and once ``data_end()`` gives the time
    (wall clock) the data ended, flush every smoother (again, until their latest stamps hold
    still) and the merger (:func:`~csam_ros.run.live.end_of_data`) and wait for the joined
    map of those final local maps."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter
    from std_srvs.srv import Trigger

    from csam_ros.nodes.common import subscribe
    from csam_ros.ros.topics import (
        FLUSH,
        JOINED_MAP,
        LOCAL_MAP_UPDATES,
        MARKERS,
        merger_service,
        smoother_service,
    )

    rclpy.init()
    # a client of the smoothers and a reader of the joined map, nothing more to discover
    node = rclpy.create_node(
        "csam_run_monitor",
        enable_rosout=False,
        start_parameter_services=False,
        parameter_overrides=[Parameter("start_type_description_service", value=False)],
    )
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    joined: list = []  # every joined map received
    received: list[float] = []  # when (wall clock)
    markers = MarkersAfterJoined()

    def on_joined(message: object) -> None:
        joined.append(message)
        received.append(time.time())
        markers.on_joined()

    subscribe(node, JOINED_MAP, on_joined)
    subscribe(node, MARKERS, markers.on_markers)
    clients = {r: node.create_client(Trigger, smoother_service(r, FLUSH)) for r in robots}
    merger = node.create_client(Trigger, merger_service(FLUSH))
    deadline = time.monotonic() + timeout_s

    def spin(seconds: float) -> None:
        until = time.monotonic() + seconds
        while time.monotonic() < until:
            executor.spin_once(timeout_sec=min(0.1, max(until - time.monotonic(), 0.0)))
        if time.monotonic() > deadline:
            raise LiveRunError(f"the monitor gave up after {timeout_s} s")

    try:

        def reached() -> bool:  # every flush service and smoother's local map seen
            return all(c.service_is_ready() for c in [*clients.values(), merger]) and all(
                node.get_publishers_info_by_topic(LOCAL_MAP_UPDATES.of(r)) for r in robots
            )

        while not reached():
            spin(0.1)
        progress(f"  base station: the smoothers of {', '.join(robots)} answer over the links")
        ready()
        last_print = time.monotonic()
        while (end := data_end()) is None:
            spin(0.1)
            if time.monotonic() - last_print > 2.0:
                progress(f"  base station: {len(joined)} joined maps so far")
                last_print = time.monotonic()
        final, calls = end_of_data(clients, merger, spin, timeout_s=30.0)

        while not joined_map_is_final(joined[-1] if joined else None, final):
            spin(0.05)
        end_to_final = time.time() - end
        before_end = sum(t < end for t in received)
        progress(
            f"  base station: final joined map {end_to_final:.2f} s after the end of the data "
            f"({before_end} joined maps during the run, {calls} flush calls)"
        )

        until = time.monotonic() + 30
        while not markers.came() and time.monotonic() < until:
            spin(0.05)
        until = time.monotonic() + 15
        while not recorder_holds_results(node) and time.monotonic() < until:
            spin(0.1)
        spin(1.0)
        return MonitorReport(before_end, len(joined), end_to_final, calls, final)
    finally:
        node.destroy_node()
        executor.shutdown()
        rclpy.try_shutdown()


def main(argv: list[str] | None = None) -> int:
    """The base station's run monitor: ``csam demo --hosts`` starts it there; with
    ``--flush``, the end of a run by hand (every smoother flushed over ROS, then the final
    joined map awaited)."""
    p = argparse.ArgumentParser(prog="python -m csam_ros.run.hosts", description=main.__doc__)
    p.add_argument("--robots", nargs="+", required=True, help="the robots' names")
    p.add_argument(
        "--flush", action="store_true", help="the data has ended: flush the smoothers now"
    )
    p.add_argument(
        "--out",
        type=Path,
        help=f"the run's directory (a hosts run's: {MONITOR_END} there ends the data; "
        f"{MONITOR_RESULT} is written there)",
    )
    p.add_argument("--timeout", type=float, default=600.0, help="seconds before giving up")
    args = p.parse_args(argv)
    if args.out is None and not args.flush:
        p.error("either --flush or --out DIR")
    now = time.time()

    def data_end() -> float | None:
        if args.flush:
            return now
        try:
            return float((args.out / MONITOR_END).read_text())
        except (OSError, ValueError):  # not there yet, or being written
            return None

    def ready() -> None:
        if args.out is not None:
            (args.out / MONITOR_READY).write_text("ready\n")

    try:
        report = monitor(
            args.robots, data_end, ready, args.timeout, lambda line: print(line, flush=True)
        )
    except KeyboardInterrupt:
        return 130
    except LiveRunError as err:
        print(f"monitor: {err}", file=sys.stderr)
        return 1
    if args.out is not None:
        report.write(args.out / MONITOR_RESULT)
    return 0


if __name__ == "__main__":
    sys.exit(main())
