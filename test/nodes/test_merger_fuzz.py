"""Fuzz the merger's boundary: generated LocalMapUpdate and RendezvousPoses messages, after
good maps.

Every message goes to a real in-process merger through its own (guarded) subscription
callback, then the merger solves synchronously (``solve_pending``, what its worker thread
runs). Properties, for every message:

- no exception reaches ``guarded`` (``callback_error`` stays 0) and no solve fails;
- a message that leaves the merger's data as it was (refused, an update it already holds or
  one whose base it lacks, or with its bad rows dropped) leaves the joined map exactly as it
  was;
- a message the merger takes is one it can solve with.

The delta protocol is fuzzed by runs of events on robot2's topic: its smoother's real updates
(deltas, whole maps, resync answers with the map and the reply in either order) among
another publisher's (whole maps and deltas of other sessions, replays of earlier updates,
real updates with a bad kernel, a NaN or a sequence that skips). After every event the map
held of robot2 is the last one its smoother sent, and nothing raised.

Under the test profile each of the first three tests draws ``CSAM_FUZZ_EXAMPLES`` examples
(default 60, all three in about 10 s on 2 cores), the protocol test a third as many runs;
for a longer run:

    CSAM_FUZZ_EXAMPLES=1000 .venv/bin/python -m pytest -q -s test/nodes/test_merger_fuzz.py

``-s`` shows how many examples ran and how many the merger refused or took.
"""

from __future__ import annotations

import math
import os
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np
import pytest
from csam_msgs.msg import (
    LocalMapUpdate,
    RendezvousObservation,
    RendezvousObservations,
    RendezvousPoses,
)
from geometry_msgs.msg import Pose2D
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from merger_harness import (
    ROBOTS,
    STAMP_NS,
    MergerHarness,
    RunMessages,
    copied,
    resent,
    run_messages,
    with_robot2,
)
from rclpy.task import Future
from std_srvs.srv import Trigger

from csam_ros.core.exchange.map_arrays import robot_map_arrays
from csam_ros.core.exchange.map_updates import MapUpdate, UpdateSender, resync_answer
from csam_ros.core.joining.result import CsamResult
from csam_ros.ros.conversions import ns_to_time
from csam_ros.ros.map_messages import local_map_update_message

EXAMPLES = int(os.environ.get("CSAM_FUZZ_EXAMPLES", "60"))
FUZZ = settings(
    max_examples=EXAMPLES,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
PROTOCOL_FUZZ = settings(FUZZ, max_examples=max(EXAMPLES // 3, 10))
TALLY: Counter[str] = Counter()

floats = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from([0.0, -0.0, 1e-300, -1.0, 1.0, 1e9, 1e12, 1e300, math.nan, math.inf]),
)
uint32 = st.one_of(st.integers(0, 6), st.sampled_from([1000, 2**31, 4_000_000_000, 2**32 - 1]))
int64 = st.one_of(st.integers(-3, 6), st.sampled_from([999_999, -(2**63), 2**63 - 1]))
names = st.sampled_from(["robot1", "robot2", "robot9", "", "robot2/", "/robot2"])
stamp_ns = st.one_of(st.integers(0, 40 * 10**9), st.sampled_from([0, 2**62]))
int64_stamp = st.one_of(stamp_ns, st.sampled_from([-1, -(2**63), 2**63 - 1]))

# each update's flat fields: (name, values per row, what a value is)
POSE_FIELDS = (("pose_stamps", 1, "stamp"), ("poses", 3, "float"))
FEATURE_FIELDS = (("feature_labels", 1, "label"), ("features", 2, "float"))
ODOMETRY_FIELDS = (
    ("odometry_stamps", 2, "stamp"),
    ("odometry_deltas", 3, "float"),
    ("odometry_sqrt_information", 9, "float"),
)
OBSERVATION_FIELDS = (
    ("observation_stamps", 1, "stamp"),
    ("observation_labels", 1, "label"),
    ("observation_points", 2, "float"),
    ("observation_sqrt_information", 4, "float"),
)
FLAT_FIELDS = POSE_FIELDS + FEATURE_FIELDS + ODOMETRY_FIELDS + OBSERVATION_FIELDS


def _values(kind: str, stamps: list[int]) -> st.SearchStrategy[Any]:
    """One value of a flat field: a float, a label, or a stamp (often one of ``stamps``)."""
    if kind == "float":
        return floats
    if kind == "label":
        return int64
    return st.one_of(int64_stamp, st.sampled_from(stamps)) if stamps else int64_stamp


def _time() -> st.SearchStrategy[Any]:
    return stamp_ns.map(ns_to_time)


def _pose() -> st.SearchStrategy[Pose2D]:
    return st.builds(Pose2D, x=floats, y=floats, theta=floats)


@st.composite
def random_map_updates(draw: st.DrawFn, stamps: list[int]) -> LocalMapUpdate:
    """An update with every field drawn: rows of each group mostly of one count (the checks
    then go deeper), any length otherwise; stamps often robot2's."""
    robot = draw(st.one_of(st.just("robot2"), names))  # mostly the topic's: checks go deeper
    m = LocalMapUpdate(robot=robot)
    m.header.frame_id = draw(st.sampled_from([f"{robot}/map", f"{robot}/map", "world"]))
    m.session = draw(st.one_of(st.just(1), uint32))
    m.sequence = draw(uint32)
    m.base_sequence = draw(uint32)
    m.observations_before = draw(uint32)
    for group in (POSE_FIELDS, FEATURE_FIELDS, ODOMETRY_FIELDS, OBSERVATION_FIELDS):
        rows = draw(st.integers(0, 5))
        for name, width, kind in group:
            exact = draw(st.booleans()) or draw(st.booleans())
            size = rows * width if exact else draw(st.integers(0, 6 * width))
            values = draw(st.lists(_values(kind, stamps), min_size=size, max_size=size))
            setattr(m, name, values)
    m.first_pose_prior_sqrt_information = draw(st.lists(floats, min_size=9, max_size=9))
    m.observation_robust_kernel = draw(st.sampled_from(["", "huber", "cauchy", "tukey"]))
    m.observation_robust_parameter = draw(floats)
    m.cost = draw(floats)
    return m


def _mutate_list(draw: st.DrawFn, items: list[Any], fresh: Any) -> None:
    """Delete a slice of, duplicate an element of, or append a drawn element to ``items``."""
    op = draw(st.sampled_from(["delete", "duplicate", "append"]))
    if op == "append" or not items:
        items.append(draw(fresh))
    elif op == "delete":
        i = draw(st.integers(0, len(items) - 1))
        del items[i : i + draw(st.integers(1, 3))]
    else:
        items.insert(
            draw(st.integers(0, len(items))), copied(items[draw(st.integers(0, len(items) - 1))])
        )


def _set_number(draw: st.DrawFn, items: list[Any], field: str, values: Any) -> None:
    if items:
        item = items[draw(st.integers(0, len(items) - 1))]
        current = getattr(item, field)
        if not isinstance(current, str) and hasattr(current, "__len__"):
            current = list(current)
            current[draw(st.integers(0, len(current) - 1))] = draw(values)
            setattr(item, field, current)
        else:
            setattr(item, field, draw(values))


def mutated_map_updates(good: LocalMapUpdate) -> st.SearchStrategy[LocalMapUpdate]:
    """robot2's good whole map, sent again as a new update (or as one that adds it to itself),
    with one to three values, rows or header fields changed."""
    stamps = list(good.pose_stamps)
    observations = len(good.observation_labels)

    @st.composite
    def build(draw: st.DrawFn) -> LocalMapUpdate:
        m = resent(good)
        if draw(st.booleans()):  # on top of the good map: every row again, as changes
            m.base_sequence, m.observations_before = good.sequence, observations
        for _ in range(draw(st.integers(1, 3))):
            target = draw(st.sampled_from(["value", "values", "rows", "prior", "header", "kernel"]))
            name, width, kind = draw(st.sampled_from(FLAT_FIELDS))
            values = list(getattr(m, name))
            if target == "value" and values:
                values[draw(st.integers(0, len(values) - 1))] = draw(_values(kind, stamps))
            elif target == "values":
                _mutate_list(draw, values, _values(kind, stamps))
            elif target == "rows" and values:  # whole rows: the group may still agree
                rows = len(values) // width
                i = draw(st.integers(0, rows - 1))
                row = values[i * width : (i + 1) * width]
                if draw(st.booleans()):
                    del values[i * width : (i + 1) * width]
                else:
                    values[i * width : i * width] = row
            elif target == "prior":
                prior = list(m.first_pose_prior_sqrt_information)
                prior[draw(st.integers(0, 8))] = draw(floats)
                m.first_pose_prior_sqrt_information = prior
            elif target == "header":
                field = draw(
                    st.sampled_from(
                        ["session", "sequence", "base_sequence", "observations_before", "robot"]
                    )
                )
                setattr(m, field, draw(names if field == "robot" else uint32))
            elif target == "kernel":
                m.observation_robust_kernel = draw(st.sampled_from(["", "huber", "cauchy", "x"]))
                m.observation_robust_parameter = draw(floats)
            setattr(m, name, values)
        return m

    return build()


def _rows(pose_stamps: list[int]) -> st.SearchStrategy[RendezvousObservations]:
    stamps = st.one_of(stamp_ns, st.sampled_from(pose_stamps))

    def group(t: int, rows: list[RendezvousObservation]) -> RendezvousObservations:
        g = RendezvousObservations(observations=rows)
        g.header.stamp = ns_to_time(t)
        g.header.frame_id = "robot2/base_link"
        return g

    row = st.builds(
        RendezvousObservation,
        observed_robot=names,
        range=floats | st.floats(0.1, 50),
        bearing=floats | st.floats(-3, 3),
        sigma_range=floats | st.floats(0.01, 1),
        sigma_bearing=floats | st.floats(0.001, 0.1),
    )
    return st.builds(group, stamps, st.lists(row, max_size=3))


def rendezvous_messages(good: RendezvousPoses, pose_stamps: list[int]) -> st.SearchStrategy[Any]:
    """robot2's good rendezvous message with rows added, removed or changed, or one drawn
    from scratch."""

    @st.composite
    def mutated(draw: st.DrawFn) -> RendezvousPoses:
        m = copied(good)
        for _ in range(draw(st.integers(1, 3))):
            target = draw(st.sampled_from(["rows", "row", "stamps", "poses", "indices", "robot"]))
            if target == "rows":
                _mutate_list(draw, m.measurements, _rows(pose_stamps))
            elif target == "row" and m.measurements:
                g = m.measurements[draw(st.integers(0, len(m.measurements) - 1))]
                _set_number(
                    draw,
                    g.observations,
                    draw(st.sampled_from(["range", "bearing", "sigma_range", "sigma_bearing"])),
                    floats,
                )
                _set_number(draw, g.observations, "observed_robot", names)
            elif target == "stamps":
                _mutate_list(draw, m.stamps, _time())
            elif target == "poses":
                _set_number(draw, m.poses, draw(st.sampled_from(["x", "y", "theta"])), floats)
            elif target == "indices":
                values = list(m.pose_indices)
                _mutate_list(draw, values, uint32)
                m.pose_indices = values
            elif target == "robot":
                m.robot = draw(names)
                m.header.frame_id = draw(st.sampled_from([f"{m.robot}/map", "robot2/map"]))
        return m

    @st.composite
    def scratch(draw: st.DrawFn) -> RendezvousPoses:
        m = RendezvousPoses(robot=draw(names))
        m.header.frame_id = f"{m.robot}/map"
        k = draw(st.integers(0, 3))
        m.stamps = draw(st.lists(_time(), min_size=k, max_size=k + 1))
        m.poses = draw(st.lists(_pose(), min_size=k, max_size=k))
        m.pose_indices = draw(st.lists(uint32, min_size=k, max_size=k))
        m.measurements = draw(st.lists(_rows(pose_stamps), max_size=3))
        return m

    return st.one_of(mutated(), scratch())


def _view(result: CsamResult | None) -> Any:
    assert result is not None
    return (
        [(tuple(f.members), tuple(f.xy)) for f in result.features],
        [(a.a, a.b, a.mahalanobis) for a in result.associations],
        {
            n: (r.alignment, None if r.base_node is None else tuple(r.base_node))
            for n, r in result.robots.items()
        },
    )


def _same_data(policy: Any, maps: dict[str, Any], logs: dict[str, Any]) -> bool:
    def log_key(log: Any) -> Any:
        return (
            log.stamps.tolist(),
            list(log.observed),
            log.ranges.tolist(),
            log.bearings.tolist(),
            log.sigma_range.tolist(),
            log.sigma_bearing.tolist(),
        )

    return all(policy.local_maps.get(r) is maps[r] for r in ROBOTS) and all(
        log_key(policy.rendezvous[r]) == log_key(logs[r]) for r in ROBOTS
    )


class Fuzzer:
    """A merger holding the good maps; each message is fed to it from that state (its policy
    restored to a copy taken then)."""

    def __init__(self, harness: MergerHarness) -> None:
        self.merger = harness.merger
        self.harness = harness
        self.callbacks = {s.topic_name: s.callback for s in self.merger.subscriptions}
        policy = self.merger.policy
        assert not policy.dirty
        self.saved = policy.copy()
        self.maps = dict(policy.local_maps)
        self.logs = dict(policy.rendezvous)
        self.result = policy.last_result
        self.view = _view(self.result)

    def feed(self, topic_robot: str, msg: Any) -> None:
        m, policy = self.merger, self.merger.policy
        policy.restore(self.saved)
        kind = "local_map_updates" if isinstance(msg, LocalMapUpdate) else "rendezvous_poses"
        dropped = m.drops.total
        self.callbacks[f"/{topic_robot}/{kind}"](msg)
        m.solve_pending()
        counts = m.drops.as_dict()
        assert counts.get("callback_error", 0) == 0, counts
        assert counts.get("failed_solve", 0) == 0, (counts, policy.last_error)
        if _same_data(policy, self.maps, self.logs):
            assert _view(policy.last_result) == self.view
            TALLY["refused" if m.drops.total > dropped else "unchanged"] += 1
        else:
            assert policy.last_result is not self.result  # taken and solved
            TALLY["taken"] += 1


@pytest.fixture
def fuzzer(ros_context, spin) -> Iterator[Fuzzer]:
    harness = MergerHarness(ros_context, spin, solve_period=3600.0)
    try:
        harness.hold(GOOD)
        assert harness.merger.solve_pending()
        assert harness.merger.policy.last_result is not None
        yield Fuzzer(harness)
    finally:
        print(f"\nmerger fuzz: {sum(TALLY.values())} examples so far: {dict(TALLY)}")
        harness.close()


GOOD = run_messages()
ROBOT2_STAMPS = list(GOOD.local_maps["robot2"].pose_stamps)


@FUZZ
@given(msg=random_map_updates(ROBOT2_STAMPS))
def test_random_map_updates(fuzzer: Fuzzer, msg: LocalMapUpdate) -> None:
    fuzzer.feed("robot2", msg)


@FUZZ
@given(msg=mutated_map_updates(GOOD.local_maps["robot2"]))
def test_mutated_map_updates(fuzzer: Fuzzer, msg: LocalMapUpdate) -> None:
    fuzzer.feed("robot2", msg)


@FUZZ
@given(msg=rendezvous_messages(GOOD.rendezvous["robot2"], ROBOT2_STAMPS))
def test_rendezvous_messages(fuzzer: Fuzzer, msg: RendezvousPoses) -> None:
    fuzzer.feed("robot2", msg)


def test_good_messages_are_taken_unchanged(fuzzer: Fuzzer) -> None:
    """The fuzzer's baseline: the good messages again leave the joined map as it was."""
    fuzzer.feed("robot2", GOOD.rendezvous["robot2"])
    assert _view(fuzzer.merger.policy.last_result) == fuzzer.view


# the delta protocol: runs of events on robot2's topic

PROTOCOL_CUTS = (20.0, 30.0, None)  # s: robot2's map at these moments (None: the run's end)
SESSION = 1  # robot2's smoother's, held at the start
other_sessions = st.one_of(st.integers(2, 5), st.sampled_from([0, 2**31, 2**32 - 1]))
EVENTS = st.one_of(
    st.tuples(st.just("next"), st.integers(0, len(PROTOCOL_CUTS) - 1)),
    st.tuples(st.just("resync"), st.booleans()),  # the whole map before the reply, or after
    st.tuples(st.just("foreign whole"), other_sessions, st.integers(0, len(PROTOCOL_CUTS) - 1)),
    st.tuples(st.just("foreign delta"), other_sessions, uint32),
    st.tuples(st.just("replay"), st.integers(0, 20)),
    st.tuples(st.just("bad"), st.sampled_from(["kernel", "nan", "skip", "last"])),
)


@dataclass
class Smoother2:
    """robot2's smoother as the protocol fuzz plays it: its sender and what it sent."""

    sender: UpdateSender
    sent: list[LocalMapUpdate]

    def message(self, update: MapUpdate) -> LocalMapUpdate:
        return local_map_update_message(update, "robot2", STAMP_NS)


class ProtocolFuzzer:
    """A merger holding robot1's map and robot2's first one (its smoother's update 1); each
    run starts from that state."""

    def __init__(self, harness: MergerHarness, maps: list[Any], first: LocalMapUpdate) -> None:
        self.merger = harness.merger
        self.maps = maps
        self.first = first
        self.on_map = {s.topic_name: s.callback for s in self.merger.subscriptions}[
            "/robot2/local_map_updates"
        ]
        self.saved = self.merger.policy.copy()

    def smoother(self) -> Smoother2:
        sender = UpdateSender(SESSION)
        sender.update(robot_map_arrays(self.maps[0]))
        return Smoother2(sender, [self.first])

    def answer(self, sent: bool, session: int, sequence: int) -> None:
        """A reply to a resync request, as the merger's client takes it."""
        reply = Trigger.Response(success=sent, message=resync_answer(session, sequence))
        future = Future()
        future.set_result(reply)
        self.merger.resyncs._on_reply("robot2", future)

    def play(self, events: list[tuple[Any, ...]]) -> None:
        m = self.merger
        m.policy.restore(self.saved)
        smoother = self.smoother()
        errors = m.drops.as_dict().get("callback_error", 0)
        for event in events:
            self.event(smoother, event)
            assert m.drops.as_dict().get("callback_error", 0) == errors, event
            held, sent = m.policy.held["robot2"], smoother.sender.held
            assert sent is not None and (held.session, held.sequence) == (
                sent.session,
                sent.sequence,
            ), event
            assert np.array_equal(held.map.pose_stamps, sent.map.pose_stamps)
            assert np.array_equal(held.map.poses, sent.map.poses)
            assert len(m.policy.local_maps["robot2"].stamps) == len(sent.map.pose_stamps)
        m.solve_pending()
        assert m.drops.as_dict().get("failed_solve", 0) == 0, m.policy.last_error
        TALLY["protocol runs"] += 1

    def event(self, smoother: Smoother2, event: tuple[Any, ...]) -> None:
        kind, *args = event
        sender, sent = smoother.sender, smoother.sent
        if kind == "next":  # its next update, whole when the map did not grow
            msg = smoother.message(sender.update(robot_map_arrays(self.maps[args[0]])))
            sent.append(msg)
            self.on_map(msg)
        elif kind == "resync":
            update = sender.resend()
            assert update is not None
            msg = smoother.message(update)
            sent.append(msg)
            if args[0]:
                self.on_map(msg)
            self.answer(True, SESSION, update.sequence)
            if not args[0]:
                self.on_map(msg)
        elif kind == "foreign whole":
            session, cut = args
            msg = smoother.message(UpdateSender(session).update(robot_map_arrays(self.maps[cut])))
            self.on_map(msg)
        elif kind == "foreign delta":
            session, sequence = args
            sequence = min(sequence, 2**32 - 2)
            msg = copied(sent[-1])
            msg.session, msg.sequence, msg.base_sequence = session, sequence + 1, sequence
            self.on_map(msg)
        elif kind == "replay":
            self.on_map(copied(sent[args[0] % len(sent)]))
        elif kind == "bad":
            twin = UpdateSender(SESSION)
            twin.held = sender.held
            msg = smoother.message(twin.update(robot_map_arrays(self.maps[-1])))
            if msg.base_sequence == 0:
                return  # not a growth: a whole map of the session, newer, is the smoother's
            if args[0] == "kernel":
                msg.observation_robust_kernel = "tukey"
            elif args[0] == "nan":
                msg.poses = [math.nan, *list(msg.poses)[1:]]
            elif args[0] == "skip":
                msg.sequence += 1
            else:
                msg.sequence = 2**32 - 1
            self.on_map(msg)


@pytest.fixture(scope="module")
def protocol_runs() -> list[RunMessages]:
    return [run_messages(end=t) for t in PROTOCOL_CUTS]


@pytest.fixture
def protocol_fuzzer(ros_context, spin, protocol_runs) -> Iterator[ProtocolFuzzer]:
    harness = MergerHarness(ros_context, spin, solve_period=3600.0)
    try:
        maps = [r.robot_maps["robot2"] for r in protocol_runs]
        first = local_map_update_message(
            UpdateSender(SESSION).update(robot_map_arrays(maps[0])), "robot2", STAMP_NS
        )
        harness.hold(with_robot2(protocol_runs[0], first))
        yield ProtocolFuzzer(harness, maps, first)
    finally:
        print(f"\nmerger fuzz: {sum(TALLY.values())} examples so far: {dict(TALLY)}")
        harness.close()


@PROTOCOL_FUZZ
@given(events=st.lists(EVENTS, min_size=1, max_size=8))
def test_the_held_map_is_the_last_one_the_smoother_sent(
    protocol_fuzzer: ProtocolFuzzer, events: list[tuple[Any, ...]]
) -> None:
    protocol_fuzzer.play(events)
