"""Checkpoints and saved states: written and read back whole, continued runs equal whole ones,
bad files refused with one clear error."""

from __future__ import annotations

import io
import json
import os
import re
import stat
import zipfile
from dataclasses import fields, is_dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from log_slices import robot_log_between

from csam_ros.core.exchange.checkpoint import (
    FilterState,
    MergerState,
    OfflineState,
    SmootherCheckpoint,
    ThinningState,
    joined_logs,
    missed_samples,
    odometry_period,
)
from csam_ros.core.exchange.measurement_filter import MeasurementFilter
from csam_ros.core.exchange.state_files import CheckpointError, read_npz, write_npz
from csam_ros.core.joining.config import CsamConfig
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


def test_a_merger_state_of_version_1_reads_its_result_from_the_header(run, tmp_path) -> None:
    """Version 1 kept the whole result in the header; version 2 keeps its per-pose series
    as arrays (a non-finite heading sigma among them, as a warm start's template holds)."""
    path, _ = _merger_and_offline(run, tmp_path)
    state = MergerState.read(path)
    assert state.result is not None
    state.result.robots["robot1"].sigma_phi_local[0] = np.nan
    state.write(path)
    header, arrays = read_npz(path, "merger")
    assert header["version"] == 2 and "result/robot1/poses_local" in arrays
    assert header["result"]["robots"]["robot1"]["poses_local"] == []
    back = MergerState.read(path).result
    assert back is not None and np.isnan(back.robots["robot1"].sigma_phi_local[0])
    header["version"] = 1
    header["result"] = state.result.to_dict()
    old = tmp_path / "version1.npz"
    write_npz(old, "merger", header, {k: v for k, v in arrays.items() if "result/" not in k})
    from_header = MergerState.read(old).result
    assert from_header is not None
    for result in (back, from_header):
        np.testing.assert_array_equal(
            result.robots["robot1"].sigma_phi_local, state.result.robots["robot1"].sigma_phi_local
        )
        assert (
            result.to_dict()["robots"]["robot1"]["poses_local"]
            == (state.result.to_dict()["robots"]["robot1"]["poses_local"])
        )


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


def _rewritten(tmp_path: Path, data: bytes, name: str, change: Any) -> Path:
    """A whole file (CRCs that match) of the checkpoint ``data`` with ``change(header,
    arrays)`` applied."""
    good = tmp_path / "source.npz"
    good.write_bytes(data)
    header, arrays = read_npz(good, "smoother")
    change(header, arrays)
    path = tmp_path / name
    write_npz(path, "smoother", header, arrays)
    return path


def _set(where: str, key: str, value: Any) -> Any:
    """A change of ``_rewritten``: the header's (or the arrays') ``key`` set to ``value``."""

    def change(header: dict, arrays: dict) -> None:
        target = header if where == "header" else arrays
        for part in key.split(".")[:-1]:
            target = target[part]
        target[key.split(".")[-1]] = value(target.get(key.split(".")[-1]))

    return change


# a field no run could have written, and the words its error names it by
FIELD_CASES = {
    "stamp_beyond_ros_time": (_set("header", "published_ns", lambda _: 10**30), "published_ns"),
    "odometry_stamp_huge": (_set("header", "last_odometry_ns", lambda _: 2**63), "last_odometry"),
    "negative_count": (_set("header", "errors", lambda _: -3), "errors"),
    "count_a_bool": (_set("header", "errors", lambda _: False), "errors"),
    "lost_seconds_nan": (_set("header", "lost_seconds", lambda _: float("nan")), "lost_seconds"),
    "integrated_beyond": (
        _set("header", "map.integrated_features", lambda _: 10**6),
        "integrated",
    ),
    "solved_a_string": (_set("header", "map.solved", lambda _: "yes"), "map/solved"),
    "last_solved_inf": (
        _set("header", "map.last_solved_odometry", lambda _: float("inf")),
        "last_solved_odometry",
    ),
    "reversed_odometry": (
        _set("arrays", "map/odometry_stamps", lambda a: a[::-1].copy()),
        "map/odometry_stamps",
    ),
    "reversed_keys": (_set("arrays", "map/keys", lambda a: a[::-1].copy()), "map/keys"),
    "zero_sigma": (
        _set("arrays", "map/odometry_sigmas", lambda a: np.where(a > 0, 0.0, a)),
        "map/odometry_sigmas",
    ),
    "negative_sigma": (
        _set("arrays", "own_rendezvous/sigma_range", lambda a: -a),
        "own_rendezvous/sigma_range",
    ),
    "nan_key_pose": (
        _set("arrays", "map/key_values", lambda a: np.where(a == a[1, 1], np.nan, a)),
        "map/key_values",
    ),
    "scalar_array": (_set("arrays", "rendezvous_stamps", lambda a: np.float64(3.0)), "scalar"),
    "text_array": (_set("arrays", "map/keys", lambda a: np.array(["a", "b"])), "map/keys"),
    "labels_beyond_int64": (
        _set("arrays", "map/landmark_labels", lambda a: a.astype(np.uint64) + 2**63),
        "map/landmark_labels",
    ),
    "repeated_landmark": (
        _set("arrays", "map/landmark_labels", lambda a: np.zeros_like(a)),
        "map/landmark_labels",
    ),
    "unsorted_rendezvous_stamps": (
        _set("arrays", "rendezvous_stamps", lambda a: a[::-1].copy()),
        "rendezvous_stamps",
    ),
    "held_sample_zero_sigma": (
        _set(
            "header",
            "filter.streams",
            lambda rows: [r[:5] + [[0.0, 0.0, 0.0]] + r[6:] if len(r) == 7 else r for r in rows],
        ),
        "held sigmas",
    ),
    "thinning_interval_negative": (
        _set("header", "thinning.interval", lambda rows: [[a, b, -1.0] for a, b, _ in rows]),
        "thinning/interval",
    ),
    "drop_count_huge": (
        _set("header", "filter.drops", lambda d: {r: {"x": 10**40} for r in d}),
        "filter/drops",
    ),
}


@pytest.mark.parametrize("case", list(FIELD_CASES))
def test_a_whole_checkpoint_with_a_field_no_run_could_write_is_refused(
    written_checkpoint, tmp_path, case: str
) -> None:
    """The file reads (every CRC matches) but a field breaks its meaning: CheckpointError
    naming the file and the field, before any of it is used."""
    _, data = written_checkpoint
    change, field_name = FIELD_CASES[case]
    path = _rewritten(tmp_path, data, f"{case}.npz", change)
    with pytest.raises(CheckpointError) as caught:
        SmootherCheckpoint.read(path, "robot1")
    message = str(caught.value)
    assert str(path) in message and field_name in message, message
    assert "\n" not in message


def test_the_field_cases_change_what_they_name(written_checkpoint, tmp_path) -> None:
    """Each case of FIELD_CASES changes the file (a case that changed nothing would pass for
    the wrong reason): the header or arrays differ from the written ones."""
    _, data = written_checkpoint
    good = tmp_path / "good.npz"
    good.write_bytes(data)
    header, arrays = read_npz(good, "smoother")
    for case, (change, _) in FIELD_CASES.items():
        changed_header, changed_arrays = json.loads(json.dumps(header)), dict(arrays)
        change(changed_header, changed_arrays)
        same_arrays = all(
            np.shape(changed_arrays[k]) == np.shape(v)
            and np.asarray(changed_arrays[k]).dtype == v.dtype
            and np.array_equal(changed_arrays[k], v, equal_nan=True)
            for k, v in arrays.items()
        )
        assert changed_header != header or not same_arrays, case


def _merger_and_offline(run: MultiRobotLog, tmp_path: Path) -> tuple[Path, Path]:
    """Small whole merger and offline state files of the run's first 25 s."""
    logs = {n: robot_log_between(r, end=25.0) for n, r in run.robots.items()}
    offline = tmp_path / "offline.npz"
    OfflineState(logs, FilterState.of(MeasurementFilter(list(logs)))).write(offline)
    local = LocalMap("robot1")
    local.add_log(logs["robot1"])
    local.update(converge=True)
    robot_map = robot_map_from_local_map(local)
    merger = tmp_path / "merger.npz"
    rendezvous = {"robot1": logs["robot1"].rendezvous}
    MergerState(
        "robot1",
        ["robot1"],
        ["robot1", "robot2"],
        {"robot1": robot_map},
        {"robot1": 10**9},
        rendezvous,
        3,
        {},
        result=join_maps([robot_map], rendezvous, CsamConfig(skip_missing_poses=True)),
    ).write(merger)
    return merger, offline


MERGER_CASES = {
    "map_stamp_beyond_ros_time": ("header", "map_stamps", lambda v: {"robot1": 10**30}),
    "solves_negative": ("header", "solves", lambda v: -1),
    "dropped_not_counts": ("header", "dropped", lambda v: {"x": "many"}),
    "rendezvous_nan_range": ("arrays", "rendezvous/robot1/ranges", lambda a: a * np.nan),
    "poses_a_scalar": ("arrays", "maps/robot1/poses", lambda a: np.float64(1.0)),
    "ends_one_column": ("arrays", "maps/robot1/odometry_ends", lambda a: a[:, 0].copy()),
    "result_poses_short": ("arrays", "result/robot1/poses_local", lambda a: a[:-1].copy()),
    "result_sigma_as_text": ("arrays", "result/robot1/sigma_phi_local", lambda a: a.astype(str)),
}
OFFLINE_CASES = {
    "odometry_zero_sigma": ("arrays", "logs/robot1/odometry/sigmas", lambda a: 0.0 * a),
    "odometry_reversed": ("arrays", "logs/robot1/odometry/stamps", lambda a: a[::-1].copy()),
    "stamps_a_scalar": ("arrays", "logs/robot1/odometry/stamps", lambda a: np.float64(1.0)),
    "range_negative": ("arrays", "logs/robot1/features/ranges", lambda a: -a),
    "observed_not_a_list": ("header", "lists", lambda v: {k: 5 for k in v}),
    "robot_twice": ("header", "robots", lambda v: [*v, v[0]]),
}


@pytest.mark.parametrize(
    "kind, case", [("merger", c) for c in MERGER_CASES] + [("offline", c) for c in OFFLINE_CASES]
)
def test_merger_and_offline_states_with_a_field_no_run_could_write_are_refused(
    run, tmp_path, kind: str, case: str
) -> None:
    merger, offline = _merger_and_offline(run, tmp_path)
    if kind == "merger":
        source, reader, (where, key, value) = merger, MergerState.read, MERGER_CASES[case]
    else:
        source, reader, (where, key, value) = offline, OfflineState.read, OFFLINE_CASES[case]
    reader(source)  # the whole file reads
    header, arrays = read_npz(source, kind)
    target = header if where == "header" else arrays
    target[key] = value(target[key])
    path = tmp_path / f"{case}.npz"
    write_npz(path, kind, header, arrays)
    with pytest.raises(CheckpointError) as caught:
        reader(path)
    message = str(caught.value)
    assert str(path) in message and "\n" not in message, message


def _declaring(data: bytes, member: str, size: int) -> bytes:
    """``data`` with ``member`` deflated and its zip directory entry declaring ``size`` bytes
    uncompressed (its CRC that of the bytes it holds): cheap to build, a decompression bomb
    to a reader that trusts the declared size."""
    source = zipfile.ZipFile(io.BytesIO(data))
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w") as target:
        for info in source.infolist():
            content = source.read(info)
            info.compress_type = zipfile.ZIP_DEFLATED if info.filename == member else 0
            target.writestr(info, content)
    deflated = out.getvalue()
    entry = _central_entry(deflated, member)  # its uncompressed size: 4 bytes at 24
    return _patched(deflated, entry + 24, size.to_bytes(4, "little"))


def test_a_state_declaring_more_than_the_maximum_is_refused_before_decompression(
    written_checkpoint, tmp_path
) -> None:
    """An entry declaring 3 GB uncompressed (a 3 MB file may expand to that) is refused by
    the sizes in the zip directory, before any is decompressed; one declaring a few bytes
    less than it holds, and an .npy header naming a shape its bytes do not hold (10^12
    rows: numpy would allocate them first), are refused as damaged."""
    _, data = written_checkpoint
    member = "map/feature_sqrt_information.npy"
    bomb = tmp_path / "bomb.npz"
    bomb.write_bytes(_declaring(data, member, 3 * 10**9))
    with pytest.raises(CheckpointError, match=r"declare \d+ bytes, more than the 536870912"):
        SmootherCheckpoint.read(bomb, "robot1")
    held = zipfile.ZipFile(io.BytesIO(data)).getinfo(member).file_size
    short = tmp_path / "short.npz"  # decompressed no further than it declares: a CRC error
    short.write_bytes(_declaring(data, member, held - 7))
    with pytest.raises(CheckpointError, match="short.npz: not a readable .npz file"):
        SmootherCheckpoint.read(short, "robot1")
    huge_shape = tmp_path / "huge_shape.npz"
    start, end = _npy_header(data, member)
    header = data[start:end].decode("latin1")
    rows = re.search(r"'shape': \((\d+),", header)
    assert rows is not None
    claimed = (header[: rows.start(1)] + "1000000000000" + header[rows.end(1) :]).rstrip()
    assert len(claimed) < len(header)  # the header's padding takes the longer number
    claimed = claimed.ljust(len(header) - 1) + "\n"
    patched = data[:start] + claimed.encode("latin1") + data[end:]
    huge_shape.write_bytes(patched)
    with pytest.raises(CheckpointError, match="huge_shape.npz"):
        SmootherCheckpoint.read(huge_shape, "robot1")


def test_state_files_are_read_and_written_as_regular_files_only(
    written_checkpoint, tmp_path
) -> None:
    """A FIFO named as a state file is refused at once (a read would wait for a writer
    forever); one named as the output is refused and stays a FIFO (a rename would replace
    it, as it would a device). A write whose final rename fails leaves no temporary file."""
    from waiting import no_hang

    written, _ = written_checkpoint
    fifo = tmp_path / "fifo.npz"
    os.mkfifo(fifo)
    with no_hang(10.0), pytest.raises(CheckpointError, match="fifo.npz: .*a FIFO"):
        SmootherCheckpoint.read(fifo, "robot1")
    with pytest.raises(OSError, match="a FIFO, not a regular file"):
        written.write(fifo)
    assert stat.S_ISFIFO(os.lstat(fifo).st_mode)
    assert not list(tmp_path.glob(".*.tmp"))
    folder = tmp_path / "taken"
    (folder / "inside").mkdir(parents=True)
    with pytest.raises(OSError):
        written.write(folder)  # a rename onto a folder that holds something fails
    assert not list(tmp_path.glob(".*.tmp")), list(tmp_path.glob(".*"))
    back = tmp_path / "back.npz"
    written.write(back)
    _assert_same(SmootherCheckpoint.read(back, "robot1"), written)
