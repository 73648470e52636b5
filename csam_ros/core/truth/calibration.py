"""Noise model and range-scale estimation of robots with a range-bearing sensor and velocity
odometry, against known landmark positions (no robot ground truth needed).

Steps (:func:`estimate_noise`, on a :class:`~csam_ros.core.model.log.MultiRobotLog` with its
:class:`~csam_ros.core.model.log.GroundTruth` landmarks):

1. Snapshot localisation (:func:`snapshot_localisation`). Every camera frame (one stamp) that
   sees at least three distinct landmarks fixes the robot pose from range-bearing measurements
   to the known landmarks alone, without odometry: the best pair of measurements gives the
   start (:func:`_two_point_start`), then a few Gauss-Newton steps on range and bearing with a
   Cauchy kernel.
2. Sensor noise (:func:`estimate_sensor_noise`). The residuals of those fits, each divided by
   ``sqrt(1 - h)`` (``h`` the leverage of its row in the whitened fit, so that the three pose
   degrees of freedom per frame do not shrink the estimate), give ``s_range`` as a robust
   (MAD) spread per range bin fitted by ``a + b r``, and ``s_bearing`` as one robust spread.
   Alternating with the fit (weights from the current sigmas) three times.
3. Odometry noise (:func:`estimate_odometry_noise`). Between consecutive snapshots of one
   robot, the snapshot relative pose minus the dead-reckoned one (both in the frame of the
   first) is modelled as ``N(0, q_v^2 A_v + q_vlat^2 A_vlat + q_omega^2 A_omega + C)``:
   ``A_k`` propagates a unit white velocity noise density through the odometry samples in
   between (first order), ``C`` is the two snapshots' covariance. The densities ``q`` [per
   sqrt-second] maximise the likelihood over all pairs, after gating out pairs beyond the
   chi-square(3) 99.9% quantile (bad snapshots) in a second pass.
4. Final values (:func:`em_noise`): expectation-maximisation over every robot's localisation
   with the known landmarks by the smoothing engine (:func:`localise`), starting from 1-3;
   then the rendezvous factors from residuals against both robots' localisations
   (:func:`rendezvous_noise`).
5. Range calibration (:func:`range_scale`): per robot, the weighted least-squares ratio of
   measured to predicted range over the final localisations' inliers.

The model (:class:`NoiseModel`): ``sigma_range(r) = sigma_range + sigma_range_per_m * r``,
one bearing sigma, white velocity noise densities ``q`` per sqrt-second on ``(v, v_lat,
omega)`` (the pose noise of an interval of length ``t`` grows as ``q^2 t``), and factors by
which measurements of other robots spread more than those of landmarks.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from csam_ros.core.joining.consistency import chi2_quantile
from csam_ros.core.model import se2
from csam_ros.core.model.log import GroundTruth, MultiRobotLog, OdometryLog, RobotLog
from csam_ros.core.model.motion import (
    dead_reckoning,
    odometry_between,
    odometry_poses,
    odometry_poses_at,
)
from csam_ros.core.model.sensor import polar_to_cartesian
from csam_ros.core.sam.covariance import factorize_at_estimate
from csam_ros.core.sam.factors import (
    POINT,
    POSE,
    Cauchy,
    PointObservation,
    PointPrior,
    RelativePose,
)
from csam_ros.core.sam.solver import Problem, SolverOptions

FloatArray = NDArray[np.float64]
Progress = Callable[[str], None]
CAUCHY_SCALE = 2.3849  # 95% efficiency at the normal distribution
MAD_TO_SIGMA = 1.4826
# the values the estimation fits (the rendezvous factors come after, from its localisations)
# Smallest odometry noise density a fit may return [m/sqrt(s), rad/sqrt(s)]: a density the
# data drive to zero (MR.CLAM Dataset 4's first estimate of q_vlat: 6e-10) would make the
# odometry factors of short intervals singular.
DENSITY_FLOOR = 1e-3
ESTIMATED = ("sigma_range", "sigma_range_per_m", "sigma_bearing", "q_v", "q_vlat", "q_omega")


@dataclass(frozen=True)
class NoiseModel:
    """Sensor and odometry noise (module docstring): range sigma ``sigma_range +
    sigma_range_per_m * r`` [m], bearing sigma [rad], odometry densities ``q_v``, ``q_vlat``
    [m/sqrt(s)] and ``q_omega`` [rad/sqrt(s)]; measurements of other robots get the landmark
    sigmas times ``rendezvous_*_factor``."""

    sigma_range: float
    sigma_range_per_m: float
    sigma_bearing: float
    q_v: float
    q_vlat: float
    q_omega: float
    rendezvous_range_factor: float = 1.0
    rendezvous_bearing_factor: float = 1.0

    def __post_init__(self) -> None:
        for name, value in asdict(self).items():
            low_ok = value >= 0 if name == "sigma_range_per_m" else value > 0
            if not (np.isfinite(value) and low_ok):
                bound = ">= 0" if name == "sigma_range_per_m" else "> 0"
                raise ValueError(f"noise {name} must be finite and {bound}, got {value!r}")

    @classmethod
    def from_dict(cls, values: dict, defaults: NoiseModel | None = None) -> NoiseModel:
        """Build from a mapping (e.g. a config file's ``noise`` section); keys it leaves out
        come from ``defaults`` (all are required without)."""
        known = set(cls.__dataclass_fields__)
        unknown = set(values) - known
        if unknown:
            raise ValueError(f"unknown noise keys {sorted(unknown)}; known: {sorted(known)}")
        given = {k: float(v) for k, v in values.items()}
        if defaults is not None:
            return replace(defaults, **given)
        return cls(**given)

    def densities(self) -> FloatArray:
        """``(q_v, q_vlat, q_omega)``."""
        return np.array([self.q_v, self.q_vlat, self.q_omega])


# Where the estimation starts (deliberately not a data set's known values, so that re-running
# it does not feed its own output back in).
NEUTRAL_START = NoiseModel(
    sigma_range=0.1, sigma_range_per_m=0.0, sigma_bearing=0.02, q_v=0.02, q_vlat=0.01, q_omega=0.04
)


# ---------------------------------------------------------------------------------------------
# snapshot localisation


@dataclass
class Snapshots:
    """Poses fixed by single camera frames seeing >= 3 known landmarks, and their residuals."""

    robot: str
    stamps: FloatArray  # (S,)
    poses: FloatArray  # (S, 3) world frame
    covariances: FloatArray  # (S, 3, 3)
    snapshot: NDArray[np.int64]  # (K,) observation -> snapshot
    labels: NDArray[np.int64]  # (K,) the robot's landmark label
    ranges: FloatArray  # (K,)
    range_residuals: FloatArray  # (K,) measured - predicted
    bearing_residuals: FloatArray  # (K,)
    range_leverage: FloatArray  # (K,)
    bearing_leverage: FloatArray  # (K,)


def _landmark_positions(robot: RobotLog, truth: GroundTruth) -> FloatArray:
    labels = truth.label_to_feature[robot.name]
    where = {int(i): k for k, i in enumerate(truth.feature_ids)}
    subject_rows = np.array([where[labels[int(lab)]] for lab in robot.features.labels], dtype=int)
    return truth.feature_positions[subject_rows].reshape(-1, 2)


def snapshot_localisation(
    robot: RobotLog,
    truth: GroundTruth,
    noise: NoiseModel,
    min_landmarks: int = 3,
    iterations: int = 10,
) -> Snapshots:
    """Fit one pose per frame with >= ``min_landmarks`` distinct landmarks (module docstring)."""
    features = robot.features
    landmarks = _landmark_positions(robot, truth)
    stamps, frame, counts = np.unique(features.stamps, return_inverse=True, return_counts=True)
    distinct = _distinct_per_frame(frame, features.labels, stamps.size)
    keep_frame = distinct >= min_landmarks
    frame_ids = np.flatnonzero(keep_frame)
    renumber = -np.ones(stamps.size, dtype=int)
    renumber[frame_ids] = np.arange(frame_ids.size)
    obs = np.flatnonzero(keep_frame[frame])
    snap = renumber[frame[obs]]
    n_snap = frame_ids.size
    if n_snap == 0:  # no frame sees enough landmarks (a short window)
        none, ids = np.zeros(0), np.zeros(0, dtype=np.int64)
        return Snapshots(
            robot.name, none, np.zeros((0, 3)), np.zeros((0, 3, 3)), ids, ids, *[none] * 5
        )
    width = int(counts[frame_ids].max())
    # padded (S, M) layout
    order = np.argsort(snap, kind="stable")
    obs, snap = obs[order], snap[order]
    slot = np.arange(obs.size) - np.searchsorted(snap, snap)
    valid = np.zeros((n_snap, width), dtype=bool)
    valid[snap, slot] = True
    r = np.ones((n_snap, width))
    b = np.zeros((n_snap, width))
    lm = np.zeros((n_snap, width, 2))
    r[snap, slot] = features.ranges[obs]
    b[snap, slot] = features.bearings[obs]
    lm[snap, slot] = landmarks[obs]
    sigma_r = noise.sigma_range + noise.sigma_range_per_m * r
    sigma_b = np.full_like(r, noise.sigma_bearing)

    body = np.stack([r * np.cos(b), r * np.sin(b)], -1)
    poses = _two_point_start(body, lm, valid, sigma_r, sigma_b)

    def linearise(p: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        d = lm - p[:, None, :2]
        rr = np.maximum(np.linalg.norm(d, axis=-1), 1e-9)
        e_r = r - rr
        e_b = se2.wrap_angle(b - (np.arctan2(d[..., 1], d[..., 0]) - p[:, None, 2]))
        j_r = np.stack([-d[..., 0] / rr, -d[..., 1] / rr, np.zeros_like(rr)], -1)
        j_b = np.stack([d[..., 1] / rr**2, -d[..., 0] / rr**2, -np.ones_like(rr)], -1)
        return e_r, e_b, j_r, j_b

    for _ in range(iterations):
        e_r, e_b, j_r, j_b = linearise(poses)
        w_r = valid / sigma_r**2 / (1 + (e_r / sigma_r / CAUCHY_SCALE) ** 2)
        w_b = valid / sigma_b**2 / (1 + (e_b / sigma_b / CAUCHY_SCALE) ** 2)
        normal = np.einsum("sm,smi,smj->sij", w_r, j_r, j_r) + np.einsum(
            "sm,smi,smj->sij", w_b, j_b, j_b
        )
        gradient = np.einsum("sm,smi,sm->si", w_r, j_r, e_r) + np.einsum(
            "sm,smi,sm->si", w_b, j_b, e_b
        )
        # e = z - h(x) with J = dh/dx: the Gauss-Newton step is +N^-1 J^T W e
        step = np.linalg.solve(normal, gradient[..., None])[..., 0]
        poses = poses + step
        poses[:, 2] = se2.wrap_angle(poses[:, 2])
        if np.abs(step).max(initial=0.0) < 1e-10:
            break
    e_r, e_b, j_r, j_b = linearise(poses)
    w_r = valid / sigma_r**2 / (1 + (e_r / sigma_r / CAUCHY_SCALE) ** 2)
    w_b = valid / sigma_b**2 / (1 + (e_b / sigma_b / CAUCHY_SCALE) ** 2)
    normal = np.einsum("sm,smi,smj->sij", w_r, j_r, j_r) + np.einsum(
        "sm,smi,smj->sij", w_b, j_b, j_b
    )
    covariance = np.linalg.inv(normal)
    lev_r = w_r * np.einsum("smi,sij,smj->sm", j_r, covariance, j_r)
    lev_b = w_b * np.einsum("smi,sij,smj->sm", j_b, covariance, j_b)
    # covariance with the unweighted (Gaussian) model, for the odometry fit
    w_r0, w_b0 = valid / sigma_r**2, valid / sigma_b**2
    gaussian_cov = np.linalg.inv(
        np.einsum("sm,smi,smj->sij", w_r0, j_r, j_r) + np.einsum("sm,smi,smj->sij", w_b0, j_b, j_b)
    )
    return Snapshots(
        robot=robot.name,
        stamps=stamps[frame_ids],
        poses=poses,
        covariances=gaussian_cov,
        snapshot=snap,
        labels=features.labels[obs],
        ranges=r[snap, slot],
        range_residuals=e_r[snap, slot],
        bearing_residuals=e_b[snap, slot],
        range_leverage=np.clip(lev_r[snap, slot], 0.0, 0.99),
        bearing_leverage=np.clip(lev_b[snap, slot], 0.0, 0.99),
    )


def _two_point_start(
    body: FloatArray,
    landmarks: FloatArray,
    valid: NDArray[np.bool_],
    sigma_r: FloatArray,
    sigma_b: FloatArray,
) -> FloatArray:
    """Robust start per frame: the pose fixed by the best pair of measurements.

    Every pair (i, j) of a frame fixes a pose in closed form (heading from the direction of
    the pair, translation from point i); the pair whose pose explains the most measurements
    (truncated squared whitened residuals, cap 9 per row) wins. One misread landmark in a
    frame then cannot drag the fit into a wrong basin.
    """
    n_snap, width = valid.shape
    i, j = np.triu_indices(width, 1)
    pair_ok = valid[:, i] & valid[:, j]
    d_body = body[:, j] - body[:, i]
    d_world = landmarks[:, j] - landmarks[:, i]
    heading = np.arctan2(d_world[..., 1], d_world[..., 0]) - np.arctan2(
        d_body[..., 1], d_body[..., 0]
    )
    c, s = np.cos(heading), np.sin(heading)
    bx, by = body[:, i, 0], body[:, i, 1]
    tx = landmarks[:, i, 0] - (c * bx - s * by)
    ty = landmarks[:, i, 1] - (s * bx + c * by)
    candidates = np.stack([tx, ty, heading], -1)  # (S, P, 3)
    d = landmarks[:, None, :, :] - candidates[:, :, None, :2]  # (S, P, M, 2)
    predicted_r = np.linalg.norm(d, axis=-1)
    predicted_b = np.arctan2(d[..., 1], d[..., 0]) - candidates[:, :, None, 2]
    measured_r = np.linalg.norm(body, axis=-1)[:, None, :]
    measured_b = np.arctan2(body[..., 1], body[..., 0])[:, None, :]
    cost = np.minimum(((measured_r - predicted_r) / sigma_r[:, None, :]) ** 2, 9.0) + np.minimum(
        (se2.wrap_angle(measured_b - predicted_b) / sigma_b[:, None, :]) ** 2, 9.0
    )
    cost = np.where(valid[:, None, :], cost, 0.0).sum(-1)
    cost = np.where(pair_ok, cost, np.inf)
    best = np.argmin(cost, axis=1)
    return candidates[np.arange(n_snap), best]


def _distinct_per_frame(frame: NDArray[np.int64], labels: NDArray[np.int64], n: int) -> NDArray:
    pairs = np.unique(np.stack([frame, labels], -1), axis=0)
    return np.bincount(pairs[:, 0], minlength=n)


# ---------------------------------------------------------------------------------------------
# sensor noise


def robust_sigma(values: FloatArray) -> float:
    """Median absolute deviation about zero, scaled to a normal sigma."""
    return float(MAD_TO_SIGMA * np.median(np.abs(values))) if values.size else float("nan")


@dataclass
class SensorNoiseEstimate:
    """Step 2 (module docstring): ``noise`` holds the fitted sensor sigmas (its odometry
    densities are the start's); per range bin spreads, counts and tails."""

    noise: NoiseModel
    range_bins: list[dict] = field(default_factory=list)
    bearing_bins: list[dict] = field(default_factory=list)
    n_observations: int = 0
    n_snapshots: int = 0
    range_beyond_3_sigma: float = 0.0
    bearing_beyond_3_sigma: float = 0.0
    range_beyond_5_sigma: float = 0.0
    bearing_beyond_5_sigma: float = 0.0


def estimate_sensor_noise(
    log: MultiRobotLog, noise: NoiseModel = NEUTRAL_START, rounds: int = 3
) -> tuple[SensorNoiseEstimate, dict[str, Snapshots]]:
    """Alternate snapshot fits and robust spreads of their residuals (module docstring)."""
    if log.truth is None:
        raise ValueError("noise estimation needs the landmark ground truth")
    edges = np.array([0.0, 1.5, 2.0, 2.5, 3.0, 3.5, 4.0, 5.0, 6.0, 20.0])
    estimate = None
    snapshots: dict[str, Snapshots] = {}
    for _ in range(rounds):
        snapshots = {
            name: snapshot_localisation(robot, log.truth, noise)
            for name, robot in log.robots.items()
        }
        ranges = np.concatenate([s.ranges for s in snapshots.values()])
        e_r = np.concatenate(
            [s.range_residuals / np.sqrt(1 - s.range_leverage) for s in snapshots.values()]
        )
        e_b = np.concatenate(
            [s.bearing_residuals / np.sqrt(1 - s.bearing_leverage) for s in snapshots.values()]
        )
        bins = np.digitize(ranges, edges) - 1
        range_bins, bearing_bins = [], []
        for k in range(edges.size - 1):
            inside = bins == k
            if inside.sum() < 30:
                continue
            range_bins.append(
                {
                    "range_m": [float(edges[k]), float(edges[k + 1])],
                    "n": int(inside.sum()),
                    "mean_range_m": float(ranges[inside].mean()),
                    "sigma_range": robust_sigma(e_r[inside]),
                    "median_residual": float(np.median(e_r[inside])),
                }
            )
            bearing_bins.append(
                {
                    "range_m": [float(edges[k]), float(edges[k + 1])],
                    "n": int(inside.sum()),
                    "sigma_bearing": robust_sigma(e_b[inside]),
                    "median_residual": float(np.median(e_b[inside])),
                }
            )
        x = np.array([b["mean_range_m"] for b in range_bins])
        y = np.array([b["sigma_range"] for b in range_bins])
        weights = np.sqrt([b["n"] for b in range_bins])
        design = np.column_stack([np.ones_like(x), x]) * weights[:, None]
        intercept, slope = np.linalg.lstsq(design, y * weights, rcond=None)[0]
        if slope < 0 or intercept <= 0:
            intercept, slope = robust_sigma(e_r), 0.0
        sigma_b = robust_sigma(e_b)
        noise = replace(
            noise,
            sigma_range=float(intercept),
            sigma_range_per_m=float(slope),
            sigma_bearing=sigma_b,
        )
        normalised_r = e_r / (intercept + slope * ranges)
        normalised_b = e_b / sigma_b
        estimate = SensorNoiseEstimate(
            noise=noise,
            range_bins=range_bins,
            bearing_bins=bearing_bins,
            n_observations=int(ranges.size),
            n_snapshots=int(sum(s.stamps.size for s in snapshots.values())),
            range_beyond_3_sigma=float(np.mean(np.abs(normalised_r) > 3)),
            bearing_beyond_3_sigma=float(np.mean(np.abs(normalised_b) > 3)),
            range_beyond_5_sigma=float(np.mean(np.abs(normalised_r) > 5)),
            bearing_beyond_5_sigma=float(np.mean(np.abs(normalised_b) > 5)),
        )
    assert estimate is not None
    return estimate, snapshots


# ---------------------------------------------------------------------------------------------
# odometry noise


@dataclass
class OdometryNoiseEstimate:
    """Step 3 (module docstring): the densities ``q = (q_v, q_vlat, q_omega)``, how many
    snapshot pairs gave them, and refits on other gap ranges."""

    q: list[float]
    n_pairs: int
    gated_fraction: float
    median_gap_s: float
    by_gap: list[dict] = field(default_factory=list)
    mean_residual: list[float] = field(default_factory=list)


def _pair_terms(
    odometry: OdometryLog, reckoned: FloatArray, start: float, end: float
) -> tuple[FloatArray, FloatArray]:
    """Dead-reckoned relative pose from ``start`` to ``end`` and the unit-density terms."""
    inside = np.flatnonzero((odometry.stamps > start) & (odometry.stamps < end))
    knots = np.concatenate([[start], odometry.stamps[inside], [end]])
    knot_poses = odometry_poses_at(odometry.stamps, odometry.inputs, reckoned, knots)
    relative = se2.between(knot_poses[0], knot_poses)  # (n, 3) in the frame of the start
    durations = np.diff(knots)
    heading = relative[:-1, 2]  # heading during each piece (first order)
    tail = relative[-1, :2] - relative[1:, :2]  # from the end of each piece to the end
    c, s = np.cos(heading), np.sin(heading)
    terms = np.zeros((3, 3, 3))
    forward = np.stack([c, s, np.zeros_like(c)], -1)
    lateral = np.stack([-s, c, np.zeros_like(c)], -1)
    turn = np.stack([-tail[:, 1], tail[:, 0], np.ones_like(c)], -1)
    for k, direction in enumerate((forward, lateral, turn)):
        terms[k] = np.einsum("n,ni,nj->ij", durations, direction, direction)
    return relative[-1], terms


def _snapshot_pairs(
    log: MultiRobotLog, snapshots: dict[str, Snapshots], min_gap: float, max_gap: float
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Chains of snapshot pairs, each the first snapshot at least ``min_gap`` after the last.

    Returns residuals (n, 3), unit-density terms (n, 3, 3, 3), snapshot covariances (n, 3, 3)
    of the measured relative pose, and gaps (n,).
    """
    residuals, terms, covs, gaps = [], [], [], []
    for name, snap in snapshots.items():
        odometry = log.robots[name].odometry
        reckoned = odometry_poses(odometry.stamps, odometry.inputs)
        a = 0
        while a < snap.stamps.size - 1:
            b = int(np.searchsorted(snap.stamps, snap.stamps[a] + min_gap, side="left"))
            b = max(b, a + 1)
            if b >= snap.stamps.size:
                break
            start, end = snap.stamps[a], snap.stamps[b]
            if end - start <= max_gap:
                predicted, unit_terms = _pair_terms(odometry, reckoned, start, end)
                measured = se2.between(snap.poses[a], snap.poses[b])
                residual = measured - predicted
                residual[2] = se2.wrap_angle(residual[2])
                j1, j2 = se2.compose_jacobians(se2.inverse(snap.poses[a]), snap.poses[b])
                ja = j1 @ se2.inverse_jacobian(snap.poses[a])
                residuals.append(residual)
                terms.append(unit_terms)
                covs.append(ja @ snap.covariances[a] @ ja.T + j2 @ snap.covariances[b] @ j2.T)
                gaps.append(end - start)
            a = b
    return np.array(residuals), np.array(terms), np.array(covs), np.array(gaps)


def _fit_densities(
    e: FloatArray, a_terms: FloatArray, c: FloatArray
) -> tuple[FloatArray, NDArray[np.bool_]]:
    """ML densities ``q``, refitted twice without pairs beyond the chi-square(3) 99.9% gate."""
    from scipy.optimize import minimize  # on use: scipy.optimize loads slowly

    def covariance(q: FloatArray, use: NDArray[np.bool_]) -> FloatArray:
        return np.einsum("k,nkij->nij", q**2, a_terms[use]) + c[use]

    def negative_log_likelihood(log_q: FloatArray, use: NDArray[np.bool_]) -> float:
        sigma = covariance(np.exp(log_q), use)
        _, logdet = np.linalg.slogdet(sigma)
        maha = np.einsum("ni,ni->n", e[use], np.linalg.solve(sigma, e[use][..., None])[..., 0])
        return float(0.5 * np.sum(logdet + maha))

    use = np.ones(e.shape[0], dtype=bool)
    q = np.array([0.01, 0.01, 0.02])
    for _ in range(3):
        result = minimize(
            negative_log_likelihood,
            np.log(q),
            args=(use,),
            method="Nelder-Mead",
            options={"xatol": 1e-4, "fatol": 1e-6, "maxiter": 2000},
        )
        q = np.exp(result.x)
        everything = np.ones_like(use)
        sigma = covariance(q, everything)
        maha = np.einsum("ni,ni->n", e, np.linalg.solve(sigma, e[..., None])[..., 0])
        use = maha < chi2_quantile(0.999, 3)
    return np.maximum(q, DENSITY_FLOOR), use


def estimate_odometry_noise(
    log: MultiRobotLog,
    snapshots: dict[str, Snapshots],
    min_gap: float = 5.0,
    max_gap: float = 60.0,
) -> OdometryNoiseEstimate:
    """Maximum-likelihood white-noise densities from snapshot pairs (module docstring).

    The main fit uses pairs ``min_gap`` to ``max_gap`` seconds apart: at shorter gaps the
    snapshot noise hides the odometry noise. ``by_gap`` refits on other gap ranges; densities
    that grow with the gap betray systematic (not white) odometry errors.
    """
    e, a_terms, c, gap = _snapshot_pairs(log, snapshots, min_gap, max_gap)
    if e.shape[0] < 10:
        raise ValueError(f"only {e.shape[0]} snapshot pairs {min_gap}-{max_gap} s apart")
    q, use = _fit_densities(e, a_terms, c)
    by_gap = []
    for low, high in ((0.0, 1.0), (1.0, 3.0), (3.0, 10.0), (10.0, 30.0), (30.0, 90.0)):
        eb, ab, cb, gb = _snapshot_pairs(log, snapshots, low, high)
        if eb.shape[0] >= 20:
            qb, ub = _fit_densities(eb, ab, cb)
            by_gap.append(
                {
                    "gap_s": [low, high],
                    "n": int(ub.sum()),
                    "median_gap_s": float(np.median(gb)),
                    "q": [float(v) for v in qb],
                }
            )
    return OdometryNoiseEstimate(
        q=[float(v) for v in q],
        n_pairs=int(use.sum()),
        gated_fraction=float(1 - use.mean()),
        median_gap_s=float(np.median(gap)),
        by_gap=by_gap,
        mean_residual=[float(v) for v in e[use].mean(axis=0)],
    )


# ---------------------------------------------------------------------------------------------
# localisation with known landmarks (the smoothing engine), expectation-maximisation of noise


@dataclass
class Localisation:
    """One robot's smoothed poses at its feature stamps, landmarks held at their truth."""

    robot: str
    stamps: FloatArray  # (N,) key stamps
    poses: FloatArray  # (N, 3) world frame
    pose_covariances: FloatArray  # (N, 3, 3)
    pair_covariances: FloatArray  # (N-1, 6, 6) joint of consecutive poses
    odometry_z: FloatArray  # (N-1, 3) composed odometry between keys
    odometry_unit: FloatArray  # (N-1, 3, 3, 3) covariance per unit density of v, v_lat, omega
    observation_key: NDArray[np.int64]  # (K,) observation -> key
    ranges: FloatArray  # (K,)
    range_residuals: FloatArray  # (K,) measured - predicted
    bearing_residuals: FloatArray  # (K,)
    range_variance: FloatArray  # (K,) of the prediction, from the pose covariance
    bearing_variance: FloatArray  # (K,)
    iterations: int
    seconds: float


def _unit_density_odometry(
    odometry: OdometryLog, keys: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Composed odometry between keys and its covariance for a unit density of each input."""
    durations = np.diff(odometry.stamps)
    per_sample = np.concatenate([[durations[0]], durations])
    unit = []
    relative = np.zeros((keys.size - 1, 3))
    for k in range(3):
        sigmas = np.zeros((odometry.stamps.size, 3))
        sigmas[:, k] = 1.0 / np.sqrt(per_sample)
        factors = odometry_between(odometry.stamps, odometry.inputs, sigmas, keys)
        relative = factors.relative_poses
        unit.append(factors.covariances)
    return relative, np.stack(unit, axis=1)


def localise(
    robot: RobotLog,
    truth: GroundTruth,
    noise: NoiseModel,
    snapshots: Snapshots,
    robust: bool = True,
) -> Localisation:
    """Smooth one robot's poses at its feature stamps given the true landmarks.

    Odometry factors between consecutive feature stamps (covariance from the densities of
    ``noise``), Cartesian landmark observations with a Cauchy kernel, landmarks tied to their
    truth by a 1 mm prior. Started from the snapshot poses, dead reckoning in between.
    """
    began = time.perf_counter()
    features = robot.features
    odometry = robot.odometry
    inside = (features.stamps >= odometry.stamps[0]) & (features.stamps <= odometry.stamps[-1])
    keys, key_of = np.unique(features.stamps[inside], return_inverse=True)
    relative, unit = _unit_density_odometry(odometry, keys)
    odometry_cov = np.einsum("k,nkij->nij", noise.densities() ** 2, unit)

    # start: snapshot poses, dead reckoning from the nearest snapshot elsewhere
    reckoned = dead_reckoning(relative)
    snap_key = np.searchsorted(keys, snapshots.stamps)
    snap_key = np.clip(snap_key, 0, keys.size - 1)
    exact = keys[snap_key] == snapshots.stamps
    anchor_keys, anchor_poses = snap_key[exact], snapshots.poses[exact]
    nearest = np.clip(np.searchsorted(anchor_keys, np.arange(keys.size)), 0, anchor_keys.size - 1)
    previous = np.clip(nearest - 1, 0, anchor_keys.size - 1)
    closer = np.abs(anchor_keys[previous] - np.arange(keys.size)) < np.abs(
        anchor_keys[nearest] - np.arange(keys.size)
    )
    anchor = np.where(closer, previous, nearest)
    initial = se2.compose(
        anchor_poses[anchor],
        se2.between(reckoned[anchor_keys[anchor]], reckoned),
    )

    problem = Problem()
    pose_ids = problem.add_variables(POSE, [("x", k) for k in range(keys.size)], initial)
    subjects = np.array(truth.feature_ids)
    point_ids = problem.add_variables(
        POINT, [("l", int(s)) for s in subjects], truth.feature_positions
    )
    problem.add_factor(PointPrior(point_ids, truth.feature_positions, covariance=np.eye(2) * 1e-6))
    problem.add_factor(RelativePose(pose_ids[:-1], pose_ids[1:], relative, covariance=odometry_cov))
    labels = truth.label_to_feature[robot.name]
    where = {int(s): k for k, s in enumerate(subjects)}
    obs_subject_row = np.array(
        [where[labels[int(lab)]] for lab in features.labels[inside]], dtype=np.int64
    )
    ranges = features.ranges[inside]
    bearings = features.bearings[inside]
    sigma_r = noise.sigma_range + noise.sigma_range_per_m * ranges
    z, z_cov = polar_to_cartesian(ranges, bearings, sigma_r, noise.sigma_bearing)
    problem.add_factor(
        PointObservation(
            pose_ids[key_of],
            point_ids[obs_subject_row],
            z,
            covariance=z_cov,
            robust=Cauchy() if robust else None,
        )
    )
    report = problem.solve(SolverOptions(max_iterations=50))
    poses = problem.values_of(pose_ids)

    # Covariances of the poses and of consecutive pairs. The landmarks are held to 1 mm, so
    # the pose block of the information matrix (conditional on the landmarks) is block
    # tridiagonal: its selected inverse comes from one forward and one backward recursion.
    system = factorize_at_estimate(problem)
    n_pose = 3 * keys.size
    information = system.full_matrix()[:n_pose, :n_pose]
    pose_cov, pair_cov = chain_covariances(information, keys.size)
    landmarks = truth.feature_positions[obs_subject_row]
    pose_of = poses[key_of]
    d = landmarks - pose_of[:, :2]
    predicted_r = np.linalg.norm(d, axis=1)
    predicted_b = np.arctan2(d[:, 1], d[:, 0]) - pose_of[:, 2]
    j_r = np.stack([-d[:, 0] / predicted_r, -d[:, 1] / predicted_r, np.zeros_like(predicted_r)], 1)
    j_b = np.stack(
        [d[:, 1] / predicted_r**2, -d[:, 0] / predicted_r**2, -np.ones_like(predicted_r)], 1
    )
    c = pose_cov[key_of]
    return Localisation(
        robot=robot.name,
        stamps=keys,
        poses=poses,
        pose_covariances=pose_cov,
        pair_covariances=pair_cov,
        odometry_z=relative,
        odometry_unit=unit,
        observation_key=key_of,
        ranges=ranges,
        range_residuals=ranges - predicted_r,
        bearing_residuals=se2.wrap_angle(bearings - predicted_b),
        range_variance=np.einsum("ki,kij,kj->k", j_r, c, j_r),
        bearing_variance=np.einsum("ki,kij,kj->k", j_b, c, j_b),
        iterations=report.iterations,
        seconds=time.perf_counter() - began,
    )


def chain_covariances(information: sp.spmatrix, n: int) -> tuple[FloatArray, FloatArray]:
    """Diagonal and first off-diagonal blocks of the inverse of a block-tridiagonal matrix.

    ``information`` is ``(3n, 3n)`` symmetric with 3x3 blocks, nonzero only on the block
    diagonal and the first block off-diagonals. Returns the covariances ``(n, 3, 3)`` and the
    joint covariances of consecutive blocks ``(n-1, 6, 6)``.
    """
    block = np.arange(3)
    rows = 3 * np.arange(n)[:, None, None] + block[None, :, None]
    cols = 3 * np.arange(n)[:, None, None] + block[None, None, :]
    rows, cols = np.broadcast_arrays(rows, cols)
    diagonal = np.asarray(information[rows.reshape(-1), cols.reshape(-1)]).reshape(n, 3, 3)
    upper = np.asarray(information[rows[:-1].reshape(-1), (cols[:-1] + 3).reshape(-1)]).reshape(
        n - 1, 3, 3
    )
    schur = np.empty_like(diagonal)
    schur[0] = diagonal[0]
    for k in range(1, n):
        schur[k] = diagonal[k] - upper[k - 1].T @ np.linalg.solve(schur[k - 1], upper[k - 1])
    schur_inverse = np.linalg.inv(schur)
    cov = np.empty_like(diagonal)
    cross = np.empty_like(upper)
    cov[-1] = schur_inverse[-1]
    for k in range(n - 2, -1, -1):
        gain = schur_inverse[k] @ upper[k]  # S_k^-1 B_k
        cross[k] = -gain @ cov[k + 1]
        cov[k] = schur_inverse[k] - cross[k] @ gain.T
    pair = np.zeros((n - 1, 6, 6))
    pair[:, :3, :3] = cov[:-1]
    pair[:, 3:, 3:] = cov[1:]
    pair[:, :3, 3:] = cross
    pair[:, 3:, :3] = cross.transpose(0, 2, 1)
    return 0.5 * (cov + cov.transpose(0, 2, 1)), pair


def _fit_range_sigma(
    ranges: FloatArray, expected_squares: FloatArray, intercept: float, slope: float
) -> tuple[float, float]:
    """Maximum likelihood of ``sigma(r) = a + b r`` (``a > 0``, ``b >= 0``) from expected
    squared residuals."""
    from scipy.optimize import minimize  # on use: scipy.optimize loads slowly

    floor = 1e-3  # m: keeps a > 0 when the data favour a purely proportional model

    def negative_log_likelihood(p: FloatArray) -> float:
        sigma = floor + np.exp(p[0]) + np.exp(p[1]) * ranges
        return float(np.sum(np.log(sigma) + 0.5 * expected_squares / sigma**2))

    start = np.log([max(intercept - floor, 1e-4), max(slope, 1e-4)])
    p = minimize(
        negative_log_likelihood, start, method="Nelder-Mead", options={"xatol": 1e-5, "fatol": 1e-8}
    ).x
    return float(floor + np.exp(p[0])), float(np.exp(p[1]))


def _odometry_expected_scatter(loc: Localisation) -> tuple[FloatArray, FloatArray]:
    """Residuals of the odometry factors and their expected outer products ``e e^T + J P J^T``."""
    a, b = loc.poses[:-1], loc.poses[1:]
    residual = se2.between(a, b) - loc.odometry_z
    residual[:, 2] = se2.wrap_angle(residual[:, 2])
    j1, j2 = se2.compose_jacobians(se2.inverse(a), b)
    ja = j1 @ se2.inverse_jacobian(a)
    jab = np.concatenate([ja, j2], axis=2)  # (n, 3, 6)
    spread = jab @ loc.pair_covariances @ jab.transpose(0, 2, 1)
    return residual, residual[:, :, None] * residual[:, None, :] + spread


def em_noise(
    log: MultiRobotLog,
    noise: NoiseModel,
    snapshots: dict[str, Snapshots],
    rounds: int = 12,
    gate: float = 5.0,
    progress: Progress | None = None,
    tolerance: float = 0.01,
) -> tuple[NoiseModel, dict]:
    """Expectation-maximisation of the noise model over localisations with known landmarks.

    E-step: :func:`localise` every robot with the current model; each factor's expected
    squared residual is its residual squared plus the spread of its prediction under the
    smoothed pose covariance. M-step: range sigma per range bin (fitted ``a + b r``) and one
    bearing sigma from the expected squares of observations within ``gate`` sigmas; odometry
    densities maximise the expected log-likelihood of the odometry factors. Stops when no
    value changes by more than ``tolerance`` (relative) in a round.
    """
    from scipy.optimize import minimize  # on use: scipy.optimize loads slowly

    assert log.truth is not None
    history = []
    for _ in range(rounds):
        locs = {
            name: localise(robot, log.truth, noise, snapshots[name])
            for name, robot in log.robots.items()
        }
        ranges = np.concatenate([loc.ranges for loc in locs.values()])
        e_r = np.concatenate([loc.range_residuals for loc in locs.values()])
        e_b = np.concatenate([loc.bearing_residuals for loc in locs.values()])
        v_r = np.concatenate([loc.range_variance for loc in locs.values()])
        v_b = np.concatenate([loc.bearing_variance for loc in locs.values()])
        # The gate scales with the robust spread of the residuals themselves, not with the
        # current model: a gate tied to the model lets outliers inflate it round after round.
        normalised = e_r / (noise.sigma_range + noise.sigma_range_per_m * ranges)
        inlier = (np.abs(normalised) < gate * robust_sigma(normalised)) & (
            np.abs(e_b) < gate * robust_sigma(e_b)
        )
        intercept, slope = _fit_range_sigma(
            ranges[inlier],
            e_r[inlier] ** 2 + v_r[inlier],
            noise.sigma_range,
            noise.sigma_range_per_m,
        )
        sigma_b = float(np.sqrt(np.mean(e_b[inlier] ** 2 + v_b[inlier])))

        scatter, unit = [], []
        for loc in locs.values():
            scatter.append(_odometry_expected_scatter(loc)[1])
            unit.append(loc.odometry_unit)
        scatter_all = np.concatenate(scatter)
        unit_all = np.concatenate(unit)

        def expected_nll(
            log_q: FloatArray,
            unit_all: FloatArray = unit_all,
            scatter_all: FloatArray = scatter_all,
        ) -> float:
            sigma = np.einsum("k,nkij->nij", np.exp(2 * log_q), unit_all)
            sigma = sigma + np.eye(3) * 1e-12
            _, logdet = np.linalg.slogdet(sigma)
            trace = np.einsum("nij,nji->n", np.linalg.inv(sigma), scatter_all)
            return float(0.5 * np.sum(logdet + trace))

        q0 = np.log(noise.densities())
        q = np.exp(
            minimize(
                expected_nll, q0, method="Nelder-Mead", options={"xatol": 1e-4, "fatol": 1e-6}
            ).x
        )
        q = np.maximum(q, DENSITY_FLOOR)
        noise = replace(
            noise,
            sigma_range=float(intercept),
            sigma_range_per_m=float(slope),
            sigma_bearing=sigma_b,
            q_v=float(q[0]),
            q_vlat=float(q[1]),
            q_omega=float(q[2]),
        )
        normalised_r = e_r / (intercept + slope * ranges)
        normalised_b = e_b / sigma_b
        history.append(
            {
                "noise": asdict(noise),
                "outside_gate": float(1 - inlier.mean()),
                "range_beyond_3_sigma": float(np.mean(np.abs(normalised_r) > 3)),
                "bearing_beyond_3_sigma": float(np.mean(np.abs(normalised_b) > 3)),
                "range_beyond_5_sigma": float(np.mean(np.abs(normalised_r) > 5)),
                "bearing_beyond_5_sigma": float(np.mean(np.abs(normalised_b) > 5)),
                "seconds": float(sum(loc.seconds for loc in locs.values())),
                "iterations": {n: loc.iterations for n, loc in locs.items()},
            }
        )
        previous = history[-2]["noise"] if len(history) > 1 else None
        if progress is not None:
            last = history[-1]
            progress(
                f"  EM round {len(history)}: "
                + " ".join(f"{k}={last['noise'][k]:.4g}" for k in ESTIMATED)
                + f"  outside gate {100 * last['outside_gate']:.1f}%"
            )
        if previous is not None:
            change = max(abs(v / previous[k] - 1) for k, v in history[-1]["noise"].items())
            if change < tolerance:
                break
    return noise, {"rounds": history, "tolerance": tolerance, "localisations": locs}


def range_scale(loc: Localisation, gate: float = 5.0) -> tuple[float, float, float]:
    """Ratio of measured to true range of one robot's camera: weighted least squares of the
    measured on the predicted ranges of its localisation (weights ``1 / r^2``, the range
    sigma being proportional to range), on measurements within ``gate`` robust sigmas of
    their prediction. Returns the estimate on all measurements, on the first and on the
    second half of the run (the spread says whether it is a stable property of the camera).
    """
    predicted = loc.ranges - loc.range_residuals
    normalised = loc.range_residuals / predicted
    inlier = np.abs(normalised) < gate * robust_sigma(normalised)
    stamps = loc.stamps[loc.observation_key]
    middle = 0.5 * (stamps[0] + stamps[-1])

    def fit(use: NDArray[np.bool_]) -> float:
        w = 1.0 / predicted[use] ** 2
        return float(np.sum(w * loc.ranges[use] * predicted[use]) / np.sum(w * predicted[use] ** 2))

    return fit(inlier), fit(inlier & (stamps < middle)), fit(inlier & (stamps >= middle))


def rendezvous_noise(log: MultiRobotLog, locs: dict[str, Localisation], noise: NoiseModel) -> dict:
    """Rendezvous residuals against the two robots' localisations with known landmarks.

    Each measurement's residual is normalised by the model sigma combined with both robots'
    pose covariances (at the nearest key, odometry-composed to the stamp); the robust spread
    of the normalised residuals is the factor by which rendezvous sigmas exceed the landmark
    model ``noise``.
    """
    positions = {}

    def pose_at(name: str, t: FloatArray) -> tuple[FloatArray, FloatArray]:
        loc, odometry = locs[name], log.robots[name].odometry
        if name not in positions:
            positions[name] = odometry_poses(odometry.stamps, odometry.inputs)
        reckoned = positions[name]
        k = np.clip(np.searchsorted(loc.stamps, t, side="right") - 1, 0, loc.stamps.size - 1)
        moved = se2.between(
            odometry_poses_at(odometry.stamps, odometry.inputs, reckoned, loc.stamps[k]),
            odometry_poses_at(odometry.stamps, odometry.inputs, reckoned, t),
        )
        return se2.compose(loc.poses[k], moved), loc.pose_covariances[k]

    normalised_r, normalised_b = [], []
    for name, robot in log.robots.items():
        rv = robot.rendezvous
        if rv.stamps.size == 0 or name not in locs:
            continue
        inside = (rv.stamps >= locs[name].stamps[0]) & (rv.stamps <= locs[name].stamps[-1])
        observed = np.array(rv.observed, dtype=object)
        for other in sorted(set(rv.observed)):
            m = inside & (observed == other)
            if other not in locs or not m.any():
                continue
            p, cp = pose_at(name, rv.stamps[m])
            q, cq = pose_at(other, rv.stamps[m])
            d = q[:, :2] - p[:, :2]
            r = np.linalg.norm(d, axis=1)
            e_r = rv.ranges[m] - r
            e_b = se2.wrap_angle(rv.bearings[m] - (np.arctan2(d[:, 1], d[:, 0]) - p[:, 2]))
            zero = np.zeros_like(r)
            jr_p = np.stack([-d[:, 0] / r, -d[:, 1] / r, zero], 1)
            jb_p = np.stack([d[:, 1] / r**2, -d[:, 0] / r**2, -np.ones_like(r)], 1)
            jb_q = np.stack([-d[:, 1] / r**2, d[:, 0] / r**2, zero], 1)
            v_r = np.einsum("ki,kij,kj->k", jr_p, cp, jr_p) + np.einsum(
                "ki,kij,kj->k", jr_p, cq, jr_p
            )
            v_b = np.einsum("ki,kij,kj->k", jb_p, cp, jb_p) + np.einsum(
                "ki,kij,kj->k", jb_q, cq, jb_q
            )
            s_r = noise.sigma_range + noise.sigma_range_per_m * rv.ranges[m]
            normalised_r.append(e_r / np.sqrt(s_r**2 + v_r))
            normalised_b.append(e_b / np.sqrt(noise.sigma_bearing**2 + v_b))
    e_r, e_b = np.concatenate(normalised_r), np.concatenate(normalised_b)
    k_r, k_b = robust_sigma(e_r), robust_sigma(e_b)
    return {
        "n": int(e_r.size),
        "range_factor": k_r,
        "bearing_factor": k_b,
        "range_beyond_5": float(np.mean(np.abs(e_r) > 5 * k_r)),
        "bearing_beyond_5": float(np.mean(np.abs(e_b) > 5 * k_b)),
    }


def landmark_consistency(
    log: MultiRobotLog,
    snapshots: dict[str, Snapshots],
    range_gate: float = 1.0,
    bearing_gate: float = 0.3,
) -> dict[int, dict]:
    """Per landmark subject: share of its snapshot residuals beyond a gross gate.

    A subject whose measurements nearly all miss while the others fit has wrong ground truth
    (or a wrong barcode entry), not a noisy sensor.
    """
    assert log.truth is not None
    table: dict[int, list[int]] = {}
    for name, snap in snapshots.items():
        labels = log.truth.label_to_feature[name]
        subjects = np.array([labels[int(lab)] for lab in snap.labels], dtype=int)
        gross = (np.abs(snap.range_residuals) > range_gate) | (
            np.abs(snap.bearing_residuals) > bearing_gate
        )
        for subject in np.unique(subjects):
            mine = subjects == subject
            entry = table.setdefault(int(subject), [0, 0])
            entry[0] += int(mine.sum())
            entry[1] += int(gross[mine].sum())
    return {
        subject: {"n": n, "gross_fraction": bad / n} for subject, (n, bad) in sorted(table.items())
    }


@dataclass(frozen=True)
class LandmarkSwap:
    """Two landmark subjects whose true positions are exchanged in a ground truth, with the
    share of each one's snapshot residuals beyond the gross gate before and after."""

    subjects: tuple[int, int]
    gross_before: tuple[float, float]
    gross_after: tuple[float, float]

    def line(self) -> str:
        (a, b), before, after = self.subjects, self.gross_before, self.gross_after
        return (
            f"true positions of landmark subjects {a} and {b} exchanged (detected: "
            f"{before[0]:.0%} and {before[1]:.0%} of their measurements miss by metres, "
            f"{after[0]:.0%} and {after[1]:.0%} after)"
        )


def detect_landmark_swaps(
    log: MultiRobotLog,
    noise: NoiseModel,
    misfit: float = 0.5,
    fit: float = 0.1,
    min_measurements: int = 5,
) -> list[LandmarkSwap]:
    """Pairs of landmark subjects whose true positions are exchanged in ``log.truth``.

    A subject misfits when more than ``misfit`` of its snapshot residuals are gross
    (:func:`landmark_consistency`: its measurements miss its true position by metres while
    the other landmarks fit); two misfits are a swap when, their positions exchanged, both
    fit (at most ``fit`` gross). Needs no robot ground truth. MR.CLAM Dataset 1: subjects 11
    and 17 at 97 % and 98 %, every other subject at most 3 %; Datasets 2 and 4: none above
    2 %."""
    if log.truth is None:
        raise ValueError("detecting swapped landmarks needs the landmark ground truth")

    def gross(truth: GroundTruth) -> dict[int, float]:
        trial = replace(log, truth=truth)
        snapshots = {n: snapshot_localisation(r, truth, noise) for n, r in log.robots.items()}
        return {
            subject: entry["gross_fraction"]
            for subject, entry in landmark_consistency(trial, snapshots).items()
            if entry["n"] >= min_measurements
        }

    before = gross(log.truth)
    misfits = sorted(s for s, share in before.items() if share > misfit)
    swaps: list[LandmarkSwap] = []
    for i, a in enumerate(misfits):
        for b in misfits[i + 1 :]:
            if any({a, b} & set(s.subjects) for s in swaps):
                continue
            after = gross(exchange_landmarks(log.truth, a, b))
            if after.get(a, 1.0) <= fit and after.get(b, 1.0) <= fit:
                swaps.append(LandmarkSwap((a, b), (before[a], before[b]), (after[a], after[b])))
    return swaps


def exchange_landmarks(truth: GroundTruth, a: int, b: int) -> GroundTruth:
    """``truth`` with the positions of landmark subjects ``a`` and ``b`` exchanged."""
    rows = [int(np.flatnonzero(truth.feature_ids == s)[0]) for s in (a, b)]
    positions = truth.feature_positions.copy()
    positions[rows] = positions[rows[::-1]]
    return replace(truth, feature_positions=positions)


@dataclass
class NoiseEstimate:
    """What :func:`estimate_noise` found, with its diagnostics."""

    noise: NoiseModel  # the final model (expectation-maximisation)
    first_estimate: NoiseModel  # from the snapshots alone
    em: dict
    sensor: SensorNoiseEstimate
    odometry: OdometryNoiseEstimate
    landmarks: dict[int, dict]
    seconds: float
    # robot -> measured / true range (whole run, first half, second half)
    range_scale: dict[str, tuple[float, float, float]] = field(default_factory=dict)


def estimate_noise(
    log: MultiRobotLog,
    rounds: int = 12,
    start: NoiseModel = NEUTRAL_START,
    progress: Progress | None = None,
) -> NoiseEstimate:
    """The whole estimation (module docstring) on robots' logs with the landmark truth:
    steps 1-3, then (``rounds`` > 0) at most ``rounds`` rounds of expectation-maximisation,
    the rendezvous factors and each robot's range scale. ``progress`` receives a line per
    step and per round."""
    if log.truth is None:
        raise ValueError("noise estimation needs the landmark ground truth")
    began = time.perf_counter()

    def report(line: str) -> None:
        if progress is not None:
            progress(line)

    report("1. snapshot localisation and sensor noise")
    sensor, snapshots = estimate_sensor_noise(log, start)
    report("2. odometry noise from snapshot pairs")
    odometry = estimate_odometry_noise(log, snapshots)
    q_v, q_vlat, q_omega = odometry.q
    noise = replace(sensor.noise, q_v=q_v, q_vlat=q_vlat, q_omega=q_omega)
    landmarks = landmark_consistency(log, snapshots)
    if not rounds:
        return NoiseEstimate(
            noise, noise, {"rounds": []}, sensor, odometry, landmarks, time.perf_counter() - began
        )
    report("3. expectation-maximisation over localisations with the known landmarks")
    final, history = em_noise(log, noise, snapshots, rounds=rounds, progress=progress)
    report("4. rendezvous factors and range scales")
    locs = history.pop("localisations")
    rendezvous = rendezvous_noise(log, locs, final)
    final = replace(
        final,
        rendezvous_range_factor=max(1.0, rendezvous["range_factor"]),
        rendezvous_bearing_factor=max(1.0, rendezvous["bearing_factor"]),
    )
    history["rendezvous"] = rendezvous
    return NoiseEstimate(
        final,
        noise,
        history,
        sensor,
        odometry,
        landmarks,
        time.perf_counter() - began,
        {name: range_scale(loc) for name, loc in locs.items()},
    )
