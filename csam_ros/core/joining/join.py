"""C-SAM's join of solved local maps, in the paper's steps (section IV; docs/METHOD.md
sections 5-7).

:func:`join_maps` takes the robots' solved local maps (:class:`~csam_ros.core.smoothing.
robot_map.RobotMap`, in the robots' order; the first is the reference) and their rendezvous
logs, and runs these steps, each a function of this module:

1. :func:`check_local_maps`: each local map against its own measurements (section 6.5).
2. :func:`filter_rendezvous`, :func:`rendezvous_measurements`: the rendezvous measurements
   kept and matched to local-map poses (sections 5 and 9).
3. The local views (:mod:`csam_ros.core.joining.local_views`): from each local map only its
   rendezvous part, the marginal square-root information of its rendezvous poses, and the
   cross covariance of its features with them (sections 4.5 and 6.4).
4. :func:`align_maps`: base-node initialisation and Algorithm 1 (section 5); robots that
   cannot be aligned stay ``pending: <reason>`` and get no joined map.
5. :func:`associate_features`: Algorithm 2 (section 6.1).
6. :func:`solve_jointly`: one joint solve of all poses and features of the aligned robots
   (section 6.2); run beside step 5 on the last join's associations, and kept when step 5
   finds them again (:class:`JointSolveAhead`, section 6.4).
7. :func:`joint_marginals`, :func:`robot_results`, :func:`joined_features`: the marginal
   covariances the summary reports, from a selected inverse of each factor
   (:class:`~csam_ros.core.sam.selected_inverse.SelectedInverse`), never from the dense inverse,
   and the :class:`~csam_ros.core.joining.result.CsamResult` (section 6.3).
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
from numpy.typing import NDArray

from csam_ros.core.joining.alignment import Alignment, RendezvousPart, align
from csam_ros.core.joining.association import (
    AssociationOptions,
    Associations,
    MapFeatures,
    associate,
)
from csam_ros.core.joining.config import CsamConfig
from csam_ros.core.joining.joint_solve import (
    JointSolution,
    aligned_clusters,
    heading_sigmas,
    joint_solve,
)
from csam_ros.core.joining.local_views import (
    LocalFactor,
    LocalView,
    LocalViewCache,
    in_threads,
    map_features,
)
from csam_ros.core.joining.notes import Note
from csam_ros.core.joining.rendezvous_filters import (
    FilterReport,
    consistent_rendezvous,
    select_rendezvous,
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
from csam_ros.core.model.log import RendezvousLog
from csam_ros.core.model.rendezvous import RendezvousSet, collect
from csam_ros.core.sam.covariance import covariance_block, factorize_at_estimate
from csam_ros.core.sam.normal_equations import NormalEquations
from csam_ros.core.sam.selected_inverse import BlockInverse, SelectedInverse
from csam_ros.core.sam.solver import Problem, SolveReport
from csam_ros.core.smoothing.robot_map import RobotMap

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]


def join_maps(
    maps: Sequence[RobotMap],
    rendezvous_logs: Mapping[str, RendezvousLog],
    config: CsamConfig | None = None,
    previous: CsamResult | None = None,
    cache: LocalViewCache | None = None,
    overlap: bool = True,
    last: CsamResult | None = None,
) -> CsamResult:
    """Run C-SAM on solved local maps (the first map's robot is the reference).

    ``previous``, the result of an earlier join with the same reference, gives the initial
    values (:mod:`csam_ros.core.joining.warm_start`); ``cache`` keeps each map's
    :class:`~csam_ros.core.joining.local_views.LocalView` between calls. Neither changes the
    problem solved: converged, the result is the same as without them. With ``overlap``, the
    joint solve starts beside Algorithm 2 on the associations of ``last`` (a join of the same
    robots, by default ``previous``; :class:`JointSolveAhead`): the result is the same as
    without it."""
    config = config or CsamConfig()
    names = _robot_names(maps)
    cache = cache or LocalViewCache()
    warm = None
    if previous is not None and previous.reference == names[0]:
        warm = WarmStart.from_result(previous)
    clock = StepTimes()
    checks = check_local_maps(maps, config, cache)
    clock.lap("local_map_checks")
    logs, rendezvous_filter = filter_rendezvous(maps, rendezvous_logs, config)
    measurements, notes = rendezvous_measurements(maps, logs, config)
    views = cache.views(maps, rendezvous_poses(measurements))
    clock.lap("local_rendezvous_parts")
    notes += local_map_notes(names, checks)
    alignment = align_maps(maps, views, measurements, checks, config, warm)
    aligned = [r for r in range(len(maps)) if alignment.aligned(r)]
    clock.lap("alignment")
    in_threads(lambda view: view.factor.with_marginals(), views)  # the summary reports them
    clock.lap("local_marginals")
    associations = Associations([], [])
    ahead: JointSolveAhead | None = None
    if config.associate and len(aligned) > 1:
        last = last or previous
        if last is not None and overlap and (os.cpu_count() or 1) > 1:

            def solve(expected: Associations) -> tuple[JointSolution, JointMarginals]:
                solution = solve_jointly(
                    maps, aligned, alignment, expected, measurements, config, warm
                )
                return solution, joint_marginals(solution, maps, views)

            ahead = JointSolveAhead(merged_features(last, names), aligned, solve)
        associations = associate_features(
            maps, views, alignment, aligned, checks, config, measurements
        )
        clock.lap("association")
    solved = ahead.result(associations.clusters) if ahead is not None else None
    if solved is None:
        solution = solve_jointly(maps, aligned, alignment, associations, measurements, config, warm)
        clock.lap("joint_solve")
        marginals = joint_marginals(solution, maps, views)
    else:
        solution, marginals = solved
        clock.lap("joint_solve")
    clock.lap("joint_base_node_covariance")
    robots = robot_results(maps, views, checks, alignment, solution, marginals)
    features = joined_features(names, solution, marginals)
    clock.lap("joint_marginals")
    notes += convergence_notes(alignment, solution.report)
    return CsamResult(
        reference_frame=f"{names[0]}/map",
        robots=robots,
        features=features,
        associations=association_records(names, associations),
        timing_s=clock.with_total(),
        notes=notes,
        statistics=join_statistics(
            alignment, associations, solution, measurements, solved_ahead=solved is not None
        ),
        rendezvous_filter=rendezvous_filter,
    )


def _robot_names(maps: Sequence[RobotMap]) -> list[str]:
    """The robots' names, in order; ValueError without maps or with a name twice."""
    if not maps:
        raise ValueError("join_maps: no local maps")
    names = [m.name for m in maps]
    if len(set(names)) != len(names):
        raise ValueError(f"join_maps: duplicate robot names {names}")
    return names


@dataclass
class StepTimes:
    """Seconds of each step of a join (``CsamResult.timing_s``), each step timed from the end
    of the one before."""

    seconds: dict[str, float] = field(default_factory=dict)
    last: float = field(default_factory=time.perf_counter)

    def lap(self, step: str) -> None:
        """The time since the last lap goes to ``step``."""
        now = time.perf_counter()
        self.seconds[step] = self.seconds.get(step, 0.0) + now - self.last
        self.last = now

    def with_total(self) -> dict[str, float]:
        """The seconds of each step and, under ``total``, their sum."""
        self.seconds["total"] = sum(self.seconds.values())
        return self.seconds


# --------------------------------------------------------------------------- 1. local maps


def check_local_maps(
    maps: Sequence[RobotMap], config: CsamConfig, cache: LocalViewCache
) -> dict[int, LocalMapCheck]:
    """Each local map checked against its own measurements at its own solution
    (docs/METHOD.md section 6.5), by robot index; none when ``config`` turns the check off."""
    if not config.check_local_maps:
        return {}
    options = config.consistency_options()
    return {r: cache.check(m, options) for r, m in enumerate(maps)}


def local_map_notes(names: Sequence[str], checks: Mapping[int, LocalMapCheck]) -> list[Note]:
    """What the local-map checks decided (docs/METHOD.md section 6.5): a robot whose map
    failed stays pending (the reference is kept), features that failed are not associated."""
    notes: list[Note] = []
    for r, check in checks.items():
        if check.reason:
            notes.append(Note.local_map_inconsistent(names[r], check.reason, reference=r == 0))
        if check.inconsistent_features:
            notes.append(Note.features_not_associated(names[r], check.inconsistent_features))
    return notes


# --------------------------------------------------------------------------- 2. rendezvous


def filter_rendezvous(
    maps: Sequence[RobotMap], logs: Mapping[str, RendezvousLog], config: CsamConfig
) -> tuple[Mapping[str, RendezvousLog], dict[str, FilterReport]]:
    """The rendezvous filters of the join (docs/METHOD.md section 9): the consistency check of
    ``config`` (:func:`csam_ros.core.joining.rendezvous_filters.consistent_rendezvous`) against
    the local maps' trajectories. Thinning is not done here: it decides where the local maps hold
    poses, so the smoothers (online) and :func:`~csam_ros.core.joining.pipeline.run_csam`
    (offline) apply it. First, a measurement stamped before the first or after the last pose of
    its observer's or observed robot's map can have no pose there (clocks that differ between
    robots; online, also a map that has not caught up yet): it is left out and counted in the
    report ``trajectory_span`` under ``outside_trajectory``, per observing robot. Returns the
    kept logs and what was dropped."""
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


def rendezvous_measurements(
    maps: Sequence[RobotMap], logs: Mapping[str, RendezvousLog], config: CsamConfig
) -> tuple[RendezvousSet, list[Note]]:
    """The rendezvous measurements (eq. 22-23) among the robots of ``maps``, each matched by
    its stamp to a pose of the observer's and of the observed robot's map (docs/METHOD.md
    section 5), and notes on the measurements left out."""
    measurements, left_out = collect(
        logs,
        {m.name: m.stamps for m in maps},
        config.stamp_tolerance,
        config.skip_missing_poses,
    )
    return measurements, [Note.rendezvous_left_out(text) for text in left_out]


def rendezvous_poses(measurements: RendezvousSet) -> list[IntArray]:
    """Each robot's rendezvous poses ``rho_r`` (docs/METHOD.md section 5): the indices of its
    local-map poses that observe or are observed in a measurement, sorted."""
    return [
        np.unique(
            np.concatenate(
                [
                    measurements.observer_pose[measurements.observer == r],
                    measurements.observed_pose[measurements.observed == r],
                ]
            )
        )
        for r in range(len(measurements.robots))
    ]


# --------------------------------------------------------------------------- 4. Algorithm 1


def align_maps(
    maps: Sequence[RobotMap],
    views: Sequence[LocalView],
    measurements: RendezvousSet,
    checks: Mapping[int, LocalMapCheck],
    config: CsamConfig,
    warm: WarmStart | None,
) -> Alignment:
    """Base-node initialisation (eq. 18-19) and Algorithm 1 (eq. 25) on the local maps'
    rendezvous parts (paper section IV-A; docs/METHOD.md section 5), started where the
    previous join ended when ``warm`` (section 6.4). A robot whose local map failed its check
    (section 6.5), but the reference, is not placed."""
    parts = [v.part for v in views]
    return align(
        parts,
        measurements,
        config.alignment_options(),
        start=warm.base_node_starts([m.name for m in maps]) if warm is not None else None,
        rendezvous_start=None
        if warm is None
        else _rendezvous_starts(warm, maps, parts, config.stamp_tolerance),
        excluded={r: c.reason for r, c in checks.items() if c.reason and r > 0},
    )


def _rendezvous_starts(
    warm: WarmStart,
    maps: Sequence[RobotMap],
    parts: Sequence[RendezvousPart | None],
    tolerance: float,
) -> list[Array | None]:
    """Where each robot's rendezvous poses start Algorithm 1 warm (docs/METHOD.md 6.4)."""
    return [
        None
        if p is None
        else warm.rendezvous_start(
            m.name, np.asarray(m.stamps, dtype=float)[p.pose_indices], p.poses, tolerance
        )
        for m, p in zip(maps, parts, strict=True)
    ]


# --------------------------------------------------------------------------- 5. Algorithm 2


def associate_features(
    maps: Sequence[RobotMap],
    views: Sequence[LocalView],
    alignment: Alignment,
    aligned: Sequence[int],
    checks: Mapping[int, LocalMapCheck],
    config: CsamConfig,
    measurements: RendezvousSet,
) -> Associations:
    """Algorithm 2 (paper section IV-B, eq. 26; docs/METHOD.md section 6.1) over the features
    of the ``aligned`` robots, but those that failed their map's check (section 6.5); robots
    that measured each other (``measurements``) compared first."""
    features: list[MapFeatures | None] = [None] * len(maps)
    for r in aligned:
        left_out = checks[r].inconsistent_features if r in checks else []
        features[r] = map_features(maps[r], views[r], left_out)
    return associate(
        features,
        alignment,
        [v.part.sqrt_information if v.part is not None else None for v in views],
        AssociationOptions(chi2_gate=config.chi2_gate),
        met={
            (min(a, c), max(a, c))
            for a, c in zip(
                measurements.observer.tolist(), measurements.observed.tolist(), strict=True
            )
        },
    )


# --------------------------------------------------------------------------- 6. joint solve


def solve_jointly(
    maps: Sequence[RobotMap],
    aligned: list[int],
    alignment: Alignment,
    associations: Associations,
    measurements: RendezvousSet,
    config: CsamConfig,
    warm: WarmStart | None,
) -> JointSolution:
    """The joint solve of every pose and feature of the ``aligned`` robots, the last step of
    Algorithm 2 (docs/METHOD.md section 6.2), started from the previous join when ``warm``
    (section 6.4)."""
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
    return joint_solve(
        maps,
        aligned,
        alignment.base_nodes,
        associations.clusters,
        measurements,
        config.solver_options(),
        initial_poses,
        initial_features,
    )


def merged_features(result: CsamResult, names: Sequence[str]) -> list[list[tuple[int, int]]]:
    """The merged features of ``result`` as ``(index in names, label)`` members, without
    robots not in ``names``."""
    index = {name: r for r, name in enumerate(names)}
    split = [[m.rsplit("/", 1) for m in f.members] for f in result.features if len(f.members) > 1]
    return [[(index[n], int(label)) for n, label in members if n in index] for members in split]


class JointSolveAhead:
    """The joint solve and its marginals of a join, run in a thread while Algorithm 2 runs,
    on the associations it is expected to find again: the last join's (docs/METHOD.md
    section 6.4). That work releases the interpreter lock for most of its time (sparse
    factorisations, large array operations), so on a second core it costs the join little.
    :meth:`result` gives it when Algorithm 2 found the same clusters (the joint problem is
    then the same: :func:`~csam_ros.core.joining.joint_solve.aligned_clusters`), else None,
    and the join solves on what Algorithm 2 found."""

    def __init__(
        self,
        expected: list[list[tuple[int, int]]],
        aligned: list[int],
        solve: Callable[[Associations], tuple[JointSolution, JointMarginals]],
    ) -> None:
        self.aligned = aligned
        self.clusters = aligned_clusters(expected, aligned)

        def ahead() -> tuple[JointSolution, JointMarginals]:
            solution, marginals = solve(Associations([], self.clusters))
            marginals.inverse  # noqa: B018  (its selected inverse, here beside Algorithm 2)
            return solution, marginals

        pool = ThreadPoolExecutor(1, thread_name_prefix="csam-joint")
        self._future = pool.submit(ahead)
        pool.shutdown(wait=False)  # a join given up leaves the thread to finish alone

    def result(
        self, clusters: Sequence[Sequence[tuple[int, int]]]
    ) -> tuple[JointSolution, JointMarginals] | None:
        """The solve and marginals when ``clusters`` (Algorithm 2's) are the expected ones."""
        if aligned_clusters(clusters, self.aligned) != self.clusters:
            return None
        return self._future.result()


# --------------------------------------------------------------------------- 7. the result


@dataclass
class JointMarginals:
    """Where the joined map's marginals come from (docs/METHOD.md section 6.3): the factor
    of the joint problem at its solution or, when that is the reference's local problem at
    its local estimate, the reference's local factor (``alone``)."""

    problem: Problem
    system: NormalEquations  # factorised at the estimate
    pose_ids: dict[int, IntArray]  # robot -> ids of its poses in ``problem``
    base_covariances: dict[int, Array]  # aligned robot -> (3, 3) covariance of its first pose
    alone: LocalFactor | None

    @cached_property
    def inverse(self) -> SelectedInverse | BlockInverse:
        """The selected inverse of ``system`` (by blocks when it was factored by blocks)."""
        if self.alone is not None:
            return self.alone.inverse
        if self.system.block_factor is not None:
            return BlockInverse(self.system.block_factor)
        return SelectedInverse(self.system)

    def feature_covariances(self, solution: JointSolution) -> Array:
        """(F, 2, 2) marginal covariances of the joined features (``solution.features``)."""
        if self.alone is not None:
            return self.alone.feature_covariances
        return self.inverse.blocks(solution.problem, solution.feature_var_ids)


def joint_marginals(
    solution: JointSolution, maps: Sequence[RobotMap], views: Sequence[LocalView]
) -> JointMarginals:
    """The joint problem factorised at its solution and the covariance of each aligned
    robot's first pose, its base node (docs/METHOD.md section 6.3). The reference joined
    alone at its local estimate (no rendezvous rows, nothing to associate) takes its local
    view's factor: there the local marginals are the joint ones."""
    if solution.robots == [0] and _at_local_estimate(solution, maps[0]):
        m = maps[0]
        return JointMarginals(
            m.problem,
            views[0].factor.system,
            {0: m.pose_ids},
            {0: np.zeros((3, 3))},
            views[0].factor,
        )
    joint, aligned = solution.problem, solution.robots
    marginals = JointMarginals(joint, factorize_at_estimate(joint), solution.pose_ids, {}, None)
    first = np.array([solution.pose_ids[r][0] for r in aligned], dtype=np.int64)
    if marginals.system.block_factor is not None:  # its selected inverse holds them
        base_cov = marginals.inverse.blocks(joint, first)
    else:  # a few columns of the inverse, cheaper than qdldl's selected inverse
        scalars = joint.scalar_indices(first)
        blocks = covariance_block(marginals.system, scalars).reshape(len(aligned), 3, -1, 3)
        base_cov = blocks[np.arange(len(aligned)), :, np.arange(len(aligned)), :]
    marginals.base_covariances.update(zip(aligned, base_cov, strict=True))
    return marginals


def _at_local_estimate(solution: JointSolution, m: RobotMap, tolerance: float = 1e-6) -> bool:
    """Whether the joint solve left robot ``m``'s (the reference's) poses and features within
    ``tolerance`` (m, rad) of its local estimate (marginals there differ by as little)."""
    joint = solution.problem
    moved = np.abs(joint.values_of(solution.pose_ids[0]) - m.poses).max(initial=0.0)
    if len(m.feature_ids):
        features = joint.values_of(solution.feature_ids[0]) - m.feature_positions
        moved = max(moved, np.abs(features).max())
    return moved <= tolerance


def robot_results(
    maps: Sequence[RobotMap],
    views: Sequence[LocalView],
    checks: Mapping[int, LocalMapCheck],
    alignment: Alignment,
    solution: JointSolution,
    marginals: JointMarginals,
) -> dict[str, RobotResult]:
    """Each robot's local estimate with its local marginals and, when aligned, its joined
    poses, heading sigmas and base node (docs/METHOD.md section 6.3)."""
    robots: dict[str, RobotResult] = {}
    for r, m in enumerate(maps):
        stamps = np.asarray(m.stamps, dtype=float)
        result = RobotResult(
            name=m.name,
            alignment=alignment.status[r],
            stamps=stamps,
            poses_local=m.poses,
            sigma_phi_local=views[r].factor.sigma_phi,
            alignment_method=alignment.methods.get(r, ""),
            rendezvous_stamps=stamps[views[r].rendezvous_poses],
            alignment_rendezvous_poses=alignment.rendezvous_poses.get(r),
            feature_labels_local=np.asarray(m.feature_labels, dtype=np.int64),
            features_local=m.feature_positions,
            feature_covariances_local=views[r].factor.feature_covariances,
            local_check=checks.get(r),
            odometry_calibration=m.odometry_calibration,
        )
        if alignment.aligned(r):
            _add_joined(result, r, m, alignment, solution, marginals)
        robots[m.name] = result
    return robots


def _add_joined(
    result: RobotResult,
    r: int,
    m: RobotMap,
    alignment: Alignment,
    solution: JointSolution,
    marginals: JointMarginals,
) -> None:
    """Aligned robot ``r``'s joined poses, heading sigmas (in its own frame and in the
    reference frame) and base node with its covariance, from the joint solve and from
    Algorithm 1 (docs/METHOD.md section 6.3)."""
    poses = solution.problem.values_of(solution.pose_ids[r])
    in_reference, own = heading_sigmas(
        marginals.problem, marginals.system, marginals.pose_ids[r], marginals.inverse
    )
    result.poses_joined = poses
    result.sigma_phi_joined = own
    result.sigma_phi_joined_reference = in_reference
    if r == 0:
        result.base_node = np.zeros(3)
        result.base_node_cov = np.zeros((3, 3))
    else:
        # G_r is defined by the robot's first pose (docs/METHOD.md section 6.2)
        result.base_node = se2.compose(poses[0], se2.inverse(m.poses[0]))
        result.base_node_cov = marginals.base_covariances[r]
        result.alignment_base_node = alignment.base_nodes[r].copy()
        result.alignment_base_node_cov = alignment.base_covariance(r).copy()


def joined_features(
    names: Sequence[str], solution: JointSolution, marginals: JointMarginals
) -> list[FeatureResult]:
    """The features of the joined map in the reference frame, with their members
    ``robot/label`` and marginal covariances (docs/METHOD.md section 6.3)."""
    covariances = marginals.feature_covariances(solution)
    ids = solution.feature_var_ids
    xy = solution.problem.values_of(ids) if len(ids) else []
    return [
        FeatureResult([f"{names[r]}/{label}" for r, label in members], xy[i], covariances[i])
        for i, members in enumerate(solution.features)
    ]


def association_records(
    names: Sequence[str], associations: Associations
) -> list[AssociationRecord]:
    """Each accepted association with its Mahalanobis distance (eq. 26)."""
    return [
        AssociationRecord(
            f"{names[mt.robot_a]}/{mt.label_a}", f"{names[mt.robot_c]}/{mt.label_c}", mt.mahalanobis
        )
        for mt in associations.matches
    ]


def convergence_notes(alignment: Alignment, report: SolveReport) -> list[Note]:
    """A note for Algorithm 1 and one for the joint solve when it stopped unconverged."""
    notes: list[Note] = []
    if not alignment.converged:
        notes.append(
            Note.not_converged_alignment(
                alignment.stop_reason, alignment.iterations, alignment.final_cost
            )
        )
    if not report.converged:
        notes.append(Note.not_converged_joint(report.reason, report.iterations, report.final_cost))
    return notes


def join_statistics(
    alignment: Alignment,
    associations: Associations,
    solution: JointSolution,
    measurements: RendezvousSet,
    solved_ahead: bool = False,
) -> dict[str, float]:
    """The counts of the join (``CsamResult.statistics``): iterations and convergence of
    Algorithm 1 and of the joint solve, whether the joint solve ran beside Algorithm 2
    (:class:`JointSolveAhead`), association counts, rendezvous measurements."""
    report = solution.report
    return {
        "algorithm1_iterations": alignment.iterations,
        "algorithm1_converged": float(alignment.converged),
        "algorithm1_warm_start": float(alignment.warm_start),
        "joint_iterations": report.iterations,
        "joint_converged": float(report.converged),
        "joint_warm_start": float(solution.warm_start),
        "joint_solve_ahead": float(solved_ahead),
        "joint_final_cost": report.final_cost,
        "association_candidates": associations.candidates,
        "association_gated": associations.gated,
        "association_rejected_conflicts": associations.rejected_conflicts,
        "association_rejected_incompatible": associations.rejected_incompatible,
        "rendezvous_measurements": len(measurements),
    }
