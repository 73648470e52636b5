"""The merger's boundary: through a real merger node, with the messages smoothers publish.

A malformed local map or rendezvous message never replaces good data: the joined map solved
again afterwards is exactly the one before, and the message is counted once under its
reason. The topic names the robot. A smoother restart is reported once, and its new map
taken.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any

import pytest
from csam_msgs.msg import (
    LocalMap,
    RendezvousObservation,
    RendezvousObservations,
    RendezvousPoses,
)
from diagnostic_msgs.msg import DiagnosticStatus
from merger_harness import (
    MergerHarness,
    RunMessages,
    copied,
    joined_view,
    run_messages,
    status_values,
)

import csam_ros.nodes.merger as merger_module
from csam_ros.core.result import RunSummary
from csam_ros.ros.conversions import ns_to_time, time_to_ns

RESTART_AT = 12.0  # s: robot2's smoother restarted here (the run: 0-40 s, rendezvous 18-22 s)


@pytest.fixture(scope="module")
def good() -> RunMessages:
    return run_messages()


@pytest.fixture
def harness(ros_context, spin, tmp_path):
    h = MergerHarness(ros_context, spin, summary_path=str(tmp_path / "summary.json"))
    yield h
    h.close()


def _nan() -> float:
    return float("nan")


def _set(path: Callable[[LocalMap], Any], name: str, value: Any) -> Callable[[LocalMap], None]:
    return lambda m: setattr(path(m), name, value)


def _empty(m: LocalMap) -> None:
    for name in ("pose_stamps", "poses", "pose_covariances", "features"):
        setattr(m, name, [])
    m.odometry_factors, m.observation_factors = [], []


def _drop_a_stamp(m: LocalMap) -> None:
    del m.poses[3:]
    del m.pose_stamps[2:]


def _duplicate_label(m: LocalMap) -> None:
    m.features[1].members = list(m.features[0].members)


# every malformation the issue lists, on robot2's good local map
MALFORMED_MAPS: dict[str, Callable[[LocalMap], None]] = {
    "empty": _empty,
    "3 poses with 2 stamps": _drop_a_stamp,
    "odometry index 1000": lambda m: setattr(m.odometry_factors[5], "to_pose", 1000),
    "observation index 4e9": lambda m: setattr(m.observation_factors[7], "pose", 4_000_000_000),
    "unknown label": lambda m: setattr(m.observation_factors[2], "label", 999_999),
    "duplicate labels": _duplicate_label,
    "nan pose": lambda m: setattr(m.poses[4], "y", _nan()),
    "nan odometry sqrt-information": lambda m: m.odometry_factors[3].sqrt_information.__setitem__(
        4, _nan()
    ),
    "zero odometry sqrt-information": _set(
        lambda m: m.odometry_factors[3], "sqrt_information", [0.0] * 9
    ),
    "zero observation sqrt-information": _set(
        lambda m: m.observation_factors[3], "sqrt_information", [0.0] * 4
    ),
    "zero gauge sqrt-information": lambda m: setattr(
        m, "first_pose_prior_sqrt_information", [0.0] * 9
    ),
    "nan observation sqrt-information": lambda m: m.observation_factors[
        0
    ].sqrt_information.__setitem__(0, _nan()),
}


def test_feature_without_members_is_dropped_not_fatal(harness, good, ros_context, spin) -> None:
    """Case 1: a FeatureEstimate with no members raised IndexError and killed the merger,
    and a merger restarted while that map stayed latched died again."""
    before = joined_view(harness.start(good))
    bad = copied(good.local_maps["robot2"])
    bad.features[0].members = []
    counts = harness.send_and_wait_drop("robot2", bad)
    assert counts == {"malformed_local_map": 1}
    assert joined_view(harness.resolve()) == before
    assert harness.merger.drops.as_dict() == {"malformed_local_map": 1}

    # a second merger starting while the bad map is latched comes up and counts it once
    late = MergerHarness(ros_context, spin)
    try:
        late.publish("robot1", good.local_maps["robot1"])  # its own injector, latched too
        late.wait(lambda: late.merger.drops.total >= 1 and "robot1" in late.merger.local_maps)
        late.settle(0.3)
        assert late.merger.drops.as_dict() == {"malformed_local_map": 1}
        assert "robot2" not in late.merger.local_maps
    finally:
        late.close()


@pytest.mark.parametrize("malformation", MALFORMED_MAPS, ids=list(MALFORMED_MAPS))
def test_malformed_local_map_keeps_the_last_valid_one(harness, good, malformation) -> None:
    """Case 5: a malformed map replaced the robot's good one (84 -> 74 features, 65 -> 0
    associations) and was counted at every solve."""
    before = harness.start(good)
    assert len(before.associations) > 0
    bad = copied(good.local_maps["robot2"])
    MALFORMED_MAPS[malformation](bad)
    counts = harness.send_and_wait_drop("robot2", bad)
    assert counts == {"malformed_local_map": 1}
    for _ in range(2):  # solving again neither changes the joined map nor counts again
        assert joined_view(harness.resolve()) == joined_view(before)
    assert harness.merger.drops.as_dict() == {"malformed_local_map": 1}


def test_topic_names_the_robot(harness, good) -> None:
    """Case 6: a robot2 map sent on /robot1/local_map replaced robot2's real one."""
    before = joined_view(harness.start(good))
    held = dict(harness.merger.local_maps)
    counts = harness.send_and_wait_drop("robot1", good.local_maps["robot2"])
    assert counts == {"robot_mismatch": 1}
    counts = harness.send_and_wait_drop("robot1", good.rendezvous["robot2"])
    assert counts == {"robot_mismatch": 2}
    assert harness.merger.local_maps == held
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


def _between_poses(m: LocalMap) -> int:
    """A stamp inside robot2's map where it holds no pose."""
    a, b = (time_to_ns(t) for t in m.pose_stamps[10:12])
    return (a + b) // 2


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
    real = harness.merger.rendezvous["robot2"]
    msg: RendezvousPoses = copied(good.rendezvous["robot2"])
    row = _row(observed, _between_poses(good.local_maps["robot2"]))
    msg.measurements = [row] if alone else [*msg.measurements, row]
    counts = harness.send_and_wait_drop("robot2", msg)
    assert counts == {reason: 1}
    kept = harness.merger.rendezvous["robot2"]
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
    old_stamps = [time_to_ns(t) for t in good.local_maps["robot2"].pose_stamps]
    new_start = time_to_ns(new_map.pose_stamps[0])
    lost = sum(t < new_start for t in old_stamps)
    assert lost > 0 and len(new_map.poses) < len(old_stamps)

    status: dict[str, dict[str, str]] = {}
    harness.injector.create_subscription(
        __import__("diagnostic_msgs.msg").msg.DiagnosticArray,
        "/csam/status",
        lambda a: status.update({s.name: {kv.key: kv.value for kv in s.values} for s in a.status}),
        10,
    )
    solves = harness.merger.solves
    harness.publish("robot2", restarted.rendezvous["robot2"])
    harness.publish("robot2", new_map)
    harness.wait(
        lambda: (
            len(harness.merger.local_maps["robot2"].stamps) == len(new_map.poses)
            and harness.merger.solves > solves
            and status.get("merger/robot2", {}).get("restarts") == "1"
        )
    )
    harness.publish("robot2", new_map)  # the same map again is no new restart
    harness.settle(0.5)
    harness.resolve()
    assert harness.merger.restarts == {"robot2": 1}
    assert harness.merger.restart_poses_lost == {"robot2": lost}
    assert status["merger/robot2"]["restart_poses_lost"] == str(lost)
    assert status["merger"]["restarts"] == "1"
    assert harness.merger.drops.total == 0
    summary = RunSummary.read(tmp_path / "summary.json")
    assert summary.merger is not None
    assert summary.merger.restarts == {"robot2": 1}
    assert summary.merger.restart_poses_lost == {"robot2": lost}
    result = harness.merger.last_result
    assert result is not None and len(result.robots["robot2"].stamps) == len(new_map.poses)


def test_a_running_solve_blocks_neither_status_nor_input(harness, good, monkeypatch) -> None:
    """The issue: the merger solved in its executor thread, so while C-SAM ran no status was
    published and no message taken. Now a solve runs in a worker; input arriving meanwhile is
    held and solved once, newest, after the running solve ends."""
    harness.start(good)
    real_join = merger_module.join_maps
    started, release = threading.Event(), threading.Event()
    solved: list[dict[str, int]] = []  # poses per robot of each solve's inputs

    def slow_join(maps: Any, logs: Any, config: Any, **options: Any) -> Any:
        solved.append({m.name: len(m.stamps) for m in maps})
        started.set()
        assert release.wait(60.0), "never released"
        return real_join(maps, logs, config, **options)

    monkeypatch.setattr(merger_module, "join_maps", slow_join)
    status: list[dict[str, str]] = []
    harness.injector.create_subscription(
        __import__("diagnostic_msgs.msg").msg.DiagnosticArray,
        "/csam/status",
        lambda a: status.extend(
            {kv.key: kv.value for kv in s.values} for s in a.status if s.name == "merger"
        ),
        10,
    )
    solves = harness.merger.solves
    harness.merger.dirty = True
    try:
        harness.wait(lambda: started.is_set() and harness.merger.solving)
        seen = len(status)
        harness.wait(lambda: len(status) > seen + 1 and status[-1]["solving"] == "True")

        restarted = run_messages(restart_at=RESTART_AT)
        new_map = restarted.local_maps["robot2"]
        harness.publish("robot2", new_map)
        harness.wait(
            lambda: (
                len(harness.merger.local_maps["robot2"].stamps) == len(new_map.poses)
                and harness.merger.dirty
            )
        )
        old_log = harness.merger.rendezvous["robot2"]
        harness.publish("robot2", restarted.rendezvous["robot2"])
        harness.wait(lambda: harness.merger.rendezvous["robot2"] is not old_log)
        assert harness.merger.solving and harness.merger.solves == solves
        assert len(solved) == 1
    finally:
        release.set()
    harness.wait(
        lambda: (
            harness.merger.solves == solves + 2
            and not harness.merger.dirty
            and not harness.merger.solving
        )
    )
    harness.settle(0.5)
    assert harness.merger.solves == solves + 2 and len(solved) == 2
    assert solved[0]["robot2"] == len(good.local_maps["robot2"].poses)
    assert solved[1]["robot2"] == len(new_map.poses)
    result = harness.merger.last_result
    assert result is not None and len(result.robots["robot2"].stamps) == len(new_map.poses)
    assert harness.merger.drops.total == 0


def test_destroying_the_node_leaves_a_running_solve_behind(harness, good, monkeypatch) -> None:
    """destroy_node returns while a solve runs; the solve finishes unpublished, unfailed."""
    harness.start(good)
    real_join = merger_module.join_maps
    started, release = threading.Event(), threading.Event()

    def slow_join(maps: Any, logs: Any, config: Any, **options: Any) -> Any:
        started.set()
        assert release.wait(60.0), "never released"
        return real_join(maps, logs, config, **options)

    monkeypatch.setattr(merger_module, "join_maps", slow_join)
    monkeypatch.setattr(merger_module, "SHUTDOWN_JOIN_S", 0.2)
    merger, solves, published = harness.merger, harness.merger.solves, len(harness.joined)
    merger.dirty = True
    harness.wait(lambda: started.is_set())
    merger.destroy_node()
    worker = merger._worker
    assert worker.is_alive()
    release.set()
    worker.join(60.0)
    assert not worker.is_alive()
    assert merger.solves == solves + 1 and merger.drops.total == 0
    harness.settle(0.3)
    assert len(harness.joined) == published


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
        summary = RunSummary.read(summary_path)
        assert not summary.result.converged
        assert any(n.startswith("joint solve not converged") for n in summary.result.notes)
    finally:
        h.close()
