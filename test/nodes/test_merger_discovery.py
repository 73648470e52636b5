"""Robots found, not listed: the merger joins every robot that publishes local map updates
(asking a robot found after its first update for its whole map), picks its reference once,
honours an allow-list, and reports robots gone quiet."""

from __future__ import annotations

from typing import Any

import pytest
from merger_harness import (
    ROBOTS,
    MergerHarness,
    RunMessages,
    Smoothers,
    resent,
    run_messages,
    status_values,
)
from rclpy.publisher import Publisher

from csam_ros.nodes.common import publisher
from csam_ros.ros.topics import RENDEZVOUS_POSES


@pytest.fixture(scope="module")
def renamed() -> RunMessages:
    """The same run with robots no test lists: robotA and robotB."""
    return run_messages(names={"robot1": "robotA", "robot2": "robotB"})


@pytest.fixture
def make(ros_context, spin):
    made: list[MergerHarness] = []

    def build(**parameters) -> MergerHarness:
        made.append(MergerHarness(ros_context, spin, **parameters))
        return made[-1]

    yield build
    for h in made:
        h.close()


def _send(h: MergerHarness, good: RunMessages, robot: str) -> None:
    """The robot's smoother sends its map (lost if the merger has not found it yet: the
    merger then asks for it, and the smoother sends it again)."""
    h.smoothers.whole[robot] = good.local_maps[robot]
    h.publish(robot, good.rendezvous[robot])
    h.publish(robot, good.local_maps[robot])


def _joined_robots(h: MergerHarness) -> set[str]:
    return {t.robot for t in h.joined[-1].trajectories} if h.joined else set()


def _last_status(h: MergerHarness, name: str) -> dict[str, str] | None:
    for array in reversed(h.status):
        values = status_values(array, name)
        if values is not None:
            return values
    return None


def test_robots_not_listed_are_found_and_joined(make, good) -> None:
    h = make(robots=[])
    assert h.merger.policy.robots == []
    # the injector's publishers are on the graph: both robots are found before any map
    h.wait(lambda: set(h.merger.policy.robots) == set(ROBOTS))
    _send(h, good, "robot1")
    h.wait(lambda: "robot1" in h.merger.policy.local_maps and len(h.joined) > 0)
    assert _joined_robots(h) == {"robot1"}
    # a robot that starts publishing later joins at its first usable rendezvous
    _send(h, good, "robot2")
    h.wait(lambda: _joined_robots(h) == set(ROBOTS))
    assert h.joined[-1].reference_robot == "robot1"
    aligned = {n.robot: n.alignment for n in h.joined[-1].base_nodes}
    assert aligned == {"robot1": "reference", "robot2": "aligned"}


def test_an_absent_reference_is_replaced_and_the_choice_kept(make, good) -> None:
    h = make(robots=[], reference="robot1", reference_wait=0.5)
    _send(h, good, "robot2")  # robot1, the configured reference, is not there yet
    h.wait(lambda: len(h.joined) > 0)
    assert h.joined[-1].reference_robot == "robot2"
    h.wait(lambda: (_last_status(h, "merger") or {}).get("reference") == "robot2")
    _send(h, good, "robot1")
    h.wait(lambda: _joined_robots(h) == set(ROBOTS))
    assert h.joined[-1].reference_robot == "robot2"
    assert (
        h.merger.policy.last_result is not None
        and h.merger.policy.last_result.reference == "robot2"
    )


def test_an_allow_list_leaves_other_robots_out(make, good) -> None:
    h = make(robots=["robot1"])
    _send(h, good, "robot2")
    _send(h, good, "robot1")
    h.wait(lambda: len(h.joined) > 0 and "robot2" in h.merger.policy.ignored)
    h.settle(0.3)
    assert h.merger.policy.robots == ["robot1"]
    assert "robot2" not in h.merger.policy.local_maps
    assert _joined_robots(h) == {"robot1"}


def test_a_quiet_robot_is_reported_stale_and_stays_joined(make, good) -> None:
    h = make(stale_after=0.5)
    h.start(good)
    h.wait(lambda: (_last_status(h, "merger/robot2") or {}).get("stale") == "True")
    assert float(_last_status(h, "merger/robot2")["seconds_since_map"]) >= 0.5
    assert _joined_robots(h) == set(ROBOTS)
    # a new update makes it fresh again
    fresh = len(h.status)
    h.publish("robot2", resent(good.local_maps["robot2"]))
    h.wait(
        lambda: any(
            (status_values(a, "merger/robot2") or {}).get("stale") == "False"
            for a in h.status[fresh:]
        )
    )


def test_a_map_delivered_twice_changes_nothing(make, good) -> None:
    """The same whole map again (same session and sequence): no new arrival, no solve."""
    h = make()
    h.start(good)
    solves, joined = h.merger.policy.solves, len(h.joined)
    arrivals = dict(h.merger.policy.map_arrival)
    h.publish("robot2", good.local_maps["robot2"])  # acknowledged: taken in the settle
    h.settle(0.5)
    assert not h.merger.policy.dirty and h.merger.policy.map_arrival == arrivals
    assert (h.merger.policy.solves, len(h.joined)) == (solves, joined)
    assert h.merger.drops.total == 0


def _publishers(h: MergerHarness, robot: str) -> tuple[Smoothers, Publisher]:
    """``robot``'s smoother (local map updates, resync) and rendezvous poses publisher:
    from now on on the graph."""
    return (
        Smoothers(h.injector, [robot]),
        publisher(h.injector, RENDEZVOUS_POSES, RENDEZVOUS_POSES.of(robot)),
    )


def _publish_update(h: MergerHarness, smoother: Smoothers, robot: str, msg: Any) -> None:
    """Publish once the merger's subscription matched (updates are volatile)."""
    pub = smoother.updates[robot]
    h.wait(lambda: pub.get_subscription_count() > 0)
    pub.publish(msg)


def test_robots_appearing_later_on_the_graph_join(make, renamed) -> None:
    """Names known nowhere in advance; robotB's topics appear after robotA's map was joined."""
    h = make(robots=[])
    maps_a, rendezvous_a = _publishers(h, "robotA")
    h.wait(lambda: "robotA" in h.merger.policy.robots)
    assert "robotB" not in h.merger.policy.robots
    rendezvous_a.publish(renamed.rendezvous["robotA"])
    _publish_update(h, maps_a, "robotA", renamed.local_maps["robotA"])
    h.wait(lambda: _joined_robots(h) == {"robotA"})
    maps_b, rendezvous_b = _publishers(h, "robotB")
    h.wait(lambda: "robotB" in h.merger.policy.robots)
    rendezvous_b.publish(renamed.rendezvous["robotB"])
    _publish_update(h, maps_b, "robotB", renamed.local_maps["robotB"])
    h.wait(lambda: _joined_robots(h) == {"robotA", "robotB"})
    joined = h.joined[-1]
    assert joined.reference_robot == "robotA"
    nodes = [(n.robot, n.alignment) for n in joined.base_nodes]
    # the solve's order; the harness's robot1 and robot2 publishers were found too, mapless
    assert nodes[:2] == [("robotA", "reference"), ("robotB", "aligned")]
    assert {r for r, _ in nodes[2:]} == set(ROBOTS)
    assert all(a.startswith("pending") for _, a in nodes[2:])
    h.wait(lambda: (_last_status(h, "merger/robotB") or {}).get("alignment") == "aligned")
    assert (_last_status(h, "merger") or {}).get("reference") == "robotA"
    assert (_last_status(h, "merger/robot1") or {}).get("alignment") == (
        "pending: no local map received"
    )


def test_the_configured_reference_is_awaited(make, good) -> None:
    """Smoothers' first maps come in any order: robot2's coming first does not make it the
    reference while robot1, the first of robots, may still come."""
    h = make(reference_wait=3600.0)
    _send(h, good, "robot2")
    h.wait(lambda: "robot2" in h.merger.policy.local_maps)
    assert not h.merger.solve_pending()
    assert h.merger.policy.reference == "" and h.merger.policy.dirty and not h.joined
    _send(h, good, "robot1")
    h.wait(lambda: _joined_robots(h) == set(ROBOTS))
    assert h.joined[-1].reference_robot == "robot1"
    assert [n.robot for n in h.joined[-1].base_nodes] == ROBOTS
