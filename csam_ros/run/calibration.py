"""A data set's noise model and range scales estimated and written as a config file
(``csam calibrate``)."""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

from csam_ros.run.errors import RunError
from csam_ros.run.importing import robot_numbers


def calibrate_dataset(
    source: Path,
    out: Path,
    config: Path | None = None,
    no_swaps: bool = False,
    robots: str | None = None,
    start: float = 0.0,
    duration: float | None = None,
    rounds: int = 12,
    progress: Callable[[str], None] = print,
) -> list[str]:
    """Estimate the MR.CLAM data set ``source``'s noise model and range scales and write
    them as the new config file ``out`` (the rest as in ``config``, default: the installed
    mrclam.yaml); what was estimated, as lines. The window, each expectation-maximisation
    round and the like go to ``progress`` as they happen."""
    from csam_ros.core.model.config_file import ConfigFileError, resolve_config_path
    from csam_ros.datasets.mrclam import MrclamFormatError, landmark_swaps_of, load_config
    from csam_ros.datasets.mrclam_calibration import (
        calibrate_mrclam,
        calibration_config,
        range_scales,
    )

    if out.exists():
        raise RunError(f"{out} exists: calibrate never overwrites a file")
    if not source.is_dir():
        raise RunError(f"{source}: no such data set directory")
    if rounds < 1:
        raise RunError(f"--rounds must be at least 1, got {rounds}")
    try:
        base = resolve_config_path(config or "mrclam")
        swaps = landmark_swaps_of(load_config(base))
    except (ConfigFileError, OSError, ValueError) as err:
        raise RunError(f"--config: {err}") from None
    numbers = robot_numbers(robots)
    window = f"[{start}, {'end' if duration is None else start + duration}] s"
    progress(f"calibrating on {source}, window {window} (about 40 s for all of Dataset 1)")
    began = time.perf_counter()
    try:
        estimate = calibrate_mrclam(
            source,
            landmark_swaps=[] if no_swaps else swaps,
            robots=numbers,
            start=start,
            duration=duration,
            rounds=rounds,
            progress=progress,
        )
    except MrclamFormatError as err:  # names the file and line
        raise RunError(str(err)) from None
    except ValueError as err:  # numbers the estimate cannot use (a LinAlgError too)
        raise RunError(f"{source}: no calibration from this data ({err})") from None
    text = calibration_config(
        estimate, base, f"{source} (window {window}, robots {robots or 'all'})"
    )
    out.parent.mkdir(parents=True, exist_ok=True)
    try:
        with open(out, "x") as stream:
            stream.write(text)
    except FileExistsError:
        raise RunError(f"{out} exists: calibrate never overwrites a file") from None
    n = estimate.noise
    scales = ", ".join(f"robot{k} {v:.4f}" for k, v in range_scales(estimate).items())
    return [
        f"noise: sigma_range {n.sigma_range:.4f} + {n.sigma_range_per_m:.4f} r m, "
        f"sigma_bearing {n.sigma_bearing:.4f} rad, q = ({n.q_v:.4f}, {n.q_vlat:.4f}, "
        f"{n.q_omega:.4f}), rendezvous factors {n.rendezvous_range_factor:.2f}, "
        f"{n.rendezvous_bearing_factor:.2f}",
        f"range scale (measured / true): {scales}",
        f"wrote {out} ({time.perf_counter() - began:.0f} s)",
    ]
