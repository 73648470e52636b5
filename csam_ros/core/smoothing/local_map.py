"""One robot's local map by square-root smoothing, fed online (offline, from a whole log:
:func:`csam_ros.core.smoothing.local_map_build.build_local_map`).

The map lives in the robot's frame ``G_r``: its first pose (at the first odometry stamp) is
the origin, fixed by a pose prior of sigma ``gauge_sigma`` (far below every other sigma).

Key poses are held at: the first odometry stamp, every feature-scan stamp, every requested
stamp (rendezvous: the robot's own observations of others and other robots' observations of
it, which may arrive late) and, optionally, a regular grid ``t0 + k * key_interval`` so that
the path is sampled during stretches without observations (only where odometry samples are at
most ``key_interval`` apart: none inside a gap in the odometry, whatever its length). Stamps
closer than ``stamp_tolerance`` share one key pose. Odometry samples between consecutive keys
are composed into one relative-pose factor (:func:`csam_ros.core.model.motion.odometry_between`); a
key inserted in the past splits the factor of its interval (exact for the mean); odometry
inputs may be correlated (:class:`~csam_ros.core.model.log.OdometryLog`). Features give Cartesian
observation factors (docs/METHOD.md section 3), and so do feature points (Cartesian
observations with their own 2x2 covariance, :meth:`LocalMap.add_points`); a new landmark is
initialised from its first observation.

Update policy (online). Data are buffered as they arrive. :meth:`LocalMap.update` integrates
everything covered by odometry: new keys (appended or inserted in the past) get initial values
by composing odometry from their preceding key's current estimate, new landmarks from their
first observation; then Gauss-Newton runs warm-started from the previous estimate over the
whole map (full relinearisation every iteration; the sparsity pattern and ordering are rebuilt
only because keys or factors were added). An ordinary update stops at ``online_solver``'s
looser tolerance (relative cost decrease 1e-6, at most 10 iterations): the next update
continues from there, so the estimate stays within a small tolerance of the optimum of the
data so far (tested: < 1e-4 m). ``update(converge=True)`` runs to ``solver``'s tolerance, the
batch optimum. :meth:`LocalMap.maybe_update` updates once ``update_period`` seconds of new
odometry have arrived. Measured on the five MR.CLAM robots (about 1,490 s, 95,000-100,000
odometry samples and 3,300-7,100 feature observations each, Cauchy kernel, one update per
second of data): 35-57x real time on a shared 2-core machine, worst update 0.1-0.25 s
(``python -m csam_ros.bench.smoothing --mrclam DIR``).
"""

from __future__ import annotations

import time
from collections.abc import Hashable, Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from csam_ros.core.model import motion, se2, sensor
from csam_ros.core.model.chi_square import chi2_quantile
from csam_ros.core.model.log import RobotLog, correlations_valid
from csam_ros.core.model.stamps import nearest_stamp, regular_stamps
from csam_ros.core.sam.covariance import (
    factorize_at_estimate,
    marginal_covariance,
    marginal_sqrt_information,
)
from csam_ros.core.sam.factors import (
    POINT,
    POSE,
    PointObservation,
    PosePrior,
    RelativePose,
    sqrt_information_from_covariance,
)
from csam_ros.core.sam.normal_equations import NormalEquations
from csam_ros.core.sam.selected_inverse import SelectedInverse
from csam_ros.core.sam.solver import Problem, SolveReport, SolverOptions
from csam_ros.core.smoothing.fold_check import ConsistencyOptions, factor_outliers
from csam_ros.core.smoothing.fold_recovery import robust_odometry_solve, slipped_sample_scale
from csam_ros.core.smoothing.local_map_config import LocalMapOptions
from csam_ros.core.smoothing.local_map_state import LocalMapState, UpdateReport, check_state
from csam_ros.core.smoothing.odometry_calibration import (
    CALIBRATION_ROUNDS,
    OdometryCalibration,
    OdometryCalibrator,
)

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]


class LocalMap:
    """Square-root smoothing of one robot's poses and landmarks (see the module docstring)."""

    def __init__(self, name: str = "robot", options: LocalMapOptions | None = None) -> None:
        self.name = name
        self.options = options or LocalMapOptions()
        # raw data buffers
        self._odo_chunks: list[tuple[Array, Array, Array, Array]] = []
        self._odo_t = np.zeros(0)
        self._odo_u = np.zeros((0, 3))
        self._odo_q = np.zeros((0, 3))
        self._odo_rho = np.zeros((0, 3))
        self._feat_chunks: list[tuple[Array, IntArray, Array, Array]] = []
        self._feat_t = np.zeros(0)
        self._feat_label = np.zeros(0, dtype=np.int64)
        self._feat_z = np.zeros((0, 2))
        self._feat_w = np.zeros((0, 2, 2))
        self._requested: list[float] = []
        # state
        self._keys = np.zeros(0)
        self._key_values = np.zeros((0, 3))
        self._rel = np.zeros((0, 3))
        self._rel_w = np.zeros((0, 3, 3))
        self._calibrator = (
            OdometryCalibrator(self.options) if self.options.odometry_calibration else None
        )
        self._landmark_index: dict[int, int] = {}
        self._landmark_labels: list[int] = []
        self._landmark_values = np.zeros((0, 2))
        self._integrated_features = 0  # features (sorted by stamp) already in the map
        self._dropped_features = 0
        self._last_solved_odometry = -np.inf
        self._problem: Problem | None = None
        self._system: NormalEquations | None = None
        self._inverse: SelectedInverse | None = None
        self.last_report: UpdateReport | None = None
        self.fold_recoveries = 0  # recoveries that scaled some odometry (options.fold_recovery)
        self._next_recovery_keys = 0

    # -- feeding ------------------------------------------------------------------------------

    def add_odometry(
        self,
        stamps: ArrayLike,
        inputs: ArrayLike,
        sigmas: ArrayLike,
        correlations: ArrayLike | None = None,
    ) -> None:
        """Append odometry samples, sorted; sample ``i`` holds the input over ``(t_{i-1}, t_i]``
        (``correlations`` of its input noise as in
        :class:`~csam_ros.core.model.log.OdometryLog`)."""
        t = np.atleast_1d(np.asarray(stamps, dtype=float))
        u = np.asarray(inputs, dtype=float).reshape(len(t), 3)
        q = np.asarray(sigmas, dtype=float).reshape(len(t), 3)
        rho = (
            np.zeros((len(t), 3))
            if correlations is None
            else np.asarray(correlations, dtype=float).reshape(len(t), 3)
        )
        if len(t) == 0:
            return
        motion.check_odometry(t, u, q)
        if not (q > 0).all():
            bad = np.flatnonzero((q <= 0).any(axis=1))
            raise ValueError(
                f"{self.name}: odometry sample {bad[0]} has a non-positive sigma "
                f"{q[bad[0]].tolist()}; the motion model needs s_v, s_vlat, s_omega > 0"
            )
        bad = np.flatnonzero(~correlations_valid(rho)) if correlations is not None else ()
        if len(bad):
            raise ValueError(
                f"{self.name}: odometry sample {bad[0]}: correlations {rho[bad[0]].tolist()} "
                "do not give a positive definite covariance"
            )
        last = self._last_odometry_stamp()
        if t[0] <= last:
            raise ValueError(
                f"{self.name}: odometry stamp {t[0]} does not follow the previous one {last}"
            )
        self._odo_chunks.append((t, u, q, rho))

    def add_features(
        self,
        stamps: ArrayLike,
        labels: ArrayLike,
        ranges: ArrayLike,
        bearings: ArrayLike,
        sigma_range: ArrayLike,
        sigma_bearing: ArrayLike,
    ) -> None:
        """Add range-bearing observations of labelled point features (any stamp order): as
        Cartesian points with their first-order covariance (:meth:`add_points`)."""
        t = np.atleast_1d(np.asarray(stamps, dtype=float))
        if len(t) == 0:
            return
        z, cov = sensor.polar_to_cartesian(ranges, bearings, sigma_range, sigma_bearing)
        self.add_points(t, labels, z, cov)

    def add_points(
        self, stamps: ArrayLike, labels: ArrayLike, points: ArrayLike, covariances: ArrayLike
    ) -> None:
        """Add Cartesian observations of labelled point features: positions ``(K, 2)`` in the
        body frame with covariances ``(K, 2, 2)`` (any stamp order)."""
        t = np.atleast_1d(np.asarray(stamps, dtype=float))
        if len(t) == 0:
            return
        if not np.all(np.isfinite(t)):
            bad = np.flatnonzero(~np.isfinite(t))[0]
            raise ValueError(f"{self.name}: feature observation {bad}: stamp is not finite")
        lab = np.atleast_1d(np.asarray(labels)).astype(np.int64)
        z = np.asarray(points, dtype=float).reshape(-1, 2)
        cov = np.asarray(covariances, dtype=float).reshape(-1, 2, 2)
        if not len(z) == len(cov) == len(t) == len(lab):
            raise ValueError(f"{self.name}: feature observation arrays have different lengths")
        bad = np.flatnonzero(~np.isfinite(z).all(axis=1))
        if bad.size:
            raise ValueError(f"{self.name}: feature observation {bad[0]} is not finite")
        w = sqrt_information_from_covariance(cov, f"{self.name} feature observations")
        self._feat_chunks.append((t, lab, z, w))

    def request_poses(self, stamps: ArrayLike) -> None:
        """Ask for key poses at these stamps (rendezvous, also ones observed by others)."""
        t = np.atleast_1d(np.asarray(stamps, dtype=float))
        if not np.all(np.isfinite(t)):
            raise ValueError(f"{self.name}: requested pose stamps must be finite")
        self._requested.extend(t.tolist())

    def add_log(self, log: RobotLog, extra_pose_stamps: ArrayLike = ()) -> None:
        """Feed a whole robot log; its own rendezvous stamps are requested as poses."""
        self.add_log_part(log)
        self.request_poses(log.rendezvous.stamps)
        self.request_poses(extra_pose_stamps)

    def add_log_part(
        self,
        log: RobotLog,
        odometry: slice | ArrayLike = slice(None),
        features: slice | ArrayLike = slice(None),
        points: slice | ArrayLike = slice(None),
    ) -> None:
        """Add the odometry samples, feature observations and feature points of ``log`` that
        ``odometry``, ``features`` and ``points`` select (slices, boolean masks or index
        arrays); no pose is requested."""
        o, f, p = log.odometry, log.features, log.points
        rho = None if o.correlations is None else o.correlations[odometry]
        self.add_odometry(o.stamps[odometry], o.inputs[odometry], o.sigmas[odometry], rho)
        self.add_features(
            f.stamps[features],
            f.labels[features],
            f.ranges[features],
            f.bearings[features],
            f.sigma_range[features],
            f.sigma_bearing[features],
        )
        self.add_points(p.stamps[points], p.labels[points], p.points[points], p.covariances[points])

    # -- updating -----------------------------------------------------------------------------

    def _last_odometry_stamp(self) -> float:
        if self._odo_chunks:
            return float(self._odo_chunks[-1][0][-1])
        return float(self._odo_t[-1]) if len(self._odo_t) else -np.inf

    def _consolidate(self) -> None:
        if self._odo_chunks:
            self._odo_t = np.concatenate([self._odo_t, *(c[0] for c in self._odo_chunks)])
            self._odo_u = np.concatenate([self._odo_u, *(c[1] for c in self._odo_chunks)])
            self._odo_q = np.concatenate([self._odo_q, *(c[2] for c in self._odo_chunks)])
            self._odo_rho = np.concatenate([self._odo_rho, *(c[3] for c in self._odo_chunks)])
            self._odo_chunks = []
        if self._feat_chunks:
            done = self._integrated_features
            t = np.concatenate([self._feat_t[done:], *(c[0] for c in self._feat_chunks)])
            lab = np.concatenate([self._feat_label[done:], *(c[1] for c in self._feat_chunks)])
            z = np.concatenate([self._feat_z[done:], *(c[2] for c in self._feat_chunks)])
            w = np.concatenate([self._feat_w[done:], *(c[3] for c in self._feat_chunks)])
            order = np.argsort(t, kind="stable")
            self._feat_t = np.concatenate([self._feat_t[:done], t[order]])
            self._feat_label = np.concatenate([self._feat_label[:done], lab[order]])
            self._feat_z = np.concatenate([self._feat_z[:done], z[order]])
            self._feat_w = np.concatenate([self._feat_w[:done], w[order]])
            self._feat_chunks = []

    def maybe_update(self) -> UpdateReport | None:
        """Update if ``update_period`` seconds of odometry arrived since the last solve."""
        if self._last_odometry_stamp() - self._last_solved_odometry < self.options.update_period:
            return None
        return self.update()

    def update(self, converge: bool = False) -> UpdateReport:
        """Integrate all data covered by odometry and solve (warm-started Gauss-Newton).

        With ``converge`` the solve runs to ``options.solver``'s tolerance (the batch
        optimum); otherwise with ``options.online_solver`` (looser, capped iterations: the
        next update continues from where this one stopped).
        """
        start = time.perf_counter()
        self._consolidate()
        tol = self.options.stamp_tolerance
        if len(self._odo_t) < 2:
            return UpdateReport(0, 0, 0, 0, None, time.perf_counter() - start)
        t0, t_end = float(self._odo_t[0]), float(self._odo_t[-1])
        first_new_feature = self._integrated_features
        # features stamped before the first odometry sample cannot be attached to a pose
        early = first_new_feature + np.searchsorted(
            self._feat_t[first_new_feature:], t0 - tol, side="left"
        )
        if early > first_new_feature:
            self._dropped_features += int(early - first_new_feature)
            keep = np.r_[np.arange(first_new_feature), np.arange(early, len(self._feat_t))]
            self._feat_t = self._feat_t[keep]
            self._feat_label = self._feat_label[keep]
            self._feat_z = self._feat_z[keep]
            self._feat_w = self._feat_w[keep]
        covered = first_new_feature + int(
            np.searchsorted(self._feat_t[first_new_feature:], t_end + tol, side="right")
        )
        candidates = [np.array([t0]), self._feat_t[first_new_feature:covered]]
        req = np.asarray(self._requested, dtype=float)
        candidates.append(req[(req >= t0 - tol) & (req <= t_end + tol)])
        if self.options.key_interval:
            # grid keys of the samples before the last update are keys already (or in a gap)
            since = max(int(np.searchsorted(self._odo_t, self._last_solved_odometry)) - 1, 0)
            candidates.append(regular_stamps(self._odo_t[since:], self.options.key_interval, t0))
        cand = np.clip(np.unique(np.concatenate(candidates)), t0, t_end)
        new_keys = self._new_key_stamps(cand, tol)
        inserted = self._insert_keys(new_keys)
        covered = self._with_key_pose(first_new_feature, covered)
        new_landmarks, new_obs = self._integrate_features(covered)
        solve = self._solve(
            self.options.solver if converge else self.options.online_solver, converge
        )
        if self.options.fold_recovery and len(self._keys) > 1 and self._recover_fold():
            self.fold_recoveries += 1
        self._last_solved_odometry = t_end
        self.last_report = UpdateReport(
            new_poses=len(new_keys),
            inserted_poses=inserted,
            new_landmarks=new_landmarks,
            new_observations=new_obs,
            solve=solve,
            seconds=time.perf_counter() - start,
        )
        return self.last_report

    def _new_key_stamps(self, candidates: Array, tol: float) -> Array:
        """Candidates not within ``tol`` of an existing key, clustered (first of a cluster)."""
        if len(self._keys):
            pos = np.searchsorted(self._keys, candidates)
            near_next = np.abs(self._keys[np.minimum(pos, len(self._keys) - 1)] - candidates)
            near_prev = np.abs(self._keys[np.maximum(pos - 1, 0)] - candidates)
            candidates = candidates[np.minimum(near_next, near_prev) > tol]
        # each key starts a cluster and takes the candidates within ``tol`` after it (not a
        # chain of steps of ``tol`` each, which would leave stamps too far from their key)
        starts: list[float] = []
        for stamp in candidates.tolist():
            if not starts or stamp - starts[-1] > tol:
                starts.append(stamp)
        return np.asarray(starts, dtype=float)

    def _insert_keys(self, new_keys: Array) -> int:
        """Add key poses, recompute the odometry factors of changed intervals; count inserts."""
        if len(new_keys) == 0:
            return 0
        old = self._keys
        keys = np.union1d(old, new_keys)
        is_new = ~np.isin(keys, old)
        if len(old) == 0:
            values = np.zeros((len(keys), 3))
            changed_runs = [(0, len(keys) - 1)] if len(keys) > 1 else []
            inserted = 0
        else:
            values = np.zeros((len(keys), 3))
            values[~is_new] = self._key_values
            # an interval changes when either end is new: runs between consecutive old keys
            old_pos = np.flatnonzero(~is_new)
            changed_runs = []
            for a, b in zip(old_pos[:-1], old_pos[1:], strict=True):
                if b - a > 1:
                    changed_runs.append((int(a), int(b)))
            if old_pos[-1] < len(keys) - 1:
                changed_runs.append((int(old_pos[-1]), len(keys) - 1))
            inserted = int(is_new[: old_pos[-1]].sum())
        rel = np.zeros((len(keys) - 1, 3))
        rel_w = np.zeros((len(keys) - 1, 3, 3))
        rel_dc = np.zeros((len(keys) - 1, 3, 3))
        if len(old) > 1:
            # unchanged intervals keep their factors: map old interval i -> new index
            old_pos = np.flatnonzero(~is_new)
            same = np.flatnonzero(np.diff(old_pos) == 1)
            rel[old_pos[same]] = self._rel[same]
            rel_w[old_pos[same]] = self._rel_w[same]
            if self._calibrator is not None:
                rel_dc[old_pos[same]] = self._calibrator.jacobians[same]
        for a, b in changed_runs:
            odo = self._odometry_between(keys[a : b + 1])
            rel[a:b] = odo.relative_poses
            rel_w[a:b] = sqrt_information_from_covariance(odo.covariances, f"{self.name} odometry")
            if isinstance(odo, motion.CalibratedOdometryFactors):
                rel_dc[a:b] = odo.calibration_jacobians
            chain = motion.dead_reckoning(odo.relative_poses, values[a])
            fill = is_new[a + 1 : b + 1]
            values[a + 1 : b + 1][fill] = chain[1:][fill]
        self._keys, self._key_values, self._rel, self._rel_w = keys, values, rel, rel_w
        if self._calibrator is not None:
            self._calibrator.jacobians = rel_dc
        return inserted

    def _odometry_between(self, keys: Array) -> motion.OdometryFactors:
        """The odometry composed between consecutive ``keys`` (at the calibration's
        linearisation point, with ``dz/dc``, when calibrating)."""
        rho = self._odo_rho if self._odo_rho.any() else None
        if self._calibrator is not None:
            return self._calibrator.compose(self._odo_t, self._odo_u, self._odo_q, keys, rho)
        return motion.odometry_between(
            self._odo_t, self._odo_u, self._odo_q, keys, check=False, correlations=rho
        )

    def _recompose_odometry(self) -> None:
        """Compose every odometry factor anew (at the current calibration estimate)."""
        calibrator = self._calibrator
        if calibrator is not None:
            calibrator.linearised_at = calibrator.estimate.copy()
        if len(self._keys) < 2:
            return
        odo = self._odometry_between(self._keys)
        self._rel = odo.relative_poses
        self._rel_w = sqrt_information_from_covariance(odo.covariances, f"{self.name} odometry")
        if calibrator is not None:
            assert isinstance(odo, motion.CalibratedOdometryFactors)
            calibrator.jacobians = odo.calibration_jacobians

    def _take_solution(self, problem: Problem) -> bool:
        """Take the poses, features (and calibration) solved in ``problem``; whether the
        calibration moved enough to compose the odometry anew."""
        n = len(self._keys)
        self._key_values = problem.values[: 3 * n].reshape(n, 3).copy()
        if self._calibrator is None:
            self._landmark_values = problem.values[3 * n :].reshape(-1, 2).copy()
        elif self._landmark_labels:  # the calibration variable sits between
            ids = problem.indices([("l", lab) for lab in self._landmark_labels])
            self._landmark_values = problem.values_of(ids).reshape(-1, 2).copy()
        return self._calibrator is not None and n > 1 and self._calibrator.take(problem)

    def _recover_fold(self) -> int:
        """When the map fails its check, find the odometry it cannot believe and solve again
        (:mod:`~csam_ros.core.smoothing.fold_recovery`); the odometry factors whose samples were
        scaled. Tried again only once the map has grown by half since the last try."""
        limits = ConsistencyOptions()
        if len(self._keys) < self._next_recovery_keys:
            return 0  # (not even checked: the map has not grown enough since the last try)
        if not factor_outliers(self.problem, limits.gate_probability).reasons(limits):
            return 0
        self._next_recovery_keys = (3 * len(self._keys)) // 2
        problem = self._build_problem(calibrated=self._calibrator is not None)
        squared = robust_odometry_solve(problem, self.options.solver)
        scale = slipped_sample_scale(self._odo_t, self._keys, squared, limits.gate_probability)
        if not np.any(scale > 1.0):
            return 0
        self._take_solution(problem)
        self._odo_q = self._odo_q * scale[:, None]
        self._recompose_odometry()
        self._solve(self.options.solver, converge=True)
        return int(np.count_nonzero(squared > chi2_quantile(limits.gate_probability, 3)))

    def _with_key_pose(self, start: int, covered: int) -> int:
        """``covered`` less the last features with no key pose within ``stamp_tolerance``:
        stamped just past the odometry, where the nearest key is more than that away, they wait
        for the next update (its odometry reaches them)."""
        t = self._feat_t[start:covered]
        if len(t) == 0:
            return covered
        without = (
            np.abs(self._keys[nearest_stamp(self._keys, t)] - t) > self.options.stamp_tolerance
        )
        with_key = np.flatnonzero(~without)
        return start + (int(with_key[-1]) + 1 if len(with_key) else 0)

    def _integrate_features(self, covered: int) -> tuple[int, int]:
        start = self._integrated_features
        if covered <= start:
            return 0, 0
        idx = self._key_index_of(self._feat_t[start:covered])
        labels = self._feat_label[start:covered]
        unknown = [lab for lab in dict.fromkeys(labels.tolist()) if lab not in self._landmark_index]
        if unknown:
            first = np.array([int(np.flatnonzero(labels == lab)[0]) for lab in unknown])
            xy = se2.transform_point(self._key_values[idx[first]], self._feat_z[start + first])
            for lab in unknown:
                self._landmark_index[lab] = len(self._landmark_labels)
                self._landmark_labels.append(lab)
            self._landmark_values = np.concatenate([self._landmark_values, xy])
        self._integrated_features = covered
        return len(unknown), covered - start

    def _key_index_of(self, stamps: Array) -> IntArray:
        pick = nearest_stamp(self._keys, stamps)
        off = np.abs(self._keys[pick] - stamps)
        if np.any(off > self.options.stamp_tolerance):
            bad = int(np.argmax(off))
            raise RuntimeError(f"{self.name}: no key pose at stamp {stamps[bad]}")
        return pick

    def _build_problem(self, calibrated: bool = False) -> Problem:
        """The map's problem; ``calibrated``: with the calibration unknowns (and odometry
        factors in them), else with the odometry at the calibration estimate."""
        problem = Problem()
        n = len(self._keys)
        poses = problem.add_variables(POSE, [("x", i) for i in range(n)], self._key_values)
        gauge = np.eye(3) / self.options.gauge_sigma
        problem.add_factor(PosePrior(poses[:1], np.zeros((1, 3)), gauge, name="gauge prior"))
        if n > 1 and calibrated and self._calibrator is not None:
            self._calibrator.add_factors(problem, poses, self._rel, self._rel_w)
        elif n > 1:
            relative = (
                self._rel if self._calibrator is None else self._calibrator.at_estimate(self._rel)
            )
            problem.add_factor(
                RelativePose(poses[:-1], poses[1:], relative, self._rel_w, name="odometry")
            )
        if self._landmark_labels:
            lms = problem.add_variables(
                POINT, [("l", lab) for lab in self._landmark_labels], self._landmark_values
            )
            done = self._integrated_features
            if done:
                obs_pose = self._key_index_of(self._feat_t[:done])
                obs_lm = np.array(
                    [self._landmark_index[lab] for lab in self._feat_label[:done].tolist()]
                )
                problem.add_factor(
                    PointObservation(
                        poses[obs_pose],
                        lms[obs_lm],
                        self._feat_z[:done],
                        self._feat_w[:done],
                        robust=self.options.robust,
                        name="feature observations",
                    )
                )
        return problem

    def _solve(self, options: SolverOptions, converge: bool = False) -> SolveReport:
        """Solve; when calibrating, the odometry is recomposed at the new calibration if it
        moved (and, with ``converge``, solved again until it stays: at most
        ``CALIBRATION_ROUNDS`` rounds)."""
        calibrator = self._calibrator if len(self._keys) > 1 else None
        calibrating = calibrator is not None
        for _ in range(CALIBRATION_ROUNDS if calibrating and converge else 1):
            problem = self._build_problem(calibrated=calibrating)
            report = problem.solve(options)
            if not self._take_solution(problem):
                break
            self._recompose_odometry()
        if calibrating:
            problem = self._build_problem()
        self._problem = problem
        self._system = None
        self._inverse = None
        return report

    # -- state --------------------------------------------------------------------------------

    def state(self) -> LocalMapState:
        """Everything this map holds, as arrays (buffered data merged in first, as
        :meth:`update` would)."""
        self._consolidate()
        return LocalMapState(
            self._odo_t.copy(),
            self._odo_u.copy(),
            self._odo_q.copy(),
            self._odo_rho.copy(),
            self._feat_t.copy(),
            self._feat_label.copy(),
            self._feat_z.copy(),
            self._feat_w.copy(),
            np.asarray(self._requested, dtype=float),
            self._keys.copy(),
            self._key_values.copy(),
            self._rel.copy(),
            self._rel_w.copy(),
            np.array(self._landmark_labels, dtype=np.int64),
            self._landmark_values.copy(),
            self._integrated_features,
            self._dropped_features,
            float(self._last_solved_odometry),
            self._problem is not None,
            np.zeros(0) if self._calibrator is None else self._calibrator.estimate.copy(),
        )

    @classmethod
    def from_state(
        cls, name: str, state: LocalMapState, options: LocalMapOptions | None = None
    ) -> LocalMap:
        """The map of :meth:`state`, at its saved estimate (its problem rebuilt, not
        solved). ValueError when the arrays do not fit together."""
        check_state(name, state)
        s = state
        n_lm = len(s.landmark_labels)
        local = cls(name, options)
        local._odo_t, local._odo_u, local._odo_q = (
            np.asarray(s.odometry_stamps, dtype=float),
            np.asarray(s.odometry_inputs, dtype=float),
            np.asarray(s.odometry_sigmas, dtype=float),
        )
        local._odo_rho = np.asarray(s.odometry_correlations, dtype=float)
        local._feat_t = np.asarray(s.feature_stamps, dtype=float)
        local._feat_label = np.asarray(s.feature_labels, dtype=np.int64)
        local._feat_z = np.asarray(s.feature_points, dtype=float)
        local._feat_w = np.asarray(s.feature_sqrt_information, dtype=float)
        local._requested = np.asarray(s.requested, dtype=float).tolist()
        local._keys = np.asarray(s.keys, dtype=float)
        local._key_values = np.asarray(s.key_values, dtype=float)
        local._rel = np.asarray(s.relative, dtype=float).reshape(-1, 3)
        local._rel_w = np.asarray(s.relative_sqrt_information, dtype=float).reshape(-1, 3, 3)
        local._landmark_labels = [int(v) for v in s.landmark_labels]
        local._landmark_index = {lab: i for i, lab in enumerate(local._landmark_labels)}
        if len(local._landmark_index) != n_lm:
            raise ValueError(f"{name}: repeated landmark labels")
        local._landmark_values = np.asarray(s.landmark_values, dtype=float).reshape(-1, 2)
        local._integrated_features = int(s.integrated_features)
        local._dropped_features = int(s.dropped_features)
        local._last_solved_odometry = float(s.last_solved_odometry)
        if local._calibrator is not None:
            local._calibrator.restore(s.odometry_calibration, name)
            local._recompose_odometry()
        if s.solved:
            local._problem = local._build_problem()
        return local

    # -- results ------------------------------------------------------------------------------

    @property
    def stamps(self) -> Array:
        """Stamps of the key poses ``(N,)``."""
        return self._keys.copy()

    @property
    def poses(self) -> Array:
        """Key poses ``(N, 3)`` in the robot's frame ``G_r`` (first pose = origin)."""
        return self._key_values.copy()

    @property
    def landmark_labels(self) -> IntArray:
        return np.array(self._landmark_labels, dtype=np.int64)

    @property
    def landmarks(self) -> Array:
        """Landmark positions ``(L, 2)`` in ``G_r``, in the order of :attr:`landmark_labels`."""
        return self._landmark_values.copy()

    @property
    def odometry_calibration(self) -> OdometryCalibration | None:
        """The calibration estimate and its marginal sigmas (``None``: calibration off or not
        solved yet; after :meth:`from_state` the sigmas wait for the next solve: NaN)."""
        if self._calibrator is None or self._problem is None:
            return None
        return self._calibrator.result()

    @property
    def dropped_features(self) -> int:
        """Feature observations stamped before the first odometry sample (not used)."""
        return self._dropped_features

    @property
    def problem(self) -> Problem:
        """The solved least-squares problem (variables ``("x", i)`` and ``("l", label)``)."""
        if self._problem is None:
            raise RuntimeError(f"{self.name}: the local map has not been solved yet")
        return self._problem

    def pose_index(self, stamps: ArrayLike) -> IntArray:
        """Indices of the key poses at ``stamps`` (within ``stamp_tolerance``)."""
        return self._key_index_of(np.atleast_1d(np.asarray(stamps, dtype=float)))

    def pose_keys(self, stamps: ArrayLike) -> list[Hashable]:
        return [("x", int(i)) for i in self.pose_index(stamps)]

    def _factorization(self) -> NormalEquations:
        if self._system is None:
            self._system = factorize_at_estimate(self.problem)
        return self._system

    def covariance(self, pose_stamps: ArrayLike = (), landmark_labels: Sequence[int] = ()) -> Array:
        """Joint marginal covariance of the poses at ``pose_stamps`` then the landmarks."""
        keys = self.pose_keys(pose_stamps) if len(np.atleast_1d(pose_stamps)) else []
        keys += [("l", int(lab)) for lab in landmark_labels]
        return marginal_covariance(self.problem, keys, self._factorization())

    def _selected_inverse(self) -> SelectedInverse:
        """Entries of the covariance on the factor's pattern (Takahashi), cached per solve."""
        if self._inverse is None:
            self._inverse = SelectedInverse(self._factorization())
        return self._inverse

    def pose_covariances(self, indices: ArrayLike | None = None) -> Array:
        """Marginal covariance ``(k, 3, 3)`` of key poses (all by default; no cross terms).

        From a selected inverse on the factor's pattern: linear in the size of the factor.
        """
        idx = np.arange(len(self._keys)) if indices is None else np.asarray(indices)
        ids = self.problem.indices([("x", int(i)) for i in idx])
        return self._selected_inverse().blocks(self.problem, ids)

    def landmark_covariances(self) -> Array:
        """Marginal covariance ``(L, 2, 2)`` of every landmark (no cross terms)."""
        if not self._landmark_labels:
            return np.zeros((0, 2, 2))
        ids = self.problem.indices([("l", lab) for lab in self._landmark_labels])
        return self._selected_inverse().blocks(self.problem, ids)

    def sqrt_information(self, pose_stamps: ArrayLike) -> tuple[Array, Array, Array]:
        """Marginal square-root information of the poses at ``pose_stamps``.

        Returns ``(R, stamps, poses)``: upper-triangular ``R`` ``(3m, 3m)`` with ``R^T R`` the
        marginal information of those poses (the last block of the map's ``R`` with them
        ordered last), their key stamps ``(m,)`` and estimates ``(m, 3)``, in stamp order.
        """
        idx = np.unique(self.pose_index(pose_stamps))
        keys = [("x", int(i)) for i in idx]
        r, _ = marginal_sqrt_information(self.problem, keys, self._factorization())
        return r, self._keys[idx].copy(), self._key_values[idx].copy()
