"""The merger's boundary: through a real merger node, with the messages smoothers publish.

A malformed local map update or rendezvous message never replaces good data: the joined map
solved again afterwards is exactly the one before, and the message is counted once under its
reason. The topic names the robot. A smoother restart is reported once, and its new map
taken. A merger that missed an update asks for the whole map and ends where one that missed
nothing does; an update delivered twice is applied once.
"""

from __future__ import annotations

import contextlib
import os
import signal
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import pytest
from csam_msgs.msg import (
    JoinedMap,
    LocalMapUpdate,
    RendezvousObservation,
    RendezvousObservations,
    RendezvousPoses,
)
from diagnostic_msgs.msg import DiagnosticStatus
from merger_harness import (
    ROBOTS,
    STAMP_NS,
    MergerHarness,
    RunMessages,
    copied,
    joined_view,
    poses_of,
    resent,
    run_messages,
    status_values,
    with_robot2,
)
from std_srvs.srv import Trigger

import csam_ros.nodes.merger as merger_module
from csam_ros.core.exchange.map_arrays import Refined, held_robot_map, robot_map_arrays
from csam_ros.core.exchange.map_updates import KeyedMap, MapUpdate, UpdateSender, apply_update
from csam_ros.core.exchange.validation import FAILED_SOLVE
from csam_ros.core.joining.notes import NoteKind
from csam_ros.core.joining.result import RunSummary
from csam_ros.core.joining.warm_start import carried_forward
from csam_ros.core.merging.joiner import JoinRequest
from csam_ros.ros.conversions import ns_to_time, time_to_ns
from csam_ros.ros.map_messages import local_map_update_message
from csam_ros.ros.topics import FLUSH, PROVISIONAL_MAP, merger_service

RESTART_AT = 12.0  # s: robot2's smoother restarted here (the run: 0-40 s, rendezvous 18-22 s)
CUTS = (20.0, 30.0, None)  # s: robot2's map at these moments of the run (None: its end)


@pytest.fixture(scope="module")
def growing() -> list[RunMessages]:
    """The smoothers' messages at three moments of the run: robot2's map grows."""
    return [run_messages(end=t) for t in CUTS]


@pytest.fixture
def harness(ros_context, spin, tmp_path):
    h = MergerHarness(ros_context, spin, summary_path=str(tmp_path / "summary.json"))
    yield h
    h.close()


def _nan() -> float:
    return float("nan")


def _set(name: str, index: int | slice, value: Any) -> Callable[[LocalMapUpdate], None]:
    """Set element(s) ``index`` of the flat field ``name``."""

    def change(m: LocalMapUpdate) -> None:
        values = list(getattr(m, name))
        values[index] = value
        setattr(m, name, values)

    return change


def _cut(name: str, keep: int) -> Callable[[LocalMapUpdate], None]:
    """Keep the first ``keep`` values of the flat field ``name``."""
    return lambda m: setattr(m, name, list(getattr(m, name))[:keep])


def _empty(m: LocalMapUpdate) -> None:
    for name in (
        "pose_stamps",
        "poses",
        "feature_labels",
        "features",
        "odometry_stamps",
        "odometry_deltas",
        "odometry_sqrt_information",
        "observation_stamps",
        "observation_labels",
        "observation_points",
        "observation_sqrt_information",
    ):
        setattr(m, name, [])


def _drop_a_stamp(m: LocalMapUpdate) -> None:
    m.poses = list(m.poses)[: 3 * 3]
    m.pose_stamps = list(m.pose_stamps)[:2]


def _between_poses(m: LocalMapUpdate) -> int:
    """A stamp inside robot2's map where it holds no pose."""
    a, b = m.pose_stamps[10:12]
    return (a + b) // 2


def _odometry_off_the_poses(m: LocalMapUpdate) -> None:
    _set("odometry_stamps", 2 * 5 + 1, _between_poses(m))(m)


def _observation_after_the_poses(m: LocalMapUpdate) -> None:
    _set("observation_stamps", 7, m.pose_stamps[-1] + 4_000_000_000)(m)


def _duplicate_label(m: LocalMapUpdate) -> None:
    _set("feature_labels", 1, m.feature_labels[0])(m)


def _stamps_out_of_order(m: LocalMapUpdate) -> None:
    stamps = list(m.pose_stamps)
    stamps[3], stamps[4] = stamps[4], stamps[3]
    m.pose_stamps = stamps


# every malformation the issue lists, on robot2's good local map (sent as a new update)
MALFORMED_MAPS: dict[str, Callable[[LocalMapUpdate], None]] = {
    "empty": _empty,
    "3 poses with 2 stamps": _drop_a_stamp,
    "pose stamps out of order": _stamps_out_of_order,
    "features one short of their labels": _cut("features", -2),
    "odometry deltas one short": _cut("odometry_deltas", -3),
    "observation information one short": _cut("observation_sqrt_information", -4),
    "odometry stamp with no pose": _odometry_off_the_poses,
    "observation 4 s after the last pose": _observation_after_the_poses,
    "unknown label": _set("observation_labels", 2, 999_999),
    "duplicate labels": _duplicate_label,
    "nan pose": _set("poses", 3 * 4 + 1, _nan()),
    "nan feature": _set("features", 2 * 3, _nan()),
    "nan odometry sqrt-information": _set("odometry_sqrt_information", 9 * 3 + 4, _nan()),
    "zero odometry sqrt-information": _set("odometry_sqrt_information", slice(27, 36), [0.0] * 9),
    "zero observation sqrt-information": _set(
        "observation_sqrt_information", slice(12, 16), [0.0] * 4
    ),
    "zero gauge sqrt-information": lambda m: setattr(
        m, "first_pose_prior_sqrt_information", [0.0] * 9
    ),
    "nan observation sqrt-information": _set("observation_sqrt_information", 0, _nan()),
    "unknown robust kernel": lambda m: setattr(m, "observation_robust_kernel", "tukey"),
    "sequence 0": lambda m: setattr(m, "sequence", 0),
}


@pytest.mark.parametrize("malformation", MALFORMED_MAPS, ids=list(MALFORMED_MAPS))
def test_malformed_local_map_keeps_the_last_valid_one(harness, good, malformation) -> None:
    """Case 5: a malformed map replaced the robot's good one (84 -> 74 features, 65 -> 0
    associations) and was counted at every solve. Case 1: a feature a map could not name
    (a FeatureEstimate with no members then, a feature without its label now) killed the
    merger."""
    before = harness.start(good)
    assert len(before.associations) > 0
    bad = resent(good.local_maps["robot2"])  # a new update: the same one again is no news
    MALFORMED_MAPS[malformation](bad)
    counts = harness.send_and_wait_drop("robot2", bad)
    assert counts == {"malformed_local_map": 1}
    for _ in range(2):  # solving again neither changes the joined map nor counts again
        assert joined_view(harness.resolve()) == joined_view(before)
    assert harness.merger.drops.as_dict() == {"malformed_local_map": 1}


def test_topic_names_the_robot(harness, good) -> None:
    """Case 6: a robot2 map sent on /robot1/local_map replaced robot2's real one."""
    before = joined_view(harness.start(good))
    held = dict(harness.merger.policy.local_maps)
    counts = harness.send_and_wait_drop("robot1", resent(good.local_maps["robot2"]))
    assert counts == {"robot_mismatch": 1}
    counts = harness.send_and_wait_drop("robot1", good.rendezvous["robot2"])
    assert counts == {"robot_mismatch": 2}
    elsewhere = resent(good.local_maps["robot1"])  # robot1's map in another frame
    elsewhere.header.frame_id = "world"
    counts = harness.send_and_wait_drop("robot1", elsewhere)
    assert counts == {"robot_mismatch": 3}
    assert harness.merger.policy.local_maps == held
    assert joined_view(harness.resolve()) == before


def _row(observed: str, stamp_ns: int) -> RendezvousObservations:
    group = RendezvousObservations()
    group.header.stamp = ns_to_time(stamp_ns)
    group.header.frame_id = "robot2/base_link"
    group.observations = [
        RendezvousObservation(
            observed_robot=observed, range=2.0, bearing=0.1, sigma_range=0.05, sigma_bearing=0.01
        )
    ]
    return group


@pytest.mark.parametrize(
    ("observed", "reason"),
    [("robot9", "unknown_robot"), ("robot2", "self_observation"), ("robot1", "no_pose_at_stamp")],
)
@pytest.mark.parametrize("alone", [False, True], ids=["added", "alone"])
def test_bad_rendezvous_rows_are_dropped_one_by_one(
    harness, good, observed: str, reason: str, alone: bool
) -> None:
    """Case 6: rendezvous naming robot9, the robot itself or a stamp without a pose replaced
    robot2's real measurements (its base node moved 7 cm, 0.4 degrees), uncounted."""
    before = joined_view(harness.start(good))
    real = harness.merger.policy.rendezvous["robot2"]
    msg: RendezvousPoses = copied(good.rendezvous["robot2"])
    row = _row(observed, _between_poses(good.local_maps["robot2"]))
    msg.measurements = [row] if alone else [*msg.measurements, row]
    counts = harness.send_and_wait_drop("robot2", msg)
    assert counts == {reason: 1}
    kept = harness.merger.policy.rendezvous["robot2"]
    assert kept.observed == real.observed and list(kept.stamps) == list(real.stamps)
    assert joined_view(harness.resolve()) == before


def test_malformed_rendezvous_message_keeps_the_last_one(harness, good) -> None:
    """A rendezvous message whose stamps and poses disagree is refused whole."""
    before = joined_view(harness.start(good))
    msg = copied(good.rendezvous["robot2"])
    del msg.stamps[1:]
    counts = harness.send_and_wait_drop("robot2", msg)
    assert counts == {"malformed_rendezvous_poses": 1}
    assert joined_view(harness.resolve()) == before


def test_smoother_restart_is_reported_once_and_its_new_map_taken(harness, good, tmp_path) -> None:
    """Case 7: after a restart robot2's map held half its poses and the joined map half its
    associations, and nothing said so."""
    harness.start(good)
    restarted = run_messages(restart_at=RESTART_AT)
    new_map = restarted.local_maps["robot2"]
    old_stamps = list(good.local_maps["robot2"].pose_stamps)
    lost = sum(t < new_map.pose_stamps[0] for t in old_stamps)
    assert lost > 0 and poses_of(new_map) < len(old_stamps)
    assert new_map.session != good.local_maps["robot2"].session

    status: dict[str, dict[str, str]] = {}
    harness.injector.create_subscription(
        __import__("diagnostic_msgs.msg").msg.DiagnosticArray,
        "/csam/status",
        lambda a: status.update({s.name: {kv.key: kv.value for kv in s.values} for s in a.status}),
        10,
    )
    solves = harness.merger.policy.solves
    harness.smoothers.whole["robot2"] = new_map  # the restarted smoother answers with it
    harness.publish("robot2", restarted.rendezvous["robot2"])
    harness.publish("robot2", new_map)
    harness.wait(
        lambda: (
            len(harness.merger.policy.local_maps["robot2"].stamps) == poses_of(new_map)
            and harness.merger.policy.solves > solves
            and status.get("merger/robot2", {}).get("restarts") == "1"
        )
    )
    harness.publish("robot2", new_map)  # the same map again is no new restart
    harness.settle(0.5)
    harness.resolve()
    assert harness.merger.policy.restarts == {"robot2": 1}
    assert harness.merger.policy.restart_poses_lost == {"robot2": lost}
    assert status["merger/robot2"]["restart_poses_lost"] == str(lost)
    assert status["merger"]["restarts"] == "1"
    assert harness.merger.drops.total == 0
    summary = RunSummary.read(tmp_path / "summary.json")
    assert summary.merger is not None
    assert summary.merger.restarts == {"robot2": 1}
    assert summary.merger.restart_poses_lost == {"robot2": lost}
    result = harness.merger.policy.last_result
    assert result is not None and len(result.robots["robot2"].stamps) == poses_of(new_map)


def test_a_running_solve_blocks_neither_status_nor_input(harness, good) -> None:
    """The issue: the merger solved in its executor thread, so while C-SAM ran no status was
    published and no message taken. Now a solve runs in the solve process; input arriving
    meanwhile is held and solved once, newest, after the running solve ends."""
    harness.start(good)
    status: list[dict[str, str]] = []
    harness.injector.create_subscription(
        __import__("diagnostic_msgs.msg").msg.DiagnosticArray,
        "/csam/status",
        lambda a: status.extend(
            {kv.key: kv.value for kv in s.values} for s in a.status if s.name == "merger"
        ),
        10,
    )
    solves, published = harness.merger.policy.solves, len(harness.joined)
    with _held_solves(harness.merger):
        harness.merger.policy.inputs_changed()
        harness.wait(lambda: _solving_newest(harness.merger))
        seen = len(status)
        harness.wait(lambda: len(status) > seen + 1 and status[-1]["solving"] == "True")

        restarted = run_messages(restart_at=RESTART_AT)
        new_map = restarted.local_maps["robot2"]
        harness.smoothers.whole["robot2"] = new_map  # the restarted smoother answers with it
        harness.publish("robot2", new_map)
        harness.wait(
            lambda: (
                len(harness.merger.policy.local_maps["robot2"].stamps) == poses_of(new_map)
                and harness.merger.policy.dirty
            )
        )
        old_log = harness.merger.policy.rendezvous["robot2"]
        harness.publish("robot2", restarted.rendezvous["robot2"])
        harness.wait(lambda: harness.merger.policy.rendezvous["robot2"] is not old_log)
        assert harness.merger.policy.solving and harness.merger.policy.solves == solves
    harness.wait(
        lambda: (
            harness.merger.policy.solves == solves + 2
            and not harness.merger.policy.dirty
            and not harness.merger.policy.solving
            and len(harness.joined) == published + 2
        )
    )
    harness.settle(0.5)
    assert harness.merger.policy.solves == solves + 2 and len(harness.joined) == published + 2
    poses = [{t.robot: len(t.poses) for t in m.trajectories} for m in harness.joined[-2:]]
    assert poses[0]["robot2"] == poses_of(good.local_maps["robot2"])
    assert poses[1]["robot2"] == poses_of(new_map)
    assert harness.merger.drops.total == 0


@contextlib.contextmanager
def _held_solves(merger: merger_module.Merger) -> Iterator[None]:
    """Stop the merger's solve process until the block ends: a solve started meanwhile
    waits in it."""
    pid = merger.solve_process.pid
    assert pid is not None, "the merger has not solved yet"
    os.kill(pid, signal.SIGSTOP)
    try:
        yield
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, signal.SIGCONT)


def _solving_newest(merger: merger_module.Merger) -> bool:
    """Whether a solve of the newest inputs runs (the last solve may still be ending when its
    joined map arrives)."""
    return merger.policy.solving and not merger.policy.dirty


def test_destroying_the_node_stops_a_running_solve(harness, good) -> None:
    """destroy_node stops the solve process at once; the solve it ran is neither published
    nor counted as failed."""
    harness.start(good)
    merger, solves, published = harness.merger, harness.merger.policy.solves, len(harness.joined)
    with _held_solves(merger):
        merger.policy.inputs_changed()
        harness.wait(lambda: _solving_newest(merger))
        merger.destroy_node()
        worker = merger._worker
        worker.join(10.0)
        assert not worker.is_alive()
    assert merger.solve_process.pid is None
    assert merger.policy.solves == solves and merger.drops.total == 0
    harness.settle(0.3)
    assert len(harness.joined) == published


def test_a_solve_process_that_dies_is_a_failed_solve_and_started_again(harness, good) -> None:
    """The solve process killed during a solve: that solve counts as failed, the last joined
    map stays, and the next solve starts a new process that is sent every map again."""
    harness.start(good)
    merger, solves = harness.merger, harness.merger.policy.solves
    before = merger.policy.last_result
    starts = merger.solve_process.starts
    with _held_solves(merger):
        merger.policy.inputs_changed()
        harness.wait(lambda: _solving_newest(merger))
        os.kill(merger.solve_process.pid, signal.SIGKILL)
        harness.wait(lambda: not merger.policy.solving)
    assert merger.drops.as_dict() == {FAILED_SOLVE: 1}
    assert merger.policy.solves == solves and merger.policy.last_result is before
    assert "the solve process ended" in merger.policy.last_error
    merger.policy.inputs_changed()
    harness.wait(lambda: merger.policy.solves == solves + 1)
    assert merger.solve_process.starts == starts + 1
    after = merger.policy.last_result
    assert after is not None and after is not before
    for f, g in zip(before.features, after.features, strict=True):
        np.testing.assert_allclose(f.xy, g.xy, atol=1e-9)


def test_flush_gives_up_a_solve_of_older_maps_and_solves_the_newest(
    harness, growing: list[RunMessages]
) -> None:
    """``~/flush`` while a solve of older maps runs (held in the stopped solve process) and
    robot2's newer map has come: that solve is given up (neither published nor failed) and
    the newest maps are solved at once. A flush with nothing newer does nothing."""
    middle, last = growing[1], growing[2]
    sender = UpdateSender(11)
    harness.start(
        with_robot2(middle, _message(sender.update(robot_map_arrays(middle.robot_maps["robot2"]))))
    )
    merger, solves, published = harness.merger, harness.merger.policy.solves, len(harness.joined)
    flush = _flush_client(harness)
    assert flush().startswith("the joined map (or the running solve) holds the newest")
    newer = STAMP_NS + 10**9
    update = sender.update(robot_map_arrays(last.robot_maps["robot2"]))
    with _held_solves(merger):
        merger.policy.inputs_changed()
        harness.wait(lambda: _solving_newest(merger))
        harness.publish("robot2", local_map_update_message(update, "robot2", newer))
        harness.wait(lambda: merger.policy.dirty)
        assert flush() == "a solve of older inputs was given up: solving the newest"
    harness.wait(lambda: merger.policy.solves > solves and not merger.policy.solving)
    harness.settle(0.3)
    assert merger.policy.solves == solves + 1 and merger.policy.solves_given_up == 1
    assert len(harness.joined) == published + 1 and merger.drops.total == 0
    assert time_to_ns(harness.joined[-1].base_nodes[1].local_map_stamp) == newer
    assert status_values(harness.status[-1], "merger")["solves_given_up"] == "1"


def test_after_a_flush_each_robots_next_map_gives_up_a_running_solve_once(
    harness, growing: list[RunMessages]
) -> None:
    """After ``~/flush``, a robot's next local map arriving during a solve of older maps gives
    that solve up as a flush would (a smoother's final map may come after the flush that
    asked for it); the robot's map after that waits for the running solve, as during a run."""
    sender = UpdateSender(11)
    maps = [_message(sender.update(robot_map_arrays(g.robot_maps["robot2"]))) for g in growing]
    harness.start(with_robot2(growing[0], maps[0]))
    merger, solves = harness.merger, harness.merger.policy.solves
    assert _flush_client(harness)().startswith("the joined map (or the running solve) holds")
    for k, stamp in ((1, STAMP_NS + 10**9), (2, STAMP_NS + 2 * 10**9)):
        with _held_solves(merger):
            merger.policy.inputs_changed()
            harness.wait(lambda: _solving_newest(merger))
            maps[k].header.stamp = ns_to_time(stamp)
            harness.publish("robot2", maps[k])
            harness.wait(lambda: merger.policy.dirty)
        harness.wait(
            lambda stamp=stamp: (
                time_to_ns(harness.joined[-1].base_nodes[1].local_map_stamp) == stamp
            )
        )
        assert merger.policy.solves_given_up == 1  # the first map given up for, not the second
    harness.wait(lambda: not merger.policy.solving)
    assert merger.policy.solves == solves + 3 and merger.drops.total == 0


def _flush_client(harness: MergerHarness) -> Callable[[], str]:
    """A function that calls the merger's ``~/flush`` and returns the reply's message."""
    client = harness.injector.create_client(Trigger, merger_service(FLUSH))

    def flush() -> str:
        future = client.call_async(Trigger.Request())
        harness.wait(future.done)
        return future.result().message

    return flush


def test_an_unconverged_solve_is_a_warning_in_status_and_summary(
    ros_context, spin, good, tmp_path
) -> None:
    summary_path = tmp_path / "summary.json"
    h = MergerHarness(ros_context, spin, summary_path=str(summary_path), max_iterations=1)
    try:
        h.start(good)
        h.wait(
            lambda: (
                bool(h.status)
                and (status_values(h.status[-1], "merger") or {}).get("converged") == "False"
            )
        )
        (merger,) = [s for s in h.status[-1].status if s.name == "merger"]
        assert merger.level == DiagnosticStatus.WARN
        assert "did not converge" in merger.message
        h.wait(summary_path.exists)  # written once the joined map is out
        summary = RunSummary.read(summary_path)
        assert not summary.result.converged
        assert summary.result.notes_of(NoteKind.NOT_CONVERGED_JOINT)
    finally:
        h.close()


def _message(update: MapUpdate | None) -> LocalMapUpdate | None:
    return None if update is None else local_map_update_message(update, "robot2", STAMP_NS)


def _keyed_equal(a: KeyedMap, b: KeyedMap) -> None:
    for name in KeyedMap.__dataclass_fields__:
        x, y = getattr(a, name), getattr(b, name)
        assert np.array_equal(x, y) if isinstance(x, np.ndarray) else x == y, name


def _assert_joined_close(a: JoinedMap, b: JoinedMap, atol: float, distance_rtol: float) -> None:
    """The same joined map: its estimates to ``atol``, the same associations, their Mahalanobis
    distances to ``distance_rtol``."""
    (fa, aa, na, ta), (fb, ab, nb, tb) = joined_view(a), joined_view(b)
    assert [f[0] for f in fa] == [f[0] for f in fb]
    np.testing.assert_allclose([f[1:3] + f[3] for f in fa], [f[1:3] + f[3] for f in fb], 0, atol)
    assert [x[:2] for x in aa] == [x[:2] for x in ab]
    np.testing.assert_allclose([x[2] for x in aa], [x[2] for x in ab], distance_rtol, 0)
    assert [n[:2] for n in na] == [n[:2] for n in nb] and ta == tb
    np.testing.assert_allclose([n[2:] for n in na], [n[2:] for n in nb], 0, atol)


def _joined_from_updates(
    context: Any, spin: Any, growing: list[RunMessages], missed: bool
) -> JoinedMap:
    """robot2's smoother sends updates 1 (whole), 2 and 3 of its growing map (with ``missed``,
    2 never reaches the merger); the joined map once the merger holds what it sent."""
    arrays = [robot_map_arrays(g.robot_maps["robot2"]) for g in growing]
    last = growing[-1]
    sender = UpdateSender(7)
    h = MergerHarness(context, spin)
    try:
        h.smoothers.answer["robot2"] = lambda: _message(sender.resend())
        h.smoothers.whole["robot1"] = last.local_maps["robot1"]
        # both robots held nothing at the start: the merger asked for their maps
        h.wait(lambda: h.smoothers.resyncs["robot2"] > 0 and "robot1" in h.merger.policy.held)
        for r in ("robot1", "robot2"):
            h.publish(r, last.rendezvous[r])
        first = _message(sender.update(arrays[0]))
        h.publish("robot2", first)
        h.wait(lambda: "robot2" in h.merger.policy.held)
        asked = h.merger.policy.resync_requests.get("robot2", 0)
        second, third = (_message(sender.update(a)) for a in arrays[1:])
        assert first.base_sequence == 0 and second.base_sequence and third.base_sequence
        if not missed:
            h.publish("robot2", second)
        h.publish("robot2", third)

        def holds_what_was_sent() -> bool:
            sent = sender.held  # a resync sends it again, as a new update
            assert sent is not None
            mine = h.merger.policy.held["robot2"]
            return (mine.session, mine.sequence) == (sent.session, sent.sequence)

        h.wait(holds_what_was_sent)
        held = h.merger.policy.held["robot2"]
        assert sender.held is not None
        _keyed_equal(held.map, sender.held.map)
        if missed:
            assert h.merger.policy.resync_requests["robot2"] > asked
            assert held.sequence == third.sequence + 1  # the whole map, sent again
        else:
            assert h.merger.policy.resync_requests.get("robot2", 0) == asked
            assert held.sequence == third.sequence
        h.wait(
            lambda: not h.merger.policy.dirty and h.merger.policy.solves > 0 and len(h.joined) > 0
        )
        joined = h.resolve()
        assert h.merger.drops.total == 0
        assert len(h.merger.policy.local_maps["robot2"].stamps) == len(arrays[-1].stamps)
        return joined
    finally:
        h.close()


def test_a_merger_that_missed_updates_resyncs_and_ends_equal(
    ros_context, spin, growing: list[RunMessages]
) -> None:
    """A merger that never got update 2 cannot apply 3: it asks for the whole map, then holds
    exactly what the smoother holds and joins what a merger given every update joins.

    The association's distances are measured on each map as the merger refined it, and a refine
    starts from the robot's last one, so they depend on which updates were joined on the way
    (within a fraction of a standard deviation of the converged map); the joint solve's estimates
    do not."""
    missed = _joined_from_updates(ros_context, spin, growing, missed=True)
    every = _joined_from_updates(ros_context, spin, growing, missed=False)
    _assert_joined_close(missed, every, 1e-9, distance_rtol=1e-3)


def test_an_update_delivered_twice_changes_nothing(harness, growing: list[RunMessages]) -> None:
    """The same update (here one that adds to the map) delivered twice: applied once, one
    solve, nothing dropped, the joined map that of the update."""
    middle, last = growing[1], growing[2]
    sender = UpdateSender(11)
    first = _message(sender.update(robot_map_arrays(middle.robot_maps["robot2"])))
    harness.start(with_robot2(middle, first))
    solves, published = harness.merger.policy.solves, len(harness.joined)
    update = _message(sender.update(robot_map_arrays(last.robot_maps["robot2"])))
    assert update.base_sequence == first.sequence
    harness.publish("robot2", update)
    harness.publish("robot2", update)
    harness.wait(
        lambda: (
            harness.merger.policy.held["robot2"].sequence == update.sequence
            and harness.merger.policy.solves > solves
            and not harness.merger.policy.dirty
            and not harness.merger.policy.solving
        )
    )
    harness.settle(0.5)  # both deliveries acknowledged: the second one is taken in here
    assert harness.merger.policy.solves == solves + 1 and len(harness.joined) == published + 1
    assert harness.merger.drops.total == 0 and not harness.merger.policy.dirty
    assert len(harness.merger.policy.local_maps["robot2"].stamps) == len(
        last.robot_maps["robot2"].stamps
    )
    once = harness.joined[-1]
    assert joined_view(harness.resolve()) == joined_view(once)


def test_an_update_of_another_session_asks_for_the_whole_map(
    harness, good, growing: list[RunMessages]
) -> None:
    """robot2's smoother restarted (a new session) and its first update, the whole map, did
    not come: its next one names a base the merger never had. The merger asks for the whole
    map (counted in the status), drops nothing, and takes the new session's map."""
    harness.start(good)
    before = int(status_values(harness.status[-1], "merger/robot2")["resync_requests"])
    sender = UpdateSender(99)
    sender.update(robot_map_arrays(growing[1].robot_maps["robot2"]))  # never arrives
    update = _message(sender.update(robot_map_arrays(growing[2].robot_maps["robot2"])))
    assert update.base_sequence != 0
    harness.smoothers.answer["robot2"] = lambda: _message(sender.resend())
    harness.publish("robot2", update)
    harness.wait(lambda: harness.merger.policy.held["robot2"].session == 99)
    harness.wait(
        lambda: int(status_values(harness.status[-1], "merger/robot2")["resync_requests"]) > before
    )
    assert int(status_values(harness.status[-1], "merger")["resync_requests"]) > before
    assert sender.held is not None
    _keyed_equal(harness.merger.policy.held["robot2"].map, sender.held.map)
    assert harness.merger.drops.total == 0 and harness.merger.policy.restarts == {}


def test_a_running_solve_publishes_the_newest_maps_provisionally(
    harness, growing: list[RunMessages]
) -> None:
    """While a solve runs, robot2's newer map goes out on /csam/joined_map/provisional, once:
    placed by the last join, as the core carries it forward. The solved map follows."""
    middle, last = growing[1], growing[2]
    sender = UpdateSender(11)
    first = _message(sender.update(robot_map_arrays(middle.robot_maps["robot2"])))
    harness.start(with_robot2(middle, first))
    joined = harness.merger.policy.last_result
    provisional: list[JoinedMap] = []
    harness.injector.create_subscription(
        JoinedMap, PROVISIONAL_MAP.of(), provisional.append, PROVISIONAL_MAP.qos
    )
    newer = STAMP_NS + 10**9
    update = sender.update(robot_map_arrays(last.robot_maps["robot2"]))
    with _held_solves(harness.merger):
        harness.publish("robot2", local_map_update_message(update, "robot2", newer))
        harness.wait(lambda: _solving_newest(harness.merger) and len(provisional) > 0)
        harness.settle(1.5)  # past provisional_period: nothing newer to publish
        assert len(provisional) == 1 and harness.merger.policy.solving
    message = provisional[0]
    stamps = {b.robot: time_to_ns(b.local_map_stamp) for b in message.base_nodes}
    assert stamps == {"robot1": STAMP_NS, "robot2": newer}
    maps = [harness.merger.policy.local_maps[r] for r in ROBOTS]
    expected = carried_forward(joined, maps, harness.merger.config.stamp_tolerance)
    trajectories = {t.robot: t for t in message.trajectories}
    for name, robot in expected.robots.items():
        poses = [[p.x, p.y, p.theta] for p in trajectories[name].poses]
        np.testing.assert_allclose(poses, robot.poses_joined, atol=1e-12)
        assert not trajectories[name].sigma_phi
    assert len(trajectories["robot2"].poses) == len(last.robot_maps["robot2"].stamps)
    assert [tuple(f.members) for f in message.features] == [
        tuple(f.members) for f in expected.features
    ]
    solves, published = harness.merger.policy.solves, len(harness.joined)
    harness.wait(lambda: harness.merger.policy.solves > solves and len(harness.joined) > published)
    harness.settle(1.5)
    assert len(provisional) == 1  # the solved map holds the newest maps: nothing provisional
    assert time_to_ns(harness.joined[-1].base_nodes[1].local_map_stamp) == newer


def test_a_provisional_map_waits_for_quiet_unless_every_robot_has_a_new_map(
    ros_context, spin, growing: list[RunMessages]
) -> None:
    """With provisional_quiet and provisional_period far off, robot2's newer map alone does
    not go out; once robot1's is in too, both go out at once in one provisional joined map,
    while no solve runs (solve_period is far off too: the test solves when it means to)."""
    harness = MergerHarness(
        ros_context, spin, provisional_period=600.0, provisional_quiet=600.0, solve_period=3600.0
    )
    try:
        middle, last = growing[1], growing[2]
        sender = UpdateSender(11)
        first = _message(sender.update(robot_map_arrays(middle.robot_maps["robot2"])))
        harness.hold(with_robot2(middle, first))
        assert harness.merger.solve_pending() and harness.merger.policy.last_result is not None
        provisional: list[JoinedMap] = []
        harness.injector.create_subscription(
            JoinedMap, PROVISIONAL_MAP.of(), provisional.append, PROVISIONAL_MAP.qos
        )
        newer = STAMP_NS + 10**9
        robot1_sender = UpdateSender(1)  # robot1's smoother: its first update is held
        robot1_sender.update(robot_map_arrays(middle.robot_maps["robot1"]))
        robot1 = robot1_sender.update(robot_map_arrays(last.robot_maps["robot1"]))
        robot2 = sender.update(robot_map_arrays(last.robot_maps["robot2"]))
        policy = harness.merger.policy
        harness.publish("robot2", local_map_update_message(robot2, "robot2", newer))
        harness.wait(lambda: policy.local_map_stamps.get("robot2") == newer)
        harness.settle(1.0)
        assert not provisional
        harness.publish("robot1", local_map_update_message(robot1, "robot1", newer))
        harness.wait(lambda: len(provisional) > 0)
        harness.settle(0.5)
        assert len(provisional) == 1 and not policy.solving and policy.dirty
        stamps = {b.robot: time_to_ns(b.local_map_stamp) for b in provisional[0].base_nodes}
        assert stamps == {"robot1": newer, "robot2": newer}
    finally:
        harness.close()


def test_maps_are_checked_on_arrival_and_joined_refined(
    harness, growing: list[RunMessages]
) -> None:
    """The executor holds robot2's grown map as its updates built it (within the smoother's
    update tolerance of its optimum); the solve joins it refined from its first map as the
    solve refined that (within 1e-4 of the optimum, where a refine from the held estimate
    reaches it to 1e-6)."""
    middle, last = growing[1], growing[2]
    sender = UpdateSender(11)
    update = sender.update(robot_map_arrays(middle.robot_maps["robot2"]))
    harness.start(with_robot2(middle, _message(update)))
    solves = harness.merger.policy.solves
    harness.publish("robot2", _message(sender.update(robot_map_arrays(last.robot_maps["robot2"]))))
    harness.wait(
        lambda: harness.merger.policy.solves > solves and not harness.merger.policy.solving
    )
    held_first = apply_update(None, update)
    first = Refined(held_robot_map("robot2", held_first), held_first.map)
    held = harness.merger.policy.local_maps["robot2"]
    refined = held_robot_map("robot2", harness.merger.policy.sources["robot2"], last=first)
    joined = harness.merger.policy.last_result.robots["robot2"]
    assert np.abs(held.poses - refined.poses).max() > 1e-9  # the update left some behind
    np.testing.assert_allclose(joined.poses_local, refined.poses, atol=1e-12)
    optimum = last.robot_maps["robot2"].poses
    np.testing.assert_allclose(refined.poses, optimum, atol=1e-4)
    from_held = held_robot_map("robot2", harness.merger.policy.sources["robot2"])
    np.testing.assert_allclose(from_held.poses, optimum, atol=1e-6)


def test_maps_are_prepared_in_the_solve_process_while_the_solve_waits(
    ros_context, spin, growing: list[RunMessages]
) -> None:
    """robot2's newer map, robot1's not yet (solve_wait far off, so no solve is wanted): the
    solve process holds it before the next solve, which then does not send it."""
    harness = MergerHarness(ros_context, spin, solve_period=3600.0, solve_wait=3600.0)
    try:
        middle, last = growing[1], growing[2]
        sender = UpdateSender(11)
        first = _message(sender.update(robot_map_arrays(middle.robot_maps["robot2"])))
        harness.hold(with_robot2(middle, first))
        merger = harness.merger
        assert merger.solve_pending() and merger.policy.solves == 1
        update = sender.update(robot_map_arrays(last.robot_maps["robot2"]))
        harness.publish("robot2", local_map_update_message(update, "robot2", STAMP_NS + 10**9))

        def sent() -> list[bool]:
            sources = tuple(merger.policy.sources.items())
            request = JoinRequest(sources, {}, merger.config)
            return [s is None for _, s in merger.solve_process.stripped(request).maps]

        harness.wait(lambda: merger.policy.sources["robot2"].sequence == update.sequence)
        harness.wait(lambda: all(sent()))
        assert merger.policy.solves == 1 and not merger.policy.solve_wanted()
        assert merger.solve_pending() and merger.policy.solves == 2
        joined = merger.policy.last_result.robots["robot2"]
        assert len(joined.stamps) == len(last.robot_maps["robot2"].stamps)
        assert merger.solve_process.starts == 1
    finally:
        harness.close()
