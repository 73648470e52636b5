"""Fuzz tests of the importers: corrupted files are imported or refused by name, nothing else.

Each example takes the files of a small synthetic MR.CLAM data set (or a small 2D SLAM text
file and g2o file), applies one to four random byte flips, truncations and deletions to one
or more of them, and imports the result. The importer must either succeed or raise its own
format error (:class:`MrclamFormatError`, :class:`Slam2dFormatError`), whose message names
the file; any other exception, and any numpy warning (which the ``csam`` command would print
beside its one line), fails the test.

``make test`` runs a bounded number of examples under the derandomised profile (seconds). A
longer run raises the number of examples with ``CSAM_FUZZ_EXAMPLES``, e.g.::

    CSAM_FUZZ_EXAMPLES=20000 .venv/bin/python -m pytest -q -p no:cacheprovider \\
        test/datasets/test_importer_fuzz.py
"""

from __future__ import annotations

import os
import tempfile
import warnings
from pathlib import Path

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from mrclam_files import small_dataset

from csam_ros.core.model.log import correlations_valid
from csam_ros.datasets.mrclam import MrclamFormatError, import_mrclam
from csam_ros.datasets.slam2d import Slam2dFormatError
from csam_ros.datasets.slam2d_log import read_slam2d_log

EXAMPLES = int(os.environ.get("CSAM_FUZZ_EXAMPLES", "150"))

SLAM2D_TEXT = """# a small single-robot run
ODOMETRY 0 1 1.0 0.0 0.1 0.01 0 0 0.01 0 0.001
ODOMETRY 1 2 1.0 0.1 0.0 0.01 0 0 0.01 0 0.001
ODOMETRY 2 3 0.9 0.0 -0.1 0.01 0 0 0.01 0 0.001
LANDMARK 0 7 2.0 1.0 0.01 0 0.01
LANDMARK 1 7 1.0 1.0 0.01 0 0.01
LANDMARK 2 8 1.5 -1.0 0.01 0.001 0.01
LANDMARK 3 8 0.5 -1.0 0.01 0 0.01
"""
SLAM2D_G2O = """VERTEX_SE2 0 0 0 0
VERTEX_SE2 1 1 0 0.1
VERTEX_XY 10 2 1
EDGE_SE2 0 1 1.0 0.0 0.1 100 0 0 100 0 1000
EDGE_SE2 1 2 1.0 0.1 0.0 100 0 0 100 0 1000
EDGE_SE2_XY 0 10 2.0 1.0 100 0 100
EDGE_SE2_XY 1 10 1.0 1.0 100 0 100
EDGE_SE2_XY 2 10 0.1 1.0 100 10 100
"""

# bytes that turn numbers into other numbers or into garbage of every kind
INTERESTING = b"0123456789.-+eE nainfNAIF#\t\n\r\x00\xff\xc3"
byte_values = st.one_of(st.sampled_from(list(INTERESTING)), st.integers(0, 255))


@st.composite
def mutations(draw: st.DrawFn) -> list[tuple[str, float, float, int]]:
    """One to four edits ``(kind, where, length, byte)``, positions as fractions of the file."""
    edit = st.tuples(
        st.sampled_from(["flip", "truncate", "delete", "insert"]),
        st.floats(0, 1),
        st.floats(0, 0.2),
        byte_values,
    )
    return draw(st.lists(edit, min_size=1, max_size=4))


def mutate(data: bytes, edits: list[tuple[str, float, float, int]]) -> bytes:
    for kind, where, length, byte in edits:
        at = min(int(where * len(data)), max(len(data) - 1, 0))
        if kind == "flip" and data:
            data = data[:at] + bytes([byte]) + data[at + 1 :]
        elif kind == "truncate":
            data = data[:at]
        elif kind == "delete":
            data = data[:at] + data[at + max(1, int(length * len(data))) :]
        elif kind == "insert":
            data = data[:at] + bytes([byte]) + data[at:]
    return data


DATASET_FILES = [
    "Barcodes.dat",
    "Landmark_Groundtruth.dat",
    "Robot1_Odometry.dat",
    "Robot1_Measurement.dat",
    "Robot2_Odometry.dat",
    "Robot2_Measurement.dat",
]


@settings(max_examples=EXAMPLES)
@given(st.lists(st.tuples(st.sampled_from(DATASET_FILES), mutations()), min_size=1, max_size=3))
def test_corrupted_mrclam_files_import_or_raise_their_format_error(
    corruptions: list[tuple[str, list[tuple[str, float, float, int]]]],
) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        directory = small_dataset(Path(tmp) / "dataset")
        for name, edits in corruptions:
            path = directory / name
            path.write_bytes(mutate(path.read_bytes(), edits))
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            try:
                log, report = import_mrclam(directory)
            except MrclamFormatError as err:
                assert str(err) and "\n" not in str(err)
                return
        for name, robot in log.robots.items():
            assert np.isfinite(robot.odometry.stamps).all(), name
            assert np.isfinite(robot.odometry.inputs).all(), name
            assert (robot.odometry.sigmas > 0).all(), name
            assert (robot.features.ranges > 0).all(), name
        assert report.summary()


@settings(max_examples=EXAMPLES)
@given(st.sampled_from(["text", "g2o"]), mutations())
def test_corrupted_slam2d_files_import_or_raise_their_format_error(
    kind: str, edits: list[tuple[str, float, float, int]]
) -> None:
    original = SLAM2D_TEXT if kind == "text" else SLAM2D_G2O
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / ("run.txt" if kind == "text" else "run.g2o")
        path.write_bytes(mutate(original.encode(), edits))
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            try:
                log = read_slam2d_log(path)
            except Slam2dFormatError as err:
                assert str(path) in str(err) and "\n" not in str(err)
                return
        odometry = log.robots["robot1"].odometry
        assert len(odometry.stamps) >= 2
        assert np.isfinite(odometry.inputs).all() and (odometry.sigmas > 0).all()
        assert correlations_valid(odometry.correlations).all()
        points = log.robots["robot1"].points
        assert np.isfinite(points.points).all()
        assert (np.linalg.eigvalsh(points.covariances) > 0).all()


def test_the_unmutated_files_import() -> None:
    """The fuzzed files are valid to begin with (a mutation is what makes them fail)."""
    with tempfile.TemporaryDirectory() as tmp:
        log, _ = import_mrclam(small_dataset(Path(tmp) / "dataset"))
        assert list(log.robots) == ["robot1", "robot2"]
        for kind, text in (("txt", SLAM2D_TEXT), ("g2o", SLAM2D_G2O)):
            path = Path(tmp) / f"run.{kind}"
            path.write_text(text)
            assert len(read_slam2d_log(path).robots["robot1"].odometry.stamps) >= 3
