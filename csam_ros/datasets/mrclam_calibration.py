"""Noise model and camera range scales of an MR.CLAM data set, written as a config file.

:func:`calibrate_mrclam` imports the data set with its landmark truth and runs the generic
estimation of :mod:`csam_ros.core.truth.calibration` on it; :func:`calibration_config` turns the
result into the text of a parameter file in the format of ``config/mrclam.yaml`` (read by
:func:`csam_ros.datasets.mrclam.load_config`, ``csam import mrclam`` and ``csam replay
--config``). ``csam calibrate mrclam DATASET_DIR --out FILE.yaml`` does both.
"""

from __future__ import annotations

import re
import textwrap
from dataclasses import asdict
from pathlib import Path

from csam_ros.core.truth.calibration import NoiseEstimate, Progress, estimate_noise
from csam_ros.core.truth.noise_model import NoiseModel
from csam_ros.datasets.mrclam import LandmarkSwaps, import_mrclam, landmark_swaps_of, load_config

_TOP_LEVEL_KEY = re.compile(r"^[A-Za-z_][\w-]*:")


def calibrate_mrclam(
    directory: str | Path,
    landmark_swaps: LandmarkSwaps = (),
    robots: list[int] | None = None,
    start: float = 0.0,
    duration: float | None = None,
    rounds: int = 12,
    progress: Progress | None = None,
) -> NoiseEstimate:
    """Estimate the noise model and each camera's range scale from (a window of) a data set,
    after exchanging the true positions of ``landmark_swaps`` (see the importer)."""
    if progress is not None:
        progress(f"importing {directory}")
    log, _ = import_mrclam(
        directory,
        robots=robots,
        start=start,
        duration=duration,
        landmark_swaps=landmark_swaps,
    )
    return estimate_noise(log, rounds=rounds, progress=progress)


def range_scales(estimate: NoiseEstimate) -> dict[int, float]:
    """Robot number -> measured / true range over the whole window (``mrclam.range_scale``)."""
    return {int(name[5:]): whole for name, (whole, _, _) in sorted(estimate.range_scale.items())}


def calibration_config(estimate: NoiseEstimate, base: str | Path, source: str) -> str:
    """Text of a parameter file: an ``mrclam:`` section with the estimated ``noise`` and
    ``range_scale`` (its window, labels and truth swaps from ``base``), followed by ``base``'s
    other sections (``local_map:``, ``merger:``, ``csam:``) verbatim with their comments.
    ``source`` says in the header what was calibrated."""
    settings = load_config(base)
    n = estimate.noise
    s, o, f = estimate.sensor, estimate.odometry, estimate.first_estimate
    rounds = estimate.em.get("rounds", [])
    rendezvous = estimate.em.get("rendezvous")
    scales = range_scales(estimate)
    halves = ", ".join(
        f"robot{name[5:]} {first:.4f} / {second:.4f}"
        for name, (_, first, second) in sorted(estimate.range_scale.items())
    )
    lines = [
        "# MR.CLAM noise model and camera range scales estimated by `csam calibrate mrclam`",
        "# against the landmark ground truth (steps in csam_ros/core/truth/calibration.py) from",
        f"#   {source}.",
        "# The import window, label seed and truth swaps, and the sections after `mrclam:`,",
        f"# are those of {base}.",
        "mrclam:",
        f"  robots: {_flow(settings.get('robots'))}",
        f"  start: {_flow(settings.get('start', 0.0))}        # s after the data set's first stamp",
        f"  duration: {_flow(settings.get('duration'))}    # s; null = to the end",
        f"  label_seed: {_flow(settings.get('label_seed', 0))}     # seeds each robot's local "
        "landmark numbering",
        "",
        f"  # 1. First estimate, without odometry: {s.n_snapshots} camera frames that see >= 3",
        f"  #    landmarks, {s.n_observations} residuals: s_r = {f.sigma_range:.4f} + "
        f"{f.sigma_range_per_m:.4f} r, s_b = {f.sigma_bearing:.4f} rad; {o.n_pairs} snapshot",
        f"  #    pairs vs dead reckoning: q = ({f.q_v:.4f}, {f.q_vlat:.4f}, {f.q_omega:.4f}).",
        f"  # 2. Expectation-maximisation over the localisations with the known landmarks, "
        f"{len(rounds)}",
        "  #    rounds (the values below).",
    ]
    if rounds:
        last = rounds[-1]
        lines.append(
            f"  #    Beyond 5 robust sigmas: range {100 * last['range_beyond_5_sigma']:.2f}%, "
            f"bearing {100 * last['bearing_beyond_5_sigma']:.2f}%."
        )
    if rendezvous:
        lines.append(
            f"  # 3. Rendezvous: {rendezvous['n']} measurements spread "
            f"{rendezvous['range_factor']:.2f} x the range model, "
            f"{rendezvous['bearing_factor']:.2f} x the bearing model."
        )
    lines += [
        "  noise:",
        *_noise_lines(n),
        "",
        "  # 4. Range calibration: measured / true range of each robot's camera (robot number:",
        "  #    ratio); the importer divides every range the robot measured by it. First /",
        "  #    second half of the window:",
        *textwrap.wrap(halves or "none", 88, initial_indent="  #    ", subsequent_indent="  #    "),
        "  range_scale: {"
        + ", ".join(f"{number}: {value:.6g}" for number, value in scales.items())
        + "}",
        "",
        "  # Ground-truth correction (scoring only): pairs of landmark subjects whose listed",
        "  # positions are exchanged, or auto: found from the measurements.",
        f"  landmark_swaps: {_swaps_text(landmark_swaps_of(settings))}",
    ]
    rest = _other_sections(Path(base).read_text())
    return "\n".join(lines) + "\n" + ("\n" + rest if rest else "")


def _noise_lines(noise: NoiseModel) -> list[str]:
    """The ``noise:`` entries, each with its unit or meaning."""
    notes = {
        "sigma_range": "m, at zero range",
        "sigma_range_per_m": "m per m of range",
        "sigma_bearing": "rad",
        "q_v": "m/sqrt(s): odometry noise densities, pose noise q^2 t",
        "q_vlat": "m/sqrt(s)",
        "q_omega": "rad/sqrt(s)",
        "rendezvous_range_factor": "measurements of other robots: landmark sigmas times these",
        "rendezvous_bearing_factor": "",
    }
    lines = []
    for key, value in asdict(noise).items():
        entry = f"    {key}: {value:.6g}"
        lines.append(f"{entry:<35} # {notes[key]}" if notes[key] else entry)
    return lines


def _swaps_text(swaps: LandmarkSwaps) -> str:
    return swaps if isinstance(swaps, str) else _flow([list(p) for p in swaps])


def _flow(value: object) -> str:
    """A YAML flow-style scalar or list."""
    if value is None:
        return "null"
    if isinstance(value, list | tuple):
        return "[" + ", ".join(_flow(v) for v in value) + "]"
    return str(value)


def _other_sections(text: str) -> str:
    """The part of a config file after its ``mrclam:`` section: from the comment block that
    leads the next top-level key to the end."""
    lines = text.splitlines()
    begin = next((i for i, line in enumerate(lines) if line.startswith("mrclam:")), None)
    if begin is None:
        return text
    after = next((i for i in range(begin + 1, len(lines)) if _TOP_LEVEL_KEY.match(lines[i])), None)
    if after is None:
        return ""
    while after > begin + 1 and lines[after - 1].startswith("#"):
        after -= 1
    return "\n".join(lines[after:]) + "\n"
