"""The typed result of C-SAM and of a whole run, and their ``summary.json`` form.

:class:`CsamResult` is what :func:`csam_ros.core.joining.join.join_maps` returns;
:class:`RunSummary` adds where the run came from (scenario, bag, dropped messages, the merger's
counts). Inside the package only these types travel; ``to_dict`` / ``from_dict`` are the only
places that know the keys of ``summary.json``, and ``from_dict`` is the exact inverse of
``to_dict`` (JSON keeps every float exactly). A malformed summary raises :class:`SummaryError`
naming the key.

Two encodings are not one-to-one by themselves: a robot's feature label ``k`` is written as
``"<robot>/<k>"``, and the joined fields of a robot without a joined map (``None``) are
written as ``[]`` (a joined robot always has at least one pose). A note
(:class:`~csam_ros.core.joining.notes.Note`) is written as its text alone; reading it, its kind
comes back from the text (:meth:`~csam_ros.core.joining.notes.Note.of_text`).

Heading standard deviations of a :class:`RobotResult`: ``sigma_phi_local`` is the local map's
marginal heading sigma in ``G_r``; ``sigma_phi_joined`` is the heading sigma after joining
*relative to the robot's own first pose* (in ``G_r``, the like-for-like comparison of the
paper's figures 5c and 6c: it can only shrink); ``sigma_phi_joined_reference`` is the heading
sigma in the reference frame (which adds the base node's uncertainty). A pending robot keeps its
local estimate (``poses_local``, ``sigma_phi_local``); its base node and joined fields are
``None`` (``null`` / ``[]`` in the summary) and its features are not in
:attr:`CsamResult.features`, which is the joined map in the reference frame.
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from csam_ros.core.joining.alignment import joined
from csam_ros.core.joining.notes import Note, NoteKind
from csam_ros.core.joining.rendezvous_filters import FilterReport
from csam_ros.core.model.regular_files import open_regular

Array = NDArray[np.float64]


class SummaryError(ValueError):
    """A summary is malformed; the message names the key."""


# --------------------------------------------------------------------------- reading values


def _object(
    value: Any, where: str, keys: Sequence[str], optional: Sequence[str] = ()
) -> Mapping[str, Any]:
    """``value`` as a JSON object with exactly ``keys`` (those in ``optional`` may be
    absent: summaries written before they were added)."""
    if not isinstance(value, Mapping):
        raise SummaryError(f"{where}: expected an object, got {type(value).__name__}")
    missing = [k for k in keys if k not in value and k not in optional]
    if missing:
        raise SummaryError(f"{where}: no {missing[0]!r} entry (has {sorted(value)})")
    unknown = sorted(set(value) - set(keys))
    if unknown:
        raise SummaryError(f"{where}: unknown key(s) {unknown}; allowed: {list(keys)}")
    return value


def _mapping(value: Any, where: str) -> Mapping[str, Any]:
    if not isinstance(value, Mapping):
        raise SummaryError(f"{where}: expected an object, got {type(value).__name__}")
    return value


def _list(value: Any, where: str) -> list[Any]:
    if not isinstance(value, list):
        raise SummaryError(f"{where}: expected a list, got {type(value).__name__}")
    return value


def _string(value: Any, where: str) -> str:
    if not isinstance(value, str):
        raise SummaryError(f"{where}: expected a string, got {value!r:.80}")
    return value


def _number(value: Any, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise SummaryError(f"{where}: expected a number, got {value!r:.80}")
    return float(value)


def _count(value: Any, where: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < 0:
        raise SummaryError(f"{where}: expected a count (integer >= 0), got {value!r:.80}")
    return value


def _numbers(value: Any, where: str) -> dict[str, float]:
    return {k: _number(v, f"{where}.{k}") for k, v in _mapping(value, where).items()}


def _counts(value: Any, where: str) -> dict[str, int]:
    return {k: _count(v, f"{where}.{k}") for k, v in _mapping(value, where).items()}


def _array(value: Any, shape: tuple[int | None, ...], where: str) -> Array:
    """``value`` as a float array of ``shape`` (``None``: any length, also 0)."""
    if not isinstance(value, list):
        raise SummaryError(f"{where}: expected a list of numbers, got {value!r:.80}")
    try:
        array = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise SummaryError(f"{where}: expected numbers, got {str(value)[:80]!r}") from None
    # numpy reads null as NaN; to_dict writes NaN as NaN, so a null is a broken entry
    if np.isnan(array).any() and any(v is None for v in np.asarray(value, dtype=object).flat):
        raise SummaryError(f"{where}: null among the numbers")
    if array.size == 0 and shape and shape[0] is None:
        array = array.reshape(0, *(n or 0 for n in shape[1:]))
    if array.ndim != len(shape) or any(
        n is not None and n != m for n, m in zip(shape, array.shape, strict=True)
    ):
        expected = ", ".join("N" if n is None else str(n) for n in shape)
        raise SummaryError(f"{where}: expected shape ({expected}), got {array.shape}")
    return array


def _optional_array(value: Any, shape: tuple[int, ...], where: str) -> Array | None:
    return None if value is None else _array(value, shape, where)


def _array_list(value: Any) -> Any:
    return None if value is None else np.asarray(value, dtype=float).tolist()


# --------------------------------------------------------------------------- C-SAM result


@dataclass(frozen=True)
class LocalMapCheck:
    """A local map checked against its own measurements (:mod:`csam_ros.core.joining.consistency`);
    ``reason`` is empty when it passed."""

    trajectory_factors: int
    trajectory_outliers: int
    observation_factors: int
    observation_outliers: int
    inconsistent_features: list[int] = field(default_factory=list)  # the robot's labels
    reason: str = ""

    @property
    def passed(self) -> bool:
        return not self.reason

    def to_dict(self) -> dict[str, Any]:
        return {
            "trajectory_factors": self.trajectory_factors,
            "trajectory_outliers": self.trajectory_outliers,
            "observation_factors": self.observation_factors,
            "observation_outliers": self.observation_outliers,
            "inconsistent_features": list(self.inconsistent_features),
            "reason": self.reason,
        }

    @classmethod
    def from_dict(cls, node: Any, where: str) -> LocalMapCheck:
        """The inverse of :meth:`to_dict`."""
        node = _object(node, where, list(cls(0, 0, 0, 0).to_dict()))

        def count(key: str) -> int:
            value = node[key]
            if not isinstance(value, int) or isinstance(value, bool) or value < 0:
                raise SummaryError(f"{where}.{key}: expected a count, got {value!r:.40}")
            return value

        labels = _list(node["inconsistent_features"], f"{where}.inconsistent_features")
        if not all(isinstance(k, int) and not isinstance(k, bool) for k in labels):
            raise SummaryError(f"{where}.inconsistent_features: expected integer labels")
        return cls(
            trajectory_factors=count("trajectory_factors"),
            trajectory_outliers=count("trajectory_outliers"),
            observation_factors=count("observation_factors"),
            observation_outliers=count("observation_outliers"),
            inconsistent_features=list(labels),
            reason=_string(node["reason"], f"{where}.reason"),
        )


@dataclass
class RobotResult:
    """One robot in the result; ``None`` / empty joined fields when it is pending."""

    name: str
    alignment: str  # "reference" | "aligned" | "pending: <reason>"
    stamps: Array
    poses_local: Array  # (N, 3) in G_r
    sigma_phi_local: Array  # (N,)
    base_node: Array | None = None  # G_r in the reference frame
    base_node_cov: Array | None = None  # (3, 3)
    poses_joined: Array | None = None  # (N, 3) in the reference frame
    sigma_phi_joined: Array | None = None  # (N,) relative to the robot's own first pose
    sigma_phi_joined_reference: Array | None = None  # (N,) in the reference frame
    alignment_method: str = ""  # "mutual" | "registration" | "" (reference, pending)
    alignment_base_node: Array | None = None  # Algorithm 1 (rendezvous parts only)
    alignment_base_node_cov: Array | None = None
    rendezvous_stamps: Array = field(default_factory=lambda: np.zeros(0))  # poses that met
    # Algorithm 1's estimate of the poses at rendezvous_stamps, in G_r (the next join's start)
    alignment_rendezvous_poses: Array | None = None
    feature_labels_local: NDArray[np.int64] = field(
        default_factory=lambda: np.zeros(0, dtype=np.int64)
    )
    features_local: Array = field(default_factory=lambda: np.zeros((0, 2)))  # in G_r
    feature_covariances_local: Array = field(default_factory=lambda: np.zeros((0, 2, 2)))
    local_check: LocalMapCheck | None = None  # None: not checked
    # (2, 3): the local map's odometry calibration (s, k_d, k_s) and its sigmas; None: off
    odometry_calibration: Array | None = None

    @property
    def joined(self) -> bool:
        """Whether the robot is in the joined map (the reference or aligned)."""
        return joined(self.alignment)

    def to_dict(self) -> dict[str, Any]:
        """The robot's entry of ``summary.json`` (its name is the key of the entry;
        ``odometry_calibration`` only when estimated)."""
        entry = {
            "base_node": _array_list(self.base_node),
            "base_node_cov": _array_list(self.base_node_cov),
            "alignment": self.alignment,
            "alignment_method": self.alignment_method,
            "alignment_base_node": _array_list(self.alignment_base_node),
            "alignment_base_node_cov": _array_list(self.alignment_base_node_cov),
            "stamps": _array_list(self.stamps),
            "poses_local": _array_list(self.poses_local),
            "poses_joined": _array_list(self.poses_joined) or [],
            "sigma_phi_local": _array_list(self.sigma_phi_local),
            "rendezvous_stamps": _array_list(self.rendezvous_stamps),
            "alignment_rendezvous_poses": _array_list(self.alignment_rendezvous_poses),
            "features_local": [
                {"label": f"{self.name}/{int(k)}", "xy": _array_list(xy), "cov": _array_list(c)}
                for k, xy, c in zip(
                    self.feature_labels_local,
                    self.features_local,
                    self.feature_covariances_local,
                    strict=True,
                )
            ],
            "sigma_phi_joined": _array_list(self.sigma_phi_joined) or [],
            "sigma_phi_joined_reference": _array_list(self.sigma_phi_joined_reference) or [],
            "local_check": self.local_check.to_dict() if self.local_check else None,
        }
        if self.odometry_calibration is not None:
            scale, sigma = np.asarray(self.odometry_calibration, dtype=float).reshape(2, 3)
            entry["odometry_calibration"] = {"scale": scale.tolist(), "sigma": sigma.tolist()}
        return entry

    @classmethod
    def from_dict(cls, name: str, node: Any, where: str | None = None) -> RobotResult:
        """The inverse of :meth:`to_dict` for the robot ``name``."""
        where = where or f"robots.{name}"
        keys = list(cls(name, "", np.zeros(0), np.zeros((0, 3)), np.zeros(0)).to_dict())
        node = _object(
            node,
            where,
            [*keys, "odometry_calibration"],
            optional=("local_check", "alignment_rendezvous_poses", "odometry_calibration"),
        )
        calibration = None
        if node.get("odometry_calibration") is not None:
            at = f"{where}.odometry_calibration"
            entry = _object(node["odometry_calibration"], at, ("scale", "sigma"))
            calibration = np.stack(
                [_array(entry[k], (3,), f"{at}.{k}") for k in ("scale", "sigma")]
            )
        stamps = _array(node["stamps"], (None,), f"{where}.stamps")
        rendezvous_stamps = _array(node["rendezvous_stamps"], (None,), f"{where}.rendezvous_stamps")
        check = node.get("local_check")
        n = len(stamps)

        def series(key: str, tail: tuple[int, ...] = (), joined: bool = False) -> Array | None:
            value = node[key]
            if joined and value == []:
                return None
            array = _array(value, (None, *tail), f"{where}.{key}")
            if len(array) != n:
                raise SummaryError(f"{where}.{key}: {len(array)} entries but {n} stamps")
            return array

        local_features = _list(node["features_local"], f"{where}.features_local")
        labels, xy, cov = [], [], []
        for i, entry in enumerate(local_features):
            at = f"{where}.features_local[{i}]"
            entry = _object(entry, at, ("label", "xy", "cov"))
            label = _string(entry["label"], f"{at}.label")
            robot, _, local = label.rpartition("/")
            if robot != name or not local.lstrip("-").isdigit():
                raise SummaryError(f"{at}.label: expected '{name}/<integer>', got {label!r}")
            labels.append(int(local))
            xy.append(_array(entry["xy"], (2,), f"{at}.xy"))
            cov.append(_array(entry["cov"], (2, 2), f"{at}.cov"))
        return cls(
            name=name,
            alignment=_string(node["alignment"], f"{where}.alignment"),
            stamps=stamps,
            poses_local=series("poses_local", (3,)),
            sigma_phi_local=series("sigma_phi_local"),
            base_node=_optional_array(node["base_node"], (3,), f"{where}.base_node"),
            base_node_cov=_optional_array(node["base_node_cov"], (3, 3), f"{where}.base_node_cov"),
            poses_joined=series("poses_joined", (3,), joined=True),
            sigma_phi_joined=series("sigma_phi_joined", joined=True),
            sigma_phi_joined_reference=series("sigma_phi_joined_reference", joined=True),
            alignment_method=_string(node["alignment_method"], f"{where}.alignment_method"),
            alignment_base_node=_optional_array(
                node["alignment_base_node"], (3,), f"{where}.alignment_base_node"
            ),
            alignment_base_node_cov=_optional_array(
                node["alignment_base_node_cov"], (3, 3), f"{where}.alignment_base_node_cov"
            ),
            rendezvous_stamps=rendezvous_stamps,
            alignment_rendezvous_poses=_optional_array(
                node.get("alignment_rendezvous_poses"),
                (len(rendezvous_stamps), 3),
                f"{where}.alignment_rendezvous_poses",
            ),
            feature_labels_local=np.array(labels, dtype=np.int64),
            features_local=np.array(xy, dtype=float).reshape(-1, 2),
            feature_covariances_local=np.array(cov, dtype=float).reshape(-1, 2, 2),
            local_check=None
            if check is None
            else LocalMapCheck.from_dict(check, f"{where}.local_check"),
            odometry_calibration=calibration,
        )


@dataclass(frozen=True)
class FeatureResult:
    """A feature of the joined map: its members ``robot/label``, position and covariance."""

    members: list[str]
    xy: Array
    cov: Array

    def to_dict(self) -> dict[str, Any]:
        return {
            "members": list(self.members),
            "xy": _array_list(self.xy),
            "cov": _array_list(self.cov),
        }

    @classmethod
    def from_dict(cls, node: Any, where: str) -> FeatureResult:
        node = _object(node, where, ("members", "xy", "cov"))
        members = _list(node["members"], f"{where}.members")
        if not members:
            raise SummaryError(f"{where}.members: a feature needs at least one member")
        return cls(
            members=[_string(m, f"{where}.members[{i}]") for i, m in enumerate(members)],
            xy=_array(node["xy"], (2,), f"{where}.xy"),
            cov=_array(node["cov"], (2, 2), f"{where}.cov"),
        )


@dataclass(frozen=True)
class AssociationRecord:
    """An accepted association with its Mahalanobis distance ``D`` (eq. 26)."""

    a: str
    b: str
    mahalanobis: float

    def to_dict(self) -> dict[str, Any]:
        return {"a": self.a, "b": self.b, "mahalanobis": float(self.mahalanobis)}

    @classmethod
    def from_dict(cls, node: Any, where: str) -> AssociationRecord:
        node = _object(node, where, ("a", "b", "mahalanobis"))
        return cls(
            a=_string(node["a"], f"{where}.a"),
            b=_string(node["b"], f"{where}.b"),
            mahalanobis=_number(node["mahalanobis"], f"{where}.mahalanobis"),
        )


@dataclass
class CsamResult:
    """Everything C-SAM reports (``summary.json`` without the run's provenance)."""

    reference_frame: str
    robots: dict[str, RobotResult]
    features: list[FeatureResult]
    associations: list[AssociationRecord]
    timing_s: dict[str, float]
    notes: list[Note] = field(default_factory=list)
    statistics: dict[str, float] = field(default_factory=dict)
    # what the rendezvous filters dropped: "consistency" and / or "thinning"
    rendezvous_filter: dict[str, FilterReport] = field(default_factory=dict)

    @property
    def reference(self) -> str:
        """The reference robot (the frame's owner)."""
        return self.reference_frame.rpartition("/")[0]

    @property
    def converged(self) -> bool:
        """False when Algorithm 1 or the joint solve stopped unconverged (the notes say how);
        True in summaries written before convergence was recorded."""
        return all(
            self.statistics.get(key, 1.0) == 1.0
            for key in ("algorithm1_converged", "joint_converged")
        )

    def notes_of(self, *kinds: NoteKind) -> list[Note]:
        """The notes of the given kinds, in order."""
        return [note for note in self.notes if note.kind in kinds]

    @property
    def note_texts(self) -> list[str]:
        """The notes' texts, as ``summary.json`` holds them."""
        return [note.text for note in self.notes]

    def joined_robots(self) -> set[str]:
        """The robots in the joined map (the reference and the aligned ones)."""
        return {name for name, robot in self.robots.items() if robot.joined}

    def to_dict(self) -> dict[str, Any]:
        """The JSON-ready summary (lists and floats only)."""
        return {
            "reference_frame": self.reference_frame,
            "robots": {name: r.to_dict() for name, r in self.robots.items()},
            "features": [f.to_dict() for f in self.features],
            "associations": [a.to_dict() for a in self.associations],
            "timing_s": {k: float(v) for k, v in self.timing_s.items()},
            "statistics": {k: float(v) for k, v in self.statistics.items()},
            "notes": self.note_texts,
            "rendezvous_filter": {k: r.to_dict() for k, r in self.rendezvous_filter.items()},
        }

    @classmethod
    def from_dict(cls, node: Any, where: str = "summary") -> CsamResult:
        """The inverse of :meth:`to_dict`."""
        keys = list(cls("", {}, [], [], {}).to_dict())
        node = _object(node, where, keys)
        robots = _mapping(node["robots"], "robots")
        filters = _mapping(node["rendezvous_filter"], "rendezvous_filter")
        rendezvous_filter = {}
        for name, report in filters.items():
            try:
                rendezvous_filter[name] = FilterReport.from_dict(
                    report, f"rendezvous_filter.{name}"
                )
            except ValueError as err:
                raise SummaryError(str(err)) from None
        return cls(
            reference_frame=_string(node["reference_frame"], "reference_frame"),
            robots={name: RobotResult.from_dict(name, entry) for name, entry in robots.items()},
            features=[
                FeatureResult.from_dict(f, f"features[{i}]")
                for i, f in enumerate(_list(node["features"], "features"))
            ],
            associations=[
                AssociationRecord.from_dict(a, f"associations[{i}]")
                for i, a in enumerate(_list(node["associations"], "associations"))
            ],
            timing_s=_numbers(node["timing_s"], "timing_s"),
            notes=[
                Note.of_text(_string(s, f"notes[{i}]"))
                for i, s in enumerate(_list(node["notes"], "notes"))
            ],
            statistics=_numbers(node["statistics"], "statistics"),
            rendezvous_filter=rendezvous_filter,
        )


# --------------------------------------------------------------------------- a run


@dataclass(frozen=True)
class MergerStats:
    """What the merger node counted up to the solve of a live run's summary."""

    dropped: dict[str, int]  # dropped messages and failed solves by reason
    solves: int
    # per robot: smoother restarts seen (a new local map starting later or holding fewer
    # poses than the last one) and the poses of history they lost; no key when none
    restarts: dict[str, int] = field(default_factory=dict)
    restart_poses_lost: dict[str, int] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        document: dict[str, Any] = {"dropped": dict(self.dropped), "solves": self.solves}
        if self.restarts:
            document["restarts"] = dict(self.restarts)
            document["restart_poses_lost"] = dict(self.restart_poses_lost)
        return document

    @classmethod
    def from_dict(cls, node: Any, where: str = "merger") -> MergerStats:
        restarted = isinstance(node, Mapping) and "restarts" in node
        keys = ("dropped", "solves", *(("restarts", "restart_poses_lost") if restarted else ()))
        node = _object(node, where, keys)
        return cls(
            dropped=_counts(node["dropped"], f"{where}.dropped"),
            solves=_count(node["solves"], f"{where}.solves"),
            restarts=_counts(node["restarts"], f"{where}.restarts") if restarted else {},
            restart_poses_lost=(
                _counts(node["restart_poses_lost"], f"{where}.restart_poses_lost")
                if restarted
                else {}
            ),
        )


@dataclass
class RunSummary:
    """``summary.json``: the C-SAM result and, when known, where the run came from."""

    result: CsamResult
    merger: MergerStats | None = None  # live runs
    dropped: dict[str, dict[str, int]] | None = None  # offline replay: per robot and reason
    source: str | None = None  # replay: the bag
    scenario: str | None = None  # demo: the scenario; replay: the bag's name

    def to_dict(self) -> dict[str, Any]:
        """The JSON-ready ``summary.json`` (absent parts have no key)."""
        document = self.result.to_dict()
        if self.merger is not None:
            document["merger"] = self.merger.to_dict()
        if self.dropped is not None:
            document["dropped"] = {r: dict(c) for r, c in self.dropped.items()}
        if self.source is not None:
            document["source"] = self.source
        if self.scenario is not None:
            document["scenario"] = self.scenario
        return document

    @classmethod
    def from_dict(cls, node: Any) -> RunSummary:
        """The inverse of :meth:`to_dict`."""
        node = dict(_mapping(node, "summary"))
        merger, dropped = node.pop("merger", None), node.pop("dropped", None)
        source, scenario = node.pop("source", None), node.pop("scenario", None)
        return cls(
            result=CsamResult.from_dict(node),
            merger=None if merger is None else MergerStats.from_dict(merger),
            dropped=None
            if dropped is None
            else {r: _counts(c, f"dropped.{r}") for r, c in _mapping(dropped, "dropped").items()},
            source=None if source is None else _string(source, "source"),
            scenario=None if scenario is None else _string(scenario, "scenario"),
        )

    def text(self) -> str:
        """The ``summary.json`` text of this summary."""
        return _dumps_outline(self.to_dict(), SUMMARY_OUTLINE_DEPTH) + "\n"

    def write(self, path: Path) -> None:
        """Write ``summary.json`` to ``path`` (:func:`write_summary_text`)."""
        write_summary_text(path, self.text())

    @classmethod
    def read(cls, path: Path) -> RunSummary:
        """The summary in the file ``path``; a malformed file is a :class:`SummaryError`."""
        with open_regular(path) as stream:  # a FIFO would block the read forever
            data = stream.read()
        try:
            return cls.from_dict(json.loads(data.decode("utf-8")))
        except UnicodeDecodeError as err:
            raise SummaryError(f"{path}: not UTF-8 text (byte {err.start})") from None
        except (json.JSONDecodeError, SummaryError, RecursionError) as err:
            raise SummaryError(f"{path}: {err}") from None


def write_summary_text(path: Path, text: str) -> None:
    """Write a summary's text to ``path`` by a rename (a reader never sees half of it)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


# summary.json: its sections, robots and each robot's fields one a line; their values compact
SUMMARY_OUTLINE_DEPTH = 3


def _dumps_outline(value: Any, depth: int, indent: str = "") -> str:
    """JSON of ``value`` with its objects ``depth`` levels deep laid out one key a line, and
    everything deeper compact (written by the C encoder: ``indent=`` would write all of a
    run's poses through the pure-Python one, 5x slower)."""
    if depth == 0 or not isinstance(value, dict) or not value:
        return json.dumps(value)
    inner = indent + " "
    items = ",\n".join(
        f"{inner}{json.dumps(key)}: {_dumps_outline(item, depth - 1, inner)}"
        for key, item in value.items()
    )
    return "{\n" + items + "\n" + indent + "}"
