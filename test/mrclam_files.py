"""Small synthetic MR.CLAM data sets written as text files (importer, command and fuzz tests)."""

from __future__ import annotations

from pathlib import Path

HEADER = "# a comment line\n# another one\n"
# subjects 1-3 robots, 6-9 landmarks
BARCODES = {1: 5, 2: 14, 3: 41, 6: 72, 7: 27, 8: 54, 9: 70}
LANDMARKS = {6: (1.0, 2.0), 7: (3.0, -1.0), 8: (-2.0, 0.5), 9: (0.0, 4.0)}
# a config without the range scales of Dataset 1's five robots (config/mrclam.yaml has them)
PLAIN_CONFIG = "mrclam:\n  noise: {}\n"


def write_dataset(
    directory: Path,
    odometry: dict[int, list[str]],
    measurements: dict[int, list[str]],
) -> Path:
    """Write a data set; rows are given as raw text lines so that tests can corrupt them."""
    directory.mkdir(parents=True, exist_ok=True)
    (directory / "Barcodes.dat").write_text(
        HEADER + "".join(f"  {s} \t {b}\n" for s, b in BARCODES.items())
    )
    (directory / "Landmark_Groundtruth.dat").write_text(
        HEADER + "".join(f"{s} {x} {y} 0.001 0.001\n" for s, (x, y) in LANDMARKS.items())
    )
    for robot, rows in odometry.items():
        (directory / f"Robot{robot}_Odometry.dat").write_text(HEADER + "\n".join(rows) + "\n")
    for robot, rows in measurements.items():
        (directory / f"Robot{robot}_Measurement.dat").write_text(HEADER + "\n".join(rows) + "\n")
    return directory


def clean_odometry(t0: float = 1000.0, n: int = 11, v: float = 0.1) -> list[str]:
    return [f"{t0 + 0.5 * i:.3f} {v} 0.0" for i in range(n)]


def small_dataset(directory: Path) -> Path:
    """Two robots, 5 s each, that see landmarks and each other."""
    measurements = {
        1: ["1001.0 72 2.0 0.1", "1001.5 27 3.0 -0.2", "1002.0 14 1.5 0.0"],
        2: ["1001.2 72 2.1 0.1", "1001.7 70 3.5 -0.2", "1002.2 5 1.4 0.05"],
    }
    return write_dataset(directory, {r: clean_odometry() for r in (1, 2)}, measurements)
