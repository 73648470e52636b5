"""How long a live run's local maps take to reach the joined map, and the merger's solve times.

A local map update of robot ``r`` with header stamp ``s`` that arrives (is logged in the run's
bag) at time ``a`` is *included* by the first joined map logged at a time ``t >= a`` whose base node
for ``r`` has ``local_map_stamp >= s``; its lag is ``t - a``. A map superseded before any
joined map used it (the merger took a newer map of that robot first) therefore counts with the
lag until the first joined map that includes a newer map of that robot. A map that no later
joined map includes (e.g. the last one published after the merger's last solve) is *never
included*: counted apart, not in the mean, p95 or max. Times are the recorder's log times (its
wall clock at reception): a local map and a joined map that reach the recorder out of order
are measured from the next joined map, and a recorder that falls behind (many robots on few
cores) records both late, in bursts, which blurs the lags by its delay. The same lags to
the first joined map, solved or provisional (``/csam/joined_map/provisional``, the newest
local maps placed by the last join), say how soon a map shows in the joined frame at all.

:func:`lag_stats` computes this on plain arrays, :func:`lags_over_run` the same over equal spans
of the run (a join that grows with the data shows as lags that grow with it);
:func:`read_timeline` takes them from a recorded bag (``bag/`` of a ``csam demo`` or live
``csam replay`` output).
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
SOLVED = "the joined map"  # what lags are to by default: the solved joined maps
NOT_USED = -np.inf  # the used stamp of a robot that a joined map holds no local map of
_CHUNK = 1 << 22  # most (local map x joined map) comparisons held at once
RUN_PARTS = 10  # the equal spans a run's lags are shown over (Timeline.lags_over_run)


@dataclass(frozen=True)
class LagStats:
    """Lags [s] from a local map's arrival to the first joined map that includes it."""

    count: int  # local maps included by a joined map (the lags below are over these)
    mean: float  # NaN when count is 0
    p95: float  # numpy's linear interpolation
    max: float
    never_included: int  # local maps that no later joined map includes
    to: str = SOLVED  # the maps that include them (what the lags are to)

    @classmethod
    def of(cls, lags: ArrayLike, to: str = SOLVED) -> LagStats:
        """The statistics of per-map lags, NaN marking a map never included."""
        lags = np.asarray(lags, dtype=float).reshape(-1)
        done = lags[np.isfinite(lags)]
        if len(done) == 0:
            return cls(0, np.nan, np.nan, np.nan, len(lags), to)
        return cls(
            count=len(done),
            mean=float(done.mean()),
            p95=float(np.percentile(done, 95)),
            max=float(done.max()),
            never_included=len(lags) - len(done),
            to=to,
        )

    def __str__(self) -> str:
        never = f", {self.never_included} never included" if self.never_included else ""
        head = f"lag from a local map to {self.to} that uses it"
        if self.count == 0:
            return f"{head}: no local map included ({self.never_included} local maps)"
        return (
            f"{head}: mean {self.mean:.2f} s, p95 {self.p95:.2f} s, max {self.max:.2f} s "
            f"({self.count} local maps{never})"
        )


@dataclass(frozen=True)
class SolveStats:
    """The merger's solves and the solve times [s] its ``/csam/status`` reported."""

    solves: int  # the merger's count
    seen: int  # solves whose time a recorded status message carried (one per status at most)
    mean: float  # NaN when none was seen
    max: float

    @classmethod
    def of(cls, solves: int, seconds: ArrayLike) -> SolveStats:
        seconds = np.asarray(seconds, dtype=float).reshape(-1)
        if len(seconds) == 0:
            return cls(solves, 0, np.nan, np.nan)
        return cls(solves, len(seconds), float(seconds.mean()), float(seconds.max()))

    def __str__(self) -> str:
        if self.seen == 0:
            return f"merger: {self.solves} solves (no solve time in /csam/status)"
        return (
            f"merger: {self.solves} solves, solve time mean {self.mean:.3f} s, "
            f"max {self.max:.3f} s ({self.seen} of them in /csam/status)"
        )


def _vectors(*values: ArrayLike) -> list[FloatArray]:
    """Each of ``values`` as a flat float array."""
    return [np.asarray(v, dtype=float).reshape(-1) for v in values]


def map_lags(
    arrivals: ArrayLike,
    stamps: ArrayLike,
    joined_times: ArrayLike,
    used_stamps: ArrayLike,
) -> FloatArray:
    """Per local map of one robot (``arrivals``, ``stamps``) its lag [s] to the first joined
    map (``joined_times``, and the stamp of this robot's map each one used: ``used_stamps``,
    :data:`NOT_USED` for none) logged no earlier and using a stamp at least as new; NaN for a
    map never included."""
    a, s, t, u = _vectors(arrivals, stamps, joined_times, used_stamps)
    if a.shape != s.shape or t.shape != u.shape:
        raise ValueError("arrivals and stamps, joined times and used stamps: equal lengths")
    order = np.argsort(t, kind="stable")
    t, u = t[order], u[order]
    lags = np.full(len(a), np.nan)
    if len(t) == 0:
        return lags
    rows = max(1, _CHUNK // len(t))
    for k in range(0, len(a), rows):
        part = slice(k, k + rows)
        includes = (t[None, :] >= a[part, None]) & (u[None, :] >= s[part, None])
        first = includes.argmax(axis=1)
        found = includes[np.arange(len(first)), first]
        lags[part] = np.where(found, t[first] - a[part], np.nan)
    return lags


def robot_lags(
    map_arrivals: Mapping[str, ArrayLike],
    map_stamps: Mapping[str, ArrayLike],
    joined_times: ArrayLike,
    used_stamps: Mapping[str, ArrayLike],
) -> dict[str, FloatArray]:
    """:func:`map_lags` of every robot's local maps (robot -> arrival times and stamps [s]) to
    the joined maps (their times, and robot -> the stamp each used, :data:`NOT_USED` for none;
    a robot missing from ``used_stamps`` is in no joined map)."""
    n = len(np.asarray(joined_times).reshape(-1))
    return {
        robot: map_lags(
            map_arrivals[robot],
            map_stamps[robot],
            joined_times,
            used_stamps.get(robot, np.full(n, NOT_USED)),
        )
        for robot in map_arrivals
    }


def lag_stats(
    map_arrivals: Mapping[str, ArrayLike],
    map_stamps: Mapping[str, ArrayLike],
    joined_times: ArrayLike,
    used_stamps: Mapping[str, ArrayLike],
    to: str = SOLVED,
) -> LagStats:
    """The statistics of :func:`robot_lags` pooled over the robots; ``to`` names the joined
    maps."""
    lags = list(robot_lags(map_arrivals, map_stamps, joined_times, used_stamps).values())
    return LagStats.of(np.concatenate(lags) if lags else np.zeros(0), to)


@dataclass(frozen=True)
class RunPart:
    """The local maps that arrived in ``[start, end)`` s of a run with their lags, and the
    merger's solves reported in that span."""

    start: float
    end: float
    lags: LagStats
    solves: SolveStats

    def __str__(self) -> str:
        span = f"{self.start:7.0f} -{self.end:7.0f} s"
        solves = (
            f"{self.solves.seen:4d} solves of {self.solves.mean:5.2f} s"
            if self.solves.seen
            else f"{'no solve':>20}"
        )
        if self.lags.count == 0:
            return f"{span}  {solves}  {self.lags.never_included:5d} maps, none included"
        return (
            f"{span}  {solves}  {self.lags.count:5d} maps, lag mean {self.lags.mean:5.2f} s, "
            f"p95 {self.lags.p95:5.2f} s, max {self.lags.max:5.2f} s"
        )


def lags_over_run(
    arrivals: ArrayLike,
    lags: ArrayLike,
    parts: int,
    solve_times: ArrayLike = (),
    solve_seconds: ArrayLike = (),
) -> list[RunPart]:
    """The lags of local maps (their ``arrivals`` [s] and ``lags``, NaN: never included) and
    the solves (reported at ``solve_times`` [s], each ``solve_seconds`` long) in ``parts``
    equal spans from the first arrival to the last: whether maps wait longer as the run goes
    on (a join that grows with the data) or only at its start."""
    a, x, t, d = _vectors(arrivals, lags, solve_times, solve_seconds)
    if a.shape != x.shape or t.shape != d.shape:
        raise ValueError("arrivals and lags, solve times and seconds: equal lengths")
    if parts < 1:
        raise ValueError(f"parts must be at least 1, not {parts}")
    if len(a) == 0:
        return []
    edges = np.linspace(a.min(), a.max(), parts + 1)

    def part_of(times: FloatArray) -> IntArray:
        return np.minimum(np.searchsorted(edges, times, side="right") - 1, parts - 1)

    maps, solves = part_of(a), part_of(t)
    return [
        RunPart(
            float(edges[k]),
            float(edges[k + 1]),
            LagStats.of(x[maps == k]),
            SolveStats.of(int(np.sum(solves == k)), d[solves == k]),
        )
        for k in range(parts)
    ]


@dataclass(frozen=True)
class Timeline:
    """What a run's bag says about its local maps, joined maps and solves (times [s] since
    the first message read)."""

    map_arrivals: dict[str, FloatArray]
    map_stamps: dict[str, FloatArray]
    joined_times: FloatArray
    used_stamps: dict[str, FloatArray]
    solves: int
    solve_seconds: FloatArray
    solve_times: FloatArray  # when the status that reported each of solve_seconds was logged
    provisional_times: FloatArray  # /csam/joined_map/provisional, as the joined maps above
    provisional_used: dict[str, FloatArray]

    def lag_stats(self) -> LagStats:
        """The lags to the solved joined maps."""
        return lag_stats(self.map_arrivals, self.map_stamps, self.joined_times, self.used_stamps)

    def robot_lags(self) -> dict[str, FloatArray]:
        """Each robot's local maps' lags to the solved joined maps (NaN: never included)."""
        return robot_lags(self.map_arrivals, self.map_stamps, self.joined_times, self.used_stamps)

    def map_lags(self) -> tuple[FloatArray, FloatArray]:
        """Every robot's local maps pooled: their arrival times and their lags to the solved
        joined maps (NaN: never included), in arrival order."""
        lags = self.robot_lags()
        if not lags:
            return np.zeros(0), np.zeros(0)
        a = np.concatenate([np.asarray(self.map_arrivals[r], dtype=float) for r in lags])
        x = np.concatenate(list(lags.values()))
        order = np.argsort(a, kind="stable")
        return a[order], x[order]

    def lags_over_run(self, parts: int = RUN_PARTS) -> list[RunPart]:
        """:func:`lags_over_run` of the lags to the solved joined maps, and of the solves."""
        return lags_over_run(*self.map_lags(), parts, self.solve_times, self.solve_seconds)

    def provisional_lag_stats(self) -> LagStats | None:
        """The lags to the first joined map, solved or provisional, that uses a local map;
        None when the run published no provisional map."""
        if len(self.provisional_times) == 0:
            return None
        return lag_stats(
            self.map_arrivals,
            self.map_stamps,
            np.concatenate([self.joined_times, self.provisional_times]),
            {r: np.concatenate([u, self.provisional_used[r]]) for r, u in self.used_stamps.items()},
            to="the first joined or provisional map",
        )

    def solve_stats(self, solves: int | None = None) -> SolveStats:
        """The solve times in the bag; ``solves`` is the merger's own count where known
        (summary.json): the last statuses of a run may not be in the bag."""
        return SolveStats.of(self.solves if solves is None else solves, self.solve_seconds)


def read_timeline(bag: str | os.PathLike[str], on_damage=None) -> Timeline:
    """The local maps, joined maps and merger status of a recorded run (``on_damage`` as in
    :func:`~csam_ros.bag.read_bag`)."""
    from csam_ros.bag import inspect_bag, read_bag_messages
    from csam_ros.ros.conversions import time_to_ns
    from csam_ros.ros.topics import JOINED_MAP, LOCAL_MAP_UPDATES, PROVISIONAL_MAP, STATUS, parse

    declared = [parse(name) for name in inspect_bag(bag).topics]
    robots = sorted(d[1] for d in declared if d is not None and d[0] is LOCAL_MAP_UPDATES)
    joined_kinds = (JOINED_MAP.name, PROVISIONAL_MAP.name)
    topics = [LOCAL_MAP_UPDATES.of(r) for r in robots] + [*joined_kinds, STATUS.name]
    arrivals: dict[str, list[int]] = {r: [] for r in robots}
    stamps: dict[str, list[int]] = {r: [] for r in robots}
    # per kind of joined map: the log times and the local map stamps each used
    joined: dict[str, list[int]] = {k: [] for k in joined_kinds}
    used: dict[str, list[dict[str, int]]] = {k: [] for k in joined_kinds}
    solves, solve_seconds, solve_times = 0, [], []
    start: int | None = None
    for m in read_bag_messages(bag, topics, on_damage=on_damage):
        start = m.log_time_ns if start is None else start
        if m.topic in joined_kinds:
            joined[m.topic].append(m.log_time_ns)
            used[m.topic].append(
                {
                    b.robot: time_to_ns(b.local_map_stamp)
                    for b in m.message.base_nodes
                    if not b.alignment.startswith("pending: no local map")
                }
            )
        elif m.topic == STATUS.name:
            for status in m.message.status:
                if status.name != "merger":
                    continue
                values = {kv.key: kv.value for kv in status.values}
                try:
                    count = int(values.get("solves", solves))
                    seconds_ = float(values.get("solve_seconds", "nan"))
                except ValueError:
                    continue
                if count > solves and np.isfinite(seconds_):
                    solve_seconds.append(seconds_)
                    solve_times.append(m.log_time_ns)
                solves = max(solves, count)
        else:
            robot = parse(m.topic)[1]
            arrivals[robot].append(m.log_time_ns)
            stamps[robot].append(time_to_ns(m.message.header.stamp))
    start = start or 0

    def seconds(ns: list[int], origin: int = 0) -> FloatArray:
        return (np.asarray(ns, dtype=np.int64).reshape(-1) - origin) / 1e9

    def used_by(robot: str, kind: str) -> FloatArray:
        held = np.array([robot in u for u in used[kind]], dtype=bool)
        return np.where(held, seconds([u.get(robot, 0) for u in used[kind]]), NOT_USED)

    return Timeline(
        map_arrivals={r: seconds(arrivals[r], start) for r in robots},
        map_stamps={r: seconds(stamps[r]) for r in robots},
        joined_times=seconds(joined[JOINED_MAP.name], start),
        used_stamps={r: used_by(r, JOINED_MAP.name) for r in robots},
        solves=solves,
        solve_seconds=np.asarray(solve_seconds, dtype=float),
        solve_times=seconds(solve_times, start),
        provisional_times=seconds(joined[PROVISIONAL_MAP.name], start),
        provisional_used={r: used_by(r, PROVISIONAL_MAP.name) for r in robots},
    )
