"""Checkpoints and saved states: written and read back whole, continued runs equal whole ones,
bad files refused with one clear error."""

from __future__ import annotations

import json
import re
import zipfile
from dataclasses import fields, is_dataclass
from pathlib import Path
from typing import Any

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
from csam_ros.core.exchange.measurement_filter import MeasurementFilter
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


def _assert_same(read: Any, written: Any, where: str = "checkpoint") -> None:
    """``read`` equals ``written`` field by field; arrays in dtype, shape and every value."""
    if is_dataclass(written):
        assert type(read) is type(written), where
        for f in fields(written):
            _assert_same(getattr(read, f.name), getattr(written, f.name), f"{where}.{f.name}")
    elif isinstance(written, dict):
        assert isinstance(read, dict) and list(read) == list(written), where
        for key, value in written.items():
            _assert_same(read[key], value, f"{where}[{key!r}]")
    elif isinstance(written, list | tuple):
        assert isinstance(read, list | tuple) and len(read) == len(written), where
        for i, (x, y) in enumerate(zip(read, written, strict=True)):
            _assert_same(x, y, f"{where}[{i}]")
    elif isinstance(written, np.ndarray):
        assert isinstance(read, np.ndarray), where
        assert (read.dtype, read.shape) == (written.dtype, written.shape), where
        np.testing.assert_array_equal(read, written, err_msg=where)
    else:
        assert type(read) is type(written) and read == written, (where, read, written)


@pytest.fixture(scope="module")
def written_checkpoint(run, tmp_path_factory) -> tuple[SmootherCheckpoint, bytes]:
    """A smoother checkpoint with something in every part, and the bytes of its file."""
    local = LocalMap("robot1")
    _feed(local, run.robots["robot1"], 0.0, 10.0)
    local.update()
    checks = MeasurementFilter(["robot1", "robot2"])
    checks.odometry("robot1", 5.0, [0.1, 0.0, 0.0], [0.1, 0.1, 0.1])  # held back
    checks.features("robot1", -1.0, [1.0], [0.0], [-1.0], [0.1])  # counted
    thinning = RendezvousThinning(1.0, 4)
    for t in np.arange(0.0, 10.0, 0.5):
        thinning.offer("robot1", "robot2", t)
    own = run.robots["robot1"].rendezvous
    checkpoint = SmootherCheckpoint(
        "robot1",
        local.state(),
        FilterState.of(checks),
        FilterState.of(MeasurementFilter(["robot1", "robot2"])),
        ThinningState.of(thinning),
        own,
        np.unique(own.stamps),
        123,
        100,
        2,
        restarts=1,
        lost_seconds=1.5,
    )
    path = tmp_path_factory.mktemp("checkpoint") / "good.npz"
    checkpoint.write(path)
    _assert_same(SmootherCheckpoint.read(path, "robot1"), checkpoint)  # undamaged: all of it
    return checkpoint, path.read_bytes()


def _read_damaged(path: Path, data: bytes, written: SmootherCheckpoint) -> bool:
    """Write ``data`` to ``path`` and read it: True when it reads back exactly ``written``,
    False when it raises CheckpointError. Anything else - another exception, or a checkpoint
    that differs in any array or value - fails the test."""
    path.write_bytes(data)
    try:
        back = SmootherCheckpoint.read(path, "robot1")
    except CheckpointError as err:
        assert str(path) in str(err)
        return False
    _assert_same(back, written)
    return True


def _central_entry(data: bytes, member: str) -> int:
    """Where ``member``'s entry in the zip central directory starts."""
    end = data.rfind(b"PK\x05\x06")  # the end of central directory record
    at = int.from_bytes(data[end + 16 : end + 20], "little")
    while data[at : at + 4] == b"PK\x01\x02":
        name_length, extra, comment = (
            int.from_bytes(data[at + k : at + k + 2], "little") for k in (28, 30, 32)
        )
        if data[at + 46 : at + 46 + name_length] == member.encode():
            return at
        at += 46 + name_length + extra + comment
    raise AssertionError(f"no {member} in the central directory")


def _npy_header(data: bytes, member: str) -> tuple[int, int]:
    """The byte range of ``member``'s .npy header (its magic, dtype and shape)."""
    entry = _central_entry(data, member)
    local = int.from_bytes(data[entry + 42 : entry + 46], "little")
    name_length, extra = (
        int.from_bytes(data[local + k : local + k + 2], "little") for k in (26, 28)
    )
    start = local + 30 + name_length + extra
    assert data[start : start + 6] == b"\x93NUMPY" and data[start + 6] == 1
    return start, start + 10 + int.from_bytes(data[start + 8 : start + 10], "little")


def _fewer_rows(data: bytes, member: str) -> bytes:
    """``data`` with ``member``'s .npy header claiming one row fewer than it holds (the
    header's text stays as long, its CRC is not recomputed)."""
    start, end = _npy_header(data, member)
    header = data[start:end].decode("latin1")
    rows = re.search(r"'shape': \((\d+),", header)
    assert rows is not None and int(rows[1]) > 1, header
    fewer = f"{int(rows[1]) - 1:>{len(rows[1])}}"
    return (
        data[:start]
        + (header[: rows.start(1)] + fewer + header[rows.end(1) :]).encode("latin1")
        + data[end:]
    )


def _patched(data: bytes, at: int, value: bytes) -> bytes:
    return data[:at] + value + data[at + len(value) :]


def test_damaged_checkpoints_read_back_whole_or_raise_checkpoint_errors(
    written_checkpoint, tmp_path
) -> None:
    """Bytes flipped or cut anywhere in a checkpoint: reading it either raises CheckpointError
    or gives back exactly the checkpoint written, never a damaged one and never another
    exception (a node would die of that at start, or go on from a wrong state)."""
    written, data = written_checkpoint
    bad = tmp_path / "bad.npz"
    rng = np.random.default_rng(5)
    outcomes = []
    for i in range(150):
        damaged = bytearray(data)
        if i % 3 == 0:
            damaged = damaged[: int(rng.integers(0, len(data)))]
        else:
            for at in rng.integers(0, len(data), size=int(rng.integers(1, 8))):
                damaged[at] = int(rng.integers(0, 256))
        outcomes.append(_read_damaged(bad, bytes(damaged), written))
    assert not all(outcomes)  # the damage is seen


def test_damage_to_the_zip_and_npy_headers_is_seen(written_checkpoint, tmp_path) -> None:
    """Every byte of two members' headers (local, .npy and central directory entry) and of the
    end record flipped (the array data is under the zip's CRCs): read back whole or
    CheckpointError. Some flips (dates, attributes) change nothing read, most are errors."""
    written, data = written_checkpoint
    bad = tmp_path / "bad.npz"
    offsets = list(range(data.rfind(b"PK\x05\x06"), len(data)))
    for member in ("header.npy", "map/feature_sqrt_information.npy"):
        entry = _central_entry(data, member)
        local = int.from_bytes(data[entry + 42 : entry + 46], "little")
        offsets += range(entry, entry + 46 + len(member))
        offsets += range(local, _npy_header(data, member)[1])
    read = errors = 0
    for at in offsets:
        for pattern in (0x01, 0xFF):
            if _read_damaged(bad, _patched(data, at, bytes([data[at] ^ pattern])), written):
                read += 1
            else:
                errors += 1
    assert read > 0 and errors > read


@pytest.mark.parametrize(
    "damage",
    [
        "fewer rows",  # the array stops early: its CRC is never reached
        "encrypted",  # zipfile: RuntimeError, password required
        "compression",  # zipfile: NotImplementedError, unsupported method
        "zip version",  # zipfile: NotImplementedError, version needed to extract
    ],
)
def test_named_damage_raises_checkpoint_error(written_checkpoint, tmp_path, damage: str) -> None:
    written, data = written_checkpoint
    member = "map/feature_sqrt_information.npy"
    entry = _central_entry(data, member)
    damaged = {
        "fewer rows": lambda: _fewer_rows(data, member),
        "encrypted": lambda: _patched(data, entry + 8, bytes([data[entry + 8] | 0x01])),
        "compression": lambda: _patched(data, entry + 10, (99).to_bytes(2, "little")),
        "zip version": lambda: _patched(data, entry + 6, (99).to_bytes(2, "little")),
    }[damage]()
    assert damaged != data and len(damaged) == len(data)
    assert not _read_damaged(tmp_path / "bad.npz", damaged, written)
