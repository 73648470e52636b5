"""One MCAP file against records made to hurt its reader (csam_ros/bag/mcapfile.py): chunks
whose data decompresses to far more than they declare, records posing as chunks that overlap
each other, a summary indexing the same chunk again and again. Each is read in memory and work
of the order of the file's size: the work is counted (bytes checked, bytes through CRC-32,
memory allocated), never timed."""

from __future__ import annotations

import io
import tracemalloc
import zlib
from pathlib import Path
from types import SimpleNamespace

import pytest
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer

from csam_ros.bag import mcapfile, read_bag
from csam_ros.bag.mcapfile import EXAMINED_PER_BYTE, MAGIC, OP_CHUNK, scan_file
from csam_ros.bag.writer import BagWriter

SECOND = 1_000_000_000
BOMB = 64 * 2**20  # what the bomb chunk's data decompresses to


def _bomb_file(path: Path, compression: CompressionType) -> tuple[int, int]:
    """An MCAP file whose one chunk (a 64 MiB message of zeros, a few hundred kB compressed)
    declares 100 bytes of records; the chunk's offset and the file's size."""
    stream = io.BytesIO()
    writer = Writer(stream, compression=compression)
    writer.start(profile="ros2", library="test")
    schema = writer.register_schema("std_msgs/msg/String", "ros2msg", b"string data")
    channel = writer.register_channel("/big", "cdr", schema)
    writer.add_message(channel, log_time=SECOND, data=bytes(BOMB), publish_time=SECOND)
    writer.finish()
    data = bytearray(stream.getvalue())
    summary = make_reader(io.BytesIO(bytes(data))).get_summary()
    assert summary is not None
    (index,) = summary.chunk_indexes
    offset = index.chunk_start_offset
    assert data[offset] == OP_CHUNK
    data[offset + 25 : offset + 33] = (100).to_bytes(8, "little")  # its uncompressed size
    path.write_bytes(bytes(data))
    return offset, len(data)


@pytest.mark.parametrize("compression", ["zstd", "lz4"])
def test_a_chunk_whose_data_holds_more_than_it_declares_is_skipped_unexpanded(
    tmp_path: Path, compression: str
) -> None:
    """A chunk declaring 100 bytes whose data decompresses to 64 MiB (zstd: its frame names
    the larger size, which zstandard would allocate; lz4: no bound at all) is a damaged
    chunk, decompressed no further than its declared size: far less than 64 MiB allocated."""
    if compression == "lz4":
        pytest.importorskip("lz4.frame")
    kind = CompressionType.ZSTD if compression == "zstd" else CompressionType.LZ4
    path = tmp_path / f"{compression}.mcap"
    offset, size = _bomb_file(path, kind)
    assert size < BOMB // 50
    tracemalloc.start()
    try:
        scan = scan_file(path)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    (chunk,) = scan.chunks
    assert chunk.offset == offset and not chunk.ok
    assert "more than the 100 bytes it declares" in chunk.reason, chunk.reason
    assert peak < 8 * 2**20, f"{peak / 2**20:.1f} MiB allocated"


def _posing_chunks(count: int) -> bytes:
    """An MCAP magic, one byte that is no record, then ``count`` chunk record headers 49
    bytes apart, each naming the rest of the file as its uncompressed records (a CRC that
    does not match): every header is a candidate whose check reads to the end."""
    head = 1 + 8 + 16 + 8 + 4 + 4 + 8  # opcode, length, times, size, CRC, compression, data
    size = len(MAGIC) + 1 + count * head + 64
    out = bytearray(MAGIC + b"\xff")
    while len(out) + head <= size - 64:
        length = size - len(out) - 9
        records = length - (head - 9)
        out += bytes([OP_CHUNK]) + length.to_bytes(8, "little") + bytes(16)
        out += records.to_bytes(8, "little") + (1).to_bytes(4, "little") + bytes(4)
        out += records.to_bytes(8, "little")
    out += bytes(size - len(out))
    return bytes(out)


@pytest.mark.parametrize("count", [1000, 3000])
def test_records_posing_as_overlapping_chunks_are_checked_in_linear_work(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, count: int
) -> None:
    """Thousands of chunk headers, each spanning the rest of the file: a search that checks
    each in full does quadratic work (16 MB took 159 s). The bytes of chunk data checked,
    and the bytes through CRC-32 (counted at zlib), stay within EXAMINED_PER_BYTE times the
    file's size; the rest is reported as not searched."""
    path = tmp_path / "posing.mcap"
    path.write_bytes(_posing_chunks(count))
    size = path.stat().st_size
    crc_bytes = [0]

    def counted_crc32(data: bytes, value: int = 0) -> int:
        crc_bytes[0] += len(data)
        return zlib.crc32(data, value)

    monkeypatch.setattr(mcapfile, "zlib", SimpleNamespace(crc32=counted_crc32))
    scan = scan_file(path)
    assert not [c for c in scan.chunks if c.ok]
    assert 0 < scan.examined <= EXAMINED_PER_BYTE * size
    assert crc_bytes[0] <= EXAMINED_PER_BYTE * size
    assert any("not searched: too many records that pose as chunks" in p for p in scan.problems)


def test_a_summary_indexing_each_chunk_many_times_is_read_without_it(tmp_path: Path) -> None:
    """A complete file whose summary lists every chunk 50 times (summary CRC left out, as
    MCAP allows): each chunk would be checked 50 times and its messages given 50 times. The
    overlapping index is refused, the file read linearly: every message once."""
    with BagWriter(tmp_path / "counter", chunk_size=100) as bag:
        bag.add_topic("/counter", "std_msgs/msg/UInt32")
        for i in range(40):
            bag.write("/counter", i * SECOND, b"\x00\x01\x00\x00" + i.to_bytes(4, "little"))
    mcap = tmp_path / "counter" / "counter_0.mcap"
    data = mcap.read_bytes()
    footer = len(data) - len(MAGIC) - 29
    summary_start = int.from_bytes(data[footer + 9 : footer + 17], "little")
    indexes, pos = b"", summary_start
    while pos < footer:
        length = int.from_bytes(data[pos + 1 : pos + 9], "little")
        if data[pos] == mcapfile.OP_CHUNK_INDEX:
            indexes += data[pos : pos + 9 + length]
        pos += 9 + length
    assert indexes
    new_footer = bytes([mcapfile.OP_FOOTER]) + (20).to_bytes(8, "little")
    new_footer += summary_start.to_bytes(8, "little") + bytes(8) + bytes(4)  # no CRC
    mcap.write_bytes(data[:footer] + indexes * 50 + new_footer + MAGIC)
    scan = scan_file(mcap)
    assert scan.examined <= mcap.stat().st_size
    assert any("chunk indexes overlap" in p for p in scan.problems)
    values = [int.from_bytes(m.data[4:], "little") for m in read_bag(mcap.parent)]
    assert values == list(range(40))
