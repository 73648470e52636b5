"""Local map updates: a receiver applying every update holds the sender's map (factors
exactly, estimates within the tolerance), late poses included; duplicates and gaps."""

from dataclasses import replace

import numpy as np
import pytest

from csam_ros.core.exchange.local_map_checks import LocalMapArrays
from csam_ros.core.exchange.map_arrays import robot_map_arrays
from csam_ros.core.exchange.map_updates import (
    HeldMap,
    KeyedMap,
    MissingBaseError,
    UpdateSender,
    UpdateTolerance,
    apply_update,
)
from csam_ros.core.joining.pipeline import robot_map_from_local_map
from csam_ros.core.model import se2
from csam_ros.core.smoothing.local_map import LocalMap
from csam_ros.datasets.simulation import simulate_robot_log


def growing_maps(duration: float = 30.0, late: tuple[float, ...] = ()) -> list[LocalMapArrays]:
    """The arrays of a local map after each second of a simulated log (``late``: stamps of
    poses requested in the past after two thirds of the log)."""
    log, _, stamps, _ = simulate_robot_log(duration, 67.0, 0, 12, 2.0)
    local = LocalMap(log.name)
    odo, f = log.odometry, log.features
    edges = np.arange(odo.stamps[0], odo.stamps[-1] + 1.0, 1.0)
    maps = []
    for a, b in zip(edges[:-1], edges[1:], strict=True):
        local.add_log_part(
            log, (odo.stamps >= a) & (odo.stamps < b), (f.stamps >= a) & (f.stamps < b)
        )
        if late and b > edges[0] + 2 * duration / 3:
            local.request_poses([stamps[0] + s for s in late])
            late = ()
        local.update()
        if len(local.stamps) >= 2:
            maps.append(robot_map_arrays(robot_map_from_local_map(local)))
    return maps


def assert_same_map(held: LocalMapArrays, sent: LocalMapArrays, tolerance: UpdateTolerance) -> None:
    for name in (
        "feature_labels",
        "odometry_ends",
        "odometry_delta",
        "odometry_sqrt_information",
        "observation_pose",
        "observation_label",
        "observation_xy",
        "observation_sqrt_information",
        "prior_sqrt_information",
    ):
        np.testing.assert_array_equal(getattr(held, name), getattr(sent, name), err_msg=name)
    np.testing.assert_allclose(held.stamps, sent.stamps, rtol=0, atol=1e-9)
    assert np.abs(held.poses[:, :2] - sent.poses[:, :2]).max() <= tolerance.position
    assert np.abs(se2.wrap_angle(held.poses[:, 2] - sent.poses[:, 2])).max() <= tolerance.heading
    assert np.abs(held.feature_xy - sent.feature_xy).max() <= tolerance.key
    assert (held.robust_kernel, held.cost) == (sent.robust_kernel, sent.cost)


@pytest.fixture(scope="module")
def maps() -> list[LocalMapArrays]:
    return growing_maps(late=(3.3337, 12.5))


@pytest.mark.parametrize("tolerance", [UpdateTolerance.exact(), UpdateTolerance()])
def test_receiver_holds_the_senders_map_after_every_update(maps, tolerance) -> None:
    sender = UpdateSender(session=7, tolerance=tolerance)
    held: HeldMap | None = None
    for current in maps:
        update = sender.update(current)
        held = apply_update(held, update)
        assert sender.held is not None and held.sequence == sender.held.sequence
        assert_same_map(held.map.arrays(), sender.held.map.arrays(), UpdateTolerance.exact())
        assert_same_map(held.map.arrays(), current, tolerance)
    # only the first was complete: the late poses split odometry factors within updates
    assert sender.complete_updates == 1
    assert len(maps[-1].stamps) > len(maps[0].stamps)
    # an exact update leaves no difference at all
    final = apply_update(held, sender.update(maps[-1], exact=True)).map.arrays()
    assert_same_map(final, maps[-1], UpdateTolerance.exact())


def test_updates_carry_only_what_changed(maps) -> None:
    sender = UpdateSender(session=1)
    first = sender.update(maps[0])
    assert first.complete and len(first.changes.pose_stamps) == len(maps[0].stamps)
    sizes, replaced = [], 0
    for current in maps[1:]:
        assert sender.held is not None
        held_firsts = sender.held.map.odometry_stamps[:, 0]
        changes = sender.update(current).changes
        sizes.append(len(changes.observation_label))
        assert len(changes.odometry_stamps) < len(current.odometry_ends)
        # a late pose splits a held factor: it is sent again under its first pose's stamp
        replaced += int(np.isin(changes.odometry_stamps[:, 0], held_firsts).sum())
    assert replaced == 2
    total = sum(sizes) + len(first.changes.observation_label)
    assert total == len(maps[-1].observation_label)  # each observation sent once


def test_an_update_delivered_twice_changes_nothing(maps) -> None:
    sender = UpdateSender(session=3)
    updates = [sender.update(m) for m in maps[:6]]
    held = None
    for u in updates:
        held = apply_update(held, u)
        again = apply_update(held, u)
        assert again is held
    assert held is not None
    # an older update delivered late changes nothing either
    assert apply_update(held, updates[2]) is held


def test_a_missed_update_needs_a_complete_one(maps) -> None:
    sender = UpdateSender(session=4)
    updates = [sender.update(m) for m in maps[:5]]
    held = apply_update(apply_update(None, updates[0]), updates[1])
    with pytest.raises(MissingBaseError, match="update 3 is held|applies to update 3"):
        apply_update(held, updates[3])
    with pytest.raises(MissingBaseError, match="no update of that session"):
        apply_update(None, updates[2])
    with pytest.raises(MissingBaseError, match="session"):
        apply_update(held, replace(updates[2], session=5))
    resync = sender.resend()
    assert resync is not None and resync.complete
    held = apply_update(held, resync)
    for current in maps[5:8]:
        held = apply_update(held, sender.update(current))
    assert_same_map(held.map.arrays(), maps[7], sender.tolerance)


def test_a_map_that_did_not_grow_from_the_held_one_is_sent_complete(maps) -> None:
    sender = UpdateSender(session=2)
    sender.update(maps[5])
    assert sender.update(maps[3]).complete  # fewer poses: a restart, not growth
    changed_kernel = replace(maps[4], robust_kernel="cauchy", robust_parameter=1.0)
    assert sender.update(changed_kernel).complete
    assert sender.update(maps[5], complete=True).complete


def test_keyed_map_round_trip(maps) -> None:
    m = maps[-1]
    back = KeyedMap.of(m).arrays()
    assert_same_map(back, m, UpdateTolerance.exact())
    broken = replace(KeyedMap.of(m), observation_stamps=KeyedMap.of(m).observation_stamps + 1)
    with pytest.raises(ValueError, match="observation factor at stamp .* has no pose"):
        broken.arrays()


def test_key_poses_and_features_are_held_to_the_key_tolerance(maps) -> None:
    sender = UpdateSender(session=8, tolerance=UpdateTolerance(position=0.5, heading=0.5, key=1e-4))
    held: HeldMap | None = None
    loose = 0.0
    for current in maps:
        keys = np.arange(0, len(current.stamps), 3)  # every third pose is a rendezvous pose
        held = apply_update(held, sender.update(current, key_poses=keys))
        got = held.map.arrays()
        moved = np.abs(got.poses[:, :2] - current.poses[:, :2]).max(axis=1)
        assert moved[keys].max() <= 1e-4 and moved.max() <= 0.5
        assert np.abs(got.feature_xy - current.feature_xy).max() <= 1e-4
        loose = max(loose, moved.max())
    assert loose > 1e-4  # the other poses were held back within the loose bound
