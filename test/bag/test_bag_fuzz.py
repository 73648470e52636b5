"""Fuzzing the bag reader and `csam bag recover` with damaged copies of a small valid bag.

Random byte flips (position, length, pattern) and truncations of the bag's MCAP file, drawn by
hypothesis under the project's derandomised profile: reading the damaged bag raises BagError
when its MCAP magic is damaged (an empty or non-MCAP file) and never any other exception;
otherwise it reads, yielding only messages identical to ones written (never a corrupted one),
each once, in log-time order, and at least every message of the chunks before the damage (and
of every whole chunk while the summary is whole). A fixed sample of damage counts the cases
that read. `csam bag recover` on it either writes a bag that rosbags' Reader opens, holding
exactly the messages the reader gives, or ends in a one-line error (exit 2) when none read.

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

import numpy as np
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
MAGIC = 8  # bytes of the MCAP magic that opens the file


def _layout() -> tuple[list[tuple[int, int, frozenset[tuple[str, str, int, bytes]]]], int]:
    """Each chunk of MCAP in file order (its first byte, the byte after it, the messages it
    holds) and where the summary section starts, read with the mcap library."""
    from mcap.reader import breakup_chunk, make_reader
    from mcap.records import Chunk, Message
    from mcap.stream_reader import StreamReader

    summary = make_reader(io.BytesIO(MCAP)).get_summary()
    assert summary is not None
    channels = summary.channels
    indexes = sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset)
    records = StreamReader(io.BytesIO(MCAP), emit_chunks=True).records
    chunks = [r for r in records if isinstance(r, Chunk)]
    assert len(chunks) == len(indexes)
    layout = []
    for index, chunk in zip(indexes, chunks, strict=True):
        held = frozenset(
            (
                channels[m.channel_id].topic,
                summary.schemas[channels[m.channel_id].schema_id].name,
                m.log_time,
                m.data,
            )
            for m in breakup_chunk(chunk, validate_crc=True)
            if isinstance(m, Message)
        )
        layout.append(
            (index.chunk_start_offset, index.chunk_start_offset + index.chunk_length, held)
        )
    footer = len(MCAP) - MAGIC - 20  # the footer's summary_start field
    return layout, int.from_bytes(MCAP[footer : footer + 8], "little")


CHUNKS, SUMMARY_START = _layout()

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


def _untouched(damaged: bytes, start: int, end: int) -> bool:
    """Whether ``damaged`` still holds MCAP[start:end] as written."""
    return len(damaged) >= end and damaged[start:end] == MCAP[start:end]


def _must_read(damaged: bytes) -> set[tuple[str, str, int, bytes]]:
    """The messages a reader must still give: those of every chunk before the first damaged
    byte (read in step from the start), and, while the summary and footer are whole (the
    file is read through its chunk index), those of every chunk the damage left whole."""
    first = next(
        (k for k, (a, b) in enumerate(zip(damaged, MCAP, strict=False)) if a != b),
        min(len(damaged), len(MCAP)),
    )
    indexed = _untouched(damaged, SUMMARY_START, len(MCAP))
    must: set[tuple[str, str, int, bytes]] = set()
    for start, end, held in CHUNKS:
        if end <= first or indexed and _untouched(damaged, start, end):
            must |= held
    return must


def _check_damaged(flip_list: list[tuple[int, int, int]], cut: int | None) -> bool:
    """Read the damaged bag and check it; True when it read (False: BagError).

    BagError exactly when the magic is damaged (an empty or non-MCAP file, as documented);
    otherwise only messages written, each once, in log-time order, at least those
    :func:`_must_read` names (all of them for an undamaged bag)."""
    damaged = _damage(flip_list, cut)
    with tempfile.TemporaryDirectory() as tmp, contextlib.redirect_stdout(io.StringIO()):
        read = _read_all(_bag_of(Path(tmp), damaged))
    magic_whole = _untouched(damaged, 0, MAGIC)
    assert (read is not None) == magic_whole, (read is not None, magic_whole)
    if read is None:
        return False
    assert set(read) <= WRITTEN
    assert len(read) == len(set(read))  # no message twice
    stamps = [m[2] for m in read]
    assert stamps == sorted(stamps)
    missing = _must_read(damaged) - set(read)
    assert not missing, f"{len(missing)} message(s) of whole chunks not read"
    return True


def test_the_chunk_layout_holds_every_message_once() -> None:
    held = [m for _, _, chunk in CHUNKS for m in chunk]
    assert len(held) == len(set(held)) and set(held) == WRITTEN
    assert all(a[1] <= b[0] for a, b in zip(CHUNKS, CHUNKS[1:], strict=False))
    assert CHUNKS[-1][1] <= SUMMARY_START < len(MCAP)


def test_the_undamaged_bag_reads_every_message() -> None:
    assert _must_read(MCAP) == WRITTEN
    assert _check_damaged([], None)


@settings(max_examples=EXAMPLES, suppress_health_check=[HealthCheck.too_slow])
@given(flip_list=flips, cut=cuts)
def test_a_damaged_bag_reads_only_written_messages_or_fails_with_bag_error(
    flip_list: list[tuple[int, int, int]], cut: int | None
) -> None:
    _check_damaged(flip_list, cut)


def test_most_fuzz_cases_read() -> None:
    """A fixed sample of damage (numpy's generator, seeded): every case is checked as above,
    and the cases that read are counted - a reader that raises on any damage fails here."""
    rng = np.random.default_rng(11)
    read = magic_whole = 0
    for _ in range(60):
        flip_list = [
            (int(rng.integers(0, len(MCAP))), int(rng.integers(1, 65)), int(rng.integers(1, 256)))
            for _ in range(int(rng.integers(1, 4)))
        ]
        cut = int(rng.integers(0, len(MCAP))) if rng.random() < 0.4 else None
        read += _check_damaged(flip_list, cut)
        magic_whole += _untouched(_damage(flip_list, cut), 0, MAGIC)
    assert read == magic_whole and read >= 40


@settings(max_examples=EXAMPLES // 2, suppress_health_check=[HealthCheck.too_slow])
@given(flip_list=flips, cut=cuts)
def test_recover_of_a_damaged_bag_writes_a_readable_bag_or_one_error_line(
    flip_list: list[tuple[int, int, int]], cut: int | None
) -> None:
    from rosbags.rosbag2 import Reader

    from csam_ros.cli import main

    with tempfile.TemporaryDirectory() as tmp:
        bag = _bag_of(Path(tmp), _damage(flip_list, cut))
        with contextlib.redirect_stdout(io.StringIO()):
            read = _read_all(bag)
        out = Path(tmp) / "recovered"
        stdout, stderr = io.StringIO(), io.StringIO()
        with contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(stderr):
            code = main(["bag", "recover", str(bag), "--out", str(out)])
        if code != 0:
            assert not read, "a bag whose messages read was not recovered"
            assert code == 2
            assert len(stderr.getvalue().strip().splitlines()) == 1, stderr.getvalue()
            assert stderr.getvalue().startswith("csam bag: ")
            assert not out.exists()
            return
        with Reader(out) as reader:
            rows = [(c.topic, c.msgtype, t, bytes(raw)) for c, t, raw in reader.messages()]
            assert reader.message_count == len(rows)
        assert set(rows) <= WRITTEN and len(rows) == len(set(rows))
        assert set(rows) == set(read or [])  # what the reader gives, no more, no less
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
    assert read and set(read) == _must_read(MCAP[:cut])  # every chunk before the cut, no more


def test_a_cut_bag_reads_the_whole_chunks_after_a_chunk_of_damaged_length() -> None:
    """Read linearly (cut before its summary), a chunk whose length field is 256 too long is
    skipped; the whole chunk after it, inside the span its length names, still reads."""
    start, _, lost = CHUNKS[1]
    damaged = _damage([(start + 2, 1, 0x01)], SUMMARY_START)
    with tempfile.TemporaryDirectory() as tmp, contextlib.redirect_stdout(io.StringIO()):
        read = _read_all(_bag_of(Path(tmp), damaged))
    assert read is not None and set(read) == WRITTEN - lost
