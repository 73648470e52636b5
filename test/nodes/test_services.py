"""The state services of live nodes, called over DDS in the isolated domain: ``~/save_state``,
``~/load_state``, ``~/reset`` and ``~/pause`` of a smoother and of the merger
(csam_ros/nodes/state_services.py).

A state saved, the node destroyed and a new one started and loaded holds the same map (a
smoother's local map, the merger's joined map); a file that cannot be used is refused in one
line and the node keeps its state; a reset node holds nothing and takes data from the start
again; a paused node drops (and counts) its input and takes it again once resumed."""

from __future__ import annotations

import contextlib
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
from merger_harness import ROBOTS, MergerHarness, joined_view, resent, run_messages
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter

from csam_ros.core.exchange.checkpoint import UNUSABLE_STATE, MergerState, SmootherCheckpoint
from csam_ros.core.exchange.map_updates import HeldMap, KeyedMap, MissingBaseError, apply_update
from csam_ros.core.exchange.state_files import read_npz, write_npz
from csam_ros.core.merging.policy_inputs import NO_MAP_HELD
from csam_ros.core.model.log import MultiRobotLog
from csam_ros.datasets.scenario import load_scenario
from csam_ros.datasets.simulation import simulate
from csam_ros.nodes.state_services import PAUSED

ATOL = 1e-9
SMOOTHER_TOPICS = ("/robot1/odom", "/robot1/features", "/robot1/rendezvous", "/robot2/rendezvous")


def _call(spin: Any, executor: Any, client: Any, request: Any) -> Any:
    """``request`` sent over DDS; the reply (spinning ``executor``, which serves it)."""
    assert spin(executor, client.service_is_ready, 20.0), f"{client.srv_name} never came"
    future = client.call_async(request)
    assert spin(executor, future.done, 60.0), f"{client.srv_name} never answered"
    return future.result()


def _refused(reply: Any) -> None:
    """A reply that says no, in one line."""
    assert not reply.success
    assert reply.message and "\n" not in reply.message, reply.message


def service_types() -> dict[str, type]:
    """The type of each service a smoother and the merger answer, by name."""
    from csam_msgs.srv import LoadState, SaveState
    from std_srvs.srv import SetBool, Trigger

    from csam_ros.ros.topics import FLUSH, LOAD_STATE, PAUSE, RESET, SAVE_STATE

    return {
        FLUSH: Trigger,
        SAVE_STATE: SaveState,
        LOAD_STATE: LoadState,
        RESET: Trigger,
        PAUSE: SetBool,
    }


def _loads_refused(
    client: Any, tmp_path: Path, garbage: Path, other: tuple[Path, str], unchanged: Any
) -> None:
    """``~/load_state`` of a missing file, garbage, ``other`` (a file of another robot or
    kind, and why it is refused) and no path: each refused in one line naming why, and the
    node's state ``unchanged()``."""
    from csam_ros.ros.topics import LOAD_STATE

    for path, why in (
        (tmp_path / "missing.npz", "no such file"),
        (garbage, "not a readable .npz file"),
        other,
        ("", "no path given"),
    ):
        reply = client.call(LOAD_STATE, path=str(path))
        _refused(reply)
        assert why in reply.message, reply.message
        assert unchanged()


def _sensor_messages() -> tuple[list[Any], float]:
    """robot1's sensor messages of map_joining and robot2's rendezvous (robot1's smoother
    takes those too), in stamp order; and the first odometry stamp."""
    from csam_ros.ros.conversions import log_to_messages

    log = simulate(load_scenario("map_joining"), seed=3)
    messages = log_to_messages(MultiRobotLog(log.robots), False)
    return [m for m in messages if m.topic in SMOOTHER_TOPICS], float(
        log.robots["robot1"].odometry.stamps[0]
    )


def _between(messages: list[Any], t0: float, start: float, end: float) -> list[Any]:
    return [m for m in messages if start < m.stamp_ns / 1e9 - t0 <= end]


class SmootherClient:
    """Smoothers of robot1 in-process, one at a time, and a client node over DDS: it feeds
    them, builds the map their local map updates send, and calls their services."""

    def __init__(self, context: Any, spin: Any) -> None:
        import rclpy

        from csam_ros.nodes.common import publisher, subscribe
        from csam_ros.ros.topics import (
            LOCAL_MAP_UPDATES,
            Topic,
            declaration,
            smoother_service,
        )

        self.context, self.spin = context, spin
        self.node = rclpy.create_node("services_client", context=context)
        self.pubs = {}
        for name in SMOOTHER_TOPICS:
            topic: Topic = declaration(name)
            self.pubs[name] = publisher(self.node, topic, name)
        self.updates: list[Any] = []
        self.held: HeldMap | None = None  # the map the updates build
        subscribe(self.node, LOCAL_MAP_UPDATES, self._on_update, LOCAL_MAP_UPDATES.of("robot1"))
        service = service_types()
        self.clients = {
            name: self.node.create_client(kind, smoother_service("robot1", name))
            for name, kind in service.items()
        }
        self.types = service
        self.executor = SingleThreadedExecutor(context=context)
        self.executor.add_node(self.node)
        self.smoother: Any = None

    def start(self, checkpoint: Path | None = None) -> Any:
        """A new smoother of robot1 (the last one destroyed first), with ``checkpoint_path``
        ``checkpoint`` when given."""
        from csam_ros.nodes.smoother import Smoother

        self.stop()
        self.smoother = Smoother(
            context=self.context,
            namespace="robot1",
            parameter_overrides=[
                Parameter("robots", value=ROBOTS),
                Parameter("publish_period", value=1000.0),
                *([Parameter("checkpoint_path", value=str(checkpoint))] if checkpoint else []),
            ],
        )
        self.executor.add_node(self.smoother)
        # every topic fed here reaches it (odometry is best effort: not resent)
        for pub in self.pubs.values():
            self.wait(lambda pub=pub: pub.get_subscription_count() > 0)
        self.spin(self.executor, lambda: False, 0.5)
        return self.smoother

    def stop(self) -> None:
        if self.smoother is not None:
            self.executor.remove_node(self.smoother)
            self.smoother.destroy_node()
            self.smoother = None

    def _on_update(self, msg: Any) -> None:
        from csam_ros.ros.map_messages import map_update_from_message

        self.updates.append(msg)
        with contextlib.suppress(MissingBaseError):  # the test asks for the whole map
            self.held = apply_update(self.held, map_update_from_message(msg, "robot1"))

    def wait(self, condition: Any, timeout_s: float = 30.0) -> None:
        assert self.spin(self.executor, condition, timeout_s), "timed out"

    def send(self, messages: list[Any]) -> None:
        for m in messages:
            self.pubs[m.topic].publish(m.message)
            self.executor.spin_once(timeout_sec=0.001)

    def call(self, name: str, **fields: Any) -> Any:
        request = self.types[name].Request(**fields)
        return _call(self.spin, self.executor, self.clients[name], request)

    def flush(self) -> int:
        """Flush until the published stamp stays the same (messages may still be queued)."""
        from csam_ros.ros.topics import FLUSH

        previous, final = None, int(self.call(FLUSH).message)
        while final != previous:
            self.spin(self.executor, lambda: False, 0.3)
            previous, final = final, int(self.call(FLUSH).message)
        return final

    def close(self) -> None:
        self.stop()
        self.node.destroy_node()
        self.executor.shutdown()


def _local_map(smoother: Any) -> tuple[np.ndarray, ...]:
    """A smoother's local map: pose stamps and poses, feature labels and positions (copies)."""
    m = smoother.map
    return tuple(np.array(a) for a in (m.stamps, m.poses, m.landmark_labels, m.landmarks))


def _same_local_map(a: tuple[np.ndarray, ...], b: tuple[np.ndarray, ...]) -> None:
    stamps_a, poses_a, labels_a, features_a = a
    stamps_b, poses_b, labels_b, features_b = b
    np.testing.assert_array_equal(stamps_a, stamps_b)
    np.testing.assert_array_equal(labels_a, labels_b)
    np.testing.assert_allclose(poses_a, poses_b, rtol=0, atol=ATOL)
    np.testing.assert_allclose(features_a, features_b, rtol=0, atol=ATOL)


def _same_held(a: HeldMap, b: HeldMap) -> None:
    """Two maps built from updates are the same: stamps and labels exactly, numbers to ATOL."""
    for name in KeyedMap.__dataclass_fields__:
        x, y = getattr(a.map, name), getattr(b.map, name)
        if isinstance(x, np.ndarray) and x.dtype.kind == "f":
            np.testing.assert_allclose(x, y, rtol=0, atol=ATOL, err_msg=name)
        elif isinstance(x, np.ndarray):
            np.testing.assert_array_equal(x, y, err_msg=name)
        else:
            assert x == y, name


def test_a_smoother_saved_destroyed_and_loaded_into_a_new_one_holds_the_same_map(
    ros_context, spin, tmp_path
) -> None:
    from csam_ros.ros.topics import LOAD_STATE, SAVE_STATE

    messages, t0 = _sensor_messages()
    client = SmootherClient(ros_context, spin)
    try:
        first = client.start()
        client.send(_between(messages, t0, -1.0, 15.0))
        client.flush()  # the last update after a flush is exact
        assert client.held is not None and len(first.map.stamps) > 10
        saved_map, sent, session = _local_map(first), client.held, first.sender.session
        drops = first.drops.as_dict()

        state = tmp_path / "robot1.npz"
        reply = client.call(SAVE_STATE, path=str(state))
        assert reply.success and "\n" not in reply.message and str(state) in reply.message
        assert SmootherCheckpoint.read(state, "robot1").published_ns == first.published_ns

        # a new smoother with a map of its own (the first 5 s), replaced by the saved one
        second = client.start()
        client.send(_between(messages, t0, -1.0, 5.0))
        client.flush()
        assert len(second.map.stamps) < len(saved_map[0])
        updates = len(client.updates)
        reply = client.call(LOAD_STATE, path=str(state))
        assert reply.success and "\n" not in reply.message, reply.message
        _same_local_map(_local_map(second), saved_map)
        assert second.drops.as_dict() == drops and second.restarts == 1
        # published at once: the whole map, the first update of a new session
        client.wait(lambda: len(client.updates) > updates)
        update = client.updates[-1]
        assert update.session == second.sender.session != session
        assert update.base_sequence == 0
        assert client.held is not None and client.held.session == update.session
        _same_held(client.held, sent)

        # a file that cannot be used: refused in one line, the state as it was
        garbage = tmp_path / "garbage.npz"
        garbage.write_bytes(b"\x00" * 100)
        robot2 = tmp_path / "robot2.npz"
        replace(SmootherCheckpoint.read(state, "robot1"), robot="robot2").write(robot2)
        held_map, held_session = second.map, second.sender.session
        _loads_refused(
            client,
            tmp_path,
            garbage,
            (robot2, "the checkpoint of 'robot2', not of 'robot1'"),
            lambda: second.map is held_map and second.sender.session == held_session,
        )
        _same_local_map(_local_map(second), saved_map)
        reply = client.call(SAVE_STATE, path=str(tmp_path))  # a folder: cannot be written
        _refused(reply)
        assert reply.message.startswith("not saved:"), reply.message
    finally:
        client.close()


def test_a_paused_smoother_drops_and_counts_its_input_and_a_reset_one_starts_empty(
    ros_context, spin
) -> None:
    from csam_ros.ros.topics import FLUSH, PAUSE, RESET

    messages, t0 = _sensor_messages()
    client = SmootherClient(ros_context, spin)
    try:
        smoother = client.start()
        early = _between(messages, t0, -1.0, 10.0)
        client.send(early)
        stamp = client.flush()
        before = _local_map(smoother)

        reply = client.call(PAUSE, data=True)
        assert reply.success and reply.message == "paused: input is dropped"
        # features and rendezvous are reliable: every one arrives, and is dropped
        later = _between(messages, t0, 10.0, 20.0)
        reliable = [m for m in later if m.topic != "/robot1/odom"]
        client.send(reliable)
        client.wait(lambda: smoother.drops.as_dict().get(PAUSED) == len(reliable))
        assert client.call(PAUSE, data=True).message == "already paused: input is dropped"
        # it answers its services and keeps its map
        assert client.call(FLUSH).message == str(stamp)
        _same_local_map(_local_map(smoother), before)
        assert smoother.drops.as_dict() == {PAUSED: len(reliable)}

        assert client.call(PAUSE, data=False).message == "taking input"
        client.send(later)
        client.flush()
        assert len(smoother.map.stamps) > len(before[0])
        assert smoother.drops.as_dict() == {PAUSED: len(reliable)}

        # reset: nothing held, nothing counted, a new session
        session = smoother.sender.session
        reply = client.call(RESET)
        assert reply.success and "\n" not in reply.message
        assert len(smoother.map.stamps) == 0 and smoother.published_ns == -1
        assert smoother.drops.as_dict() == {} and smoother.sender.session != session
        assert smoother.frames.correction is None  # no map -> odom of the forgotten map
        # the data from the start again (earlier stamps than it had): taken, and its first
        # update is the whole map of the new session
        updates = len(client.updates)
        client.send(early)
        client.flush()
        assert smoother.drops.as_dict() == {}
        first_new = client.updates[updates]
        assert first_new.session == smoother.sender.session and first_new.base_sequence == 0
        assert client.held is not None and client.held.session == smoother.sender.session
        assert len(smoother.map.stamps) > 2 and smoother.map.stamps[0] - t0 < 10.0
        # map -> odom again from the replayed odometry: the latest key pose of the new map
        assert smoother.frames.correction is not None
        assert smoother.frames.odometry.pose_at(float(smoother.map.stamps[-1])) is not None
    finally:
        client.close()


def test_a_reset_writes_the_empty_state_where_the_smoother_keeps_its_checkpoint(
    ros_context, spin, tmp_path: Path
) -> None:
    from csam_ros.ros.topics import RESET

    messages, t0 = _sensor_messages()
    checkpoint = tmp_path / "robot1.npz"
    client = SmootherClient(ros_context, spin)
    try:
        client.start(checkpoint)
        client.send(_between(messages, t0, -1.0, 10.0))
        client.flush()
        assert len(SmootherCheckpoint.read(checkpoint, "robot1").local_map.keys) > 2
        assert client.call(RESET).success
        empty = SmootherCheckpoint.read(checkpoint, "robot1")
        assert len(empty.local_map.keys) == 0 and empty.published_ns == -1
        # a smoother started from it starts empty
        restarted = client.start(checkpoint)
        assert len(restarted.map.stamps) == 0 and restarted.published_ns == -1
    finally:
        client.close()


def test_a_smoother_given_a_checkpoint_no_run_could_write_keeps_its_state_and_answers(
    ros_context, spin, tmp_path: Path
) -> None:
    """Whole files (their CRCs match) holding a stamp no ROS time holds (10^30 ns), reversed
    odometry stamps or zero sigmas: at start each is refused, logged and counted
    (``unusable_state``), the smoother starts empty and answers ``~/resync``; given to
    ``~/load_state`` each is refused in one line and the map held stays."""
    from std_srvs.srv import Trigger

    from csam_ros.ros.topics import LOAD_STATE, RESYNC, SAVE_STATE, smoother_service

    messages, t0 = _sensor_messages()
    client = SmootherClient(ros_context, spin)
    resync = client.node.create_client(Trigger, smoother_service("robot1", RESYNC))
    try:
        client.start()
        client.send(_between(messages, t0, -1.0, 10.0))
        client.flush()
        good = tmp_path / "good.npz"
        assert client.call(SAVE_STATE, path=str(good)).success
        header, arrays = read_npz(good, "smoother")
        stamps, sigmas = arrays["map/odometry_stamps"], arrays["map/odometry_sigmas"]
        bad = {
            "huge_stamp.npz": ({**header, "published_ns": 10**30}, arrays),
            "reversed.npz": (header, {**arrays, "map/odometry_stamps": stamps[::-1].copy()}),
            "zero_sigma.npz": (header, {**arrays, "map/odometry_sigmas": 0.0 * sigmas}),
        }
        for name, (h, a) in bad.items():
            write_npz(tmp_path / name, "smoother", h, a)
        for name in bad:
            smoother = client.start(tmp_path / name)
            assert len(smoother.map.stamps) == 0 and smoother.restarts == 0, name
            assert smoother.drops.as_dict() == {UNUSABLE_STATE: 1}, name
            reply = _call(spin, client.executor, resync, Trigger.Request())
            assert not reply.success  # nothing sent yet, and alive
            assert reply.message.endswith("sequence 0"), reply.message

        smoother = client.start(good)
        held_map, held = smoother.map, _local_map(smoother)
        assert len(held[0]) > 2 and smoother.restarts == 1
        for count, name in enumerate(bad, 1):
            reply = client.call(LOAD_STATE, path=str(tmp_path / name))
            _refused(reply)
            assert name in reply.message and "not loaded" in reply.message, reply.message
            assert smoother.map is held_map
            assert smoother.drops.as_dict()[UNUSABLE_STATE] == count
        _same_local_map(_local_map(smoother), held)
        assert _call(spin, client.executor, resync, Trigger.Request()).success
    finally:
        client.close()


def _close_joined_maps(a: Any, b: Any) -> None:
    """Two joined map messages say the same to ATOL: robots, features, associations, base
    nodes, trajectories."""
    assert a.reference_robot == b.reference_robot
    assert [(tuple(f.members)) for f in a.features] == [(tuple(f.members)) for f in b.features]
    for f, g in zip(a.features, b.features, strict=True):
        np.testing.assert_allclose([f.x, f.y, *f.covariance], [g.x, g.y, *g.covariance], atol=ATOL)
    assert [(x.a, x.b) for x in a.associations] == [(x.a, x.b) for x in b.associations]
    assert [(n.robot, n.alignment) for n in a.base_nodes] == [
        (n.robot, n.alignment) for n in b.base_nodes
    ]
    for n, m in zip(a.base_nodes, b.base_nodes, strict=True):
        np.testing.assert_allclose(
            [n.pose.x, n.pose.y, n.pose.theta], [m.pose.x, m.pose.y, m.pose.theta], atol=ATOL
        )
    assert [t.robot for t in a.trajectories] == [t.robot for t in b.trajectories]
    for s, t in zip(a.trajectories, b.trajectories, strict=True):
        poses = [[p.x, p.y, p.theta] for p in s.poses]
        np.testing.assert_allclose(poses, [[p.x, p.y, p.theta] for p in t.poses], atol=ATOL)


class MergerServiceClients:
    """Clients of the merger's services on the harness's injector node."""

    def __init__(self, harness: MergerHarness) -> None:

        from csam_ros.ros.topics import merger_service

        self.harness = harness
        self.types = service_types()
        self.clients = {
            name: harness.injector.create_client(kind, merger_service(name))
            for name, kind in self.types.items()
        }

    def call(self, name: str, **fields: Any) -> Any:
        h = self.harness
        return _call(h.spin, h.executor, self.clients[name], self.types[name].Request(**fields))


def _new_merger(harness: MergerHarness, context: Any) -> None:
    """Destroy the harness's merger and start a new one."""
    from csam_ros.nodes.merger import Merger

    harness.executor.remove_node(harness.merger)
    harness.merger.destroy_node()
    harness.merger = Merger(
        context=context,
        parameter_overrides=[
            Parameter("robots", value=ROBOTS),
            Parameter("solve_period", value=0.02),
            Parameter("solve_wait", value=0.0),
        ],
    )
    harness.executor.add_node(harness.merger)


def test_a_merger_saved_destroyed_and_loaded_into_a_new_one_publishes_the_same_joined_map(
    ros_context, spin, tmp_path
) -> None:
    from csam_ros.ros.topics import LOAD_STATE, SAVE_STATE

    harness = MergerHarness(ros_context, spin)
    services = MergerServiceClients(harness)
    state = tmp_path / "merger.npz"
    try:
        refused = services.call(SAVE_STATE, path=str(state))  # nothing joined yet
        _refused(refused)
        assert not state.exists()
        joined = harness.start(run_messages())
        merger = harness.merger
        reference, solves = merger.policy.reference, merger.policy.solves
        reply = services.call(SAVE_STATE, path=str(state))
        assert reply.success and "\n" not in reply.message and str(state) in reply.message
        solved_again = harness.resolve()  # the next solve, warm-started from the saved one

        # the smoothers are gone: what the new merger holds comes from the file alone
        for r in ROBOTS:
            harness.smoothers.destroy(r)
            harness.injector.destroy_publisher(harness.rendezvous[r])
        _new_merger(harness, ros_context)
        assert harness.merger.policy.last_result is None
        published = len(harness.joined)
        reply = services.call(LOAD_STATE, path=str(state))
        assert reply.success and "\n" not in reply.message, reply.message
        harness.wait(lambda: len(harness.joined) > published)
        _close_joined_maps(harness.joined[-1], joined)
        assert joined_view(harness.joined[-1]) == joined_view(joined)
        merger = harness.merger
        assert merger.policy.reference == reference and merger.policy.solves == solves
        assert set(merger.policy.local_maps) == set(ROBOTS)
        # it goes on as the merger that saved it: the next solve is the same
        _close_joined_maps(harness.resolve(), solved_again)

        # a file that cannot be used: refused in one line, the state as it was
        garbage = tmp_path / "garbage.npz"
        garbage.write_bytes(b"\x00" * 100)
        smoother_file = tmp_path / "robot1.npz"
        held_maps, result = merger.policy.local_maps, merger.policy.last_result
        checkpoint = _smoother_checkpoint(ros_context)
        checkpoint.write(smoother_file)
        _loads_refused(
            services,
            tmp_path,
            garbage,
            (smoother_file, "a 'smoother' file, not a 'merger' one"),
            lambda: merger.policy.local_maps is held_maps and merger.policy.last_result is result,
        )
    finally:
        harness.close()


def _smoother_checkpoint(context: Any) -> SmootherCheckpoint:
    """An (empty) smoother's checkpoint."""
    from csam_ros.nodes.smoother import Smoother

    smoother = Smoother(context=context, namespace="robot1")
    try:
        return smoother.checkpoint()
    finally:
        smoother.destroy_node()


def test_a_paused_merger_drops_and_counts_its_input_and_a_reset_one_starts_empty(
    ros_context, spin
) -> None:
    from csam_ros.ros.topics import FLUSH, PAUSE, RESET

    harness = MergerHarness(ros_context, spin)
    services = MergerServiceClients(harness)
    messages = run_messages()
    try:
        joined = harness.start(messages)
        merger = harness.merger
        harness.smoothers.whole.clear()  # a resync request gets nothing from now on

        reply = services.call(PAUSE, data=True)
        assert reply.success and reply.message == "paused: input is dropped"
        held, solves = merger.policy.local_maps, merger.policy.solves
        harness.publish("robot1", resent(messages.local_maps["robot1"]))
        harness.publish("robot2", messages.rendezvous["robot2"])
        harness.wait(lambda: merger.drops.as_dict().get(PAUSED) == 2)
        assert merger.policy.local_maps is held and not merger.policy.dirty
        assert services.call(FLUSH).success  # it answers its services

        # reset (paused still): nothing held, an empty joined map, no map asked for
        published, process = len(harness.joined), merger.solve_process
        reply = services.call(RESET)
        assert reply.success and "\n" not in reply.message
        assert merger.solve_process is not process  # a new one: no map or warm start kept
        policy = merger.policy
        assert policy.local_maps == {} and policy.last_result is None and policy.solves == 0
        assert merger.drops.as_dict() == {} and policy.reference == ""
        harness.wait(lambda: len(harness.joined) > published)
        empty = harness.joined[-1]
        assert not empty.features and not empty.trajectories and not empty.base_nodes
        assert list(merger.policy.resyncs_wanted()) == []
        assert solves > 0 and merger.policy.paused

        # resumed: it wants every robot's whole map again, and takes the maps sent
        assert services.call(PAUSE, data=False).message == "taking input"
        assert list(merger.policy.resyncs_wanted()) == [(r, NO_MAP_HELD) for r in ROBOTS]
        again = harness.start(messages)
        # the same joined map as the merger's before the reset: nothing of it was kept
        assert joined_view(again) == joined_view(joined)
        assert merger.drops.as_dict() == {}
    finally:
        harness.close()


def test_a_reset_writes_the_empty_state_where_the_merger_keeps_its_state(
    ros_context, spin, tmp_path: Path
) -> None:
    from csam_ros.ros.topics import RESET

    state = tmp_path / "merger.npz"
    harness = MergerHarness(ros_context, spin, state_path=str(state))
    services = MergerServiceClients(harness)
    try:
        harness.start(run_messages())
        assert MergerState.read(state).maps
        assert services.call(RESET).success
        empty = MergerState.read(state)
        assert empty.maps == {} and empty.result is None and empty.robots == ROBOTS
    finally:
        harness.close()
