"""Camera range scales of MR.CLAM from mutual rendezvous, against the truth-fitted ones.

``python -m csam_ros.bench.range_scale DATASET_DIR... [--exponents 0,1,fit] [--max-gap 0.5]
[--tolerance 0.05] [--truth 1:0.9927,2:0.9997,...] [--json FILE]`` imports each data set
with raw ranges (no range scale), pairs every robot's range to another robot with that
robot's range back at the same stamp (:func:`csam_ros.core.truth.range_scale.mutual_pairs`) and
solves the relative scales (:func:`csam_ros.core.truth.range_scale.mutual_range_scales`, geometric
mean 1) for each depth exponent ``c`` (0: ranges are distances, as the importer takes them;
1: ranges are depths ``d cos(bearing)``; fit: one ``c`` for all cameras). Per robot it prints
the scale with its standard errors (pairs as independent; delete-one-meeting jackknife),
the scale times ``exp(c * mean log cos(bearing))`` of the robot's landmark observations
(what a fit of its landmark ranges that ignores the depth effect sees), that re-scaled to
the truth-fitted geometric mean (the relative part alone), the truth-fitted scale
(``csam calibrate mrclam``) and the difference; then per robot pair the pairs and meetings
used. About 10 s per data set.

``--joined RUNDIR/summary.json`` (per data set, in order) adds the other truth-free route:
each camera's landmark ranges against the joined map of a ``csam replay --offline`` run of
that data set (:func:`csam_ros.core.truth.range_scale.map_range_scales`), for each given
exponent; best from a run imported without range scales (``range_scale: {}``).
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import asdict
from pathlib import Path

import numpy as np

from csam_ros.core.model.log import MultiRobotLog
from csam_ros.core.truth.range_scale import (
    MapScale,
    MeetingJackknife,
    MutualPairs,
    RangeScaleEstimate,
    map_range_scales,
    meeting_jackknife,
    mutual_pairs,
    mutual_range_scales,
    reference_from_joined_map,
)

# Truth-fitted scales (`csam calibrate mrclam DIR`, measured / true range) of the three data
# sets (Dataset 1: config/mrclam.yaml; 2 and 4: `csam calibrate mrclam DIR --out FILE`).
TRUTH_FITTED: dict[str, dict[int, float]] = {
    "MRCLAM_Dataset1": {1: 0.9927, 2: 0.9997, 3: 0.9860, 4: 1.0041, 5: 0.9914},
    "MRCLAM_Dataset2": {1: 0.9935, 2: 0.9980, 3: 0.9896, 4: 1.0050, 5: 0.9893},
    "MRCLAM_Dataset4": {1: 1.0003, 2: 0.9953, 3: 0.9873, 4: 1.0057, 5: 0.9880},
}


def rendezvous_pairs(
    log: MultiRobotLog, max_gap: float, tolerance: float
) -> dict[tuple[str, str], MutualPairs]:
    """The mutual pairs of every two robots of ``log`` (both directions, with bearings)."""
    names = sorted(log.robots)
    out: dict[tuple[str, str], MutualPairs] = {}
    for k, a in enumerate(names):
        for b in names[k + 1 :]:
            ra, rb = log.robots[a].rendezvous, log.robots[b].rendezvous
            ma = np.array([o == b for o in ra.observed], dtype=bool)
            mb = np.array([o == a for o in rb.observed], dtype=bool)
            out[(a, b)] = mutual_pairs(
                ra.stamps[ma],
                ra.ranges[ma],
                rb.stamps[mb],
                rb.ranges[mb],
                ra.bearings[ma],
                rb.bearings[mb],
                max_gap=max_gap,
                tolerance=tolerance,
            )
    return out


def landmark_log_cos(log: MultiRobotLog) -> dict[str, float]:
    """Per robot, the mean ``log cos(bearing)`` of its landmark observations: with depth
    exponent ``c``, a fit of its landmark ranges on true distances that ignores the depth
    effect sees about ``s exp(c * this)`` (truth-free: bearings only)."""
    return {
        name: float(np.mean(np.log(np.cos(robot.features.bearings))))
        for name, robot in sorted(log.robots.items())
        if robot.features.bearings.size
    }


def estimate(
    log: MultiRobotLog, max_gap: float, tolerance: float, exponent: float | None
) -> tuple[RangeScaleEstimate, MeetingJackknife]:
    """The relative scales of ``log``'s cameras (raw ranges) from its mutual pairs, and
    their delete-one-meeting jackknife (meetings: pauses <= 5 s)."""
    pairs = rendezvous_pairs(log, max_gap, tolerance)
    names = sorted(log.robots)
    # Both directions of mutual_pairs share measurements: half weight each.
    result = mutual_range_scales(names, pairs, weight=0.5, exponent=exponent)
    return result, meeting_jackknife(names, pairs, weight=0.5, exponent=exponent)


def table(
    result: RangeScaleEstimate,
    jackknife: MeetingJackknife,
    truth: dict[int, float] | None,
    log_cos: dict[str, float],
) -> tuple[str, dict[str, float]]:
    """Scales per robot (estimated; times the landmark depth factor ``exp(c * mean log cos
    beta)``; that re-scaled to the truth's geometric mean; truth) and the pairs per robot
    pair. Standard errors: pairs taken as independent, and the jackknife over meetings.
    Returns the text and the re-scaled, depth-factored scales."""
    reference = {f"robot{k}": v for k, v in (truth or {}).items()}
    c = result.exponent
    factored = RangeScaleEstimate(
        **{
            **result.__dict__,
            "scales": {
                r: v * float(np.exp(c * log_cos.get(r, 0.0))) for r, v in result.scales.items()
            },
        }
    )
    rescaled = factored.rescaled(reference) if reference else {}
    lines = [
        f"depth exponent c = {c:.3f} +- {result.exponent_sigma:.3f}"
        + (
            f" (fitted; jackknife +- {jackknife.exponent_sigma:.3f})"
            if result.exponent_sigma
            else " (given)"
        ),
        "robot    s(gm=1)  +-1se  jk-1se   x depth  gm=truth   truth    diff[%]",
    ]
    diffs = []
    for name in result.robots:
        if name not in result.scales:
            lines.append(f"{name:<8} no mutual pair")
            continue
        est, se = result.scales[name], result.log_sigma[name]
        jk = jackknife.log_sigma.get(name, float("nan"))
        row = (
            f"{name:<8} {est:7.4f}  {100 * se:5.2f}%  {100 * jk:5.2f}%  "
            f"{factored.scales[name]:7.4f}"
        )
        lines.append(row + _against_truth(name, rescaled, reference, diffs))
    lines += _rms(diffs)
    lines.append(
        f"residual spread {100 * result.sigma:.2f}% (log), beyond 3 sigma {result.outliers}, "
        f"components {[len(g) for g in result.components]}, unpaired {result.unpaired}"
    )
    lines.append("pair   n(both dirs)  meetings  median(y-cz)  fitted   truth")
    for (a, b), n in result.pairs.items():
        m = jackknife.meetings.get((a, b), 0)
        t = (
            f"{np.log(reference[a] / reference[b]):+.4f}"
            if a in reference and b in reference
            else ""
        )
        lines.append(
            f"{a[5:]}-{b[5:]}    {n:5d}        {m:4d}      {result.pair_median[(a, b)]:+.4f}     "
            f"{result.pair_log_ratio[(a, b)]:+.4f}  {t}"
        )
    return "\n".join(lines), rescaled


def joined_table(
    scales: dict[str, MapScale], truth: dict[int, float] | None
) -> tuple[str, dict[str, float]]:
    """Scales against C-SAM's joined map (geometric mean 1; first / second half), re-scaled
    to the truth's geometric mean, truth and difference. Returns the text and the
    re-scaled scales."""
    reference = {f"robot{k}": v for k, v in (truth or {}).items()}
    common = [r for r in scales if r in reference]
    shift = (
        float(np.mean([np.log(reference[r] / scales[r].scale) for r in common])) if common else 0.0
    )
    rescaled = {r: m.scale * float(np.exp(shift)) for r, m in scales.items()} if common else {}
    lines = ["robot    s(gm=1)  halves           obs   spread  gm=truth   truth    diff[%]"]
    diffs = []
    for name, m in scales.items():
        row = (
            f"{name:<8} {m.scale:7.4f}  {m.first_half:.4f}/{m.second_half:.4f}  {m.observations:5d}"
            f"  {100 * m.log_spread:5.2f}%"
        )
        lines.append(row + _against_truth(name, rescaled, reference, diffs))
    lines += _rms(diffs)
    return "\n".join(lines), rescaled


def _against_truth(
    name: str, rescaled: dict[str, float], reference: dict[str, float], diffs: list[float]
) -> str:
    """The columns re-scaled, truth and difference [%] of ``name`` (the difference is added
    to ``diffs``), or nothing without both."""
    if name not in rescaled or name not in reference:
        return ""
    diff = 100 * (rescaled[name] / reference[name] - 1)
    diffs.append(diff)
    return f"  {rescaled[name]:7.4f}  {reference[name]:7.4f}  {diff:+6.2f}"


def _rms(diffs: list[float]) -> list[str]:
    return [f"rms diff {np.sqrt(np.mean(np.square(diffs))):.2f}%"] if diffs else []


def joined_scales(log: MultiRobotLog, summary: Path, exponent: float) -> dict[str, MapScale]:
    """Scales of ``log``'s cameras (raw ranges) against the joined map of a ``csam replay``
    run (its ``summary.json``: features with their member labels, which must be those of
    ``log``, i.e. the same data set and label seed)."""
    from csam_ros.datasets.mrclam import MRCLAM_NOISE

    data = json.loads(summary.read_text())
    features = [(f["members"], f["xy"]) for f in data["features"]]
    reference = reference_from_joined_map(sorted(log.robots), features)
    return map_range_scales(log, reference, MRCLAM_NOISE, exponent)


def _parse_truth(text: str) -> dict[int, float]:
    """``1:0.99,2:1.0,...`` -> {1: 0.99, 2: 1.0, ...}."""
    out = {}
    for part in text.split(","):
        k, v = part.split(":")
        out[int(k)] = float(v)
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("datasets", nargs="+", type=Path)
    parser.add_argument("--max-gap", type=float, default=0.5, help="s between bracketing ranges")
    parser.add_argument("--tolerance", type=float, default=0.05, help="s to a nearest range")
    parser.add_argument(
        "--exponents", default="0,1,fit", help="depth exponents c to try: numbers or fit"
    )
    parser.add_argument(
        "--truth", action="append", default=[], help="1:0.99,2:1.0,... per data set, in order"
    )
    parser.add_argument(
        "--joined",
        action="append",
        default=[],
        help="RUNDIR/summary.json of a csam replay of the data set, per data set in order "
        "('-': none): also the scales against that joined map",
    )
    parser.add_argument("--json", type=Path, help="write the estimates here")
    args = parser.parse_args(argv)
    from csam_ros.datasets.mrclam import import_mrclam

    exponents = [None if e == "fit" else float(e) for e in args.exponents.split(",")]
    out: dict[str, dict] = {}
    for k, directory in enumerate(args.datasets):
        truth = _parse_truth(args.truth[k]) if k < len(args.truth) else None
        truth = truth or TRUTH_FITTED.get(directory.name)
        log, _ = import_mrclam(directory)
        log_cos = landmark_log_cos(log)
        for exponent in exponents:
            result, jackknife = estimate(log, args.max_gap, args.tolerance, exponent)
            print(f"== {directory}")
            text, rescaled = table(result, jackknife, truth, log_cos)
            print(text)
            out.setdefault(str(directory), {})["fit" if exponent is None else f"{exponent:g}"] = {
                "exponent": result.exponent,
                "exponent_sigma": result.exponent_sigma,
                "scales": result.scales,
                "log_sigma": result.log_sigma,
                "jackknife_log_sigma": jackknife.log_sigma,
                "jackknife_exponent_sigma": jackknife.exponent_sigma,
                "meetings": {f"{a}-{b}": n for (a, b), n in jackknife.meetings.items()},
                "landmark_log_cos": log_cos,
                "rescaled_to_truth": rescaled,
                "pairs": {f"{a}-{b}": n for (a, b), n in result.pairs.items()},
                "sigma": result.sigma,
                "outliers": result.outliers,
                "unpaired": result.unpaired,
            }
        joined = args.joined[k] if k < len(args.joined) else "-"
        if joined != "-":
            for exponent in [e for e in exponents if e is not None]:
                scales = joined_scales(log, Path(joined), exponent)
                print(f"== {directory}: against the joined map of {joined}, c = {exponent:g}")
                text, rescaled = joined_table(scales, truth)
                print(text)
                out.setdefault(str(directory), {})[f"joined c={exponent:g}"] = {
                    "summary": joined,
                    "scales": {r: asdict(m) for r, m in scales.items()},
                    "rescaled_to_truth": rescaled,
                }
    if args.json:
        args.json.write_text(json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
