"""Steps 1-3 of the noise estimation (:mod:`csam_ros.core.truth.calibration`): poses fixed by
single camera frames against the known landmarks, and the sensor and odometry noise their
residuals give.

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

:func:`landmark_consistency` tells, per landmark, how many of its snapshot residuals miss by
metres (a wrong ground truth rather than a noisy sensor).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray

from csam_ros.core.model import se2
from csam_ros.core.model.chi_square import chi2_quantile
from csam_ros.core.model.log import GroundTruth, MultiRobotLog, OdometryLog, RobotLog
from csam_ros.core.model.motion import odometry_poses, odometry_poses_at
from csam_ros.core.truth.noise_model import (
    DENSITY_FLOOR,
    NEUTRAL_START,
    NoiseModel,
    robust_sigma,
)

FloatArray = NDArray[np.float64]
CAUCHY_SCALE = 2.3849  # 95% efficiency at the normal distribution


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


# ---------------------------------------------------------------------------------------------
# sensor noise


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
