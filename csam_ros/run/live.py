"""A live run: smoothers, merger and recorder as separate node processes fed by a source.

The source is the simulator (``csam demo``) or the player of a bag (``csam replay``). The run
ends when the source has published everything: every smoother is flushed (``~/flush``, all at
once), then the merger (its ``~/flush``: it solves those final maps at once), the merger's
joined map is awaited for those final local maps, the recorder is stopped (which
finalises the bag) and every process is gone. The merger writes ``summary.json``; each
smoother its checkpoint and the merger its state in ``state/`` of the run folder, so that a
node restarted with the same parameters resumes. The summary's ``dropped`` holds what each
smoother dropped, read from its last checkpoint.
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from csam_ros.core.joining.result import RunSummary
from csam_ros.run.launch import ProcessGroup, executable
from csam_ros.run.ros_env import (
    isolate_this_process,
    isolated_environment,
    reserve_domain_id,
    with_dds_profile,
)


class LiveRunError(RuntimeError):
    """A live run that could not finish (a node died, or a step timed out)."""


@dataclass
class LiveRun:
    """What a live run needs: where, which robots, how the nodes are configured."""

    out_dir: Path
    robots: list[str]
    source_name: str
    source_argv: list[str]  # the simulator or player command, without --ros-args
    source_ros_args: list[str] = field(default_factory=list)
    smoother_params: dict[str, object] = field(default_factory=dict)
    merger_params: dict[str, object] = field(default_factory=dict)
    extra_topics: list[str] = field(default_factory=list)
    timeout_s: float = 600.0
    # False: the caller's ROS environment (ROS_DOMAIN_ID, discovery range), so other ROS
    # tools see the run; True: a private domain with discovery on this host only (tests)
    isolated: bool = False

    @property
    def summary_path(self) -> Path:
        return self.out_dir / "summary.json"

    @property
    def state_dir(self) -> Path:
        """Checkpoints and the merger's state: a node restarted by hand with the same
        parameters resumes from them."""
        return self.out_dir / "state"

    def recorder_argv(self, bag: str = "bag", topics: list[str] | None = None) -> list[str]:
        """A recorder of ``topics`` (default: every recorded topic) to ``bag`` in the run's
        folder."""
        from csam_ros.ros.topics import recorded_topics

        if topics is None:
            topics = recorded_topics(self.robots) + self.extra_topics
        return [executable("recorder"), "-o", str(self.out_dir / bag), "--topics", *topics]

    def merger_argv(self) -> list[str]:
        params = {
            "robots": self.robots,
            "summary_path": str(self.summary_path),
            "state_path": str(self.state_dir / "merger.npz"),
            **self.merger_params,
        }
        return [executable("merger"), "--ros-args", *ros_params({"use_sim_time": True, **params})]

    def smoother_argv(self, robot: str) -> list[str]:
        params = {
            "robots": self.robots,
            "checkpoint_path": str(self.state_dir / f"{robot}.npz"),
            **self.smoother_params,
        }
        return [
            executable("smoother"),
            "--ros-args",
            *("-r", f"__ns:=/{robot}"),
            *ros_params({"use_sim_time": True, **params}),
        ]


def ros_params(params: Mapping[str, object]) -> list[str]:
    """``-p name:=value`` arguments of a node's ``--ros-args``."""
    return [arg for name, value in params.items() for arg in _param(name, value)]


def _param(name: str, value: object) -> list[str]:
    if isinstance(value, bool):
        text = "true" if value else "false"
    elif isinstance(value, list | tuple):
        text = "[" + ",".join(json.dumps(v) if isinstance(v, str) else str(v) for v in value) + "]"
    elif value == "":
        text = "''"  # an empty YAML string; a bare `name:=` does not parse
    else:
        text = str(value)
    return ["-p", f"{name}:={text}"]


def joined_map_is_final(joined: Any, final: Mapping[str, int]) -> bool:
    """Whether the JoinedMap ``joined`` (None: none yet) used each robot's local map of stamp
    ``final[robot]`` (ns)."""
    if joined is None:
        return False
    from csam_ros.ros.conversions import time_to_ns

    stamps = {b.robot: time_to_ns(b.local_map_stamp) for b in joined.base_nodes}
    return all(stamps.get(r) == s for r, s in final.items())


def flush_all(
    clients: Mapping[str, Any], spin: Callable[[float], None], timeout_s: float
) -> tuple[dict[str, str], int]:
    """Call every std_srvs/Trigger client of ``clients`` at once and wait for each reply; a
    call unanswered after ``timeout_s`` (a reply lost on a bad link) is made again. Each
    reply's message, and the number of calls made. ``spin(seconds)`` runs the clients' node."""
    from std_srvs.srv import Trigger

    pending = {name: client.call_async(Trigger.Request()) for name, client in clients.items()}
    calls, asked, messages = len(pending), time.monotonic(), {}
    while pending:
        spin(0.02)
        for name, future in list(pending.items()):
            if future.done() and future.result() is not None:
                messages[name] = future.result().message
                del pending[name]
        if pending and time.monotonic() - asked > timeout_s:
            for name, future in pending.items():
                clients[name].remove_pending_request(future)
                pending[name] = clients[name].call_async(Trigger.Request())
            calls, asked = calls + len(pending), time.monotonic()
    return messages, calls


def end_of_data(
    smoothers: Mapping[str, Any],
    merger: Any,
    spin: Callable[[float], None],
    timeout_s: float,
) -> tuple[dict[str, int], int]:
    """End a run whose data has all been sent: flush every smoother (``smoothers``: robot ->
    ``~/flush`` client) and then the merger (``merger``: its ``~/flush`` client), so that it
    solves those maps at once; flush the smoothers again, and the merger after any round that
    changed a map, until the final local maps' stamps hold still over half a second (data may
    still wait in a smoother's queue when the source ends: best-effort odometry is not
    acknowledged, and a service call can be served before it). The final stamps (ns), and the
    number of calls made."""
    final: dict[str, int] | None = None
    calls = 0
    while True:
        replies, more = flush_all(smoothers, spin, timeout_s)
        previous, final, calls = final, {r: int(m) for r, m in replies.items()}, calls + more
        if final == previous and min(final.values()) >= 0:
            return final, calls
        if min(final.values()) >= 0:
            calls += flush_all({"merger": merger}, spin, timeout_s)[1]
        spin(0.5)


class MarkersAfterJoined:
    """Whether the markers of the latest joined map came: a solved map goes out first, its
    markers once its summary is written. Feed it both topics' callbacks."""

    def __init__(self) -> None:
        self.received = 0  # markers messages
        self.before_joined = 0  # of them when the latest joined map came

    def on_markers(self, message: object) -> None:
        self.received += 1

    def on_joined(self) -> None:
        self.before_joined = self.received

    def came(self) -> bool:
        return self.received > self.before_joined


def recorder_holds_results(node: Any) -> bool:
    """Whether the recorder subscribes to the merger's (latched) results, as it must before
    it is stopped."""
    from csam_ros.ros.topics import JOINED_MAP, MARKERS

    return all(
        any(i.node_name == "recorder" for i in node.get_subscriptions_info_by_topic(t))
        for t in (JOINED_MAP.name, MARKERS.name)
    )


def run_live(run: LiveRun, progress=print) -> RunSummary:
    """Run the nodes; returns the merger's final summary (``out_dir/summary.json``)."""
    run.out_dir.mkdir(parents=True, exist_ok=True)
    if not run.isolated:
        domain = os.environ.get("ROS_DOMAIN_ID", "0")
        progress(f"  on ROS_DOMAIN_ID {domain}: other ROS tools there see the run")
        return _run_with(run, dict(os.environ), progress)
    with reserve_domain_id() as reservation:
        isolate_this_process(reservation.domain_id)
        progress(f"  isolated on ROS_DOMAIN_ID {reservation.domain_id}, this host only")
        return _run_with(run, isolated_environment(reservation.domain_id), progress)


def _run_with(run: LiveRun, env: dict[str, str], progress) -> RunSummary:
    group = ProcessGroup(run.out_dir / "logs", with_dds_profile(env))  # the shipped transport
    try:
        return _run(run, group, progress)
    finally:
        group.stop_all()


def _run(run: LiveRun, group: ProcessGroup, progress) -> RunSummary:
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from std_srvs.srv import Trigger

    from csam_ros.nodes.common import subscribe
    from csam_ros.ros.conversions import time_to_ns
    from csam_ros.ros.topics import (
        CLOCK,
        FLUSH,
        JOINED_MAP,
        MARKERS,
        merger_service,
        smoother_service,
    )

    sim_time = _param("use_sim_time", True)
    group.start("recorder", run.recorder_argv())
    group.start("merger", run.merger_argv())
    for robot in run.robots:
        group.start(f"smoother_{robot}", run.smoother_argv(robot))

    rclpy.init()
    node = rclpy.create_node("csam_run_monitor")
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    latest: dict[str, Any] = {"clock": None, "joined": None}
    markers = MarkersAfterJoined()

    def on_joined(joined: Any) -> None:
        latest["joined"] = joined
        markers.on_joined()

    subscribe(node, CLOCK, lambda m: latest.__setitem__("clock", m))
    clients = {r: node.create_client(Trigger, smoother_service(r, FLUSH)) for r in run.robots}
    merger_client = node.create_client(Trigger, merger_service(FLUSH))
    try:
        deadline = time.monotonic() + 60
        ready = [*clients.values(), merger_client]
        while not all(c.service_is_ready() for c in ready):
            _check_alive(group)
            executor.spin_once(timeout_sec=0.1)
            if time.monotonic() > deadline:
                raise LiveRunError("the smoothers and the merger did not come up within 60 s")
        group.start(
            run.source_name, [*run.source_argv, "--ros-args", *sim_time, *run.source_ros_args]
        )
        start = time.monotonic()
        last_print = 0.0
        while group.processes[run.source_name].poll() is None:
            _check_alive(group, ignore=run.source_name)
            executor.spin_once(timeout_sec=0.1)
            if time.monotonic() - last_print > 2.0:
                clock = latest["clock"]
                t = time_to_ns(clock.clock) / 1e9 if clock is not None else 0.0
                progress(
                    f"  {run.source_name}: t = {t:8.1f} s  ({time.monotonic() - start:5.1f} s wall)"
                )
                last_print = time.monotonic()
            if time.monotonic() - start > run.timeout_s:
                raise LiveRunError(f"{run.source_name} did not finish within {run.timeout_s} s")
        code = group.processes[run.source_name].returncode
        if code != 0:
            raise LiveRunError(
                f"{run.source_name} exited with {code}:\n{group.log_tail(run.source_name)}"
            )
        # only now: each joined map decoded here would cost this process a large message
        # per solve; both are latched, so the latest comes at once
        subscribe(node, JOINED_MAP, on_joined)
        subscribe(node, MARKERS, markers.on_markers)
        progress("  source done; flushing the smoothers, then the merger")
        settle_deadline = time.monotonic() + 120

        def spin(seconds: float) -> None:
            until = time.monotonic() + seconds
            while time.monotonic() < until:
                _check_alive(group, ignore=run.source_name)
                executor.spin_once(timeout_sec=min(0.1, max(until - time.monotonic(), 0.0)))
            if time.monotonic() > settle_deadline:
                raise LiveRunError("the smoothers and the merger did not settle within 120 s")

        final, _ = end_of_data(clients, merger_client, spin, timeout_s=30.0)
        progress("  waiting for the merger's final joined map")
        deadline = time.monotonic() + 300

        while not joined_map_is_final(latest["joined"], final):
            _check_alive(group, ignore=run.source_name)
            executor.spin_once(timeout_sec=0.1)
            if time.monotonic() > deadline:
                raise LiveRunError(
                    f"no final joined map from the merger within 300 s:\n{group.log_tail('merger')}"
                )
        deadline = time.monotonic() + 30
        while not markers.came() and time.monotonic() < deadline:
            _check_alive(group, ignore=run.source_name)
            executor.spin_once(timeout_sec=0.1)

        deadline = time.monotonic() + 15
        while not recorder_holds_results(node) and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.1)
        grace = time.monotonic() + 1.0
        while time.monotonic() < grace:
            executor.spin_once(timeout_sec=0.1)
    finally:
        node.destroy_node()
        executor.shutdown()
        rclpy.try_shutdown()
    group.stop("recorder", timeout=20)
    group.stop_all()
    summary = RunSummary.read(run.summary_path)
    return replace(summary, dropped=smoother_drops(run.robots, run.state_dir))


def smoother_drops(robots: list[str], folder: Path) -> dict[str, dict[str, int]]:
    """What each smoother dropped of its robot's input, by reason (data lost while it was
    down among them), from its last checkpoint in ``folder`` (robots without one left out)."""
    from csam_ros.core.exchange.checkpoint import SmootherCheckpoint
    from csam_ros.core.exchange.state_files import CheckpointError

    drops = {}
    for robot in robots:
        try:
            saved = SmootherCheckpoint.read(folder / f"{robot}.npz", robot)
        except CheckpointError:
            continue
        drops[robot] = saved.filter.drops.get(robot, {})
    return drops


def _check_alive(group: ProcessGroup, ignore: str | None = None) -> None:
    for name, code in group.dead().items():
        if name != ignore:
            raise LiveRunError(f"{name} exited with {code}:\n{group.log_tail(name)}")
