"""Faults on live nodes in the isolated domain: a smoother killed and restarted from its
checkpoint, a merger killed and restarted (from the smoothers' whole maps sent again on its
request, and from its saved state), checkpoints that cannot be used, and a robot whose clock
is offset."""

from __future__ import annotations

import signal
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from merger_harness import ROBOTS, MergerHarness, Smoothers, joined_view, run_messages
from node_group import final_joined_result, smoothers_and_merger
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from rclpy.time import Time

from csam_ros.core.exchange.checkpoint import (
    LOST_WHILE_DOWN,
    OfflineState,
    SmootherCheckpoint,
    missed_samples,
)
from csam_ros.core.exchange.map_updates import HeldMap, KeyedMap, MissingBaseError, apply_update
from csam_ros.core.model.log import MultiRobotLog
from csam_ros.datasets.scenario import load_scenario
from csam_ros.datasets.simulation import simulate
from csam_ros.ros.merger_reports import status_array
from csam_ros.run.live import smoother_drops

LOST_FROM, LOST_TO = 15.0, 18.0  # s after the start: the smoother is down in between


def _smoother_messages() -> tuple[list[Any], float]:
    """robot1's sensor messages of map_joining and robot2's rendezvous (which robot1's
    smoother also takes), in stamp order; and the first odometry stamp."""
    from csam_ros.ros.conversions import log_to_messages

    log = simulate(load_scenario("map_joining"), seed=3)
    topics = {"/robot1/odom", "/robot1/features", "/robot1/rendezvous", "/robot2/rendezvous"}
    messages = [m for m in log_to_messages(MultiRobotLog(log.robots), False) if m.topic in topics]
    return messages, float(log.robots["robot1"].odometry.stamps[0])


class SmootherClient:
    """A node that feeds a smoother process, flushes it and builds the map it sends from its
    local map updates (asking for the whole map when one does not apply)."""

    def __init__(self, context: Any, spin: Any) -> None:
        import rclpy
        from std_srvs.srv import Trigger

        from csam_ros.nodes.common import publisher, subscribe
        from csam_ros.ros.topics import (
            FEATURES,
            LOCAL_MAP_UPDATES,
            ODOM,
            RENDEZVOUS,
            RESYNC,
            STATUS,
            smoother_service,
        )

        self.spin = spin
        self.node = rclpy.create_node("fault_client", context=context)
        self.pubs = {
            "/robot1/odom": publisher(self.node, ODOM, ODOM.of("robot1")),
            "/robot1/features": publisher(self.node, FEATURES, FEATURES.of("robot1")),
            "/robot1/rendezvous": publisher(self.node, RENDEZVOUS, RENDEZVOUS.of("robot1")),
            "/robot2/rendezvous": publisher(self.node, RENDEZVOUS, RENDEZVOUS.of("robot2")),
        }
        self.updates: list[Any] = []  # every update message received
        self.held: HeldMap | None = None  # the map they build
        self.stamp_ns = -1  # of the last update applied
        self.status: dict[str, str] = {}
        subscribe(self.node, LOCAL_MAP_UPDATES, self._on_update, LOCAL_MAP_UPDATES.of("robot1"))
        subscribe(self.node, STATUS, self._on_status)
        self.flush_client = self.node.create_client(Trigger, "/robot1/smoother/flush")
        self.resync_client = self.node.create_client(Trigger, smoother_service("robot1", RESYNC))
        self.executor = SingleThreadedExecutor(context=context)
        self.executor.add_node(self.node)

    def _on_update(self, msg: Any) -> None:
        from csam_ros.ros.conversions import time_to_ns
        from csam_ros.ros.map_messages import map_update_from_message

        self.updates.append(msg)
        try:
            self.held = apply_update(self.held, map_update_from_message(msg, "robot1"))
        except MissingBaseError:
            return  # the test asks for the whole map
        self.stamp_ns = time_to_ns(msg.header.stamp)

    def resync(self) -> None:
        """Ask the smoother for its whole map (the reply is not waited for)."""
        from std_srvs.srv import Trigger

        self.resync_client.call_async(Trigger.Request())

    def _on_status(self, msg: Any) -> None:
        for status in msg.status:
            if status.name == "smoother/robot1":
                self.status = {kv.key: kv.value for kv in status.values}

    def wait(self, condition: Any, timeout_s: float = 30.0) -> None:
        assert self.spin(self.executor, condition, timeout_s), "timed out"

    def readers(self) -> set[tuple[str, bytes]]:
        """The subscription endpoints on the graph of every topic fed here."""
        return {
            (topic, bytes(info.endpoint_gid))
            for topic in self.pubs
            for info in self.node.get_subscriptions_info_by_topic(topic)
        }

    def send(self, messages: list[Any], old_readers: set[tuple[str, bytes]] = frozenset()) -> None:
        """Publish ``messages`` once a reader not among ``old_readers`` (a killed process's
        endpoints stay on the graph for a while) is on every topic."""

        def ready() -> bool:
            new = {topic for topic, _ in self.readers() - set(old_readers)}
            return new == set(self.pubs)

        self.wait(ready)
        # discovery settles both ways (odometry is best effort: a message to a reader that
        # has not matched this writer yet is gone)
        self.spin(self.executor, lambda: False, 1.0)
        for m in messages:
            self.pubs[m.topic].publish(m.message)
            self.executor.spin_once(timeout_sec=0.001)

    def reach(self, odometry: Any) -> None:
        """Send one odometry message until the smoother has it (its flush says its stamp):
        a restarted reader may not know this writer yet, and best effort is not resent."""
        stamp = odometry.stamp_ns
        for _ in range(100):
            self.pubs[odometry.topic].publish(odometry.message)
            if self.flush(settle=False) == stamp:
                return
            self.spin(self.executor, lambda: False, 0.2)
        raise AssertionError(f"the smoother never received odometry at {stamp} ns")

    def flush(self, settle: bool = True) -> int:
        """Flush until the published stamp stays the same (messages may still be queued)."""
        from std_srvs.srv import Trigger

        def once() -> int:
            future = self.flush_client.call_async(Trigger.Request())
            self.wait(future.done)
            return int(future.result().message)

        self.wait(self.flush_client.service_is_ready)
        previous, final = None, once()
        while settle and final != previous:
            self.spin(self.executor, lambda: False, 0.5)
            previous, final = final, once()
        return final

    def close(self) -> None:
        self.node.destroy_node()
        self.executor.shutdown()


def _keyed_equal(a: KeyedMap, b: KeyedMap) -> None:
    for name in KeyedMap.__dataclass_fields__:
        x, y = getattr(a, name), getattr(b, name)
        assert np.array_equal(x, y) if isinstance(x, np.ndarray) else x == y, name


def test_a_killed_smoother_resumes_from_its_checkpoint(ros_context, spin, nodes, tmp_path) -> None:
    messages, t0 = _smoother_messages()
    stamp = [m.stamp_ns / 1e9 - t0 for m in messages]
    before = [m for m, t in zip(messages, stamp, strict=True) if t <= LOST_FROM]
    after = [m for m, t in zip(messages, stamp, strict=True) if t > LOST_TO]
    checkpoint = tmp_path / "robot1.npz"
    args = [
        "--ros-args",
        "-r",
        "__ns:=/robot1",
        "-p",
        "robots:=[robot1,robot2]",
        "-p",
        "publish_period:=1000.0",
        "-p",
        f"checkpoint_path:={checkpoint}",
    ]
    client = SmootherClient(ros_context, spin)
    try:
        first = nodes.start("smoother", *args)
        client.send(before)
        client.flush()
        assert client.held is not None
        killed, killed_ns = client.held, client.stamp_ns
        assert nodes.stop(first, signal.SIGKILL) == -signal.SIGKILL
        saved = SmootherCheckpoint.read(checkpoint, "robot1")
        assert saved.published_ns == killed_ns

        old_readers = client.readers()
        second = nodes.start("smoother", *args)
        # the restarted smoother (a new session) sends the map it had before any new data:
        # at its start, or again when asked (this reader may not have matched it in time)

        def resumed() -> bool:
            return client.held is not None and client.held.session != killed.session

        for _ in range(60):
            if client.spin(client.executor, resumed, 0.5):
                break
            client.resync()
        assert resumed(), "the restarted smoother's map never came"
        assert client.held is not None
        _keyed_equal(client.held.map, killed.map)

        # the first odometry after the restart, then the rest (it comes again: a duplicate)
        client.send([], old_readers)
        client.reach(next(m for m in after if m.topic == "/robot1/odom"))
        client.send(after)
        client.flush()
        # odometry is best effort: count from what the smoother received, as it does
        last_before = float(saved.local_map.odometry_stamps[-1])
        odometry = SmootherCheckpoint.read(checkpoint, "robot1").local_map.odometry_stamps
        first_after = float(odometry[odometry > last_before][0])
        lost = missed_samples(first_after - last_before, 0.5)
        assert lost >= round((LOST_TO - LOST_FROM) / 0.5)  # 15.5 ... 18.0 s never came
        client.wait(lambda: client.status.get(f"dropped/{LOST_WHILE_DOWN}") == str(lost))
        assert client.status["restarts"] == "1"
        assert float(client.status["lost_seconds"]) == pytest.approx(lost * 0.5, abs=1e-3)
        final = client.held.map
        # what it had accepted before the kill is all there
        old, new = set(killed.map.pose_stamps.tolist()), set(final.pose_stamps.tolist())
        assert old <= new and final.pose_stamps[0] == killed.map.pose_stamps[0]
        assert len(final.pose_stamps) > len(killed.map.pose_stamps)
        # a live run's summary takes each smoother's counts from its checkpoint
        dropped = smoother_drops(["robot1", "robot2"], tmp_path)
        assert list(dropped) == ["robot1"] and dropped["robot1"][LOST_WHILE_DOWN] == lost
        # its checkpoint is what matters here (stopping on SIGINT is tested with the hosts);
        # under the whole suite's load this SIGINT once took longer than the 20 s wait
        nodes.stop(second, signal.SIGKILL)
        print(
            f"smoother killed after {LOST_FROM:g} s, restarted at {LOST_TO:g} s: "
            f"{len(killed.map.pose_stamps)} poses resumed, {lost} odometry samples lost"
        )
    finally:
        client.close()


def test_a_checkpoint_or_state_that_cannot_be_used_is_one_error_and_an_empty_start(
    ros_context, tmp_path, capfd
) -> None:
    from csam_ros.nodes.smoother import Smoother

    garbage = tmp_path / "garbage.npz"
    garbage.write_bytes(b"\x00" * 100)
    robot1 = tmp_path / "robot1.npz"
    for namespace, path, error in (
        ("robot1", garbage, "not a readable .npz file"),
        ("robot2", robot1, "the checkpoint of 'robot1', not of 'robot2'"),
    ):
        smoother = Smoother(
            context=ros_context,
            namespace=namespace,
            parameter_overrides=[
                Parameter("robots", value=["robot1", "robot2"]),
                Parameter("checkpoint_path", value=str(path)),
            ],
        )
        try:
            assert len(smoother.map.stamps) == 0 and smoother.restarts == 0
            if namespace == "robot1":  # then it writes a good checkpoint of robot1
                messages, _ = _smoother_messages()
                for m in messages[:60]:
                    if m.topic == "/robot1/odom":
                        smoother.on_odometry(m.message)
                smoother.solve_and_publish()
                smoother.write_checkpoint(robot1)
                assert smoother.errors == 0
        finally:
            smoother.destroy_node()
        logged = capfd.readouterr().err
        assert logged.count("checkpoint not used, starting empty") == 1, logged
        assert error in logged
    # the merger's state file likewise (here a smoother's checkpoint)
    from csam_ros.nodes.merger import Merger

    merger = Merger(
        context=ros_context, parameter_overrides=[Parameter("state_path", value=str(robot1))]
    )
    try:
        assert (
            merger.policy.local_maps == {}
            and merger.policy.solves == 0
            and merger.policy.last_result is None
        )
    finally:
        merger.destroy_node()
    logged = capfd.readouterr().err
    assert logged.count("merger state not used, starting empty") == 1, logged
    assert "a 'smoother' file, not a 'merger' one" in logged


def _replace_merger(harness: MergerHarness, context: Any, **parameters: Any) -> None:
    """Kill the harness's merger (destroyed, its thread left) and start a new one."""
    from csam_ros.nodes.merger import Merger

    harness.executor.remove_node(harness.merger)
    harness.merger.destroy_node()
    overrides = {"robots": ROBOTS, "solve_period": 0.02, "solve_wait": 0.0, **parameters}
    harness.merger = Merger(
        context=context,
        parameter_overrides=[Parameter(k, value=v) for k, v in overrides.items()],
    )
    harness.executor.add_node(harness.merger)


def test_a_killed_merger_republishes_the_joined_map_in_one_solve(ros_context, spin, nodes) -> None:
    """A merger process killed (SIGKILL) and started again: from the smoothers' whole local
    maps, which it asks for, and their latched rendezvous poses alone it publishes the same
    joined map, after one solve."""
    import rclpy

    from csam_ros.nodes.common import publisher, subscribe
    from csam_ros.ros.topics import JOINED_MAP, RENDEZVOUS_POSES, STATUS

    messages = run_messages()
    node = rclpy.create_node("smoothers", context=ros_context)
    smoothers = Smoothers(node, ROBOTS)  # they send their whole maps when a merger asks
    for r in ROBOTS:
        smoothers.whole[r] = messages.local_maps[r]
        publisher(node, RENDEZVOUS_POSES, RENDEZVOUS_POSES.of(r)).publish(messages.rendezvous[r])
    joined: list[Any] = []
    solves: list[str] = []
    subscribe(node, JOINED_MAP, joined.append)
    subscribe(
        node,
        STATUS,
        lambda m: solves.extend(
            kv.value
            for st in m.status
            if st.name == "merger"
            for kv in st.values
            if kv.key == "solves"
        ),
    )
    executor = SingleThreadedExecutor(context=ros_context)
    executor.add_node(node)
    # the default solve period (0.5 s): it asks for both maps at once, so they arrive together
    args = ["--ros-args", "-p", "robots:=[robot1,robot2]"]
    try:
        first = nodes.start("merger", *args)
        assert spin(executor, lambda: len(joined) > 0, 60)
        spin(executor, lambda: False, 1.5)  # any later solve of the first merger
        assert nodes.stop(first, signal.SIGKILL) == -signal.SIGKILL
        before, published = joined[-1], len(joined)
        nodes.start("merger", *args)
        assert spin(executor, lambda: len(joined) > published, 60)
        solves.clear()
        assert spin(executor, lambda: len(solves) > 0, 10)
        assert solves[-1] == "1"
        assert joined_view(joined[-1]) == joined_view(before)
        assert all(smoothers.resyncs[r] >= 2 for r in ROBOTS)  # one per merger at least
    finally:
        node.destroy_node()
        executor.shutdown()


def test_a_merger_resumed_from_its_state_goes_on_as_an_uninterrupted_one(
    ros_context, spin, tmp_path
) -> None:
    """The merger's state saved at a solve with robot2's map of the first 25 s; a new merger
    takes it up with no smoother left (its joined map comes from the state alone), then both
    whole maps arrive: the joined map equals the one of a merger that never stopped."""
    from csam_ros.nodes.common import publisher
    from csam_ros.ros.topics import RENDEZVOUS_POSES

    state = tmp_path / "merger.npz"
    early, whole = run_messages(end=25.0), run_messages(session=2)
    harness = MergerHarness(ros_context, spin, state_path=str(state))
    try:
        joined = harness.start(early)
        solves = harness.merger.policy.solves
        for r in ROBOTS:  # the smoothers are gone: nothing holds their maps any more
            harness.smoothers.destroy(r)
            harness.injector.destroy_publisher(harness.rendezvous[r])
        _replace_merger(harness, ros_context, state_path=str(state))
        published = len(harness.joined)
        harness.wait(lambda: len(harness.joined) > published)
        assert (
            harness.merger.policy.solves == solves and harness.merger.policy.reference == "robot1"
        )
        assert set(harness.merger.policy.local_maps) == set(ROBOTS)
        assert joined_view(harness.joined[-1]) == joined_view(joined)

        # the smoothers are back with their whole maps: the merger goes on from its state
        harness.smoothers = Smoothers(harness.injector, ROBOTS)
        harness.rendezvous = {
            r: publisher(harness.injector, RENDEZVOUS_POSES, RENDEZVOUS_POSES.of(r)) for r in ROBOTS
        }
        poses = len(whole.local_maps["robot2"].pose_stamps)

        def robot2_whole() -> bool:
            return any(
                t.robot == "robot2" and len(t.poses) == poses
                for t in harness.joined[-1].trajectories
            )

        harness.hold(whole)
        harness.wait(lambda: harness.merger.policy.solves > solves and robot2_whole())
        harness.wait(lambda: not harness.merger.policy.dirty and not harness.merger.policy.solving)
        continued = harness.resolve()
        assert harness.merger.policy.restarts == {}

        # a merger that never stopped, on the same maps (it asks the smoothers for them)
        _replace_merger(harness, ros_context)
        published = len(harness.joined)
        harness.wait(lambda: len(harness.joined) > published)
        harness.wait(lambda: not harness.merger.policy.dirty and not harness.merger.policy.solving)
        uninterrupted = harness.resolve()
        assert joined_view(continued) == joined_view(uninterrupted)
        assert joined_view(continued) != joined_view(joined)
    finally:
        harness.close()


OFFSET = 0.3  # s: robot2's clock against robot1's


def _clock_offset(log: MultiRobotLog, robot: str, offset: float) -> MultiRobotLog:
    """``log`` with every stamp of ``robot`` (and its true trajectory's) ``offset`` s later:
    its clock is ahead of the others' by that much."""
    from dataclasses import replace

    r = log.robots[robot]
    moved = replace(
        r,
        odometry=replace(r.odometry, stamps=r.odometry.stamps + offset),
        features=replace(r.features, stamps=r.features.stamps + offset),
        rendezvous=replace(r.rendezvous, stamps=r.rendezvous.stamps + offset),
    )
    truth = log.truth
    if truth is not None:
        stamps = {**truth.trajectory_stamps, robot: truth.trajectory_stamps[robot] + offset}
        truth = replace(truth, trajectory_stamps=stamps)
    return MultiRobotLog({**log.robots, robot: moved}, truth)


def _side_by_side() -> MultiRobotLog:
    """map_joining with robot2 starting 2 m ahead and 2 m to the left of robot1, both driving
    the same way: robot1 sees robot2 from its first sample to its last."""
    from dataclasses import replace

    scenario = load_scenario("map_joining")
    robot1, robot2 = scenario.robots
    robot2 = replace(robot2, start_pose=(-8.5, 1.0, 0.0))
    return simulate(replace(scenario, robots=(robot1, robot2)), seed=1)


def _errors(result: Any, truth: Any) -> tuple[float, float]:
    """Landmark RMSE and the largest trajectory position RMSE of a joined map [m]."""
    from csam_ros.core.truth.evaluation import evaluate

    e = evaluate(result, truth)
    trajectory = max(v["position_rmse_m"] for v in e["trajectory_error"].values())
    return e["landmark_error"]["rmse_m"], trajectory


def test_a_robot_clock_offset_drops_and_counts_rendezvous_outside_its_trajectory(
    ros_context, spin
) -> None:
    """robot2's clock 0.3 s ahead: robot1's first sighting of robot2 (at 0 s) comes before
    robot2's first pose (at 0.3 s). robot2's smoother and the merger drop it and count it,
    the others are joined at the wrong moment of robot2's path; the joined map still forms,
    equals the core's on the same data, and its error is measured."""
    import rclpy

    from csam_ros.core.joining.pipeline import run_csam
    from csam_ros.nodes.common import publisher
    from csam_ros.nodes.smoother import OUTSIDE_TRAJECTORY
    from csam_ros.ros.conversions import log_to_messages
    from csam_ros.ros.topics import parse

    clean = _side_by_side()
    log = _clock_offset(clean, "robot2", OFFSET)
    expected = run_csam(log)
    robots = list(log.robots)
    smoothers, merger = smoothers_and_merger(ros_context, robots)
    source = rclpy.create_node("clock_offset_source", context=ros_context)
    messages = log_to_messages(log, with_truth=False)
    pubs = {}
    for m in messages:
        if m.topic not in pubs:
            topic, robot = parse(m.topic)
            pubs[m.topic] = publisher(source, topic, topic.of(robot))
    executor = SingleThreadedExecutor(context=ros_context)
    for n in (source, merger, *smoothers.values()):
        executor.add_node(n)
    try:
        assert spin(executor, lambda: all(p.get_subscription_count() > 0 for p in pubs.values()))
        spin(executor, lambda: False, 1.0)
        for m in messages:
            pubs[m.topic].publish(m.message)
            executor.spin_once(timeout_sec=0.0)
        last = {r: float(log.robots[r].odometry.stamps[-1]) for r in robots}
        assert spin(
            executor,
            lambda: all(s.filter.clock(r) == last[r] for r, s in smoothers.items()),
            30,
        )
        spin(executor, lambda: False, 0.5)
        assert final_joined_result(executor, smoothers, merger) is not None
        spin(executor, lambda: False, 0.3)
        result = merger.policy.last_result
        assert result is not None
        # robot2's smoother holds no pose before its first one: the measurement is counted
        assert smoothers["robot2"].drops.as_dict() == {OUTSIDE_TRAJECTORY: 1}
        assert all(s.errors == 0 for s in smoothers.values())
        # the merger leaves it out and counts it, as the core does offline
        span = {"robot1": {"outside_trajectory": 1}}
        assert result.rendezvous_filter["trajectory_span"].dropped == span
        assert expected.rendezvous_filter["trajectory_span"].dropped == span
        assert result.robots["robot2"].alignment == "aligned"
        with merger._lock:
            status = {
                kv.key: kv.value
                for kv in status_array(merger.policy.status(), Time().to_msg()).status[-1].values
            }
        assert status["outside_trajectory"] == "1"
        for name, want in expected.robots.items():
            np.testing.assert_allclose(
                result.robots[name].poses_joined, want.poses_joined, atol=1e-6
            )
        before, after = _errors(run_csam(clean), clean.truth), _errors(result, log.truth)
        print(
            f"robot2's clock {OFFSET} s ahead: 1 rendezvous dropped; landmark RMSE "
            f"{before[0]:.3f} -> {after[0]:.3f} m, trajectory RMSE {before[1]:.3f} -> "
            f"{after[1]:.3f} m"
        )
        assert after[0] < 0.25 and after[1] < 0.25
    finally:
        for n in (source, merger, *smoothers.values()):
            n.destroy_node()
        executor.shutdown()


def _split_bag(bag: Any, first: Any, then: Any) -> None:
    """Write the messages of ``bag`` in its first half of log time to ``first``, the rest to
    ``then`` (as a recording stopped and started again)."""
    from csam_ros.bag import BagWriter, read_bag

    messages = list(read_bag(bag))
    middle = (messages[0].log_time_ns + messages[-1].log_time_ns) // 2
    for path, part in (
        (first, [m for m in messages if m.log_time_ns <= middle]),
        (then, [m for m in messages if m.log_time_ns > middle]),
    ):
        with BagWriter(path, flush_period_s=3600) as writer:
            for m in part:
                if m.topic not in writer.topics:
                    writer.add_topic(m.topic, m.msgtype)
                writer.write(m.topic, m.log_time_ns, m.data)


def test_an_offline_replay_continued_from_its_saved_state_equals_the_whole_replay(
    tmp_path, capsys
) -> None:
    """csam replay --offline of a recorded run's first half with --save-state, then of its
    second half with --resume: the same summary as one replay of the whole bag. A state file
    that cannot be used, or the options without --offline, are one-line errors."""
    from csam_ros.cli import main
    from csam_ros.run.offline import offline_summary

    bag = Path(__file__).resolve().parents[2] / "bags" / "map_joining"
    first, then, state = tmp_path / "first", tmp_path / "then", tmp_path / "state.npz"
    _split_bag(bag, first, then)
    whole, _ = offline_summary(bag)
    offline_summary(first, save_state=state)
    continued, _ = offline_summary(then, resume=state)
    assert continued.dropped == whole.dropped
    assert continued.result.to_dict() | {"timing_s": {}} == whole.result.to_dict() | {
        "timing_s": {}
    }
    halfway = OfflineState.read(state)
    assert halfway.result is not None
    assert len(halfway.result.associations) < len(whole.result.associations)

    (tmp_path / "bad.npz").write_text("not a state")
    for argv, error in (
        (["--offline", "--resume", tmp_path / "bad.npz"], "--resume: "),
        (["--save-state", tmp_path / "x.npz"], "go with --offline"),
    ):
        code = main(["replay", str(then), "--out", str(tmp_path / "out"), *map(str, argv)])
        lines = capsys.readouterr().err.strip().splitlines()
        assert code == 2 and len(lines) == 1 and error in lines[0], lines
