"""Import the UTIAS MR.CLAM data set (Leung et al., IJRR 2011) into a :class:`MultiRobotLog`.

A data set directory holds ``Barcodes.dat`` (subject, barcode), ``Landmark_Groundtruth.dat``
(subject, x, y, sx, sy), and per robot ``RobotN_Odometry.dat`` (t, v, omega) and
``RobotN_Measurement.dat`` (t, barcode, range, bearing). Subjects 1..N are the robots
(``robot1``..), the landmark subjects are those with ground truth.

Policies (every dropped or repaired row is counted in :class:`ImportReport`, with the first
offending lines quoted in ``ImportReport.notes``; no row ever raises; a required file,
``Barcodes.dat``, ``Landmark_Groundtruth.dat`` or a selected robot's ``RobotN_Odometry.dat``
or ``RobotN_Measurement.dat``, that is missing, unreadable or without one valid row raises
:class:`MrclamFormatError` naming it, quoting its first dropped line; so does a
``RobotN_Measurement.dat`` without its ``RobotN_Odometry.dat``):

- Files. A file whose last line has no newline was cut inside that line (every file of the
  data set ends with one): the line is dropped and counted (``<kind>_cut_last_line``). Rows
  dropped from ``Barcodes.dat`` and ``Landmark_Groundtruth.dat`` are counted in
  ``ImportReport.table_counts``. Other files of the directory (``RobotN_Groundtruth.dat``: the
  robots' own ground truth is not used) are not read and listed in ``ImportReport.unread``.

- Stamps. Log stamps are seconds relative to ``ImportReport.epoch``, the earliest valid stamp
  in any robot file of the data set (all robots, whatever the selection), so a window
  ``[start, start + duration]`` means the same for every robot subset.
- Malformed rows (wrong column count, non-numeric, NaN/inf, barcode not an integer,
  range <= 0 or beyond ``MAX_RANGE``, |bearing| > pi) are dropped.
- Out-of-order rows are put in place by a stable sort on the stamp and counted.
- Odometry rows sharing a stamp: the last one in file order is kept (the earlier ones would
  hold for zero seconds); the others are counted as duplicates.
- Odometry convention. A file row ``(t_k, v_k, omega_k)`` is the velocity applied from ``t_k``
  until the next row, i.e. a piecewise-constant input ``u(t)``. The log's sample ``i`` holds
  the mean input over ``(s_{i-1}, s_i]`` (:mod:`csam_ros.core.model.log`), so the log takes the
  file's stamps inside the window as its stamps and gives sample ``i`` the row active at
  ``s_{i-1}``: the input is constant over each sample, and the mean is exact. The first sample
  sits at the window start (or the robot's first row) and the last at the window end (or the
  robot's last row; the last row's command has no end and is not extrapolated).
  ``v_lat = 0`` always; its noise is its own sigma.
- Odometry noise is a white velocity noise of density ``q`` (per sqrt-second): a sample of
  duration ``T`` gets ``sigma = q / sqrt(T)``, so the pose noise over any interval grows as
  ``q^2 * duration`` whatever the sampling (``OdometryLog.sigmas`` holds per-sample sigmas of
  the mean input; the first sample, unused, copies the second's).
- Measurements: barcodes map to subjects through ``Barcodes.dat``. A barcode in no table is a
  misread (dropped); a robot barcode makes a rendezvous measurement, dropped when it names the
  observer itself or a robot outside the selection; a landmark barcode becomes a feature
  observation with the observer's own label. Measurements outside the observer's odometry
  span in the window (or, for rendezvous, outside the observed robot's) are dropped.
- Ground-truth corrections: ``landmark_swaps`` exchanges the true positions of pairs of
  landmark subjects (Dataset 1 as distributed here has subjects 11 and 17 exchanged: every
  measurement of either is ~4-5 m off the listed position while the other 13 landmarks agree
  to centimetres; Datasets 2 and 4 have no swap). With ``landmark_swaps: auto``
  (``config/mrclam.yaml``) the pairs are found from the measurements themselves: the
  robots are localised snapshot by snapshot on the listed landmarks, and two subjects whose
  measurements nearly all miss their own positions and fit each other's are exchanged
  (:func:`~csam_ros.datasets.landmark_swaps.detect_landmark_swaps`). Applied swaps are listed in
  ``ImportReport.truth_corrections``; nothing is swapped unless asked.
- Range calibration: ``range_scale`` maps robot numbers to the ratio of measured to true
  range of that robot's camera (a per-camera scale error, estimated against the landmark
  ground truth by ``csam calibrate mrclam``, listed in ``config/mrclam.yaml``).
  Every range the robot measured, of landmarks and of robots, is divided by it before its
  sigma is computed; ``ImportReport.range_scale`` lists what was applied.
- Labels are local: robot ``k`` numbers the landmarks ``k + permutation_k(index)`` with a
  permutation seeded by ``(label_seed, k)``, so label ranges overlap across robots and equal
  labels mean nothing across robots. :class:`GroundTruth` keeps each robot's label -> subject.
"""

from __future__ import annotations

import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from csam_ros.core.model.log import (
    FeatureLog,
    GroundTruth,
    MultiRobotLog,
    OdometryLog,
    RendezvousLog,
    RobotLog,
)
from csam_ros.core.truth.noise_model import NoiseModel
from csam_ros.datasets.landmark_swaps import detect_landmark_swaps, exchange_landmarks

FloatArray = NDArray[np.float64]

BARCODES_FILE = "Barcodes.dat"
AUTO = "auto"  # landmark_swaps found from the measurements
LandmarkSwaps = Sequence[tuple[int, int]] | str  # subject pairs, or AUTO
LANDMARKS_FILE = "Landmark_Groundtruth.dat"
_ROBOT_FILE = re.compile(r"^Robot(\d+)_(Odometry|Measurement)\.dat$")
_MAX_NOTES = 40
# m: a range beyond it is no camera's (Dataset 1's are below 10 m): the row is dropped, as a
# smoother's input: max_range drops it (its squares would overflow the calibration's sums)
MAX_RANGE = 1000.0
_NOTES_SHOWN = 10  # of the notes, in ImportReport.summary


def default_dataset_dir() -> Path | None:
    """MR.CLAM Dataset 1 for tests and benchmarks: ``$CSAM_MRCLAM_DIR`` if set, else None."""
    import os

    value = os.environ.get("CSAM_MRCLAM_DIR")
    return Path(value) if value else None


class MrclamFormatError(ValueError):
    """A data set that cannot be imported at all (missing file, ambiguous table)."""


# The noise model of ``config/mrclam.yaml`` (``csam calibrate mrclam`` estimates it): the
# importer's default, and the values a config file's ``noise`` section leaves out.
MRCLAM_NOISE = NoiseModel(
    sigma_range=0.001,
    sigma_range_per_m=0.0383,
    sigma_bearing=0.0047,
    q_v=0.0241,
    q_vlat=0.0073,
    q_omega=0.0559,
    rendezvous_range_factor=1.34,
    rendezvous_bearing_factor=1.93,
)


# The keys of a config file's ``mrclam:`` section (config/mrclam.yaml).
MRCLAM_KEYS = frozenset(
    {"robots", "start", "duration", "label_seed", "noise", "range_scale", "landmark_swaps"}
)


def _numbers(value: object) -> bool:
    """Whether ``value`` is a mapping whose values are all numbers."""
    return isinstance(value, Mapping) and all(
        isinstance(v, int | float) and not isinstance(v, bool) for v in value.values()
    )


def load_config(path: str | Path) -> dict:
    """Read ``config/mrclam.yaml`` (top-level key ``mrclam``) and return that section, with
    ``noise`` turned into a :class:`~csam_ros.core.truth.noise_model.NoiseModel` (keys it leaves
    out from :data:`MRCLAM_NOISE`). A file that cannot be read, or a section of the wrong
    shape, raises :class:`~csam_ros.core.model.config_file.ConfigFileError` naming file and key."""
    from csam_ros.core.model.config_file import ConfigFileError, load_document

    data = load_document(path)
    if not isinstance(data.get("mrclam"), Mapping):
        raise ConfigFileError(f"{path}: expected a top-level section 'mrclam' (a mapping)")
    section = dict(data["mrclam"])
    unknown = sorted(str(key) for key in section if key not in MRCLAM_KEYS)
    if unknown:
        raise ConfigFileError(
            f"{path}: mrclam: unknown key(s) {unknown}; allowed: {sorted(MRCLAM_KEYS)}"
        )
    noise = section.get("noise") or {}
    if not _numbers(noise):
        raise ConfigFileError(f"{path}: mrclam.noise: expected a mapping of numbers, got {noise!r}")
    try:
        section["noise"] = NoiseModel.from_dict(dict(noise), MRCLAM_NOISE)
    except (TypeError, ValueError) as err:
        raise ConfigFileError(f"{path}: mrclam.noise: {err}") from None
    scales = section.get("range_scale")
    if scales is not None and not _numbers(scales):
        raise ConfigFileError(
            f"{path}: mrclam.range_scale: expected a mapping robot: scale, got {scales!r}"
        )
    swaps = section.get("landmark_swaps")
    pair = list | tuple
    if (
        swaps is not None
        and swaps != AUTO
        and not (
            isinstance(swaps, pair)
            and all(
                isinstance(p, pair) and len(p) == 2 and _numbers(dict(enumerate(p))) for p in swaps
            )
        )
    ):
        raise ConfigFileError(
            f"{path}: mrclam.landmark_swaps: expected {AUTO!r} or a list of [subject, subject] "
            f"pairs, got {swaps!r}"
        )
    return section


def landmark_swaps_of(config: Mapping[str, Any]) -> LandmarkSwaps:
    """A config's ``landmark_swaps`` as :func:`import_mrclam` takes it: :data:`AUTO` or a
    list of subject pairs (none when absent)."""
    swaps = config.get("landmark_swaps")
    if swaps == AUTO:
        return AUTO
    return [(int(a), int(b)) for a, b in swaps or ()]


@dataclass
class ImportReport:
    """What the import kept, dropped and repaired, per robot and reason."""

    dataset: str
    epoch: float  # absolute stamp [s] that log stamps are relative to
    start: float  # window start, relative to epoch
    end: float  # window end, relative to epoch
    robots: list[str]
    counts: dict[str, dict[str, int]] = field(default_factory=dict)  # robot -> reason -> n
    notes: list[str] = field(default_factory=list)  # first offending lines, "file:line: why"
    truth_corrections: list[str] = field(default_factory=list)
    range_scale: dict[str, float] = field(default_factory=dict)  # robot -> measured / true
    table_counts: dict[str, int] = field(default_factory=dict)  # Barcodes, Landmark_Groundtruth
    unread: list[str] = field(default_factory=list)  # files of the directory not read
    occlusion: dict[str, list[list[float]]] = field(default_factory=dict)  # robot -> windows

    def total(self, reason: str) -> int:
        """Sum of one count over all robots."""
        return sum(c.get(reason, 0) for c in self.counts.values())

    def to_dict(self) -> dict:
        """JSON-ready form."""
        return {
            "dataset": self.dataset,
            "epoch": self.epoch,
            "start": self.start,
            "end": self.end,
            "robots": list(self.robots),
            "counts": {r: dict(c) for r, c in self.counts.items()},
            "notes": list(self.notes),
            "truth_corrections": list(self.truth_corrections),
            "range_scale": dict(self.range_scale),
            "table_counts": dict(self.table_counts),
            "unread": list(self.unread),
            "occlusion": dict(self.occlusion),
        }

    def summary(self) -> str:
        """A short human-readable table of the non-zero counts."""
        reasons = sorted({k for c in self.counts.values() for k, v in c.items() if v})
        lines = [f"MR.CLAM import of {self.dataset}: window [{self.start:.3f}, {self.end:.3f}] s"]
        lines.append("  " + " ".join(f"{r:>8}" for r in self.robots) + "  reason")
        for reason in reasons:
            row = " ".join(f"{self.counts[r].get(reason, 0):>8}" for r in self.robots)
            lines.append(f"  {row}  {reason}")
        if self.range_scale:
            scales = " ".join(f"{self.range_scale.get(r, 1.0):>8.4f}" for r in self.robots)
            lines.append(f"  {scales}  range scale (measured / true; ranges divided by it)")
        if self.table_counts:
            counts = ", ".join(f"{n} {k}" for k, n in sorted(self.table_counts.items()) if n)
            lines.append(f"  {BARCODES_FILE} and {LANDMARKS_FILE}: {counts}")
        for robot, windows in self.occlusion.items():
            spans = " ".join(f"[{a:.0f}, {b:.0f})" for a, b in windows)
            total = sum(b - a for a, b in windows)
            lines.append(
                f"  occluded: {robot}'s landmark observations in {spans} s ({total:.0f} s; "
                f"{self.counts.get(robot, {}).get('measurement_occluded', 0)} dropped, "
                "its rendezvous kept)"
            )
        if self.unread:
            lines.append(
                f"  not read: {', '.join(self.unread)} (an import reads {BARCODES_FILE}, "
                f"{LANDMARKS_FILE} and RobotN_Odometry.dat, RobotN_Measurement.dat)"
            )
        shown = self.notes[:_NOTES_SHOWN]
        if shown:
            total = f"{len(self.notes)}{'+' if len(self.notes) >= _MAX_NOTES else ''}"
            lines.append(f"  first dropped or repaired lines ({len(shown)} of {total}):")
            lines += [f"    {note}" for note in shown]
        return "\n".join(lines)


class _Counter:
    """Counts per robot and reason plus the first offending lines."""

    def __init__(self, robots: list[str]) -> None:
        self.counts: dict[str, dict[str, int]] = {r: {} for r in robots}
        self.tables: dict[str, int] = {}  # robot None: Barcodes.dat, Landmark_Groundtruth.dat
        self.notes: list[str] = []

    def add(self, robot: str | None, reason: str, n: int, note: str | None = None) -> None:
        if n <= 0:
            return
        if robot is None:
            self.tables[reason] = self.tables.get(reason, 0) + int(n)
        elif robot in self.counts:
            self.counts[robot][reason] = self.counts[robot].get(reason, 0) + int(n)
        if note is not None:
            self.note(note)

    def note(self, text: str) -> None:
        if len(self.notes) < _MAX_NOTES:
            self.notes.append(text)


@dataclass
class _Table:
    """Numeric rows of one text file with their 1-based line numbers."""

    values: FloatArray  # (n, ncols)
    lines: NDArray[np.int64]  # (n,)


def _read_table(
    path: Path, ncols: int, counter: _Counter, robot: str | None, prefix: str
) -> _Table:
    """Parse whitespace-separated numeric rows; drop and count malformed ones.

    Comment lines (``#``) and blank lines are skipped. Counted reasons:
    ``{prefix}_wrong_columns``, ``{prefix}_non_numeric``, ``{prefix}_non_finite``,
    ``{prefix}_cut_last_line`` (a last line without newline: the file was cut inside it).
    """
    text = _read_text(path)
    lines_of_text = text.splitlines()
    cut = bool(text) and not text.endswith(("\n", "\r"))
    rows: list[list[str]] = []
    line_numbers: list[int] = []
    for number, line in enumerate(lines_of_text, start=1):
        tokens = line.split()
        if not tokens or tokens[0].startswith("#"):
            continue
        if cut and number == len(lines_of_text):
            counter.add(
                robot,
                f"{prefix}_cut_last_line",
                1,
                f"{path.name}:{number}: the file ends inside this line (cut short?): dropped",
            )
            continue
        if len(tokens) != ncols:
            counter.add(
                robot,
                f"{prefix}_wrong_columns",
                1,
                f"{path.name}:{number}: {len(tokens)} columns, expected {ncols}",
            )
            continue
        rows.append(tokens)
        line_numbers.append(number)
    counter.add(robot, f"{prefix}_rows", len(rows))
    lines = np.asarray(line_numbers, dtype=np.int64)
    try:
        values = np.array(rows, dtype=float).reshape(len(rows), ncols)
    except ValueError:
        values, ok = _parse_slow(rows, ncols)
        for number in lines[~ok]:
            row = rows[int(np.searchsorted(lines, number))]
            counter.add(
                robot,
                f"{prefix}_non_numeric",
                1,
                f"{path.name}:{number}: non-numeric value in {' '.join(row)!r}",
            )
        values, lines = values[ok], lines[ok]
    finite = np.isfinite(values).all(axis=1)
    for number in lines[~finite][:_MAX_NOTES]:
        counter.note(f"{path.name}:{number}: NaN or inf")
    counter.add(robot, f"{prefix}_non_finite", int((~finite).sum()))
    return _Table(values[finite], lines[finite])


def _read_text(path: Path) -> str:
    """A data set file's text (undecodable bytes replaced: their rows fail to parse)."""
    if not path.is_file():
        raise MrclamFormatError(f"{path}: missing")
    try:
        return path.read_bytes().decode("utf-8", errors="replace")
    except OSError as err:
        raise MrclamFormatError(f"{path}: cannot read: {err.strerror or err}") from None


def _parse_slow(rows: list[list[str]], ncols: int) -> tuple[FloatArray, NDArray[np.bool_]]:
    """Row-by-row conversion, only used when the fast path met a non-numeric token."""
    values = np.zeros((len(rows), ncols))
    ok = np.ones(len(rows), dtype=bool)
    for i, row in enumerate(rows):
        try:
            values[i] = [float(token) for token in row]
        except ValueError:
            ok[i] = False
    return values, ok


def _sort_by_stamp(table: _Table, counter: _Counter, robot: str, prefix: str, name: str) -> _Table:
    """Stable sort on column 0; count rows stamped before an earlier row of the file."""
    stamps = table.values[:, 0]
    if stamps.size == 0:
        return table
    out_of_order = stamps < np.maximum.accumulate(stamps)
    n = int(out_of_order.sum())
    if n:
        first = int(table.lines[out_of_order][0])
        counter.add(
            robot,
            f"{prefix}_out_of_order",
            n,
            f"{name}:{first}: stamp earlier than a previous row ({n} such rows, sorted)",
        )
        order = np.argsort(stamps, kind="stable")
        table = _Table(table.values[order], table.lines[order])
    return table


def _no_rows(path: Path, what: str, counter: _Counter) -> MrclamFormatError:
    """The error of a required file without one usable row, quoting the first dropped line."""
    first = next((n for n in counter.notes if n.startswith(f"{path.name}:")), None)
    text = _read_text(path)
    if not any(line.split() and not line.lstrip().startswith("#") for line in text.splitlines()):
        why = " (the file is empty or holds only comments)"
    elif first is not None:
        why = f" (first dropped line: {first})"
    else:
        why = " (every line was dropped as malformed)"
    return MrclamFormatError(f"{path}: no valid {what} row{why}")


def _read_barcodes(directory: Path, counter: _Counter) -> dict[int, int]:
    path = directory / BARCODES_FILE
    table = _read_table(path, 2, counter, None, "barcode")
    values = table.values
    integral = (values == np.round(values)).all(axis=1) & (np.abs(values) < 2**62).all(axis=1)
    if not integral.any():
        raise _no_rows(path, "(subject, barcode)", counter)
    barcode_to_subject: dict[int, int] = {}
    for (subject, code), line in zip(
        values[integral].astype(np.int64), table.lines[integral], strict=True
    ):
        previous = barcode_to_subject.get(int(code))
        if previous is not None and previous != subject:
            raise MrclamFormatError(
                f"{directory / BARCODES_FILE}:{line}: barcode {code} names subject {subject} "
                f"and subject {previous}"
            )
        barcode_to_subject[int(code)] = int(subject)
    return barcode_to_subject


def _read_landmarks(directory: Path, counter: _Counter) -> tuple[NDArray[np.int64], FloatArray]:
    path = directory / LANDMARKS_FILE
    table = _read_table(path, 5, counter, None, "landmark")
    subjects = table.values[:, 0]
    keep = (subjects == np.round(subjects)) & (np.abs(subjects) < 2**62)
    if not keep.any():
        raise _no_rows(path, "landmark ground truth", counter)
    subjects = subjects[keep].astype(np.int64)
    unique, first = np.unique(subjects, return_index=True)
    if unique.size != subjects.size:
        raise MrclamFormatError(f"{directory / LANDMARKS_FILE}: a landmark subject appears twice")
    return unique, table.values[keep][first, 1:3]


def _local_labels(subjects: NDArray[np.int64], robot_number: int, seed: int) -> dict[int, int]:
    """Subject -> the robot's own label: ``robot_number + permutation(index)``."""
    permutation = np.random.default_rng([seed, robot_number]).permutation(subjects.size)
    return {int(s): int(robot_number + p) for s, p in zip(subjects, permutation, strict=True)}


@dataclass
class _RobotFiles:
    odometry: _Table
    measurements: _Table


def _robot_files(directory: Path) -> tuple[list[int], list[int], list[str]]:
    """Robot numbers with an odometry file, with any robot file, and the names of the other
    files of the directory (not read)."""
    odometry, robots, unread = set(), set(), []
    for path in directory.iterdir():
        match = _ROBOT_FILE.match(path.name)
        if match:
            robots.add(int(match.group(1)))
            if match.group(2) == "Odometry":
                odometry.add(int(match.group(1)))
        elif path.name not in (BARCODES_FILE, LANDMARKS_FILE) and not path.name.startswith("."):
            unread.append(path.name)
    return sorted(odometry), sorted(robots), sorted(unread)


_NO_ROWS = _Table(np.zeros((0, 4)), np.zeros(0, dtype=np.int64))


def _read_robot(directory: Path, number: int, counter: _Counter, selected: bool) -> _RobotFiles:
    """A robot's two files; a selected robot needs both with a valid row each (an unselected
    one only gives its stamps to the epoch)."""
    name = f"robot{number}"
    odometry_path = directory / f"Robot{number}_Odometry.dat"
    measurement_path = directory / f"Robot{number}_Measurement.dat"
    tables = []
    for path, ncols, prefix in (
        (odometry_path, 3, "odometry"),
        (measurement_path, 4, "measurement"),
    ):
        if not selected and not path.is_file():
            tables.append(_NO_ROWS)
            continue
        if not path.is_file():
            other = measurement_path if path == odometry_path else odometry_path
            raise MrclamFormatError(
                f"{path}: missing ({other.name} is there; leave robot {number} out with --robots)"
            )
        table = _read_table(path, ncols, counter, name, prefix)
        if selected and table.values.shape[0] == 0:
            raise _no_rows(path, prefix, counter)
        tables.append(_sort_by_stamp(table, counter, name, prefix, path.name))
    return _RobotFiles(*tables)


def _odometry_log(
    odometry: _Table,
    epoch: float,
    window: tuple[float, float],
    noise: NoiseModel,
    counter: _Counter,
    robot: str,
) -> OdometryLog | None:
    """Turn the piecewise-constant command rows into log samples (module docstring)."""
    stamps = odometry.values[:, 0] - epoch
    commands = odometry.values[:, 1:3]
    if stamps.size == 0:
        return None
    # Duplicate stamps: keep the last row of each run of equal stamps.
    last_of_run = np.append(stamps[1:] != stamps[:-1], True)
    duplicates = int((~last_of_run).sum())
    if duplicates:
        line = int(odometry.lines[~last_of_run][0])
        counter.add(
            robot,
            "odometry_duplicate_stamps",
            duplicates,
            f"Robot{robot[5:]}_Odometry.dat:{line}: stamp repeated ({duplicates} rows superseded "
            "by the last row with the same stamp)",
        )
    stamps, commands = stamps[last_of_run], commands[last_of_run]
    begin = max(window[0], stamps[0])
    end = min(window[1], stamps[-1])
    if not end > begin:
        return None
    inner = stamps[(stamps > begin) & (stamps < end)]
    sample_stamps = np.concatenate([[begin], inner, [end]])
    active = np.searchsorted(stamps, sample_stamps, side="right") - 1  # row active at s_i
    inputs = np.zeros((sample_stamps.size, 3))
    inputs[0, [0, 2]] = commands[active[0]]
    inputs[1:, [0, 2]] = commands[active[:-1]]
    durations = np.diff(sample_stamps)
    density = np.array([noise.q_v, noise.q_vlat, noise.q_omega])
    sigmas = np.empty_like(inputs)
    sigmas[1:] = density / np.sqrt(durations)[:, None]
    sigmas[0] = sigmas[1]
    counter.add(robot, "odometry_samples", sample_stamps.size)
    return OdometryLog(sample_stamps, inputs, sigmas)


def import_mrclam(
    directory: str | Path,
    robots: list[int] | None = None,
    start: float = 0.0,
    duration: float | None = None,
    noise: NoiseModel | None = None,
    label_seed: int = 0,
    landmark_swaps: LandmarkSwaps = (),
    range_scale: Mapping[int, float] | None = None,
    occlusion: str | Sequence[tuple[int, float, float]] | None = None,
) -> tuple[MultiRobotLog, ImportReport]:
    """Read an MR.CLAM data set directory into a :class:`MultiRobotLog`.

    ``robots`` selects robot numbers (default: all with an odometry file); ``start`` and
    ``duration`` [s] cut a window relative to the data set's first stamp. Returns the log
    (stamps relative to ``report.epoch``; ground truth: landmark positions and each robot's
    label -> subject map) and the :class:`ImportReport`. ``landmark_swaps`` lists pairs of
    landmark subjects whose true positions are exchanged, or is :data:`AUTO`: the pairs are
    found from the measurements (:func:`~csam_ros.datasets.landmark_swaps.detect_landmark_swaps`).
    ``range_scale`` each robot's ratio of
    measured to true range (module docstring). ``occlusion`` drops landmark observations:
    :data:`STRESS` or windows ``(robot number, start, end)`` (:func:`occlude_landmarks`).
    """
    directory = Path(directory)
    if not directory.is_dir():
        raise MrclamFormatError(f"MR.CLAM data set directory {directory} does not exist")
    for required in (BARCODES_FILE, LANDMARKS_FILE):
        if not (directory / required).is_file():
            raise MrclamFormatError(f"{directory / required}: missing")
    available, robot_numbers, unread = _robot_files(directory)
    if not available:
        raise MrclamFormatError(f"{directory}: no RobotN_Odometry.dat file")
    if robots is None:
        missing = sorted(set(robot_numbers) - set(available))
        if missing:
            raise MrclamFormatError(
                f"{directory / f'Robot{missing[0]}_Odometry.dat'}: missing "
                f"(Robot{missing[0]}_Measurement.dat is there; leave robot {missing[0]} out "
                "with --robots)"
            )
    selected = available if robots is None else sorted({int(r) for r in robots})
    missing = [r for r in selected if r not in available]
    if missing:
        raise MrclamFormatError(
            f"robots {missing} requested but {directory} has odometry only for {available}"
        )
    if not np.isfinite(start) or (duration is not None and not duration > 0):
        raise ValueError(f"bad window: start={start!r}, duration={duration!r} (need > 0)")
    noise = noise or MRCLAM_NOISE
    scales = _range_scales(range_scale or {}, available)
    names = [f"robot{r}" for r in selected]
    counter = _Counter(names)

    barcode_to_subject = _read_barcodes(directory, counter)
    landmark_subjects, landmark_xy = _read_landmarks(directory, counter)
    corrections = []
    for pair in () if landmark_swaps == AUTO else landmark_swaps:
        a, b = (int(v) for v in pair)
        rows = np.searchsorted(landmark_subjects, [a, b])
        if not all(
            r < landmark_subjects.size and landmark_subjects[r] == s
            for r, s in zip(rows, (a, b), strict=True)
        ):
            raise ValueError(f"landmark_swaps: ({a}, {b}) names a subject without ground truth")
        landmark_xy[rows] = landmark_xy[rows[::-1]]
        corrections.append(f"true positions of landmark subjects {a} and {b} exchanged")
    files = {
        r: _read_robot(directory, r, counter, True)
        if r in selected
        else _read_robot(directory, r, _Counter([]), False)
        for r in robot_numbers
    }
    first_stamps = [
        t.values[0, 0]
        for f in files.values()
        for t in (f.odometry, f.measurements)
        if t.values.shape[0]
    ]
    if not first_stamps:
        raise MrclamFormatError(f"{directory}: no valid stamp in any robot file")
    epoch = float(min(first_stamps))
    window = (float(start), float(start + duration) if duration is not None else np.inf)

    odometry: dict[str, OdometryLog] = {}
    for number, name in zip(selected, names, strict=True):
        log = _odometry_log(files[number].odometry, epoch, window, noise, counter, name)
        if log is None:
            raise MrclamFormatError(
                f"{name} has no odometry in the window [{window[0]}, {window[1]}] s "
                f"(relative to the data set's first stamp {epoch:.3f})"
            )
        odometry[name] = log
    spans = {name: (log.stamps[0], log.stamps[-1]) for name, log in odometry.items()}

    labels = {
        name: _local_labels(landmark_subjects, number, label_seed)
        for number, name in zip(selected, names, strict=True)
    }
    robot_subjects = set(robot_numbers)
    logs: dict[str, RobotLog] = {}
    for number, name in zip(selected, names, strict=True):
        features, rendezvous = _measurement_logs(
            files[number].measurements,
            number,
            epoch,
            spans,
            barcode_to_subject,
            robot_subjects,
            labels[name],
            noise,
            scales.get(number, 1.0),
            counter,
        )
        logs[name] = RobotLog(name, odometry[name], features, rendezvous)
    truth = GroundTruth(
        feature_ids=landmark_subjects,
        feature_positions=landmark_xy,
        label_to_feature={
            name: {label: subject for subject, label in labels[name].items()} for name in names
        },
    )
    if landmark_swaps == AUTO:
        for swap in detect_landmark_swaps(MultiRobotLog(logs, truth), noise):
            truth = exchange_landmarks(truth, *swap.subjects)
            corrections.append(swap.line())
    occluded = occlude_landmarks(logs, occlusion, counter) if occlusion else {}

    report = ImportReport(
        dataset=str(directory),
        epoch=epoch,
        start=window[0],
        end=float(min(window[1], max(s[1] for s in spans.values()))),
        robots=names,
        counts=counter.counts,
        notes=counter.notes,
        truth_corrections=corrections,
        range_scale={f"robot{r}": scales[r] for r in selected if r in scales},
        table_counts=dict(counter.tables),
        unread=unread,
        occlusion=occluded,
    )
    return MultiRobotLog(logs, truth), report


# Occlusion stress (``csam import mrclam --occlude``): a repeatable way to make the data hard.
STRESS = "stress"
STRESS_PERIOD = 90.0  # s: the stress case occludes every other window of this length
_WINDOW = re.compile(r"^\s*(\d+)\s*:\s*(\d+(?:\.\d*)?)\s*-\s*(\d+(?:\.\d*)?)\s*$")


def parse_occlusion(text: str) -> str | list[tuple[int, float, float]]:
    """``--occlude``'s value: :data:`STRESS`, or ``ROBOT:START-END[,ROBOT:START-END...]``
    (robot number, seconds after the data set's first stamp, ``START < END``). ValueError
    naming the part that does not read."""
    if text.strip() == STRESS:
        return STRESS
    windows = []
    for part in text.split(","):
        match = _WINDOW.match(part)
        if match is None:
            raise ValueError(
                f"{part.strip()!r} is not ROBOT:START-END (e.g. 4:90-180, seconds after the "
                f"data set's first stamp) or {STRESS!r}"
            )
        robot, begin, end = int(match.group(1)), float(match.group(2)), float(match.group(3))
        if not end > begin:
            raise ValueError(f"{part.strip()!r}: the window must end after it starts")
        windows.append((robot, begin, end))
    return windows


def stress_windows(logs: Mapping[str, RobotLog]) -> list[tuple[int, float, float]]:
    """The stress case: the robot that sees landmarks least often (observations per second of
    its odometry span) loses them in every other :data:`STRESS_PERIOD` window from one period
    after its start on: about half of its run, in windows of 90 s."""

    def rate(log: RobotLog) -> float:
        span = log.odometry.stamps[-1] - log.odometry.stamps[0]
        return log.features.stamps.size / span if span > 0 else 0.0

    name = min(logs, key=lambda n: (rate(logs[n]), n))
    first, last = logs[name].odometry.stamps[[0, -1]]
    starts = np.arange(first + STRESS_PERIOD, last, 2 * STRESS_PERIOD)
    return [(int(name[5:]), float(a), float(min(a + STRESS_PERIOD, last))) for a in starts]


def occlude_landmarks(
    logs: dict[str, RobotLog],
    occlusion: str | Sequence[tuple[int, float, float]],
    counter: _Counter,
) -> dict[str, list[list[float]]]:
    """Drop the landmark (feature) observations of ``robotN`` stamped inside each window
    ``(N, start, end)`` (``[start, end)``, s after the data set's first stamp), or in the
    :func:`stress_windows` for :data:`STRESS`; count them ``measurement_occluded``. Its
    observations of other robots (rendezvous) are kept: the stress is on the local maps. Returns
    robot -> its windows."""
    windows = stress_windows(logs) if occlusion == STRESS else list(occlusion)
    occluded: dict[str, list[list[float]]] = {}
    for number, begin, end in windows:
        name = f"robot{int(number)}"
        if name not in logs:
            raise ValueError(f"occlusion: robot {number} is not imported ({', '.join(logs)})")
        occluded.setdefault(name, []).append([float(begin), float(end)])
    for name, spans in occluded.items():
        f = logs[name].features
        hidden = np.zeros(f.stamps.size, dtype=bool)
        for begin, end in spans:
            hidden |= (f.stamps >= begin) & (f.stamps < end)
        n = int(hidden.sum())
        keep = ~hidden
        logs[name].features = FeatureLog(
            f.stamps[keep],
            f.labels[keep],
            f.ranges[keep],
            f.bearings[keep],
            f.sigma_range[keep],
            f.sigma_bearing[keep],
        )
        counter.add(name, "measurement_occluded", n)
        if n:
            counter.counts[name]["feature_measurements"] -= n
    return occluded


def _range_scales(range_scale: Mapping[int, float], available: list[int]) -> dict[int, float]:
    """Validated ``range_scale``: robot numbers of the data set, finite values > 0."""
    scales: dict[int, float] = {}
    for key, value in range_scale.items():
        number = int(key) if str(key).isdigit() else -1
        if number not in available:
            raise ValueError(f"range_scale: robot {key!r} is not in the data set ({available})")
        scale = float(value)
        if not (np.isfinite(scale) and scale > 0):
            raise ValueError(f"range_scale of robot {number} must be finite and > 0, got {value!r}")
        scales[number] = scale
    return scales


def _measurement_logs(
    table: _Table,
    number: int,
    epoch: float,
    spans: dict[str, tuple[float, float]],
    barcode_to_subject: dict[int, int],
    robot_subjects: set[int],
    labels: dict[int, int],
    noise: NoiseModel,
    range_scale: float,
    counter: _Counter,
) -> tuple[FeatureLog, RendezvousLog]:
    """Split one robot's measurement rows into feature and rendezvous logs, ranges divided by
    ``range_scale`` (module docstring)."""
    name = f"robot{number}"
    file_name = f"Robot{number}_Measurement.dat"
    values, lines = table.values, table.lines

    def drop(mask: NDArray[np.bool_], reason: str, why: str) -> None:
        if mask.any():
            counter.add(name, reason, int(mask.sum()), f"{file_name}:{lines[mask][0]}: {why}")

    codes = values[:, 1]
    ok = (codes == np.round(codes)) & (np.abs(codes) < 2**62)
    drop(~ok, "measurement_bad_barcode", "barcode is not an integer")
    bad_range = ok & ~(values[:, 2] > 0)
    drop(bad_range, "measurement_non_positive_range", "range <= 0")
    ok &= ~bad_range
    far = ok & (values[:, 2] > MAX_RANGE)
    drop(far, "measurement_range_out_of_bounds", f"range beyond {MAX_RANGE:g} m")
    ok &= ~far
    bad_bearing = ok & (np.abs(values[:, 3]) > np.pi)
    drop(bad_bearing, "measurement_bearing_out_of_range", "|bearing| > pi")
    ok &= ~bad_bearing

    code_keys = np.array(sorted(barcode_to_subject), dtype=np.int64)
    code_subjects = np.array([barcode_to_subject[c] for c in code_keys], dtype=np.int64)
    integer_codes = np.where(ok, codes, -1).astype(np.int64)
    where = np.clip(np.searchsorted(code_keys, integer_codes), 0, max(code_keys.size - 1, 0))
    known = ok & (code_keys.size > 0) & (code_keys[where] == integer_codes)
    drop(ok & ~known, "measurement_unknown_barcode", "barcode in no table (misread)")
    subject = np.where(known, code_subjects[where] if code_keys.size else -1, -1)

    is_robot = known & np.isin(subject, list(robot_subjects))
    is_landmark = known & np.isin(subject, list(labels))
    drop(
        known & ~is_robot & ~is_landmark,
        "measurement_unknown_subject",
        "barcode names a subject that is neither a robot nor a landmark with ground truth",
    )
    self_measurement = is_robot & (subject == number)
    drop(self_measurement, "measurement_self", "robot measured its own barcode")
    selected_numbers = [int(n[5:]) for n in spans]
    unselected = is_robot & ~self_measurement & ~np.isin(subject, selected_numbers)
    drop(unselected, "measurement_unselected_robot", "measured robot is not in the selection")
    is_rendezvous = is_robot & ~self_measurement & ~unselected

    stamps = values[:, 0] - epoch
    begin, end = spans[name]
    outside = (is_landmark | is_rendezvous) & ((stamps < begin) | (stamps > end))
    drop(outside, "measurement_outside_window", "outside the robot's odometry in the window")
    is_landmark &= ~outside
    is_rendezvous &= ~outside
    observed_outside = np.zeros_like(is_rendezvous)
    for other in selected_numbers:
        o_begin, o_end = spans[f"robot{other}"]
        observed_outside |= (
            is_rendezvous & (subject == other) & ((stamps < o_begin) | (stamps > o_end))
        )
    drop(
        observed_outside,
        "measurement_observed_outside_window",
        "observed robot has no odometry at this stamp",
    )
    is_rendezvous &= ~observed_outside

    ranges, bearings = values[:, 2] / range_scale, values[:, 3]
    sigma_range = noise.sigma_range + noise.sigma_range_per_m * ranges
    label_keys = np.array(sorted(labels), dtype=np.int64)
    label_values = np.array([labels[s] for s in label_keys], dtype=np.int64)
    f = is_landmark
    feature_labels = label_values[np.searchsorted(label_keys, subject[f])]
    features = FeatureLog(
        stamps[f],
        feature_labels,
        ranges[f],
        bearings[f],
        sigma_range[f],
        np.full(int(f.sum()), noise.sigma_bearing),
    )
    g = is_rendezvous
    rendezvous = RendezvousLog(
        stamps[g],
        [f"robot{s}" for s in subject[g]],
        ranges[g],
        bearings[g],
        sigma_range[g] * noise.rendezvous_range_factor,
        np.full(int(g.sum()), noise.sigma_bearing * noise.rendezvous_bearing_factor),
    )
    counter.add(name, "feature_measurements", int(f.sum()))
    counter.add(name, "rendezvous_measurements", int(g.sum()))
    return features, rendezvous
