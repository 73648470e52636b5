"""Checkpoints and saved states: a smoother's accepted data, the merger's inputs, an offline run.

Inside the package each is a dataclass: :class:`SmootherCheckpoint` (what a smoother accepted
and its solved local map, so that a restarted smoother publishes the same map), :class:`MergerState`
(the merger's inputs, reference and counts, and its last result) and :class:`OfflineState`
(the measurement logs an offline replay accepted, with its filter's state, so that a replay
continued from it equals one over all the data).

On disk each is one ``.npz`` file (numpy arrays, never pickles) whose ``header`` entry is a JSON
document with ``format``, ``version`` and ``kind`` and the scalar parts. Files are written
atomically (:func:`write_npz`: a temporary file beside it, fsync, ``os.replace``, fsync of the
folder), so a process killed while writing leaves the previous file whole. A file that is not
one of these, of another kind or version, or damaged, raises :class:`CheckpointError` naming
the file and the fault.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import MISSING, dataclass, field, fields, replace
from pathlib import Path
from typing import Any, get_type_hints

import numpy as np
from numpy.typing import NDArray

from csam_ros.core.exchange.local_map_checks import LocalMapArrays
from csam_ros.core.exchange.map_arrays import robot_map_arrays, robot_map_from_arrays
from csam_ros.core.exchange.measurement_filter import MeasurementFilter
from csam_ros.core.exchange.state_checks import (
    MAX_COUNT,
    MAX_STAMP_NS,
    MAX_STAMP_S,
    StateFieldError,
    check_correlations,
    check_counts,
    check_integer,
    check_local_map_state,
    check_number,
    check_odometry_log,
    check_point_log,
    check_range_bearing_log,
    check_stamps,
    check_values,
)
from csam_ros.core.exchange.state_files import (
    STAMP_RANGE,
    StateReader,
    read_npz,
    stamp_from_json,
    stamp_to_json,
    write_npz,
)
from csam_ros.core.joining.rendezvous_filters import RendezvousThinning
from csam_ros.core.joining.result import CsamResult
from csam_ros.core.model.log import RendezvousLog, RobotLog
from csam_ros.core.smoothing.local_map_state import LocalMapState
from csam_ros.core.smoothing.robot_map import RobotMap

SMOOTHER = "smoother"
MERGER = "merger"
OFFLINE = "offline"
# a smoother's drop reason: odometry samples that came while it was down (after a restart
# from a checkpoint, estimated from the step of its odometry stamps)
LOST_WHILE_DOWN = "lost_while_down"
# a node's drop reason: a checkpoint or state file it was given (at start or by ~/load_state)
# that cannot be used; the node keeps the state it had
UNUSABLE_STATE = "unusable_state"

Array = NDArray[np.float64]


# --------------------------------------------------------------------------- pieces


@dataclass
class FilterState:
    """A :class:`~csam_ros.core.exchange.measurement_filter.MeasurementFilter`'s stream
    stamps (and any odometry sample it holds back) and its drop counts."""

    streams: dict[tuple[str, str], tuple[float, tuple[float, Array, Array] | None]]
    drops: dict[str, dict[str, int]]

    @classmethod
    def of(cls, checks: MeasurementFilter) -> FilterState:
        return cls(checks.stream_state(), {r: c.as_dict() for r, c in checks.drops.items()})

    def restore(self, checks: MeasurementFilter) -> None:
        """Put this state into ``checks`` (a new filter with the same robots and bounds)."""
        checks.restore_streams(self.streams)
        for robot, counts in self.drops.items():  # into its own counters: callers hold them
            counter = checks.counter(robot)
            counter.counts.clear()
            for reason, n in counts.items():
                counter.add(reason, n)

    def to_header(self) -> dict[str, Any]:
        return {
            "streams": [
                [robot, stream, stamp_to_json(last)]
                + ([] if held is None else [held[0], *(a.tolist() for a in held[1:])])
                for (robot, stream), (last, held) in self.streams.items()
            ],
            "drops": self.drops,
        }

    @classmethod
    def from_header(cls, node: Any, r: StateReader, where: str = "filter") -> FilterState:
        """The state of a header's ``node``, every stamp, sample and count checked."""
        try:
            streams = {}
            for row in node["streams"]:
                if not isinstance(row, list) or len(row) not in (3, 7):
                    raise StateFieldError(f"{where}: a stream entry is not 3 or 7 items")
                robot, stream = row[0], row[1]
                if not isinstance(robot, str) or not isinstance(stream, str):
                    raise StateFieldError(f"{where}: a stream entry without robot and stream names")
                name = f"{where}/{robot}/{stream}"
                last = -np.inf if row[2] is None else check_number(name, row[2], *STAMP_RANGE)
                held = None
                if len(row) == 7:  # stamp, input, sigmas, correlations
                    pose = stream.endswith(("/pose", "/held_pose"))  # a pose, no sigmas
                    held = (
                        -np.inf
                        if pose and row[3] == -np.inf
                        else check_number(f"{name}/held", row[3], *STAMP_RANGE),
                        *(np.array(v, float) for v in row[4:]),
                    )
                    if any(a.shape != (3,) for a in held[1:]):
                        raise StateFieldError(f"{name}: a held sample is not 3 + 3 + 3 numbers")
                    check_values(f"{name}/held", np.concatenate(held[1:])[None])
                    if not pose:
                        check_values(f"{name}/held sigmas", held[2][None], positive=True)
                        check_correlations(f"{name}/held correlations", held[3][None])
                streams[(robot, stream)] = (last, held)
            drops = {
                str(robot): check_counts(f"{where}/drops/{robot}", counts)
                for robot, counts in node["drops"].items()
            }
        except StateFieldError as err:
            raise r.fail(str(err)) from None
        except (KeyError, TypeError, ValueError, AttributeError) as err:
            raise r.fail(f"{where}: {err}") from None
        return cls(streams, drops)


@dataclass
class ThinningState:
    """A :class:`~csam_ros.core.joining.rendezvous_filters.RendezvousThinning`'s kept stamps and
    intervals."""

    kept: dict[tuple[str, str], list[float]]
    interval: dict[tuple[str, str], float]

    @classmethod
    def of(cls, thinning: RendezvousThinning) -> ThinningState:
        return cls(*thinning.state())

    def restore(self, thinning: RendezvousThinning) -> None:
        thinning.restore(self.kept, self.interval)

    def to_header(self) -> dict[str, Any]:
        return {
            "kept": [[a, b, stamps] for (a, b), stamps in self.kept.items()],
            "interval": [[a, b, v] for (a, b), v in self.interval.items()],
        }

    @classmethod
    def from_header(cls, node: Any, r: StateReader) -> ThinningState:
        """The state of a header's ``node``: each pair's kept stamps sorted, its interval a
        non-negative number."""
        try:
            kept = {(str(a), str(b)): [float(t) for t in s] for a, b, s in node["kept"]}
            interval = {
                (str(a), str(b)): check_number(f"thinning/interval/{a}/{b}", v, 0.0, MAX_STAMP_S)
                for a, b, v in node["interval"]
            }
            for (a, b), stamps in kept.items():
                check_stamps(f"thinning/kept/{a}/{b}", np.array(stamps), "sorted")
        except StateFieldError as err:
            raise r.fail(str(err)) from None
        except (KeyError, TypeError, ValueError) as err:
            raise r.fail(f"thinning state: {err}") from None
        return cls(kept, interval)


def _rendezvous_arrays(prefix: str, log: RendezvousLog) -> dict[str, np.ndarray]:
    return {
        f"{prefix}/stamps": log.stamps,
        f"{prefix}/ranges": log.ranges,
        f"{prefix}/bearings": log.bearings,
        f"{prefix}/sigma_range": log.sigma_range,
        f"{prefix}/sigma_bearing": log.sigma_bearing,
    }


def _rendezvous_log(prefix: str, observed: Any, r: StateReader) -> RendezvousLog:
    stamps = r.array(f"{prefix}/stamps")
    if not isinstance(observed, list) or len(observed) != len(stamps):
        raise r.fail(f"{prefix}: {len(stamps)} stamps without as many observed robot names")
    parts = [
        r.array(f"{prefix}/{k}") for k in ("ranges", "bearings", "sigma_range", "sigma_bearing")
    ]
    if stamps.ndim != 1 or any(p.shape != stamps.shape for p in parts):
        raise r.fail(f"{prefix}: arrays of different lengths")
    log = RendezvousLog(stamps, [str(o) for o in observed], *parts)
    r.checked(check_range_bearing_log, prefix, log)
    return log


# --------------------------------------------------------------------------- the smoother


@dataclass
class SmootherCheckpoint:
    """What a smoother accepted and its solved local map (see the module docstring)."""

    robot: str
    local_map: LocalMapState
    filter: FilterState  # the smoother's own checks (drops per robot)
    peer_filter: FilterState  # the checks repeated on its peers' rendezvous streams
    thinning: ThinningState
    own_rendezvous: RendezvousLog  # its kept measurements of other robots
    rendezvous_stamps: Array  # every stamp a pose was requested at
    last_odometry_ns: int
    published_ns: int
    errors: int
    restarts: int = 0  # restarts from a checkpoint so far
    lost_seconds: float = 0.0  # odometry time lost while the smoother was down

    def write(self, path: Path) -> int:
        """Write atomically; the bytes written."""
        arrays = {f"map/{f.name}": getattr(self.local_map, f.name) for f in _ARRAY_FIELDS}
        arrays.update(_rendezvous_arrays("own_rendezvous", self.own_rendezvous))
        arrays["rendezvous_stamps"] = self.rendezvous_stamps
        header = {
            "robot": self.robot,
            "map": {f.name: getattr(self.local_map, f.name) for f in _SCALAR_FIELDS},
            "filter": self.filter.to_header(),
            "peer_filter": self.peer_filter.to_header(),
            "thinning": self.thinning.to_header(),
            "own_rendezvous_observed": list(self.own_rendezvous.observed),
            "last_odometry_ns": self.last_odometry_ns,
            "published_ns": self.published_ns,
            "errors": self.errors,
            "restarts": self.restarts,
            "lost_seconds": self.lost_seconds,
        }
        header["map"]["last_solved_odometry"] = stamp_to_json(self.local_map.last_solved_odometry)
        return write_npz(path, SMOOTHER, header, arrays)

    @classmethod
    def read(cls, path: Path, robot: str | None = None) -> SmootherCheckpoint:
        """Read a smoother checkpoint (of ``robot`` when given: another robot's is an error),
        every field checked (:mod:`~csam_ros.core.exchange.state_checks`)."""
        r = StateReader(path, *read_npz(path, SMOOTHER))
        name = r.value("robot", str)
        if robot is not None and name != robot:
            raise r.fail(f"the checkpoint of {name!r:.80}, not of {robot!r}")
        scalars = r.value("map", dict)
        try:
            local_map = LocalMapState(
                **{
                    f.name: r.array(f"map/{f.name}", _DTYPES.get(f.name, float))
                    for f in _ARRAY_FIELDS
                    # a field added since (it has a default) may be absent from older files
                    if f"map/{f.name}" in r.arrays or f.default_factory is MISSING
                },
                integrated_features=check_integer(
                    "map/integrated_features", scalars["integrated_features"], 0, MAX_COUNT
                ),
                dropped_features=check_integer(
                    "map/dropped_features", scalars["dropped_features"], 0, MAX_COUNT
                ),
                last_solved_odometry=stamp_from_json(scalars["last_solved_odometry"]),
                solved=scalars["solved"],
            )
            if not isinstance(local_map.solved, bool):
                raise StateFieldError(f"map/solved: {local_map.solved!r:.40} is not true or false")
        except StateFieldError as err:
            raise r.fail(str(err)) from None
        except (KeyError, TypeError, ValueError) as err:
            raise r.fail(f"local map: {err}") from None
        r.checked(check_local_map_state, "map", local_map)
        rendezvous_stamps = r.array("rendezvous_stamps")
        r.checked(check_stamps, "rendezvous_stamps", rendezvous_stamps, "increasing")
        return cls(
            robot=name,
            local_map=local_map,
            filter=FilterState.from_header(r.value("filter", dict), r),
            peer_filter=FilterState.from_header(r.value("peer_filter", dict), r, "peer_filter"),
            thinning=ThinningState.from_header(r.value("thinning", dict), r),
            own_rendezvous=_rendezvous_log(
                "own_rendezvous", r.value("own_rendezvous_observed", list), r
            ),
            rendezvous_stamps=rendezvous_stamps,
            last_odometry_ns=r.integer("last_odometry_ns", -1, MAX_STAMP_NS),
            published_ns=r.integer("published_ns", -1, MAX_STAMP_NS),
            errors=r.integer("errors", 0, MAX_COUNT),
            restarts=r.integer("restarts", 0, MAX_COUNT),
            lost_seconds=r.checked(
                check_number, "lost_seconds", r.value("lost_seconds", (int, float)), 0.0, 1e12
            ),
        )


_SCALARS = ("integrated_features", "dropped_features", "last_solved_odometry", "solved")
_ARRAY_FIELDS = [f for f in fields(LocalMapState) if f.name not in _SCALARS]
_SCALAR_FIELDS = [f for f in fields(LocalMapState) if f.name in _SCALARS]
_DTYPES = {"feature_labels": np.int64, "landmark_labels": np.int64}


def odometry_period(stamps: Array, last: int = 50) -> float | None:
    """The usual step of the latest odometry stamps (their median), None with fewer than two."""
    steps = np.diff(np.asarray(stamps, dtype=float)[-(last + 1) :])
    steps = steps[steps > 0]
    return float(np.median(steps)) if len(steps) else None


def missed_samples(gap: float, period: float | None) -> int:
    """How many samples a stream of ``period`` missed in a step of ``gap`` seconds."""
    if period is None or not period > 0 or not gap > 0:
        return 0
    return max(int(round(gap / period)) - 1, 0)


# --------------------------------------------------------------------------- the merger


_MAP_ARRAYS = [
    f.name
    for f in fields(LocalMapArrays)
    if f.name not in ("robust_kernel", "robust_parameter", "cost", "odometry_calibration")
]
_MAP_INTS = ("feature_labels", "odometry_ends", "observation_pose", "observation_label")
# each array's shape after its rows (None: any 1-D array), and the arrays of one length
_MAP_TAILS: dict[str, tuple[int, ...] | None] = {
    "stamps": (),
    "poses": (3,),
    "pose_covariances": (),
    "feature_labels": (),
    "feature_xy": (2,),
    "feature_cov": (3,),
    "prior_sqrt_information": (),
    "odometry_ends": (2,),
    "odometry_delta": (3,),
    "odometry_sqrt_information": (9,),
    "observation_pose": (),
    "observation_label": (),
    "observation_xy": (2,),
    "observation_sqrt_information": (4,),
}
_MAP_LENGTHS = (
    ("stamps", "poses"),
    ("feature_labels", "feature_xy", "feature_cov"),
    ("odometry_ends", "odometry_delta", "odometry_sqrt_information"),
    ("observation_pose", "observation_label", "observation_xy", "observation_sqrt_information"),
)


@dataclass
class MergerState:
    """What the merger holds between solves (see the module docstring)."""

    reference: str
    heard: list[str]  # robots in the order their first local map arrived
    robots: list[str]  # robots subscribed to, in the order found
    maps: dict[str, RobotMap]
    map_stamps: dict[str, int]  # each local map message's stamp, ns
    rendezvous: dict[str, RendezvousLog]
    solves: int
    dropped: dict[str, int]
    restarts: dict[str, int] = field(default_factory=dict)
    restart_poses_lost: dict[str, int] = field(default_factory=dict)
    result: CsamResult | None = None

    def write(self, path: Path) -> int:
        """Write atomically; the bytes written."""
        arrays: dict[str, Any] = {}
        kernels = {}
        for robot, m in self.maps.items():
            a = robot_map_arrays(m)
            arrays.update({f"maps/{robot}/{k}": getattr(a, k) for k in _MAP_ARRAYS})
            kernels[robot] = [a.robust_kernel, a.robust_parameter]
        for robot, log in self.rendezvous.items():
            arrays.update(_rendezvous_arrays(f"rendezvous/{robot}", log))
        header = {
            "reference": self.reference,
            "heard": self.heard,
            "robots": self.robots,
            "maps": kernels,
            "map_stamps": self.map_stamps,
            "rendezvous_observed": {r: list(log.observed) for r, log in self.rendezvous.items()},
            "solves": self.solves,
            "dropped": self.dropped,
            "restarts": self.restarts,
            "restart_poses_lost": self.restart_poses_lost,
            "result": _put_result(self.result, arrays),
        }
        return write_npz(path, MERGER, header, arrays)

    @classmethod
    def read(cls, path: Path) -> MergerState:
        r = StateReader(path, *read_npz(path, MERGER))
        maps = {}
        for robot, (kernel, parameter) in _pairs(r.value("maps", dict), r, "maps"):
            values = {
                k: r.array(f"maps/{robot}/{k}", np.int64 if k in _MAP_INTS else float, tail)
                for k, tail in _MAP_TAILS.items()
            }
            for group in _MAP_LENGTHS:
                if len({len(values[k]) for k in group}) > 1:
                    raise r.fail(f"maps/{robot}: {', '.join(group)} of different lengths")
            if values["prior_sqrt_information"].shape != (9,):
                raise r.fail(f"maps/{robot}: prior_sqrt_information is not 9 numbers")
            if not isinstance(kernel, str) or not isinstance(parameter, int | float):
                raise r.fail(f"maps/{robot}: bad robust kernel entry")
            try:
                maps[robot] = robot_map_from_arrays(
                    robot,
                    LocalMapArrays(
                        **values, robust_kernel=kernel, robust_parameter=float(parameter), cost=0.0
                    ),
                )
            except ValueError as err:
                raise r.fail(f"local map {err}") from None
        observed = r.value("rendezvous_observed", dict)
        rendezvous = {
            robot: _rendezvous_log(f"rendezvous/{robot}", names, r)
            for robot, names in observed.items()
        }
        stamps = r.value("map_stamps", dict)
        if set(stamps) != set(maps):
            raise r.fail("map_stamps: not one integer stamp per local map")
        for robot, stamp in stamps.items():
            r.checked(check_integer, f"map_stamps/{robot}", stamp, 0, MAX_STAMP_NS)
        result = r.value("result", (dict, type(None)))
        parsed = None if result is None else _result(result, r)
        reference = r.value("reference", str)
        heard = [str(h) for h in r.value("heard", list)]
        if reference and reference not in heard or not set(heard) <= set(maps):
            raise r.fail(f"reference {reference!r} or robots heard {heard} without a local map")
        return cls(
            reference=reference,
            heard=heard,
            robots=[str(x) for x in r.value("robots", list)],
            maps=maps,
            map_stamps=dict(stamps),
            rendezvous=rendezvous,
            solves=r.integer("solves", 0, MAX_COUNT),
            dropped=r.checked(check_counts, "dropped", r.value("dropped", dict)),
            restarts=r.checked(check_counts, "restarts", r.value("restarts", dict)),
            restart_poses_lost=r.checked(
                check_counts, "restart_poses_lost", r.value("restart_poses_lost", dict)
            ),
            result=parsed,
        )


# a result's per-pose series, as arrays "result/<robot>/<series>" (version 2; the rest of the
# result is in the header as summary.json holds it): as JSON lists they took 0.27 s of a 0.39 s
# write of the merger's state at the end of live MR.CLAM, written after every solve
_RESULT_SERIES: dict[str, tuple[int, ...]] = {
    "stamps": (),
    "poses_local": (3,),
    "sigma_phi_local": (),
    "poses_joined": (3,),  # this and the other joined series: None while pending
    "sigma_phi_joined": (),
    "sigma_phi_joined_reference": (),
}
_JOINED_SERIES = ("poses_joined", "sigma_phi_joined", "sigma_phi_joined_reference")
# what a robot's entry in the header holds instead of its series
_NO_SERIES = {
    key: None if key in _JOINED_SERIES else np.zeros((0, *tail))
    for key, tail in _RESULT_SERIES.items()
}


def _put_result(result: CsamResult | None, arrays: dict[str, Any]) -> dict[str, Any] | None:
    """``result``'s header entry, without the per-pose series: those go into ``arrays``."""
    if result is None:
        return None
    for name, robot in result.robots.items():
        for key in _RESULT_SERIES:
            value = getattr(robot, key)
            if value is not None:
                arrays[f"result/{name}/{key}"] = np.asarray(value, dtype=float)
    robots = {name: replace(robot, **_NO_SERIES) for name, robot in result.robots.items()}
    return replace(result, robots=robots).to_dict()


def _with_series(result: CsamResult, r: StateReader) -> CsamResult:
    """``result`` (read from the header) with each robot's per-pose series from the arrays
    (a version-1 file has them in the header, and no such arrays)."""
    for name, robot in result.robots.items():
        prefix = f"result/{name}/"
        if prefix + "stamps" not in r.arrays:
            continue
        series = {
            key: r.array(prefix + key, float, tail, finite=False)
            if prefix + key in r.arrays
            else None
            for key, tail in _RESULT_SERIES.items()
        }
        n = len(series["stamps"])
        for key, value in series.items():
            if value is None and key not in _JOINED_SERIES:
                raise r.fail(f"result: robot {name!r:.80} has no {key}")
            if value is not None and len(value) != n:
                raise r.fail(f"result: robot {name!r:.80}: {len(value)} {key} for {n} stamps")
        result.robots[name] = replace(robot, **series)
    return result


def _result(node: dict[str, Any], r: StateReader) -> CsamResult:
    """The result of a file: its header entry, with its per-pose series from the arrays."""
    try:
        result = CsamResult.from_dict(node)
    except (ValueError, TypeError, KeyError, AttributeError, RecursionError) as err:
        raise r.fail(f"result: {err}") from None
    return _with_series(result, r)


def _pairs(node: Mapping[str, Any], r: StateReader, where: str) -> list[tuple[str, Any]]:
    out = []
    for k, v in node.items():
        if not isinstance(v, list) or len(v) != 2:
            raise r.fail(f"{where}/{k}: expected a pair")
        out.append((k, v))
    return out


# --------------------------------------------------------------------------- offline replay


def _log_parts() -> dict[str, type]:
    """The parts of a :class:`~csam_ros.core.model.log.RobotLog` (odometry, features, ...) and
    their dataclasses."""
    hints = get_type_hints(RobotLog)
    return {f.name: hints[f.name] for f in fields(RobotLog) if f.name != "name"}


@dataclass
class OfflineState:
    """What an offline replay accepted: each robot's measurement log (in the order of the
    robots), the measurement filter's state, and the result on them."""

    logs: dict[str, RobotLog]
    filter: FilterState
    result: CsamResult | None = None

    def write(self, path: Path) -> int:
        """Write atomically (every field of every part of each log, by name); the bytes."""
        arrays: dict[str, Any] = {}
        lists: dict[str, list[str]] = {}
        for name, log in self.logs.items():
            for part in _log_parts():
                data = getattr(log, part)
                for f in fields(data):
                    value, key = getattr(data, f.name), f"logs/{name}/{part}/{f.name}"
                    if isinstance(value, list):
                        lists[key] = [str(v) for v in value]
                    elif value is not None:
                        arrays[key] = np.asarray(value)
        header = {
            "robots": list(self.logs),
            "lists": lists,
            "filter": self.filter.to_header(),
            "result": _put_result(self.result, arrays),
        }
        return write_npz(path, OFFLINE, header, arrays)

    @classmethod
    def read(cls, path: Path) -> OfflineState:
        """Read an offline replay's state, every field of every log checked."""
        r = StateReader(path, *read_npz(path, OFFLINE))
        lists = r.value("lists", dict)
        logs = {}
        for name in r.value("robots", list):
            if not isinstance(name, str) or name in logs:
                raise r.fail(f"robots: {name!r:.40} is not the name of one more robot")
            parts: dict[str, Any] = {}
            for part, kind in _log_parts().items():
                values: dict[str, Any] = {}
                for f in fields(kind):
                    key = f"logs/{name}/{part}/{f.name}"
                    if key in lists:
                        if not isinstance(lists[key], list):
                            raise r.fail(f"lists/{key}: not a list")
                        values[f.name] = [str(v) for v in lists[key]]
                    elif key in r.arrays:
                        dtype = np.int64 if f.name == "labels" else float
                        values[f.name] = r.array(key, dtype, _LOG_TAILS.get(f.name, ()))
                    elif f.default is MISSING and f.default_factory is MISSING:
                        raise r.fail(f"no array {key!r}")
                lengths = {len(v) for v in values.values()}
                if len(lengths) > 1:
                    raise r.fail(f"logs/{name}/{part}: fields of different lengths")
                parts[part] = kind(**values)
                r.checked(_LOG_CHECKS[part], f"logs/{name}/{part}", parts[part])
            logs[name] = RobotLog(name, **parts)
        result = r.value("result", (dict, type(None)))
        parsed = None if result is None else _result(result, r)
        return cls(logs, FilterState.from_header(r.value("filter", dict), r), parsed)


# the shape after its rows of each array field of a log part (others: one number a row)
_LOG_TAILS = {"inputs": (3,), "sigmas": (3,), "correlations": (3,), "points": (2,)}
_LOG_TAILS["covariances"] = (2, 2)
_LOG_CHECKS: dict[str, Callable[[str, Any], None]] = {
    "odometry": check_odometry_log,
    "features": check_range_bearing_log,
    "rendezvous": check_range_bearing_log,
    "points": check_point_log,
}


def joined_logs(first: Mapping[str, RobotLog], then: Mapping[str, RobotLog]) -> dict[str, RobotLog]:
    """Each robot's log of ``first`` followed by its log of ``then`` (robots of ``first``
    first, in order, then new ones). ValueError when a field is given in one and not the
    other (e.g. odometry correlations)."""
    out = dict(first)
    for name, log in then.items():
        if name not in out:
            out[name] = log
            continue
        parts = {}
        for part in _log_parts():
            a, b = getattr(out[name], part), getattr(log, part)
            values = {}
            for f in fields(a):
                x, y = getattr(a, f.name), getattr(b, f.name)
                if x is None and y is None:
                    values[f.name] = None
                elif x is None or y is None:
                    raise ValueError(f"{name}: {part}.{f.name} is given in one log only")
                elif isinstance(x, list):
                    values[f.name] = [*x, *y]
                else:
                    values[f.name] = np.concatenate([x, y])
            parts[part] = type(a)(**values)
        out[name] = RobotLog(name, **parts)
    return out
