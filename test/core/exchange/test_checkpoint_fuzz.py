"""Fuzzing the state files (core/exchange/checkpoint.py) with damaged copies of real ones.

Three small real files (a smoother's checkpoint, a merger's state, an offline replay's state)
are damaged two ways, drawn by hypothesis under the project's derandomised profile: bytes
flipped and the file cut (the zip's CRCs see most of it), and one field of a whole file
replaced (written again with matching CRCs, so only the field checks stand in the way): a
header value by a hostile JSON value (10^30, NaN, a string, a list, ...), an array reversed,
zeroed, negated, made a scalar, of other dtype or shape, or given a NaN or 1e308.

Every outcome must be a CheckpointError naming the file in one line, or a state that holds
what it means and that its taker can use as the smoother, the merger and an offline replay
do: the local map rebuilt (one whose features lie at no key pose within the smoother's
stamp tolerance, an option of the node, is refused there as the smoother's read_checkpoint
does), the checks and the thinning restored and fed, the stamps within a ROS time, the
merger's maps and an offline replay's logs taken by the core. Any other exception fails the
test.

`make test` runs a bounded number of examples (seconds). A longer run:

    CSAM_FUZZ_EXAMPLES=1000 .venv/bin/python -m pytest -q -p no:cacheprovider \\
        test/core/exchange/test_checkpoint_fuzz.py
"""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from log_slices import robot_log_between

from csam_ros.core.exchange.checkpoint import (
    FilterState,
    MergerState,
    OfflineState,
    SmootherCheckpoint,
    ThinningState,
)
from csam_ros.core.exchange.local_map_checks import local_map_fault
from csam_ros.core.exchange.map_arrays import robot_map_arrays
from csam_ros.core.exchange.measurement_filter import MeasurementFilter
from csam_ros.core.exchange.state_files import CheckpointError, read_npz, write_npz
from csam_ros.core.joining.pipeline import robot_map_from_local_map
from csam_ros.core.joining.rendezvous_filters import RendezvousThinning
from csam_ros.core.model.log import MultiRobotLog
from csam_ros.core.smoothing.local_map import LocalMap
from csam_ros.datasets.scenario import load_scenario
from csam_ros.datasets.simulation import simulate

EXAMPLES = int(os.environ.get("CSAM_FUZZ_EXAMPLES", "40"))
ROBOTS = ["robot1", "robot2"]
MAX_SEC = 2**31 - 1  # a ROS time's sec is an int32


def _written() -> dict[str, bytes]:
    """The bytes of a small real file of each kind (map_joining, seed 3)."""
    run: MultiRobotLog = simulate(load_scenario("map_joining"), seed=3)
    logs = {n: robot_log_between(r, end=25.0) for n, r in run.robots.items()}
    local = LocalMap("robot1")
    local.add_log(logs["robot1"])
    local.update()
    checks = MeasurementFilter(ROBOTS)
    checks.odometry("robot1", 30.0, [0.1, 0.0, 0.0], [0.1, 0.1, 0.1])  # held back
    checks.features("robot1", -1.0, [1.0], [0.0], [-1.0], [0.1])  # counted
    thinning = RendezvousThinning(1.0, 4)
    for t in np.arange(0.0, 10.0, 0.5):
        thinning.offer("robot1", "robot2", t)
    own = logs["robot1"].rendezvous
    states = {
        "smoother": SmootherCheckpoint(
            "robot1",
            local.state(),
            FilterState.of(checks),
            FilterState.of(MeasurementFilter(ROBOTS)),
            ThinningState.of(thinning),
            own,
            np.unique(own.stamps),
            25 * 10**9,
            24 * 10**9,
            2,
            restarts=1,
            lost_seconds=1.5,
        ),
        "merger": MergerState(
            "robot1",
            ["robot1"],
            ROBOTS,
            {"robot1": robot_map_from_local_map(local)},
            {"robot1": 24 * 10**9},
            {"robot1": own},
            3,
            {"malformed_local_map": 1},
        ),
        "offline": OfflineState(logs, FilterState.of(checks)),
    }
    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        for kind, state in states.items():
            path = Path(tmp) / f"{kind}.npz"
            state.write(path)
            out[kind] = path.read_bytes()
    return out


WRITTEN = _written()
READERS = {
    "smoother": lambda path: SmootherCheckpoint.read(path, "robot1"),
    "merger": MergerState.read,
    "offline": OfflineState.read,
}


def _parts(kind: str) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "state.npz"
        path.write_bytes(WRITTEN[kind])
        return read_npz(path, kind)


def _header_paths(node: Any, at: tuple = ()) -> list[tuple]:
    """Every place in a header (keys and list indices), the format's own keys left out."""
    paths = [at] if at else []
    if isinstance(node, dict):
        for k, v in node.items():
            if at or k not in ("format", "version", "kind"):
                paths += _header_paths(v, (*at, k))
    elif isinstance(node, list):
        for i, v in enumerate(node[:4]):
            paths += _header_paths(v, (*at, i))
    return paths


PARTS = {kind: _parts(kind) for kind in WRITTEN}
HEADER_PATHS = {kind: _header_paths(header) for kind, (header, _) in PARTS.items()}
ARRAY_KEYS = {kind: sorted(arrays) for kind, (_, arrays) in PARTS.items()}

hostile_values = st.one_of(
    st.sampled_from([10**30, -(10**30), 2**63, 2**31 * 10**9, -1, 0, 1, -2, 10**6]),
    st.integers(),
    st.floats(),  # NaN and infinities included
    st.sampled_from([1e308, -1e308, float("nan"), float("inf"), -0.0]),
    st.booleans(),
    st.none(),
    st.text(max_size=6),
    st.lists(st.floats(), max_size=4),
    st.lists(st.lists(st.integers(-3, 3), max_size=3), max_size=3),
    st.dictionaries(st.text(max_size=4), st.integers(-2, 10**20), max_size=3),
)
ARRAY_DAMAGE = [
    "scalar",
    "reverse",
    "negate",
    "zero",
    "nan",
    "inf",
    "huge",
    "strings",
    "bools",
    "complex",
    "flatten",
    "extra_axis",
    "empty",
    "drop_row",
    "int_max",
    "swap_rows",
    "as_int",
]


def _damaged_array(value: np.ndarray, how: str, at: int) -> Any:
    v = np.array(value)
    flat = v.reshape(-1)
    i = at % flat.size if flat.size else 0
    if how in ("nan", "inf", "huge") and flat.size:
        flat = flat.astype(float)
        flat[i] = {"nan": np.nan, "inf": np.inf, "huge": 1e308}[how]
        return flat.reshape(v.shape)
    if how == "swap_rows" and len(v) > 1:
        j = (i + 1) % len(v)
        i = i % len(v)
        v[[i, j]] = v[[j, i]]
        return v
    return {
        "scalar": lambda: np.float64(at),
        "reverse": lambda: v[::-1].copy(),
        "negate": lambda: -v,
        "zero": lambda: np.zeros_like(v),
        "strings": lambda: v.astype(str),
        "bools": lambda: v.astype(bool),
        "complex": lambda: v.astype(complex),
        "flatten": lambda: v.reshape(-1),
        "extra_axis": lambda: v[None],
        "empty": lambda: v[:0],
        "drop_row": lambda: v[:-1],
        "int_max": lambda: np.full(v.shape, np.iinfo(np.int64).max),
        "as_int": lambda: v.astype(np.int64) if v.dtype.kind == "f" else v,
    }.get(how, lambda: v)()


def _set(node: Any, path: tuple, value: Any) -> None:
    for key in path[:-1]:
        node = node[key]
    node[path[-1]] = value


# --------------------------------------------------------------------------- what a taker does


def _usable_smoother(c: SmootherCheckpoint) -> None:
    """What a smoother does with a checkpoint it took up, and what must hold for it."""
    for ns in (c.last_odometry_ns, c.published_ns):
        assert ns >= -1 and max(ns, 0) // 10**9 <= MAX_SEC, ns  # a ROS time, or -1: none
    assert c.errors >= 0 and c.restarts >= 0 and 0 <= c.lost_seconds < np.inf
    s = c.local_map
    assert np.all(np.diff(s.odometry_stamps) > 0) and np.all(np.diff(s.keys) > 0)
    assert np.all(s.odometry_sigmas > 0) and np.isfinite(s.key_values).all()
    assert np.all(np.abs(s.odometry_stamps) <= MAX_SEC)
    try:
        local = LocalMap.from_state("robot1", s)  # the smoother's take-up
    except RuntimeError as err:  # features at no key pose within the node's stamp tolerance:
        assert "no key pose at stamp" in str(err)  # the smoother refuses it (read_checkpoint)
        return
    if s.solved and len(s.keys) >= 2:
        robot_map_from_local_map(local)  # its first publication
    checks, peers = MeasurementFilter(ROBOTS), MeasurementFilter(ROBOTS)
    c.filter.restore(checks)
    c.peer_filter.restore(peers)
    last = float(s.odometry_stamps[-1]) if len(s.odometry_stamps) else 0.0
    checks.odometry("robot1", last + 0.1, [0.1, 0.0, 0.0], [0.1, 0.1, 0.1])
    thinning = RendezvousThinning(1.0, 4)
    c.thinning.restore(thinning)
    thinning.offer("robot1", "robot2", last + 0.1)
    assert np.all(np.diff(c.rendezvous_stamps) > 0)
    rv = c.own_rendezvous
    assert np.all(rv.ranges > 0) and np.all(rv.sigma_range > 0) and np.all(rv.sigma_bearing > 0)


def _usable_merger(m: MergerState) -> None:
    for robot_map in m.maps.values():
        assert local_map_fault(robot_map_arrays(robot_map)) is None
    assert all(v >= 0 and v // 10**9 <= MAX_SEC for v in m.map_stamps.values())
    assert m.solves >= 0 and all(v >= 0 for v in m.dropped.values())
    for log in m.rendezvous.values():
        assert np.all(log.ranges > 0) and np.isfinite(log.bearings).all()


def _usable_offline(state: OfflineState) -> None:
    for name, log in state.logs.items():
        local = LocalMap(name)
        local.add_log(log)  # checks every sample, observation and requested stamp
        assert np.all(log.rendezvous.sigma_range > 0) and np.all(log.rendezvous.ranges > 0)
    state.filter.restore(MeasurementFilter(list(state.logs)))


USABLE = {"smoother": _usable_smoother, "merger": _usable_merger, "offline": _usable_offline}


def _check(kind: str, data: bytes) -> bool:
    """Read ``data`` as a file of ``kind``: True when it reads (and is usable), False for a
    CheckpointError naming the file in one line; anything else fails the test."""
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / f"damaged_{kind}.npz"
        path.write_bytes(data)
        try:
            state = READERS[kind](path)
        except CheckpointError as err:
            assert str(path) in str(err) and "\n" not in str(err), str(err)
            return False
    USABLE[kind](state)
    return True


kinds = st.sampled_from(sorted(WRITTEN))


@settings(max_examples=EXAMPLES, suppress_health_check=[HealthCheck.too_slow])
@given(
    kind=kinds,
    flips=st.lists(
        st.tuples(st.floats(0, 1, exclude_max=True), st.integers(1, 16), st.integers(1, 255)),
        max_size=3,
    ),
    cut=st.one_of(st.none(), st.floats(0, 1, exclude_max=True)),
)
def test_a_state_file_with_bytes_flipped_or_cut_reads_whole_or_raises_checkpoint_error(
    kind: str, flips: list[tuple[float, int, int]], cut: float | None
) -> None:
    data = bytearray(WRITTEN[kind])
    for where, length, pattern in flips:
        start = int(where * len(data))
        for k in range(start, min(start + length, len(data))):
            data[k] ^= pattern
    _check(kind, bytes(data if cut is None else data[: int(cut * len(data))]))


@settings(max_examples=EXAMPLES, suppress_health_check=[HealthCheck.too_slow])
@given(kind=kinds, pick=st.integers(0, 10**6), value=hostile_values)
def test_a_whole_state_file_with_a_hostile_header_value_is_refused_or_usable(
    kind: str, pick: int, value: Any
) -> None:
    header, arrays = PARTS[kind]
    header = json.loads(json.dumps(header))
    paths = HEADER_PATHS[kind]
    _set(header, paths[pick % len(paths)], value)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "whole.npz"
        write_npz(path, kind, header, arrays)
        _check(kind, path.read_bytes())


@settings(max_examples=EXAMPLES, suppress_health_check=[HealthCheck.too_slow])
@given(
    kind=kinds,
    pick=st.integers(0, 10**6),
    how=st.sampled_from(ARRAY_DAMAGE),
    at=st.integers(0, 10**6),
)
def test_a_whole_state_file_with_a_damaged_array_is_refused_or_usable(
    kind: str, pick: int, how: str, at: int
) -> None:
    header, arrays = PARTS[kind]
    keys = ARRAY_KEYS[kind]
    key = keys[pick % len(keys)]
    changed = {**arrays, key: _damaged_array(arrays[key], how, at)}
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "whole.npz"
        write_npz(path, kind, header, changed)
        _check(kind, path.read_bytes())


def test_the_undamaged_files_read_and_are_usable() -> None:
    assert all(_check(kind, data) for kind, data in WRITTEN.items())


def test_a_fixed_sample_of_damage_is_mostly_refused() -> None:
    """Every field of each kind damaged in a few fixed ways (numpy's generator, seeded):
    each case checked as above, and most are refused: a reader that took damaged fields as
    they were would fail here."""
    rng = np.random.default_rng(17)
    refused = total = 0
    for kind, (header, arrays) in PARTS.items():
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / "whole.npz"
            for key in ARRAY_KEYS[kind]:
                for how in ("reverse", "nan"):
                    changed = {
                        **arrays,
                        key: _damaged_array(arrays[key], how, int(rng.integers(99))),
                    }
                    if np.array_equal(changed[key], arrays[key], equal_nan=True):
                        continue  # an empty or symmetric array: nothing changed
                    write_npz(path, kind, header, changed)
                    refused += not _check(kind, path.read_bytes())
                    total += 1
    assert total > 80 and refused > 0.6 * total, (refused, total)
