"""Checkpoints and saved states: written and read back whole, continued runs equal whole ones,
bad files refused with one clear error."""

from __future__ import annotations

import json
import zipfile

import numpy as np
import pytest
from log_slices import robot_log_between

from csam_ros.core.exchange.checkpoint import (
    CheckpointError,
    FilterState,
    MergerState,
    OfflineState,
    SmootherCheckpoint,
    ThinningState,
    joined_logs,
    missed_samples,
    odometry_period,
    read_npz,
    write_npz,
)
from csam_ros.core.exchange.validation import MeasurementFilter
from csam_ros.core.joining.join import join_maps
from csam_ros.core.joining.pipeline import robot_map_from_local_map, run_csam
from csam_ros.core.joining.rendezvous_filters import RendezvousThinning
from csam_ros.core.model.log import MultiRobotLog, empty_rendezvous
from csam_ros.core.model.rendezvous import required_stamps
from csam_ros.core.smoothing.local_map import LocalMap
from csam_ros.datasets.scenario import load_scenario
from csam_ros.datasets.simulation import simulate

SPLIT = 21.0  # s: the map_joining robots meet at about 20 s


@pytest.fixture(scope="module")
def run() -> MultiRobotLog:
    return simulate(load_scenario("map_joining"), seed=3)


def _feed(local: LocalMap, log, start: float, end: float) -> None:
    part = robot_log_between(log, start, end)
    local.add_log_part(part)
    local.request_poses(part.rendezvous.stamps)


def _same_map(a: LocalMap, b: LocalMap) -> None:
    np.testing.assert_array_equal(a.stamps, b.stamps)
    np.testing.assert_array_equal(a.poses, b.poses)
    np.testing.assert_array_equal(a.landmark_labels, b.landmark_labels)
    np.testing.assert_array_equal(a.landmarks, b.landmarks)


def test_a_restored_smoother_map_is_the_same_and_goes_on_the_same(run, tmp_path) -> None:
    log = run.robots["robot1"]
    online = LocalMap("robot1")
    for t in np.arange(0.0, SPLIT, 3.0):
        _feed(online, log, t, t + 2.999)
        online.update()
    # data buffered since the last update travels with the checkpoint too
    _feed(online, log, SPLIT, SPLIT + 1.999)
    checks = MeasurementFilter(["robot1", "robot2"])
    checks.odometry("robot1", 5.0, [0.1, 0.0, 0.0], [0.1, 0.1, 0.1])  # held back: not started
    checks.features("robot1", -1.0, [1.0], [0.0], [-1.0], [0.1])  # counted: non_positive_sigma
    thinning = RendezvousThinning(1.0, 4)
    for t in np.arange(0.0, 10.0, 0.5):
        thinning.offer("robot1", "robot2", t)
    own = log.rendezvous
    checkpoint = SmootherCheckpoint(
        robot="robot1",
        local_map=online.state(),
        filter=FilterState.of(checks),
        peer_filter=FilterState.of(MeasurementFilter(["robot1", "robot2"])),
        thinning=ThinningState.of(thinning),
        own_rendezvous=own,
        rendezvous_stamps=np.unique(own.stamps),
        last_odometry_ns=123,
        published_ns=100,
        errors=2,
        restarts=1,
        lost_seconds=1.5,
    )
    path = tmp_path / "robot1.npz"
    assert checkpoint.write(path) > 0
    back = SmootherCheckpoint.read(path, "robot1")
    restored = LocalMap.from_state("robot1", back.local_map)
    _same_map(online, restored)
    a, b = robot_map_from_local_map(online), robot_map_from_local_map(restored)
    np.testing.assert_array_equal(a.problem.values, b.problem.values)
    assert a.problem.cost() == b.problem.cost()
    # both go on with the same data to the same map, bit for bit
    for local in (online, restored):
        local.update()
        _feed(local, log, SPLIT + 2.0, 40.0)
        local.update(converge=True)
    _same_map(online, restored)
    # the filter, the thinning and the counts come back as they were
    again = MeasurementFilter(["robot1", "robot2"])
    back.filter.restore(again)
    assert again.counter("robot1").as_dict() == {"non_positive_sigma": 1}
    assert len(again.odometry("robot1", 5.5, [0.1, 0.0, 0.0], [0.1] * 3)) == 2  # the held one
    thinned = RendezvousThinning(1.0, 4)
    back.thinning.restore(thinned)
    assert thinned.kept_stamps("robot1", "robot2") == thinning.kept_stamps("robot1", "robot2")
    assert thinned.offer("robot1", "robot2", 10.0) == thinning.offer("robot1", "robot2", 10.0)
    assert back.own_rendezvous.observed == own.observed
    np.testing.assert_array_equal(back.own_rendezvous.ranges, own.ranges)
    assert (back.last_odometry_ns, back.published_ns, back.errors) == (123, 100, 2)
    assert (back.restarts, back.lost_seconds) == (1, 1.5)
    with pytest.raises(CheckpointError, match="the checkpoint of 'robot1', not of 'robot2'"):
        SmootherCheckpoint.read(path, "robot2")


def test_an_offline_run_continued_from_its_saved_state_equals_the_whole_run(run, tmp_path) -> None:
    first = {n: robot_log_between(r, end=SPLIT) for n, r in run.robots.items()}
    then = {n: robot_log_between(r, start=SPLIT + 1e-9) for n, r in run.robots.items()}
    partial = run_csam(MultiRobotLog(first))
    state = OfflineState(first, FilterState.of(MeasurementFilter(list(first))), partial)
    path = tmp_path / "state.npz"
    state.write(path)
    back = OfflineState.read(path)
    assert back.result is not None and back.result.to_dict() == partial.to_dict()
    continued = run_csam(MultiRobotLog(joined_logs(back.logs, then)))
    whole = run_csam(MultiRobotLog(dict(run.robots)))
    assert continued.to_dict() | {"timing_s": {}} == whole.to_dict() | {"timing_s": {}}


def test_a_merger_state_joins_to_the_same_map(run, tmp_path) -> None:
    stamps = required_stamps({n: r.rendezvous for n, r in run.robots.items()})
    maps = []
    for name, log in run.robots.items():
        local = LocalMap(name)
        local.add_log(log, stamps[name])
        local.update(converge=True)
        maps.append(robot_map_from_local_map(local))
    logs = {n: r.rendezvous for n, r in run.robots.items()}
    result = join_maps(maps, logs)
    state = MergerState(
        reference="robot1",
        heard=["robot1", "robot2"],
        robots=["robot1", "robot2", "robot3"],
        maps={m.name: m for m in maps},
        map_stamps={"robot1": 10**12, "robot2": 10**12 + 5},
        rendezvous={**logs, "robot3": empty_rendezvous()},
        solves=4,
        dropped={"malformed_local_map": 1},
        restarts={"robot2": 1},
        restart_poses_lost={"robot2": 7},
        result=result,
    )
    path = tmp_path / "merger.npz"
    state.write(path)
    back = MergerState.read(path)
    assert (back.reference, back.heard, back.robots) == (state.reference, state.heard, state.robots)
    assert (back.map_stamps, back.solves, back.dropped) == (state.map_stamps, 4, state.dropped)
    assert (back.restarts, back.restart_poses_lost) == ({"robot2": 1}, {"robot2": 7})
    assert back.result is not None and back.result.to_dict() == result.to_dict()
    again = join_maps([back.maps[m.name] for m in maps], dict(back.rendezvous))
    assert again.to_dict() | {"timing_s": {}} == result.to_dict() | {"timing_s": {}}


def test_bad_files_are_refused_with_one_clear_error(run, tmp_path) -> None:
    good = tmp_path / "good.npz"
    OfflineState({}, FilterState({}, {})).write(good)
    assert not list(tmp_path.glob(".*.tmp"))  # the temporary file was renamed
    cases = {
        "missing.npz": None,
        "garbage.npz": b"not a zip file at all",
        "truncated.npz": good.read_bytes()[:40],
    }
    for name, data in cases.items():
        if data is not None:
            (tmp_path / name).write_bytes(data)
        with pytest.raises(CheckpointError, match=name):
            OfflineState.read(tmp_path / name)
    foreign = tmp_path / "foreign.npz"
    np.savez(foreign, x=np.zeros(3))
    with pytest.raises(CheckpointError, match="not a csam_ros state file"):
        OfflineState.read(foreign)
    with pytest.raises(CheckpointError, match="a 'offline' file, not a 'merger' one"):
        MergerState.read(good)
    future = tmp_path / "future.npz"
    header, _ = read_npz(good, "offline")
    with zipfile.ZipFile(future, "w") as z, z.open("header.npy", "w") as f:
        np.lib.format.write_array(f, np.array(json.dumps({**header, "version": 99})))
    with pytest.raises(CheckpointError, match="version 99"):
        OfflineState.read(future)
    short = tmp_path / "short.npz"
    write_npz(short, "offline", {"robots": ["robot1"], "lists": {}}, {})
    with pytest.raises(CheckpointError, match="no array 'logs/robot1/odometry/stamps'"):
        OfflineState.read(short)


def test_missed_samples_from_the_odometry_period() -> None:
    stamps = np.arange(0.0, 10.0, 0.5)
    period = odometry_period(stamps)
    assert period == 0.5
    assert missed_samples(9.5 + 3.5 - 9.5, period) == 6  # 10.0 ... 12.5 never came
    assert missed_samples(0.5, period) == 0
    assert missed_samples(3.0, None) == 0
    assert odometry_period(np.zeros(1)) is None


def test_damaged_checkpoints_raise_only_checkpoint_errors(run, tmp_path) -> None:
    """Bytes flipped or cut anywhere in a checkpoint: reading it either works or raises
    CheckpointError, never anything else (a node would die of that at start)."""
    local = LocalMap("robot1")
    local.add_log(robot_log_between(run.robots["robot1"], end=10.0))
    local.update()
    checks = MeasurementFilter(["robot1", "robot2"])
    good = tmp_path / "good.npz"
    SmootherCheckpoint(
        "robot1",
        local.state(),
        FilterState.of(checks),
        FilterState.of(checks),
        ThinningState({}, {}),
        run.robots["robot1"].rendezvous,
        np.zeros(0),
        1,
        1,
        0,
    ).write(good)
    data = good.read_bytes()
    rng = np.random.default_rng(5)
    bad = tmp_path / "bad.npz"
    for i in range(150):
        damaged = bytearray(data)
        if i % 3 == 0:
            damaged = damaged[: int(rng.integers(0, len(data)))]
        else:
            for at in rng.integers(0, len(data), size=int(rng.integers(1, 8))):
                damaged[at] = int(rng.integers(0, 256))
        bad.write_bytes(bytes(damaged))
        try:
            restored = SmootherCheckpoint.read(bad, "robot1")
            LocalMap.from_state("robot1", restored.local_map)
        except CheckpointError:
            pass
        except ValueError as err:  # from_state: arrays that do not fit together
            assert "robot1" in str(err)
