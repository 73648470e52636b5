"""Data sets into bags of sensor topics (``csam import``): MR.CLAM with its config's noise model,
range scales and truth swaps, or a 2D SLAM file."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from csam_ros.run.errors import RunError


def robot_numbers(text: str | None) -> list[int] | None:
    """``--robots 1,2,3`` as robot numbers (None: all robots)."""
    if not text:
        return None
    try:
        numbers = [int(r) for r in text.split(",")]
    except ValueError:
        raise RunError(f"--robots: expected robot numbers such as 1,2,3, got {text!r}") from None
    if any(n < 1 for n in numbers):
        raise RunError(f"--robots: robot numbers start at 1, got {text!r}")
    return numbers


def import_dataset(
    data_format: str,
    source: Path,
    out: Path,
    robots: str | None = None,
    start: float = 0.0,
    duration: float | None = None,
    config: Path | None = None,
    occlude: str | None = None,
    odometry_stress: str | None = None,
    progress: Callable[[str], None] = print,
) -> tuple[int, int]:
    """Write the data set ``source`` as a new bag ``out``; its message and robot counts.

    MR.CLAM: ``robots`` (e.g. ``1,2,3``; None: all), ``start`` and ``duration`` [s] pick the
    data, ``config`` (default: the installed mrclam.yaml) its noise model, range scales and
    truth swaps, ``occlude`` the landmark observations dropped, ``odometry_stress`` (e.g.
    ``turn_driving=1.54,resample_hz=8``) the odometry miscalibrated; the import's report goes
    to ``progress``."""
    from csam_ros.run.bag_io import write_log_bag

    if out.exists():
        raise RunError(f"{out} exists: an import never overwrites a bag")
    if data_format == "mrclam":
        from csam_ros.core.model.config_file import ConfigFileError, resolve_config_path
        from csam_ros.datasets.mrclam import (
            MrclamFormatError,
            import_mrclam,
            landmark_swaps_of,
            load_config,
            parse_occlusion,
        )

        try:
            settings = load_config(resolve_config_path(config or "mrclam"))
        except (ConfigFileError, OSError, ValueError) as err:
            raise RunError(f"--config: {err}") from None
        numbers = robot_numbers(robots)
        try:
            occlusion = parse_occlusion(occlude) if occlude is not None else None
        except ValueError as err:
            raise RunError(f"--occlude: {err}") from None
        try:
            log, report = import_mrclam(
                source,
                robots=numbers,
                start=start,
                duration=duration,
                noise=settings["noise"],
                landmark_swaps=landmark_swaps_of(settings),
                range_scale=settings.get("range_scale"),
                occlusion=occlusion,
            )
        except (MrclamFormatError, ValueError) as err:
            raise RunError(str(err)) from None
        progress(report.summary())
        if odometry_stress:
            from csam_ros.datasets.odometry_stress import parse_odometry_stress, stress_log

            try:
                log = stress_log(log, parse_odometry_stress(odometry_stress))
            except ValueError as err:
                raise RunError(f"--odometry-stress: {err}") from None
    else:
        from csam_ros.datasets.slam2d import Slam2dFormatError
        from csam_ros.datasets.slam2d_log import read_slam2d_log

        if occlude is not None:
            raise RunError("--occlude is an option of import mrclam")
        if odometry_stress:
            raise RunError("--odometry-stress is an option of import mrclam")

        try:
            log = read_slam2d_log(source)
        except Slam2dFormatError as err:
            raise RunError(str(err)) from None
    return write_log_bag(log, out), len(log.robots)
