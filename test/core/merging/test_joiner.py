"""The merger's joiner: maps refined once per source, warm joins equal to cold ones."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from growing_joins import largest_difference, maps_until

from csam_ros.core.exchange.checkpoint import MergerState
from csam_ros.core.exchange.map_arrays import held_robot_map, robot_map_arrays
from csam_ros.core.exchange.map_updates import HeldMap, UpdateSender, apply_update
from csam_ros.core.exchange.validation import MALFORMED_LOCAL_MAP
from csam_ros.core.joining.config import CsamConfig
from csam_ros.core.joining.join import join_maps
from csam_ros.core.merging.joiner import (
    JoinCancelled,
    Joiner,
    JoinRequest,
    MapSource,
    PrepareRequest,
)
from csam_ros.core.model.log import MultiRobotLog
from csam_ros.datasets.scenario import load_scenario
from csam_ros.datasets.simulation import simulate

CONFIG = CsamConfig(skip_missing_poses=True)


@pytest.fixture(scope="module")
def run() -> MultiRobotLog:
    return simulate(load_scenario("map_joining"), 1)


def _moments(log: MultiRobotLog) -> list[float]:
    first = min(r.rendezvous.stamps.min() for r in log.robots.values() if len(r.rendezvous.stamps))
    end = max(r.odometry.stamps.max() for r in log.robots.values())
    return [first + 2.0, (first + end) / 2, end]


def test_sources_sent_once_and_refined_join_as_cold_joins(run: MultiRobotLog) -> None:
    """Each robot's map as a receiver of its updates holds it; a robot whose map did not
    change is sent as None. Every join equals a cold join of the senders' maps (1e-6)."""
    joiner = Joiner()
    senders: dict[str, UpdateSender] = {}
    held: dict[str, HeldMap] = {}
    for k, t in enumerate(_moments(run)):
        maps, logs = maps_until(run, t)
        sources: list[tuple[str, MapSource | None]] = []
        for m in maps:
            if k == 1 and m.name == maps[0].name:  # the reference's map kept from the first
                sources.append((m.name, None))
                continue
            sender = senders.setdefault(m.name, UpdateSender(7))
            held[m.name] = apply_update(held.get(m.name), sender.update(robot_map_arrays(m)))
            sources.append((m.name, held[m.name]))
        reply = joiner.join(JoinRequest(tuple(sources), logs, CONFIG))
        assert reply.result is not None and reply.error == "" and reply.refused == ()
        used = [joiner.maps[m.name] for m in maps]
        for m, u in zip(maps, used, strict=True):
            if k != 1 or m.name != maps[0].name:
                np.testing.assert_allclose(u.poses, m.poses, atol=1e-6)
        assert largest_difference(reply.result, join_maps(used, logs, CONFIG)) < 1e-6
        assert joiner.previous is reply.result


def test_an_unusable_source_is_refused_and_the_last_map_joined(run: MultiRobotLog) -> None:
    maps, logs = maps_until(run, _moments(run)[1])
    joiner = Joiner()
    arrays = {m.name: robot_map_arrays(m) for m in maps}
    first = joiner.join(JoinRequest(tuple(arrays.items()), logs, CONFIG))
    assert first.result is not None
    bad_robot = maps[1].name
    poses = arrays[bad_robot].poses.copy()
    poses[3, 0] = np.nan
    bad = replace(arrays[bad_robot], poses=poses)
    reply = joiner.join(JoinRequest(((maps[0].name, None), (bad_robot, bad)), logs, CONFIG))
    assert [(r.robot, r.reason) for r in reply.refused] == [(bad_robot, MALFORMED_LOCAL_MAP)]
    assert reply.result is not None
    assert largest_difference(reply.result, first.result) < 1e-6


def test_prepared_maps_join_as_maps_sent_with_the_join(run: MultiRobotLog) -> None:
    """Maps prepared before their join (refined, factored, their marginals computed) are
    held as the join would take them: the join of None sources equals a join of the
    sources (1e-12), uses the prepared factors, and its reply carries a refusal of prepare."""
    first, later = (maps_until(run, t) for t in _moments(run)[1:])
    joiner, reference = Joiner(), Joiner()
    for joins in (joiner, reference):
        sources = tuple((m.name, robot_map_arrays(m)) for m in first[0])
        assert joins.join(JoinRequest(sources, first[1], CONFIG)).result is not None
    senders = {m.name: UpdateSender(7) for m in later[0]}
    held = {
        m.name: apply_update(None, senders[m.name].update(robot_map_arrays(m))) for m in later[0]
    }
    joiner.prepare(PrepareRequest(tuple(held.items())))
    factors = {name: joiner.local_views.factor(joiner.maps[name]) for name in held}
    assert all("feature_covariances" in vars(f) for f in factors.values())  # computed
    bad_robot = later[0][1].name
    poses = robot_map_arrays(later[0][1]).poses.copy()
    poses[3, 0] = np.nan
    bad = replace(robot_map_arrays(later[0][1]), poses=poses)
    joiner.prepare(PrepareRequest(((bad_robot, bad),)))  # refused: the last map stays
    reply = joiner.join(JoinRequest(tuple((name, None) for name in held), later[1], CONFIG))
    assert [(r.robot, r.reason) for r in reply.refused] == [(bad_robot, MALFORMED_LOCAL_MAP)]
    assert all(joiner.local_views.factor(joiner.maps[n]) is f for n, f in factors.items())
    expected = reference.join(JoinRequest(tuple(held.items()), later[1], CONFIG)).result
    assert reply.result is not None and expected is not None
    assert largest_difference(reply.result, expected) < 1e-12
    again = joiner.join(JoinRequest(tuple((name, None) for name in held), later[1], CONFIG))
    assert again.refused == ()  # reported once


def test_a_map_never_sent_cannot_be_taken_again(run: MultiRobotLog) -> None:
    """A failed reply, and the request's other sources are still taken."""
    maps, logs = maps_until(run, _moments(run)[1])
    joiner = Joiner()
    first, second = maps[0].name, maps[1].name
    request = JoinRequest(((first, None), (second, robot_map_arrays(maps[1]))), logs, CONFIG)
    reply = joiner.join(request)
    assert reply.result is None
    assert reply.error == f"ValueError: no usable map held of {first}"
    again = ((first, robot_map_arrays(maps[0])), (second, None))
    assert joiner.join(JoinRequest(again, logs, CONFIG)).result is not None


def test_a_failed_join_is_a_reply_and_keeps_the_warm_start(run: MultiRobotLog) -> None:
    maps, logs = maps_until(run, _moments(run)[1])
    joiner = Joiner()
    sources = tuple((m.name, robot_map_arrays(m)) for m in maps)
    good = joiner.join(JoinRequest(sources, logs, CONFIG)).result
    reply = joiner.join(JoinRequest((), logs, CONFIG))
    assert reply.result is None and reply.error.startswith("ValueError: ")
    assert joiner.previous is good


def test_a_cancelled_join_keeps_the_maps_taken_and_the_warm_start(run: MultiRobotLog) -> None:
    """A join given up part-way (here where the join itself begins) is a reply saying so; the
    maps it brought are held, and the next join is the one a joiner that never saw it gives."""
    early, later = (maps_until(run, t) for t in _moments(run)[1:])
    cancel = False

    @contextlib.contextmanager
    def cancellable() -> Iterator[None]:
        if cancel:
            raise JoinCancelled("given up")
        yield

    joiner, reference = Joiner(cancellable), Joiner()
    for joins in (joiner, reference):
        sources = tuple((m.name, robot_map_arrays(m)) for m in early[0])
        assert joins.join(JoinRequest(sources, early[1], CONFIG)).result is not None
    good = joiner.previous
    cancel = True
    sources = tuple((m.name, robot_map_arrays(m)) for m in later[0])
    reply = joiner.join(JoinRequest(sources, later[1], CONFIG))
    assert reply.cancelled and reply.result is None and reply.error == "cancelled: given up"
    assert joiner.previous is good
    cancel = False
    kept = tuple((name, None) for name, _ in sources)
    result = joiner.join(JoinRequest(kept, later[1], CONFIG)).result
    expected = reference.join(JoinRequest(sources, later[1], CONFIG)).result
    assert result is not None and expected is not None
    assert largest_difference(result, expected) < 1e-12


def test_the_state_holds_the_joined_maps_and_result(run: MultiRobotLog, tmp_path: Path) -> None:
    maps, logs = maps_until(run, _moments(run)[2])
    sender = UpdateSender(3)
    held = apply_update(None, sender.update(robot_map_arrays(maps[1])))
    sources = ((maps[0].name, robot_map_arrays(maps[0])), (maps[1].name, held))
    order = [m.name for m in maps]
    state = MergerState(order[0], order, order, {}, {r: 1 for r in order}, {}, 4, {})
    path = tmp_path / "merger.npz"
    joiner = Joiner()
    reply = joiner.join(JoinRequest(sources, logs, CONFIG, state=state, state_path=path))
    assert reply.result is not None and reply.state_pending and not path.exists()
    written = joiner.write_state()
    assert written is not None and written.error == "" and path.exists()
    assert joiner.write_state() is None  # written once
    saved = MergerState.read(path)
    assert saved.solves == 4 and list(saved.maps) == order and set(saved.rendezvous) == set(logs)
    refined = held_robot_map(maps[1].name, held)
    np.testing.assert_allclose(saved.maps[maps[1].name].poses, refined.poses, atol=1e-12)
    assert saved.result is not None and largest_difference(saved.result, reply.result) < 1e-9
    unwritable = JoinRequest(sources, logs, CONFIG, state=state, state_path=path / "x")
    assert joiner.join(unwritable).state_pending
    written = joiner.write_state()
    assert written is not None and "merger state not written" in written.error
    assert not joiner.join(JoinRequest(sources, logs, CONFIG)).state_pending  # none asked for
    assert joiner.write_state() is None
