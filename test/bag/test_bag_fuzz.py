"""Fuzzing the bag reader and `csam bag recover` with damaged copies of a small valid bag.

Random byte flips (position, length, pattern) and truncations of the bag's MCAP file, drawn by
hypothesis under the project's derandomised profile: reading the damaged bag yields only
messages identical to ones written (never a corrupted one) or raises BagError, never any other
exception; `csam bag recover` on it either writes a bag that rosbags' Reader opens, holding
only messages that were written, or ends in a one-line error (exit 2).

`make test` runs a bounded number of examples (seconds). A longer run:

    CSAM_BAG_FUZZ_EXAMPLES=2000 .venv/bin/python -m pytest -q -p no:cacheprovider \\
        test/bag/test_bag_fuzz.py --hypothesis-show-statistics
"""

from __future__ import annotations

import contextlib
import io
import os
import tempfile
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from csam_ros.bag import BagError, BagWriter, inspect_bag, read_bag

EXAMPLES = int(os.environ.get("CSAM_BAG_FUZZ_EXAMPLES", "80"))
SECOND = 1_000_000_000


def _written() -> tuple[bytes, bytes, set[tuple[str, str, int, bytes]]]:
    """A small valid bag (two topics, 40 messages in many zstd chunks, stamps out of order
    within a chunk): its metadata.yaml, its MCAP bytes and the messages written."""
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "small"
        written = set()
        with BagWriter(path, chunk_size=30) as bag:
            bag.add_topic("/counter", "std_msgs/msg/UInt32")
            bag.add_topic("/name", "std_msgs/msg/String")
            for i in range(40):
                stamp = (i ^ 1) * SECOND
                if i % 3:
                    topic, msgtype = "/counter", "std_msgs/msg/UInt32"
                    data = b"\x00\x01\x00\x00" + (i * 7919).to_bytes(4, "little")
                else:
                    topic, msgtype = "/name", "std_msgs/msg/String"
                    text = f"message {i}".encode() + b"\x00"
                    data = b"\x00\x01\x00\x00" + len(text).to_bytes(4, "little") + text
                bag.write(topic, stamp, data)
                written.add((topic, msgtype, stamp, data))
        return (path / "metadata.yaml").read_bytes(), (path / "small_0.mcap").read_bytes(), written


METADATA, MCAP, WRITTEN = _written()

flips = st.lists(
    st.tuples(
        st.integers(0, len(MCAP) - 1),  # where
        st.integers(1, 64),  # how many bytes
        st.integers(1, 255),  # xor pattern
    ),
    max_size=3,
)
cuts = st.one_of(st.none(), st.integers(0, len(MCAP) - 1))


def _damage(flip_list: list[tuple[int, int, int]], cut: int | None) -> bytes:
    data = bytearray(MCAP)
    for where, length, pattern in flip_list:
        for k in range(where, min(where + length, len(data))):
            data[k] ^= pattern
    return bytes(data if cut is None else data[:cut])


def _bag_of(directory: Path, mcap: bytes) -> Path:
    bag = directory / "small"
    bag.mkdir()
    (bag / "metadata.yaml").write_bytes(METADATA)
    (bag / "small_0.mcap").write_bytes(mcap)
    return bag


def _read_all(bag: Path) -> list[tuple[str, str, int, bytes]] | None:
    """Every message read, or None for a BagError (any other exception fails the test)."""
    try:
        inspect_bag(bag)
        return [(m.topic, m.msgtype, m.log_time_ns, m.data) for m in read_bag(bag, on_damage=print)]
    except BagError:
        return None


@settings(max_examples=EXAMPLES, suppress_health_check=[HealthCheck.too_slow])
@given(flip_list=flips, cut=cuts)
def test_a_damaged_bag_reads_only_written_messages_or_fails_with_bag_error(
    flip_list: list[tuple[int, int, int]], cut: int | None
) -> None:
    with tempfile.TemporaryDirectory() as tmp, contextlib.redirect_stdout(io.StringIO()):
        read = _read_all(_bag_of(Path(tmp), _damage(flip_list, cut)))
    if read is not None:
        assert set(read) <= WRITTEN
        assert len(read) == len(set(read))  # no message twice
        stamps = [m[2] for m in read]
        assert stamps == sorted(stamps)
    if not flip_list and cut is None:
        assert read is not None and set(read) == WRITTEN


@settings(max_examples=EXAMPLES // 2, suppress_health_check=[HealthCheck.too_slow])
@given(flip_list=flips, cut=cuts)
def test_recover_of_a_damaged_bag_writes_a_readable_bag_or_one_error_line(
    flip_list: list[tuple[int, int, int]], cut: int | None
) -> None:
    from rosbags.rosbag2 import Reader

    from csam_ros.cli import main

    with tempfile.TemporaryDirectory() as tmp:
        bag = _bag_of(Path(tmp), _damage(flip_list, cut))
        out = Path(tmp) / "recovered"
        stdout, stderr = io.StringIO(), io.StringIO()
        with contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(stderr):
            code = main(["bag", "recover", str(bag), "--out", str(out)])
        if code != 0:
            assert code == 2
            assert len(stderr.getvalue().strip().splitlines()) == 1, stderr.getvalue()
            assert stderr.getvalue().startswith("csam bag: ")
            assert not out.exists()
            return
        with Reader(out) as reader:
            rows = [(c.topic, c.msgtype, t, bytes(raw)) for c, t, raw in reader.messages()]
            assert reader.message_count == len(rows)
        assert set(rows) <= WRITTEN and len(rows) == len(set(rows))
        assert f"recovered {len(rows)} message(s)" in stdout.getvalue()


def test_the_fuzzed_bag_has_several_chunks() -> None:
    """The damage lands in chunks, in records between them and in the summary."""
    from mcap.reader import make_reader

    summary = make_reader(io.BytesIO(MCAP)).get_summary()
    assert summary is not None and len(summary.chunk_indexes) >= 8


@pytest.mark.parametrize("cut", [len(MCAP) // 3, len(MCAP) - 30])
def test_fuzz_cases_a_cut_bag_reads_its_complete_chunks(cut: int) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        read = _read_all(_bag_of(Path(tmp), MCAP[:cut]))
    assert read and set(read) <= WRITTEN
