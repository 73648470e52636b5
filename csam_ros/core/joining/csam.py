"""C-SAM in one call: alignment, association and the joint solve over any number of robots.

:func:`join_maps` takes the robots' solved local maps (:class:`~csam_ros.core.joining.joint_solve.
RobotMap`, in the robots' order; the first is the reference) and their rendezvous logs;
:func:`run_csam` first builds the local maps from a :class:`~csam_ros.core.model.log.MultiRobotLog`
with a pose at every rendezvous stamp. Steps (paper section IV, docs/METHOD.md sections 5-7):

1. From each local map only its rendezvous part: the marginal square-root information of its
   rendezvous poses (and, for association, the gains ``K = P_l,rho P_rho,rho^-1`` of its
   features on those poses).
2. Base-node initialisation and Algorithm 1 (:mod:`csam_ros.core.joining.alignment`); robots that
   cannot be aligned stay ``pending: <reason>`` and get no joined map.
3. Algorithm 2 (:mod:`csam_ros.core.joining.association`).
4. One joint solve of all poses and features of the aligned robots
   (:mod:`csam_ros.core.joining.joint_solve`), then the marginal covariances the summary reports.

The :class:`~csam_ros.core.joining.result.CsamResult` carries everything C-SAM reports
(:mod:`csam_ros.core.joining.result` writes and reads it as ``summary.json``). Heading standard
deviations: ``sigma_phi_local`` is the local map's marginal heading sigma in ``G_r``;
``sigma_phi_joined`` is the heading sigma after joining *relative to the robot's own first
pose* (in ``G_r``, the like-for-like comparison of the paper's figures 5c and 6c: it can
only shrink); ``sigma_phi_joined_reference`` is the heading sigma in the reference frame
(which adds the base node's uncertainty). Marginals come from a selected inverse of each
factor (:class:`~csam_ros.core.sam.selected_inverse.SelectedInverse`), never from the dense inverse.

A pending robot keeps its local estimate (``poses_local``, ``sigma_phi_local``); its
base node and joined fields are ``None`` (``null`` / ``[]`` in the summary) and its features
are not in ``features``, which is the joined map in the reference frame.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from functools import cached_property
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
from numpy.typing import NDArray

from csam_ros.core.joining.alignment import AlignmentOptions, RendezvousPart, align
from csam_ros.core.joining.association import (
    CHI2_2DOF_99,
    AssociationOptions,
    Associations,
    MapFeatures,
    associate,
)
from csam_ros.core.joining.consistency import ConsistencyOptions, check_local_map
from csam_ros.core.joining.joint_solve import JointSolution, heading_sigmas, joint_solve
from csam_ros.core.joining.rendezvous_filters import (
    FilterReport,
    RendezvousThinning,
    consistent_rendezvous,
    select_rendezvous,
    thin_rendezvous,
)
from csam_ros.core.joining.result import (
    AssociationRecord,
    CsamResult,
    FeatureResult,
    LocalMapCheck,
    RobotResult,
)
from csam_ros.core.joining.warm_start import WarmStart
from csam_ros.core.model import se2
from csam_ros.core.model.config_file import from_mapping, load_document, setting
from csam_ros.core.model.log import MultiRobotLog, RendezvousLog
from csam_ros.core.model.rendezvous import collect, required_stamps
from csam_ros.core.sam.covariance import (
    covariance_block,
    covariance_by_elimination,
    covariance_columns,
    factorize_at_estimate,
    upper_sqrt_information,
)
from csam_ros.core.sam.selected_inverse import SelectedInverse
from csam_ros.core.sam.solver import NormalEquations, SolverOptions
from csam_ros.core.smoothing.local_map import SMOOTHER, LocalMap, LocalMapConfig, build_local_map
from csam_ros.core.smoothing.robot_map import RobotMap, find_gauge_factor

Array = NDArray[np.float64]
T = TypeVar("T")
U = TypeVar("U")


MERGER = "merger"  # the node that takes most CsamConfig fields as parameters
_POSITIVE = {"minimum": 0.0, "exclusive": True, "node": MERGER}


@dataclass
class CsamConfig:
    """Parameters of C-SAM (the ``csam:`` section of a scenario or merger parameter file).

    The merger takes each field as a ROS parameter, but the rendezvous thinning, which decides
    where the local maps hold poses and so belongs to the smoothers (online) and
    :func:`run_csam` (offline)."""

    chi2_gate: float = setting(
        CHI2_2DOF_99, "association gate on the Mahalanobis distance (2 dof)", **_POSITIVE
    )
    max_heading_sigma_deg: float = setting(
        5.0, "deg: a robot stays pending if the rendezvous fix its heading worse", **_POSITIVE
    )
    mutual_time_tolerance: float = setting(
        1e-3, "s: two measurements this close are mutual", **_POSITIVE
    )
    stamp_tolerance: float = setting(
        1e-6, "s: matching rendezvous stamps to local-map poses", **_POSITIVE
    )
    skip_missing_poses: bool = setting(
        False, "leave out rendezvous measurements without a local-map pose", node=MERGER
    )
    max_iterations: int = setting(
        100, "iterations of Algorithm 1 and of the joint solve", **_POSITIVE
    )
    step_tolerance: float = setting(
        1e-9, "m, rad: stop when the largest step component is below", **_POSITIVE
    )
    # MR.CLAM's robust joint costs creep at 1e-11-1e-12 per iteration long after the map
    # settled: Dataset 2 took 103 iterations to 1e-12 (20 of them below 1e-10), so the cap of
    # 100 left it unconverged; features move < 1e-6 m over that creep
    relative_tolerance: float = setting(
        1e-10, "stop when the relative cost decrease is below", **_POSITIVE
    )
    # SolverOptions.max_step_scale; MR.CLAM: 100+ -> 68 iterations
    max_step_scale: float = setting(
        64.0,
        "joint solve: stretch a robust (reweighted) step by up to this factor while the cost "
        "falls (1: off)",
        minimum=1.0,
        node=MERGER,
    )
    associate: bool = setting(True, "false: join through rendezvous rows only", node=MERGER)
    # measured (python -m csam_ros.bench.merger_replay): no fewer iterations on simulated runs,
    # where a cold solve is the offline one; on MR.CLAM fewer, in other minima of the robust
    # cost within the poses' uncertainty (on in config/mrclam.yaml)
    warm_start: bool = setting(
        False, "start each live solve from the previous one (docs/METHOD.md 6.4)", node=MERGER
    )
    # rendezvous filters for real data (csam_ros.core.joining.rendezvous_filters; defaults keep
    # everything)
    rendezvous_min_interval: float = setting(
        0.0, "s between kept rendezvous of one ordered robot pair", minimum=0.0, node=SMOOTHER
    )
    rendezvous_max_per_pair: int = setting(
        0,
        "rendezvous kept per ordered robot pair, spread over time (0: no cap)",
        minimum=0,
        node=SMOOTHER,
    )
    rendezvous_consistency: bool = setting(
        False, "RANSAC check of rendezvous against the local maps", node=MERGER
    )
    consistency_drift: float = setting(
        0.3, "m allowed for local-map errors in that check", **_POSITIVE
    )
    # a local map's own residuals (csam_ros.core.joining.consistency; docs/METHOD.md 6.5)
    check_local_maps: bool = setting(
        True, "check each local map against its own measurements before joining", node=MERGER
    )
    max_trajectory_outliers: float = setting(
        0.02,
        "share of a map's factors between poses beyond the 99.9 % gate above which the robot "
        "stays pending",
        minimum=0.0,
        node=MERGER,
    )
    max_observation_outliers: float = setting(
        0.3,
        "share of a map's observations beyond the gate above which the robot stays pending",
        minimum=0.0,
        node=MERGER,
    )
    max_feature_outliers: float = setting(
        0.3,
        "share of one feature's observations beyond the gate above which it is not associated",
        minimum=0.0,
        node=MERGER,
    )

    @classmethod
    def from_dict(cls, node: Mapping[str, Any] | None, source: str = "csam") -> CsamConfig:
        """Build from a mapping; unknown keys and bad values are errors naming them."""
        return from_mapping(cls, node, source)

    @classmethod
    def from_file(cls, name_or_path: str | Path) -> CsamConfig:
        """The ``csam:`` section of a scenario or parameter file (defaults when absent)."""
        return cls.from_dict(load_document(name_or_path).get("csam"), f"{name_or_path}: csam")

    def thinning(self) -> RendezvousThinning:
        """The streaming rendezvous thinning these settings describe."""
        return RendezvousThinning(
            self.rendezvous_min_interval, self.rendezvous_max_per_pair or None
        )

    def alignment_options(self) -> AlignmentOptions:
        return AlignmentOptions(
            max_heading_sigma=float(np.deg2rad(self.max_heading_sigma_deg)),
            mutual_time_tolerance=self.mutual_time_tolerance,
            max_iterations=self.max_iterations,
            step_tolerance=self.step_tolerance,
            relative_tolerance=self.relative_tolerance,
        )

    def consistency_options(self) -> ConsistencyOptions:
        return ConsistencyOptions(
            max_trajectory_outliers=self.max_trajectory_outliers,
            max_observation_outliers=self.max_observation_outliers,
            max_feature_outliers=self.max_feature_outliers,
        )

    def solver_options(self) -> SolverOptions:
        return SolverOptions(
            max_iterations=self.max_iterations,
            relative_tolerance=self.relative_tolerance,
            step_tolerance=self.step_tolerance,
            max_step_scale=self.max_step_scale,
        )


@dataclass
class LocalView:
    """What a join derives from one local map alone, for its given rendezvous poses: the
    marginal square-root information of those poses (``part``), the cross covariance
    ``P_l,rho`` (F, 2, k) of the features with them (``cross``), and on first use the map's
    marginals from its selected inverse."""

    robot_map: RobotMap
    system: NormalEquations  # factorised at the map's estimate
    rendezvous_poses: NDArray[np.int64]
    part: RendezvousPart | None  # None without rendezvous poses
    cross: Array | None

    @cached_property
    def inverse(self) -> SelectedInverse:
        return SelectedInverse(self.system)

    @cached_property
    def sigma_phi(self) -> Array:
        """(N,) marginal heading sigmas of the poses."""
        headings = self.robot_map.problem.scalar_indices(self.robot_map.pose_ids)[2::3]
        return np.sqrt(np.maximum(self.inverse.entries(headings, headings), 0.0))

    @cached_property
    def feature_covariances(self) -> Array:
        """(F, 2, 2) marginal covariances of the features."""
        m = self.robot_map
        if len(m.feature_ids) == 0:
            return np.zeros((0, 2, 2))
        return self.inverse.blocks(m.problem, m.feature_ids)


def local_view(m: RobotMap, rendezvous_poses: NDArray[np.int64]) -> LocalView:
    """The :class:`LocalView` of ``m`` for ``rendezvous_poses``: the rendezvous part and
    ``P_l,rho`` both come from the covariance of the features and those poses. With no more
    feature than pose scalars (the dense work then a few times that of the rendezvous part
    itself), it is their joint covariance with the other poses eliminated along the
    trajectory (:func:`covariance_by_elimination`); otherwise, or where a map's other factors
    make that no band, the covariance columns of the poses (:func:`covariance_columns`)."""
    problem = m.problem
    system = factorize_at_estimate(problem)
    if len(rendezvous_poses) == 0:
        return LocalView(m, system, rendezvous_poses, None, None)
    pose_columns = problem.scalar_indices(m.pose_ids[rendezvous_poses])
    selected = np.r_[pose_columns, problem.scalar_indices(m.feature_ids)]
    k = len(pose_columns)
    covariance = (
        covariance_by_elimination(system, selected, _other_scalars(m, selected))
        if len(selected) <= 2 * k
        else None
    )
    columns = (
        covariance_columns(system, pose_columns, selected)
        if covariance is None
        else covariance[:, :k]
    )
    block = columns[:k]
    root = upper_sqrt_information(0.5 * (block + block.T))
    part = RendezvousPart(rendezvous_poses, m.poses[rendezvous_poses], root)
    cross = columns[k:].reshape(len(m.feature_ids), 2, k)
    return LocalView(m, system, rendezvous_poses, part, cross)


def _other_scalars(m: RobotMap, selected: NDArray[np.int64]) -> NDArray[np.int64]:
    """Every scalar of ``m``'s problem not ``selected``: its poses' in stamp order, then any
    other."""
    problem = m.problem
    poses = problem.scalar_indices(m.pose_ids)
    order = np.r_[poses, np.setdiff1d(np.arange(problem.dim), poses)]
    outside = np.ones(problem.dim, dtype=bool)
    outside[selected] = False
    return order[outside[order]]


def _with_marginals(view: LocalView) -> LocalView:
    """``view`` with its local marginals computed (cached properties)."""
    view.sigma_phi, view.feature_covariances  # noqa: B018
    return view


def in_threads(function: Callable[[T], U], items: Sequence[T]) -> list[U]:
    """``[function(x) for x in items]`` in threads, one per core (for work that releases the
    interpreter lock: sparse factorisations and solves, LAPACK)."""
    workers = min(len(items), os.cpu_count() or 1)
    if workers < 2:
        return [function(x) for x in items]
    with ThreadPoolExecutor(workers, thread_name_prefix="csam") as pool:
        return list(pool.map(function, items))


class LocalViewCache:
    """:class:`LocalView` per robot, kept while its map is the same object and its rendezvous
    poses the same (a live merger replaces a map when a new one arrives, never changes it)."""

    def __init__(self) -> None:
        self._views: dict[str, LocalView] = {}
        self._checks: dict[str, tuple[RobotMap, ConsistencyOptions, LocalMapCheck]] = {}
        self.reused = 0
        self.built = 0

    def check(self, m: RobotMap, options: ConsistencyOptions) -> LocalMapCheck:
        """:func:`~csam_ros.core.joining.consistency.check_local_map` of ``m``, kept while ``m`` is
        the same object."""
        kept = self._checks.get(m.name)
        if kept is not None and kept[0] is m and kept[1] == options:
            return kept[2]
        check = check_local_map(m, options)
        self._checks[m.name] = (m, options, check)
        return check

    def view(self, m: RobotMap, rendezvous_poses: NDArray[np.int64]) -> LocalView:
        """The cached view of ``m`` if it is still valid, else a new one (then cached)."""
        return self.views([m], [rendezvous_poses])[0]

    def views(
        self, maps: Sequence[RobotMap], rendezvous_poses: Sequence[NDArray[np.int64]]
    ) -> list[LocalView]:
        """:meth:`view` of each map; the new ones built in threads, one per core: their
        factorisations and solves release the interpreter lock."""
        out: list[LocalView | None] = []
        for m, poses in zip(maps, rendezvous_poses, strict=True):
            view = self._views.get(m.name)
            valid = (
                view is not None
                and view.robot_map is m
                and np.array_equal(view.rendezvous_poses, poses)
            )
            out.append(view if valid else None)
        todo = [i for i, view in enumerate(out) if view is None]
        self.reused += len(out) - len(todo)
        self.built += len(todo)

        built = in_threads(lambda i: local_view(maps[i], rendezvous_poses[i]), todo)
        for i, view in zip(todo, built, strict=True):
            out[i] = self._views[maps[i].name] = view
        return [view for view in out if view is not None]


def _map_features(m: RobotMap, view: LocalView, left_out: Sequence[int] = ()) -> MapFeatures | None:
    """A robot's features with their rendezvous gains ``K = P_l,rho P_rho,rho^-1`` and
    marginal covariances (the map's own when it carries them, else its view's), as
    association takes them; without the labels ``left_out``."""
    part, cross = view.part, view.cross
    if part is None or cross is None or len(m.feature_ids) == 0:
        return None
    root = part.sqrt_information
    gain = cross @ (root.T @ root)
    if m.feature_covariances is not None:
        covs = np.asarray(m.feature_covariances, dtype=float)
    else:
        covs = view.feature_covariances
    keep = ~np.isin(m.feature_labels, left_out)
    return MapFeatures(m.feature_labels[keep], m.feature_positions[keep], covs[keep], gain[keep])


def filter_rendezvous(
    maps: Sequence[RobotMap], logs: Mapping[str, RendezvousLog], config: CsamConfig
) -> tuple[Mapping[str, RendezvousLog], dict[str, FilterReport]]:
    """The consistency check of ``config``
    (:func:`csam_ros.core.joining.rendezvous_filters.consistent_rendezvous`) against the local
    maps' trajectories. Thinning is not done here: it decides where the local maps hold poses, so
    the smoothers (online) and :func:`run_csam` (offline) apply it. First, a measurement stamped
    before the first or after the last pose of its observer's or observed robot's map can have no
    pose there (clocks that differ between robots; online, also a map that has not caught up yet):
    it is left out and counted in the report ``trajectory_span`` under ``outside_trajectory``, per
    observing robot. Returns the kept logs and what was dropped."""
    logs, reports = _within_trajectories(maps, logs, config.stamp_tolerance)
    if not config.rendezvous_consistency:
        return logs, reports
    trajectories = {m.name: (np.asarray(m.stamps, dtype=float), m.poses) for m in maps}
    present = {n: log for n, log in logs.items() if n in trajectories}
    kept, checked = consistent_rendezvous(present, trajectories, drift=config.consistency_drift)
    return {**logs, **kept}, {**reports, "consistency": checked}


def _within_trajectories(
    maps: Sequence[RobotMap], logs: Mapping[str, RendezvousLog], tolerance: float
) -> tuple[Mapping[str, RendezvousLog], dict[str, FilterReport]]:
    """``logs`` without measurements stamped outside the span of their observer's or observed
    robot's map (robots without a map are left to :func:`collect`)."""
    span = {m.name: (float(m.stamps[0]) - tolerance, float(m.stamps[-1]) + tolerance) for m in maps}
    report = FilterReport()
    out = dict(logs)
    for name, log in logs.items():
        stamps = np.asarray(log.stamps, dtype=float)
        if name not in span or len(stamps) == 0:
            continue
        low = np.array([span.get(o, (-np.inf, np.inf))[0] for o in log.observed])
        high = np.array([span.get(o, (-np.inf, np.inf))[1] for o in log.observed])
        low, high = np.maximum(low, span[name][0]), np.minimum(high, span[name][1])
        keep = (stamps >= low) & (stamps <= high)
        if not keep.all():
            report.add(name, "outside_trajectory", int((~keep).sum()))
            out[name] = select_rendezvous(log, keep)
    return (out, {"trajectory_span": report}) if report.dropped else (logs, {})


def join_maps(
    maps: Sequence[RobotMap],
    rendezvous_logs: Mapping[str, RendezvousLog],
    config: CsamConfig | None = None,
    previous: CsamResult | None = None,
    cache: LocalViewCache | None = None,
) -> CsamResult:
    """Run C-SAM on solved local maps (the first map's robot is the reference).

    ``previous``, the result of an earlier join with the same reference, gives the initial
    values (:mod:`csam_ros.core.joining.warm_start`); ``cache`` keeps each map's
    :class:`LocalView` between calls. Neither changes the problem solved: converged, the
    result is the same as without them."""
    config = config or CsamConfig()
    if not maps:
        raise ValueError("join_maps: no local maps")
    names = [m.name for m in maps]
    if len(set(names)) != len(names):
        raise ValueError(f"join_maps: duplicate robot names {names}")
    cache = cache or LocalViewCache()
    warm = (
        WarmStart.from_result(previous)
        if previous is not None and previous.reference == names[0]
        else None
    )
    timing: dict[str, float] = {}
    clock = time.perf_counter()

    def lap(key: str) -> None:
        nonlocal clock
        now = time.perf_counter()
        timing[key] = timing.get(key, 0.0) + now - clock
        clock = now

    checks: dict[int, LocalMapCheck] = {}
    if config.check_local_maps:
        options = config.consistency_options()
        checks = {r: cache.check(m, options) for r, m in enumerate(maps)}
    lap("local_map_checks")
    rendezvous_logs, rendezvous_filter = filter_rendezvous(maps, rendezvous_logs, config)
    measurements, notes = collect(
        rendezvous_logs,
        {m.name: m.stamps for m in maps},
        config.stamp_tolerance,
        config.skip_missing_poses,
    )
    rdv_poses = [
        np.unique(
            np.concatenate(
                [
                    measurements.observer_pose[measurements.observer == r],
                    measurements.observed_pose[measurements.observed == r],
                ]
            )
        )
        for r in range(len(maps))
    ]
    views = cache.views(maps, rdv_poses)
    parts = [v.part for v in views]
    lap("local_rendezvous_parts")

    for r, check in checks.items():
        if check.reason:
            what = "reference kept" if r == 0 else "pending"
            notes.append(f"{names[r]}: {check.reason} ({what})")
        if check.inconsistent_features:
            notes.append(
                f"{names[r]}: features {check.inconsistent_features} not associated: their "
                "observations disagree"
            )
    alignment = align(
        parts,
        measurements,
        config.alignment_options(),
        start=warm.base_node_starts(names) if warm is not None else None,
        rendezvous_start=None
        if warm is None
        else [
            None
            if p is None
            else warm.rendezvous_start(
                m.name,
                np.asarray(m.stamps, dtype=float)[p.pose_indices],
                p.poses,
                config.stamp_tolerance,
            )
            for m, p in zip(maps, parts, strict=True)
        ],
        excluded={r: c.reason for r, c in checks.items() if c.reason and r > 0},
    )
    aligned = [r for r in range(len(maps)) if alignment.aligned(r)]
    lap("alignment")

    # the local marginals the summary reports and association uses (in threads, as the views)
    in_threads(_with_marginals, views)
    sigma_local = [v.sigma_phi for v in views]
    lap("local_marginals")

    associations = Associations([], [])
    if config.associate and len(aligned) > 1:
        feats: list[MapFeatures | None] = [None] * len(maps)
        for r in aligned:
            left_out = checks[r].inconsistent_features if r in checks else []
            feats[r] = _map_features(maps[r], views[r], left_out)
        associations = associate(
            feats,
            alignment,
            [p.sqrt_information if p is not None else None for p in parts],
            AssociationOptions(chi2_gate=config.chi2_gate),
        )
        lap("association")

    initial_poses: dict[int, Array] = {}
    initial_features: dict[int, Array] = {}
    if warm is not None:
        for r in aligned:
            m, base = maps[r], alignment.base_nodes[r]
            initial_poses[r] = warm.pose_start(
                m.name, m.stamps, m.poses, base, config.stamp_tolerance
            )
            initial_features[r] = warm.feature_start(
                m.name, m.feature_labels, m.feature_positions, base
            )
    solution = joint_solve(
        maps,
        aligned,
        alignment.base_nodes,
        associations.clusters,
        measurements,
        config.solver_options(),
        initial_poses,
        initial_features,
    )
    lap("joint_solve")

    joint = solution.problem
    # the joint problem is the reference's local problem (no rendezvous rows, nothing to
    # associate): at the local estimate, the local view's marginals are the joint ones
    alone = aligned == [0] and _at_local_estimate(solution, maps[0])
    if alone:
        marginal_problem, system, marginal_pose_ids = (
            maps[0].problem,
            views[0].system,
            {0: maps[0].pose_ids},
        )
        base_cov = np.zeros((1, 3, 3))
    else:
        marginal_problem, marginal_pose_ids = joint, solution.pose_ids
        system = factorize_at_estimate(joint)
        first = joint.scalar_indices([int(solution.pose_ids[r][0]) for r in aligned])
        base_cov = covariance_block(system, first).reshape(len(aligned), 3, -1, 3)
        base_cov = base_cov[np.arange(len(aligned)), :, np.arange(len(aligned)), :]
    lap("joint_base_node_covariance")
    inverse = views[0].inverse if alone else SelectedInverse(system)
    robots: dict[str, RobotResult] = {}
    for r, m in enumerate(maps):
        result = RobotResult(
            name=m.name,
            alignment=alignment.status[r],
            stamps=np.asarray(m.stamps, dtype=float),
            poses_local=m.poses,
            sigma_phi_local=sigma_local[r],
            alignment_method=alignment.methods.get(r, ""),
            rendezvous_stamps=np.asarray(m.stamps, dtype=float)[rdv_poses[r]],
            alignment_rendezvous_poses=alignment.rendezvous_poses.get(r),
            feature_labels_local=np.asarray(m.feature_labels, dtype=np.int64),
            features_local=m.feature_positions,
            feature_covariances_local=views[r].feature_covariances,
            local_check=checks.get(r),
        )
        if r in aligned:
            poses = joint.values_of(solution.pose_ids[r])
            in_reference, own = heading_sigmas(
                marginal_problem, system, marginal_pose_ids[r], inverse
            )
            result.poses_joined = poses
            result.sigma_phi_joined = own
            result.sigma_phi_joined_reference = in_reference
            if r == 0:
                result.base_node = np.zeros(3)
                result.base_node_cov = np.zeros((3, 3))
            else:
                # G_r is defined by the robot's first pose (module docs of joining)
                result.base_node = se2.compose(poses[0], se2.inverse(m.poses[0]))
                result.base_node_cov = base_cov[aligned.index(r)]
                result.alignment_base_node = alignment.base_nodes[r].copy()
                result.alignment_base_node_cov = alignment.base_covariance(r).copy()
        robots[m.name] = result
    feature_covs = (
        views[0].feature_covariances if alone else inverse.blocks(joint, solution.feature_var_ids)
    )
    xy = joint.values_of(solution.feature_var_ids) if len(solution.feature_var_ids) else []
    features = [
        FeatureResult([f"{names[r]}/{lab}" for r, lab in members], xy[i], feature_covs[i])
        for i, members in enumerate(solution.features)
    ]
    lap("joint_marginals")
    records = [
        AssociationRecord(
            f"{names[mt.robot_a]}/{mt.label_a}", f"{names[mt.robot_c]}/{mt.label_c}", mt.mahalanobis
        )
        for mt in associations.matches
    ]
    report = solution.report
    if not alignment.converged:
        notes.append(
            f"Algorithm 1 not converged: {alignment.stop_reason} after "
            f"{alignment.iterations} iterations (cost {alignment.final_cost:.6g})"
        )
    if not report.converged:
        notes.append(
            f"joint solve not converged: {report.reason} after {report.iterations} "
            f"iterations (cost {report.final_cost:.6g})"
        )
    statistics = {
        "algorithm1_iterations": alignment.iterations,
        "algorithm1_converged": float(alignment.converged),
        "algorithm1_warm_start": float(alignment.warm_start),
        "joint_iterations": report.iterations,
        "joint_converged": float(report.converged),
        "joint_warm_start": float(solution.warm_start),
        "joint_final_cost": report.final_cost,
        "association_candidates": associations.candidates,
        "association_gated": associations.gated,
        "association_rejected_conflicts": associations.rejected_conflicts,
        "association_rejected_incompatible": associations.rejected_incompatible,
        "rendezvous_measurements": len(measurements),
    }
    timing["total"] = sum(timing.values())
    return CsamResult(
        reference_frame=f"{names[0]}/map",
        robots=robots,
        features=features,
        associations=records,
        timing_s=timing,
        notes=notes,
        statistics=statistics,
        rendezvous_filter=rendezvous_filter,
    )


def _at_local_estimate(solution: JointSolution, m: RobotMap, tolerance: float = 1e-6) -> bool:
    """Whether the joint solve left robot ``m``'s (the reference's) poses and features within
    ``tolerance`` (m, rad) of its local estimate (marginals there differ by as little)."""
    joint = solution.problem
    moved = np.abs(joint.values_of(solution.pose_ids[0]) - m.poses).max(initial=0.0)
    if len(m.feature_ids):
        features = joint.values_of(solution.feature_ids[0]) - m.feature_positions
        moved = max(moved, np.abs(features).max())
    return moved <= tolerance


def robot_map_from_local_map(local: LocalMap, with_covariances: bool = False) -> RobotMap:
    """C-SAM's view of a solved :class:`~csam_ros.core.smoothing.local_map.LocalMap` (with its
    feature covariances when ``with_covariances``)."""
    problem = local.problem
    pose_ids = problem.indices([("x", i) for i in range(len(local.stamps))])
    labels = local.landmark_labels
    feature_ids = problem.indices([("l", int(lab)) for lab in labels])
    return RobotMap(
        name=local.name,
        problem=problem,
        stamps=local.stamps,
        pose_ids=pose_ids,
        feature_labels=labels,
        feature_ids=feature_ids,
        gauge_factor=find_gauge_factor(problem, int(pose_ids[0])),
        feature_covariances=(
            SelectedInverse(factorize_at_estimate(problem)).blocks(problem, feature_ids)
            if with_covariances
            else None
        ),
    )


@dataclass
class RobotMaps:
    """The solved local maps :func:`run_csam` joins, with the rendezvous logs after thinning
    and what was left out."""

    maps: list[RobotMap]
    rendezvous_logs: dict[str, RendezvousLog]
    left_out: list[str]  # notes: robots without a local map, and why
    thinned: FilterReport
    seconds: float  # building time


def thinned_rendezvous(
    log: MultiRobotLog, config: CsamConfig
) -> tuple[dict[str, RendezvousLog], FilterReport]:
    """Every robot's rendezvous measurements as its smoother keeps them (``config``'s
    thinning), and what the thinning left out."""
    thinning = config.thinning()
    return thin_rendezvous(
        {n: r.rendezvous for n, r in log.robots.items()},
        thinning.min_interval,
        thinning.max_per_pair,
    )


def build_robot_maps(
    log: MultiRobotLog,
    config: CsamConfig | None = None,
    local_map: LocalMapConfig | None = None,
) -> RobotMaps:
    """Every robot's local map from its log, with a pose at the stamp of every kept
    rendezvous measurement that involves it (thinning as the smoothers do).

    A robot with fewer than two odometry samples, or whose local solve fails or is not
    finite, gets no local map: it is named in ``left_out``."""
    config = config or CsamConfig()
    local_map = local_map or LocalMapConfig()
    start = time.perf_counter()
    logs, thinned = thinned_rendezvous(log, config)
    stamps = required_stamps(logs)
    maps: list[RobotMap] = []
    left_out: list[str] = []
    for name, robot in log.robots.items():
        samples = len(robot.odometry.stamps)
        if samples < 2:
            left_out.append(
                f"{name}: no local map: {samples} usable odometry sample(s), a map needs two"
            )
            continue
        try:
            # values beyond floating point range end here as an error, not as warnings
            with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
                local = build_local_map(
                    replace(robot, rendezvous=logs[name]),
                    stamps[name],
                    local_map.options(),
                    window=local_map.window,
                )
            if not (np.isfinite(local.poses).all() and np.isfinite(local.landmarks).all()):
                raise FloatingPointError("the solution is not finite")
        except (ValueError, FloatingPointError, np.linalg.LinAlgError) as err:
            left_out.append(f"{name}: no local map: its solve failed ({err})")
            continue
        maps.append(robot_map_from_local_map(local))
    return RobotMaps(maps, dict(logs), left_out, thinned, time.perf_counter() - start)


def run_csam(
    log: MultiRobotLog,
    config: CsamConfig | None = None,
    local_map: LocalMapConfig | None = None,
) -> CsamResult:
    """:func:`build_robot_maps` then :func:`join_maps`; ``timing_s["local_maps"]`` is the
    building time. A robot without a local map is left out of the joining, as the merger
    leaves out a robot whose local map never arrives, and named in the result's ``notes``.
    ValueError when no robot is left."""
    config = config or CsamConfig()
    built = build_robot_maps(log, config, local_map)
    if not built.maps:
        raise ValueError("no robot has a local map: " + "; ".join(built.left_out))
    result = join_maps(built.maps, built.rendezvous_logs, config)
    result.notes[:0] = built.left_out
    thinning = config.thinning()
    if thinning.min_interval > 0 or thinning.max_per_pair is not None:
        result.rendezvous_filter["thinning"] = built.thinned
    result.timing_s["local_maps"] = built.seconds
    result.timing_s["total"] += built.seconds
    return result
