"""Readers of single-robot 2D landmark SLAM files and their least-squares problem.

Two formats (one per file; comments start with ``#``, blank lines are skipped):

Text format::

    ODOMETRY id1 id2 dx dy dtheta c11 c12 c13 c22 c23 c33
    LANDMARK pose_id landmark_id dx dy c11 c12 c22

- ``ODOMETRY``: the pose of ``id2`` in the frame of ``id1`` (``(-)x_id1 (+) x_id2``) and the
  covariance of the vector ``(dx, dy, dtheta)`` in the frame of ``id1``, given by its upper
  triangle row by row (``c11 = var(dx)``, ``c12 = cov(dx, dy)``, ...). This is exactly the
  error of :class:`~csam_ros.core.sam.factors.RelativePose`.
- ``LANDMARK``: the landmark's position in the frame of pose ``pose_id`` with the covariance
  of ``(dx, dy)`` in that frame (``c11 c12 c22``), the error of ``PointObservation``.

g2o format::

    VERTEX_SE2 id x y theta
    VERTEX_XY id x y
    EDGE_SE2 i j dx dy dtheta I11 I12 I13 I22 I23 I33
    EDGE_SE2_XY i j dx dy I11 I12 I22

with *information* matrices (upper triangle, row by row). g2o's ``EDGE_SE2`` error is
``(R(dtheta)^T (t_ij - t_z), wrap(theta_ij - dtheta))``, the pose difference in the frame of
the measurement; it equals ``M e`` with ``e = between(x_i, x_j) - z`` (this project's
``RelativePose`` error) and ``M = blkdiag(R(dtheta)^T, 1)``, so the information used here is
``M^T I M`` and the objective is the same. ``EDGE_SE2_XY`` matches ``PointObservation``.
Vertex values are the initial estimate; missing ones are initialised by composing odometry
from the first pose and landmarks from their first observation.

Pose and landmark ids live in separate name spaces in the text format; in g2o they share one
(a vertex's type decides). A malformed line raises ``Slam2dFormatError`` naming the file and
line number.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from csam_ros.core.model import se2
from csam_ros.core.sam import factors
from csam_ros.core.sam.factors import POINT, POSE, PointObservation, PosePrior, RelativePose
from csam_ros.core.sam.solver import GAUGE_SIGMA, Problem

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]


MAX_ID = 2**62  # pose and landmark ids are 64-bit integers (labels of the log and the bag)


class Slam2dFormatError(ValueError):
    """A line of a 2D SLAM file that cannot be read."""


@dataclass
class Slam2dData:
    """Contents of a 2D landmark SLAM file, in this project's conventions."""

    source: str
    format: str  # "text" or "g2o"
    pose_vertices: dict[int, Array] = field(default_factory=dict)  # id -> (x, y, theta)
    landmark_vertices: dict[int, Array] = field(default_factory=dict)  # id -> (x, y)
    odometry_first: IntArray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    odometry_second: IntArray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    odometry: Array = field(default_factory=lambda: np.zeros((0, 3)))  # pose of 2nd in 1st
    odometry_covariance: Array = field(default_factory=lambda: np.zeros((0, 3, 3)))
    observation_pose: IntArray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    observation_landmark: IntArray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    observations: Array = field(default_factory=lambda: np.zeros((0, 2)))  # in the pose frame
    observation_covariance: Array = field(default_factory=lambda: np.zeros((0, 2, 2)))

    @property
    def pose_ids(self) -> IntArray:
        ids = set(self.pose_vertices) | set(self.odometry_first.tolist())
        ids |= set(self.odometry_second.tolist()) | set(self.observation_pose.tolist())
        return np.array(sorted(ids), dtype=np.int64)

    @property
    def landmark_ids(self) -> IntArray:
        ids = set(self.landmark_vertices) | set(self.observation_landmark.tolist())
        return np.array(sorted(ids), dtype=np.int64)


def _symmetric(upper: list[float], dim: int) -> Array:
    m = np.zeros((dim, dim))
    m[np.triu_indices(dim)] = upper
    return m + np.triu(m, 1).T


def _check_spd(matrix: Array, what: str, where: str) -> None:
    if not np.all(np.isfinite(matrix)):
        raise Slam2dFormatError(f"{where}: {what} is not finite")
    eig = np.linalg.eigvalsh(matrix)
    if not eig[0] > 1e-14 * max(abs(eig[-1]), 1e-300):
        raise Slam2dFormatError(f"{where}: {what} is not positive definite (eigenvalues {eig})")


def read_slam2d(path: str | Path) -> Slam2dData:
    """Read a text-format or g2o file (the format is recognised by its record names)."""
    path = Path(path)
    text_records = {"ODOMETRY": 12, "LANDMARK": 8}
    g2o_records = {"VERTEX_SE2": 5, "VERTEX_XY": 4, "EDGE_SE2": 12, "EDGE_SE2_XY": 8}
    fmt: str | None = None
    data = Slam2dData(source=str(path), format="")
    odo_a: list[int] = []
    odo_b: list[int] = []
    odo_z: list[list[float]] = []
    odo_c: list[Array] = []
    obs_p: list[int] = []
    obs_l: list[int] = []
    obs_z: list[list[float]] = []
    obs_c: list[Array] = []
    g2o_types: dict[int, str] = {}
    with path.open("rb") as handle:
        for number, raw in enumerate(_text_lines(handle, path), start=1):
            where = f"{path}:{number}"
            line = raw.split("#", 1)[0].strip()
            if not line:
                continue
            tokens = line.split()
            record = tokens[0]
            if record in text_records:
                kind, fields = "text", text_records[record]
            elif record in g2o_records:
                kind, fields = "g2o", g2o_records[record]
            else:
                raise Slam2dFormatError(f"{where}: unknown record {record!r}")
            if fmt is None:
                fmt = kind
            elif fmt != kind:
                raise Slam2dFormatError(f"{where}: {record} mixes g2o and text formats")
            if len(tokens) != fields:
                raise Slam2dFormatError(
                    f"{where}: {record} needs {fields - 1} values, got {len(tokens) - 1}"
                )
            try:
                if record in ("VERTEX_SE2", "VERTEX_XY"):
                    ids = [int(tokens[1])]
                    values = [float(t) for t in tokens[2:]]
                else:
                    ids = [int(t) for t in tokens[1:3]]
                    values = [float(t) for t in tokens[3:]]
            except ValueError:
                raise Slam2dFormatError(f"{where}: {record} has a non-numeric field") from None
            if any(abs(i) > MAX_ID for i in ids):
                raise Slam2dFormatError(f"{where}: {record} has an id beyond +-2^62")
            if not all(np.isfinite(values)):
                raise Slam2dFormatError(f"{where}: {record} has a non-finite value")
            if record == "VERTEX_SE2":
                _claim(g2o_types, ids[0], "pose", where)
                data.pose_vertices[ids[0]] = np.array(values)
            elif record == "VERTEX_XY":
                _claim(g2o_types, ids[0], "landmark", where)
                data.landmark_vertices[ids[0]] = np.array(values)
            elif record in ("ODOMETRY", "EDGE_SE2"):
                if ids[0] == ids[1]:
                    raise Slam2dFormatError(f"{where}: {record} connects pose {ids[0]} to itself")
                z = values[:3]
                m = _symmetric(values[3:], 3)
                if record == "EDGE_SE2":
                    _claim(g2o_types, ids[0], "pose", where)
                    _claim(g2o_types, ids[1], "pose", where)
                    _check_spd(m, "information matrix", where)
                    rot = np.eye(3)
                    rot[:2, :2] = se2.rotation(z[2]).T
                    m = np.linalg.inv(rot.T @ m @ rot)
                else:
                    _check_spd(m, "covariance", where)
                odo_a.append(ids[0])
                odo_b.append(ids[1])
                odo_z.append(z)
                odo_c.append(m)
            else:  # LANDMARK, EDGE_SE2_XY
                m = _symmetric(values[2:], 2)
                if record == "EDGE_SE2_XY":
                    _claim(g2o_types, ids[0], "pose", where)
                    _claim(g2o_types, ids[1], "landmark", where)
                    _check_spd(m, "information matrix", where)
                    m = np.linalg.inv(m)
                else:
                    _check_spd(m, "covariance", where)
                obs_p.append(ids[0])
                obs_l.append(ids[1])
                obs_z.append(values[:2])
                obs_c.append(m)
    if fmt is None:
        raise Slam2dFormatError(f"{path}: no records")
    data.format = fmt
    data.odometry_first = np.array(odo_a, dtype=np.int64)
    data.odometry_second = np.array(odo_b, dtype=np.int64)
    data.odometry = np.array(odo_z, dtype=float).reshape(-1, 3)
    data.odometry_covariance = np.array(odo_c, dtype=float).reshape(-1, 3, 3)
    data.observation_pose = np.array(obs_p, dtype=np.int64)
    data.observation_landmark = np.array(obs_l, dtype=np.int64)
    data.observations = np.array(obs_z, dtype=float).reshape(-1, 2)
    data.observation_covariance = np.array(obs_c, dtype=float).reshape(-1, 2, 2)
    return data


def _text_lines(lines: Iterable[bytes], path: Path) -> Iterator[str]:
    """The lines of a file opened in binary mode, decoded as UTF-8; a line that is not text
    raises :class:`Slam2dFormatError` naming the file and line."""
    for number, raw in enumerate(lines, start=1):
        try:
            yield raw.decode("utf-8")
        except UnicodeDecodeError as err:
            raise Slam2dFormatError(
                f"{path}:{number}: not UTF-8 text (byte {raw[err.start]:#04x} at column "
                f"{err.start + 1}): a 2D SLAM file is text"
            ) from None


def _claim(types: dict[int, str], vertex: int, kind: str, where: str) -> None:
    previous = types.setdefault(vertex, kind)
    if previous != kind:
        raise Slam2dFormatError(f"{where}: vertex {vertex} used as a {kind} and as a {previous}")


def initial_values(data: Slam2dData) -> tuple[dict[int, Array], dict[int, Array]]:
    """Initial poses and landmarks: vertices where given, else odometry / first observation.

    Poses without a vertex are reached by breadth-first composition of odometry edges (both
    directions) from the lowest pose id, which is placed at its vertex or the origin.
    """
    poses = {k: v.copy() for k, v in data.pose_vertices.items()}
    pose_ids = data.pose_ids
    if len(pose_ids) == 0:
        raise ValueError(f"{data.source}: no poses")
    adjacency: dict[int, list[tuple[int, int, bool]]] = {}
    for e, (a, b) in enumerate(zip(data.odometry_first, data.odometry_second, strict=True)):
        adjacency.setdefault(int(a), []).append((int(b), e, True))
        adjacency.setdefault(int(b), []).append((int(a), e, False))
    roots = [int(p) for p in pose_ids if int(p) in poses] or [int(pose_ids[0])]
    poses.setdefault(roots[0], np.zeros(3))
    queue = deque(roots)
    while queue:
        current = queue.popleft()
        for other, edge, forward in adjacency.get(current, []):
            if other in poses:
                continue
            z = data.odometry[edge]
            rel = z if forward else se2.inverse(z)
            poses[other] = se2.compose(poses[current], rel)
            queue.append(other)
    missing = [int(p) for p in pose_ids if int(p) not in poses]
    if missing:
        raise ValueError(
            f"{data.source}: pose {missing[0]} is not connected to the first pose by odometry "
            "and has no vertex"
        )
    landmarks = {k: v.copy() for k, v in data.landmark_vertices.items()}
    for p, lm, z in zip(
        data.observation_pose, data.observation_landmark, data.observations, strict=True
    ):
        if int(lm) not in landmarks:
            landmarks[int(lm)] = se2.transform_point(poses[int(p)], z)
    return poses, landmarks


def _add_indexed(
    problem: Problem, kind: factors.VariableKind, prefix: str, ids: Any, values: Mapping[int, Any]
) -> tuple[Any, dict[int, int]]:
    """Unknowns ``(prefix, id)`` of ``kind`` at ``values[id]`` for each of the file's ``ids``;
    their problem indices, and a map from file id to problem index."""
    added = problem.add_variables(
        kind, [(prefix, int(i)) for i in ids], np.array([values[int(i)] for i in ids])
    )
    return added, {int(i): int(v) for i, v in zip(ids, added, strict=True)}


def build_problem(data: Slam2dData, gauge_sigma: float = GAUGE_SIGMA) -> Problem:
    """Least-squares problem of a file: variables ``("x", id)`` and ``("l", id)``.

    The gauge is fixed by a prior of sigma ``gauge_sigma`` on the lowest pose id at its
    initial value.
    """
    poses, landmarks = initial_values(data)
    problem = Problem()
    pose_ids = data.pose_ids
    pid, index = _add_indexed(problem, POSE, "x", pose_ids, poses)
    problem.add_factor(
        PosePrior(pid[:1], poses[int(pose_ids[0])][None], np.eye(3) / gauge_sigma, name="gauge")
    )
    if len(data.odometry):
        problem.add_factor(
            RelativePose(
                [index[int(a)] for a in data.odometry_first],
                [index[int(b)] for b in data.odometry_second],
                data.odometry,
                covariance=data.odometry_covariance,
                name=f"{data.source} odometry",
            )
        )
    lm_ids = data.landmark_ids
    if len(lm_ids):
        _, lindex = _add_indexed(problem, POINT, "l", lm_ids, landmarks)
        if len(data.observations):
            problem.add_factor(
                PointObservation(
                    [index[int(p)] for p in data.observation_pose],
                    [lindex[int(lm)] for lm in data.observation_landmark],
                    data.observations,
                    covariance=data.observation_covariance,
                    name=f"{data.source} landmark observations",
                )
            )
    return problem
