"""Odometry that lies: local maps with and without odometry calibration on miscalibrated
odometry (csam_ros/datasets/odometry_stress.py), simulated then on MR.CLAM.

    python -m csam_ros.bench.odometry_calibration [--mrclam DIR] [--duration 300]
        [--stress turn_driving=1.54,resample_hz=8]

Simulated: two robots driving arcs and turning on the spot with ``k_d = 1.5`` (reported turn
while driving 1.5x the real one) and distance 0.95; prints the estimated scales, the applied
ones and the sigmas, and the cost of the calibration unknowns per local-map update (the online
policy: an update every ``UPDATE_PERIOD`` s of data, as a smoother publishes). MR.CLAM:
whole C-SAM on the stressed data set with calibration off and on: robots that pass the
local-map consistency check and align, landmark RMSE, the time of the local maps.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace

import numpy as np

from csam_ros.core.joining.pipeline import run_csam
from csam_ros.core.model.log import RobotLog
from csam_ros.core.sam.factors import Cauchy
from csam_ros.core.smoothing.fold_check import ConsistencyOptions, factor_outliers
from csam_ros.core.smoothing.local_map import LocalMap
from csam_ros.core.smoothing.local_map_build import build_local_map
from csam_ros.core.smoothing.local_map_config import LocalMapOptions
from csam_ros.core.smoothing.local_map_state import UpdateReport
from csam_ros.core.truth.evaluation import evaluate
from csam_ros.datasets.odometry_stress import OdometryStress, parse_odometry_stress, stress_log
from csam_ros.datasets.simulation import arcs_scenario, simulate

UPDATE_PERIOD = 5.0  # s of data between local-map updates (config/mrclam.yaml publish_period)


def update_seconds(robot: RobotLog, calibrate: bool) -> np.ndarray:
    """The time of each online update of ``robot``'s local map (the last one converged)."""
    reports: list[UpdateReport] = []
    options = LocalMapOptions(odometry_calibration=calibrate)
    build_local_map(robot, options=options, window=UPDATE_PERIOD, on_update=reports.append)
    return np.array([r.seconds for r in reports[:-1]])


def simulated(stress: OdometryStress) -> None:
    log = simulate(arcs_scenario(stress))
    print(f"simulated, applied (s, k_d, k_s) = {np.round(stress.applied, 4).tolist()}")
    for name, robot in log.robots.items():
        times = {}
        for on in (False, True):
            local = LocalMap(name, LocalMapOptions(odometry_calibration=on))
            local.add_log(robot)
            clock = time.perf_counter()
            local.update(converge=True)
            times[on] = time.perf_counter() - clock
        cal = local.odometry_calibration
        assert cal is not None
        error = (cal.scale - stress.applied) / stress.applied
        print(
            f"  {name}: scale {np.round(cal.scale, 4).tolist()} sigma "
            f"{np.round(cal.sigma, 4).tolist()} error {np.round(100 * error, 2).tolist()} % "
            f"| converged solve {times[False]:.3f} s off, {times[True]:.3f} s on"
        )
        off, on = update_seconds(robot, False), update_seconds(robot, True)
        print(
            f"    per local-map update ({len(on)} updates of {UPDATE_PERIOD:g} s of data): "
            f"mean {1e3 * off.mean():.1f} ms off, {1e3 * on.mean():.1f} ms on "
            f"({1e3 * (on.mean() - off.mean()):+.1f} ms); max {1e3 * off.max():.1f} / "
            f"{1e3 * on.max():.1f} ms"
        )


SLIPS = ((30.0, 0.6), (50.0, -0.8), (40.0, 1.2))  # (s after the start, rad) a turn never made


def slips() -> None:
    """A fold cannot persist: each arcs robot with a slip besides the stress, its local map
    (Cauchy kernel, calibration on, online updates every UPDATE_PERIOD s) without and with
    ``fold_recovery``."""
    print("slips (turn reported, never made), calibration on, Cauchy kernel:")
    for at, turn in SLIPS:
        stress = OdometryStress(turn_driving=1.5, resample_hz=8, slip_at=at, slip_turn=turn)
        for name, robot in simulate(arcs_scenario(stress)).robots.items():
            row = []
            for recover in (False, True):
                options = LocalMapOptions(
                    robust=Cauchy(1.0), odometry_calibration=True, fold_recovery=recover
                )
                clock = time.perf_counter()
                local = build_local_map(robot, options=options, window=UPDATE_PERIOD)
                seconds = time.perf_counter() - clock
                limits = ConsistencyOptions()
                counts = factor_outliers(local.problem, limits.gate_probability)
                verdict = "passes" if not counts.reasons(limits) else "fails"
                row.append(
                    f"{'with' if recover else 'without'} recovery: {verdict}, "
                    f"{counts.observation_outliers}/{counts.observation_factors} observations "
                    f"beyond the gate, k_d {local.odometry_calibration.scale[1]:.4f}, "
                    f"{local.fold_recoveries} recoveries, {seconds:.1f} s"
                )
            print(f"  slip {turn:+.1f} rad at {at:g} s, {name}: " + " | ".join(row))


def mrclam(directory: str, duration: float | None, stress: OdometryStress) -> None:
    from csam_ros.bench.mrclam import CONFIG, RunOptions
    from csam_ros.datasets.mrclam import import_mrclam, landmark_swaps_of, load_config

    options = RunOptions.from_config(CONFIG)
    config = load_config(CONFIG)
    log, _ = import_mrclam(
        directory,
        duration=duration,
        noise=config["noise"],
        label_seed=int(config.get("label_seed", 0)),
        landmark_swaps=landmark_swaps_of(config),
        range_scale=config.get("range_scale"),
    )
    log = stress_log(log, stress)
    print(f"MR.CLAM {directory} duration {duration} stress {stress}")
    for on in (False, True):
        local_map = replace(options.local_map, odometry_calibration=on)
        result = run_csam(log, options.csam, local_map)
        metrics = evaluate(result, log.truth)
        robots = result.robots.values()
        passed = sum(r.local_check is not None and r.local_check.passed for r in robots)
        aligned = sum(r.joined for r in robots)
        landmark = metrics["landmark_error"]
        print(
            f"  calibration {'on ' if on else 'off'}: consistency check passed {passed}/"
            f"{len(result.robots)}, joined {aligned}, landmark rmse "
            f"{landmark.get('rmse_m')}, local maps {result.timing_s.get('local_maps', 0):.2f} s"
        )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--mrclam", help="MR.CLAM data set directory (default: simulated only)")
    parser.add_argument("--duration", type=float, default=None)
    parser.add_argument("--stress", default="turn_driving=1.54,resample_hz=8")
    a = parser.parse_args(argv)
    simulated(OdometryStress(turn_driving=1.5, distance=0.95))
    slips()
    if a.mrclam:
        mrclam(a.mrclam, a.duration, parse_odometry_stress(a.stress))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
