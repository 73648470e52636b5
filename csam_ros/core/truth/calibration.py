"""Noise model and range-scale estimation of robots with a range-bearing sensor and velocity
odometry, against known landmark positions (no robot ground truth needed).

Steps (:func:`estimate_noise`, on a :class:`~csam_ros.core.model.log.MultiRobotLog` with its
:class:`~csam_ros.core.model.log.GroundTruth` landmarks):

1-3. Snapshot localisation, then the sensor and the odometry noise from the snapshots
   (:mod:`csam_ros.core.truth.snapshots`): every camera frame that sees at least three
   distinct landmarks fixes the robot pose; the residuals of those fits give the sensor
   sigmas, the snapshot pairs against dead reckoning the odometry densities.
4. Final values (:func:`em_noise`): expectation-maximisation over every robot's localisation
   with the known landmarks by the smoothing engine
   (:func:`~csam_ros.core.truth.localisation.localise`), starting from 1-3; then the
   rendezvous factors from residuals against both robots' localisations
   (:func:`rendezvous_noise`).
5. Range calibration (:func:`range_scale`): per robot, the weighted least-squares ratio of
   measured to predicted range over the final localisations' inliers.

The model is :class:`~csam_ros.core.truth.noise_model.NoiseModel`.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace

import numpy as np
from numpy.typing import NDArray

from csam_ros.core.model import se2
from csam_ros.core.model.log import MultiRobotLog
from csam_ros.core.model.motion import odometry_poses, odometry_poses_at
from csam_ros.core.truth.localisation import Localisation, localise
from csam_ros.core.truth.noise_model import (
    DENSITY_FLOOR,
    ESTIMATED,
    NEUTRAL_START,
    NoiseModel,
    robust_sigma,
)
from csam_ros.core.truth.snapshots import (
    OdometryNoiseEstimate,
    SensorNoiseEstimate,
    Snapshots,
    estimate_odometry_noise,
    estimate_sensor_noise,
    landmark_consistency,
)

FloatArray = NDArray[np.float64]
Progress = Callable[[str], None]


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
