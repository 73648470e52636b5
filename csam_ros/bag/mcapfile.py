"""One MCAP file read so that damage never turns into a wrong message or a traceback.

Every chunk is checked before any of its messages is used: its record must be whole, its data
must decompress to the size it declares (decompressed no further than that: a chunk that
declares 100 bytes and holds 4 GB is damaged, never a memory blow-up), and the CRC-32 of the
decompressed records must match the one stored in the chunk. A chunk that fails is skipped and
reported (file, offset, reason, and the messages lost, counted from the chunk's message index
when that still reads).

A complete file (footer, a summary whose CRC matches, chunk indexes that do not overlap) is
read through its chunk index. Any other file (cut short by SIGKILL, or with a damaged summary)
is read linearly, record by record; when a record does not parse (a damaged length, say), or a
chunk fails its checks (its length may be the damage), reading resumes at the next chunk whose
CRC matches, searched from the byte after it. The chunk data a linear read checks, candidates
included, is at most EXAMINED_PER_BYTE times the file's size, so records posing as overlapping
chunks cannot make it quadratic. Schema, channel and message records outside chunks have no
checksum of their own: they are used only while the file reads in step from its start (no
damage met), so that bytes misread after damage can never pose as a message.

Everything is parsed here with explicit bounds; damage surfaces only as :class:`ScanProblem`
entries, never as an exception (other than OSError for a file that cannot be opened).
"""

from __future__ import annotations

import heapq
import mmap
import struct
import zlib
from collections.abc import Callable, Collection, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import zstandard
from mcap.records import Channel, Schema

from csam_ros.core.model.regular_files import open_regular

MAGIC = b"\x89MCAP0\r\n"

OP_FOOTER = 0x02
OP_SCHEMA = 0x03
OP_CHANNEL = 0x04
OP_MESSAGE = 0x05
OP_CHUNK = 0x06
OP_MESSAGE_INDEX = 0x07
OP_CHUNK_INDEX = 0x08
OP_STATISTICS = 0x0B
OP_DATA_END = 0x0F
_KNOWN_OPCODES = frozenset(range(0x01, 0x10))
_FOOTER_RECORD = 1 + 8 + 20  # opcode, length, summary_start, summary_offset_start, crc
_CHUNK_FIXED = 8 + 8 + 8 + 4 + 4  # start, end, uncompressed size, crc, compression length
_MAX_UNCOMPRESSED = 1 << 31  # a chunk declaring more is damaged (rosbag2 writes ~1 MB chunks)
_PIECE = 1 << 20  # bytes decompressed at a time
# The bytes of chunk data checked (CRC, decompression) in a linear read, at most this many
# times the file's size: overlapping records posing as chunks cannot make the scan quadratic.
EXAMINED_PER_BYTE = 2


class _DamageError(Exception):
    """Bytes that do not parse as what they should be."""


class _Cursor:
    """Bounds-checked little-endian reads from ``data[pos:end]``."""

    def __init__(self, data: bytes | mmap.mmap, pos: int = 0, end: int | None = None) -> None:
        self.data = data
        self.pos = pos
        self.end = len(data) if end is None else end

    def take(self, n: int) -> bytes:
        if n < 0 or self.pos + n > self.end:
            raise _DamageError(f"a field runs past its record ({n} bytes at {self.pos})")
        chunk = self.data[self.pos : self.pos + n]
        self.pos += n
        return bytes(chunk)

    def u16(self) -> int:
        return int.from_bytes(self.take(2), "little")

    def u32(self) -> int:
        return int.from_bytes(self.take(4), "little")

    def u64(self) -> int:
        return int.from_bytes(self.take(8), "little")

    def blob(self) -> bytes:
        return self.take(self.u32())

    def text(self) -> str:
        try:
            return self.blob().decode("utf-8")
        except UnicodeDecodeError:
            raise _DamageError("a string is not UTF-8") from None

    def text_map(self) -> dict[str, str]:
        length = self.u32()
        inner = _Cursor(self.data, self.pos, self.pos + length)
        if inner.end > self.end:
            raise _DamageError("a map runs past its record")
        result = {}
        while inner.pos < inner.end:
            key = inner.text()
            result[key] = inner.text()
        self.pos = inner.end
        return result


def _schema(cursor: _Cursor) -> Schema:
    schema_id = cursor.u16()
    return Schema(id=schema_id, name=cursor.text(), encoding=cursor.text(), data=cursor.blob())


def _channel(cursor: _Cursor) -> Channel:
    channel_id, schema_id = cursor.u16(), cursor.u16()
    topic, encoding = cursor.text(), cursor.text()
    return Channel(
        id=channel_id,
        schema_id=schema_id,
        topic=topic,
        message_encoding=encoding,
        metadata=cursor.text_map(),
    )


@dataclass(frozen=True)
class RawMessage:
    channel_id: int
    log_time: int
    publish_time: int
    data: bytes


@dataclass
class ChunkRecords:
    """The records of one verified chunk, in file order."""

    schemas: list[Schema] = field(default_factory=list)
    channels: list[Channel] = field(default_factory=list)
    messages: list[RawMessage] = field(default_factory=list)


_RECORD_HEAD = struct.Struct("<BQ")
_MESSAGE_HEAD = struct.Struct("<HIQQ")  # channel id, sequence, log time, publish time


def _records(data: bytes, into: ChunkRecords) -> None:
    """Parse the schema, channel and message records of verified, decompressed chunk data."""
    pos, end = 0, len(data)
    while pos < end:
        if pos + _RECORD_HEAD.size > end:
            raise _DamageError("a record header runs past the chunk")
        opcode, length = _RECORD_HEAD.unpack_from(data, pos)
        start = pos + _RECORD_HEAD.size
        pos = start + length
        if pos > end:
            raise _DamageError("a record runs past the chunk")
        if opcode == OP_MESSAGE:
            if length < _MESSAGE_HEAD.size:
                raise _DamageError("a message record is too short")
            channel_id, _sequence, log_time, publish_time = _MESSAGE_HEAD.unpack_from(data, start)
            into.messages.append(
                RawMessage(
                    channel_id, log_time, publish_time, data[start + _MESSAGE_HEAD.size : pos]
                )
            )
        elif opcode == OP_SCHEMA:
            into.schemas.append(_schema(_Cursor(data, start, pos)))
        elif opcode == OP_CHANNEL:
            into.channels.append(_channel(_Cursor(data, start, pos)))


@dataclass(frozen=True)
class _ChunkHead:
    """What a chunk record says of its data: where the compressed bytes lie in the file,
    their compression, the size they decompress to and the CRC of that."""

    uncompressed_size: int
    crc: int
    compression: str
    start: int
    end: int


def _chunk_head(data: bytes | mmap.mmap, offset: int, size: int) -> _ChunkHead:
    """The head of the chunk record at ``offset``, every field checked against the record and
    the file (no byte of its data read); _DamageError if any does not fit."""
    cursor = _Cursor(data, offset, size)
    if cursor.take(1)[0] != OP_CHUNK:
        raise _DamageError("no chunk record at this offset")
    length = cursor.u64()
    if offset + 9 + length > size:
        raise _DamageError("the chunk runs past the end of the file")
    body = _Cursor(data, cursor.pos, cursor.pos + length)
    body.take(16)  # message start and end time: not trusted, the messages carry their own
    uncompressed_size, crc = body.u64(), body.u32()
    compression = body.text()
    compressed = body.u64()
    if body.pos + compressed != body.end:
        raise _DamageError("its record length does not match its contents")
    if uncompressed_size > _MAX_UNCOMPRESSED:
        raise _DamageError(f"it declares {uncompressed_size} bytes of records")
    if compression not in _DECOMPRESSORS:
        raise _DamageError(f"unknown compression {compression[:20]!r}")
    if compression == "" and compressed != uncompressed_size:
        raise _DamageError(f"it holds {compressed} bytes of records, not {uncompressed_size}")
    return _ChunkHead(uncompressed_size, crc, compression, body.pos, body.end)


def _read_bounded(read: Callable[[int], bytes], limit: int) -> bytes:
    """What ``read(n)`` gives until it gives nothing, but never more than ``limit + 1`` bytes
    (one more than ``limit`` says that there was more)."""
    out = bytearray()
    while len(out) <= limit:
        piece = read(min(_PIECE, limit + 1 - len(out)))
        if not piece:
            break
        out += piece
    return bytes(out)


def _zstd(compressed: bytes, limit: int) -> bytes:
    # zstandard allocates the content size a frame names, whatever the bound given: at once
    # only within the bound, else decompressed piece by piece (a size not named, or a lie)
    named = zstandard.frame_content_size(compressed)
    if 0 <= named <= limit:
        return zstandard.ZstdDecompressor().decompress(compressed, max_output_size=limit)
    with zstandard.ZstdDecompressor().stream_reader(compressed) as reader:
        return _read_bounded(reader.read, limit)


def _lz4(compressed: bytes, limit: int) -> bytes:
    import lz4.frame

    decompressor = lz4.frame.LZ4FrameDecompressor()
    pending = [compressed]

    def read(n: int) -> bytes:
        if decompressor.eof:
            return b""
        piece = decompressor.decompress(pending.pop() if pending else b"", max_length=n)
        return bytes(piece)

    return _read_bounded(read, limit)


_DECOMPRESSORS: dict[str, Callable[[bytes, int], bytes] | None] = {
    "zstd": _zstd,
    "lz4": _lz4,
    "": None,
}


def _decompressed(head: _ChunkHead, compressed: bytes) -> bytes:
    """The records of a chunk's data, decompressed no further than one byte past the size
    the chunk declares: a chunk whose data holds more is damaged, never a memory blow-up."""
    decompress = _DECOMPRESSORS[head.compression]
    if decompress is None:
        return compressed
    try:
        return decompress(compressed, head.uncompressed_size)
    except ImportError:
        raise _DamageError(f"{head.compression} compression, its module is not installed") from None
    except Exception as error:  # zstd and lz4 raise their own errors, RuntimeError and others
        raise _DamageError(f"{head.compression} decompression failed ({error})") from None


def _chunk_records(data: bytes | mmap.mmap, head: _ChunkHead) -> ChunkRecords:
    """The records of a chunk whose head was read: decompressed (bounded), their size and
    CRC checked, parsed; _DamageError if any check fails."""
    records = _decompressed(head, bytes(data[head.start : head.end]))
    declared = head.uncompressed_size
    if len(records) > declared:
        raise _DamageError(f"it decompresses to more than the {declared} bytes it declares")
    if len(records) != declared:
        raise _DamageError(f"it decompresses to {len(records)} bytes, not {declared}")
    if head.crc != 0 and zlib.crc32(records) != head.crc:
        raise _DamageError("chunk checksum mismatch")
    result = ChunkRecords()
    _records(records, result)
    return result


def decode_chunk(data: bytes | mmap.mmap, offset: int, size: int) -> ChunkRecords:
    """The records of the chunk record at ``offset``; _DamageError if any check fails."""
    return _chunk_records(data, _chunk_head(data, offset, size))


def _message_index_counts(data: bytes | mmap.mmap, pos: int, end: int) -> dict[int, int] | None:
    """Messages per channel in the message index records at ``data[pos:end]``, or None."""
    counts: dict[int, int] = {}
    try:
        cursor = _Cursor(data, pos, end)
        while cursor.pos < cursor.end:
            if cursor.take(1)[0] != OP_MESSAGE_INDEX:
                return None
            body = _Cursor(data, cursor.pos + 8, cursor.pos + 8 + cursor.u64())
            cursor.take(body.end - body.pos)
            channel_id = body.u16()
            entries = body.u32()
            if entries % 16 or body.pos + entries != body.end:
                return None
            counts[channel_id] = counts.get(channel_id, 0) + entries // 16
    except _DamageError:
        return None
    return counts


@dataclass
class ChunkInfo:
    """A chunk found in the file: verified (``ok``) or skipped with ``reason``."""

    offset: int
    ok: bool
    start_ns: int = 0
    end_ns: int = 0
    counts: dict[int, int] = field(default_factory=dict)  # ok: messages per channel
    reason: str = ""
    lost: dict[int, int] | None = None  # skipped: messages per channel (None: unknown)


@dataclass
class McapScan:
    """What one MCAP file holds as far as it reads, and what did not read."""

    path: Path
    size: int
    complete: bool  # footer and a summary whose CRC matches
    schemas: dict[int, Schema] = field(default_factory=dict)
    channels: dict[int, Channel] = field(default_factory=dict)
    chunks: list[ChunkInfo] = field(default_factory=list)  # file order
    loose: list[RawMessage] = field(default_factory=list)  # messages outside chunks
    cut_at: int | None = None  # linear read: where the readable data ends (file cut short)
    problems: list[str] = field(default_factory=list)  # damage other than skipped chunks
    orphans: int = 0  # messages whose channel definition was lost
    examined: int = 0  # bytes of chunk data checked (decompressed, CRC), candidates included

    @property
    def skipped(self) -> list[ChunkInfo]:
        return [chunk for chunk in self.chunks if not chunk.ok]

    def counts(self) -> dict[int, int]:
        """Readable messages per channel id (orphans excluded)."""
        return {k: n for k, n in self.all_counts().items() if k in self.channels}

    def all_counts(self) -> dict[int, int]:
        """Messages per channel id in verified chunks and outside chunks, orphans included."""
        counts: dict[int, int] = {}
        for chunk in self.chunks:
            for channel_id, n in chunk.counts.items():
                counts[channel_id] = counts.get(channel_id, 0) + n
        for message in self.loose:
            counts[message.channel_id] = counts.get(message.channel_id, 0) + 1
        return counts

    def span(self) -> tuple[int, int] | None:
        times = [(c.start_ns, c.end_ns) for c in self.chunks if c.ok and c.counts]
        times += [(m.log_time, m.log_time) for m in self.loose]
        if not times:
            return None
        return min(t[0] for t in times), max(t[1] for t in times)

    def topic_of(self, channel_id: int) -> str:
        channel = self.channels.get(channel_id)
        return channel.topic if channel is not None else f"channel {channel_id}"


def _count_chunk(info: ChunkInfo, records: ChunkRecords) -> None:
    for message in records.messages:
        info.counts[message.channel_id] = info.counts.get(message.channel_id, 0) + 1
    if records.messages:
        info.start_ns = min(m.log_time for m in records.messages)
        info.end_ns = max(m.log_time for m in records.messages)


def _read_summary(
    data: mmap.mmap, size: int, scan: McapScan, chunks: list[tuple[int, int, int]]
) -> str:
    """Schemas and channels of a complete file's summary into ``scan``, the chunks' offsets
    (chunk, its message index, their end) into ``chunks``. Returns "" on success, else why
    the file must be read linearly: "cut" (no footer), "unindexed" (a complete file without
    chunk index), or the damage found."""
    if size < len(MAGIC) * 2 + _FOOTER_RECORD or data[size - len(MAGIC) :] != MAGIC:
        return "cut"
    summary_end = size - len(MAGIC) - _FOOTER_RECORD
    footer = _Cursor(data, summary_end, size - len(MAGIC))
    if footer.take(1)[0] != OP_FOOTER or footer.u64() != 20:
        return "cut"  # the end magic alone is no footer
    summary_start, _offsets_start, crc = footer.u64(), footer.u64(), footer.u32()
    if summary_start == 0:
        return "unindexed"
    if not len(MAGIC) < summary_start <= summary_end:
        return "its footer is damaged"
    if crc != 0 and zlib.crc32(data[summary_start : size - len(MAGIC) - 4]) != crc:
        return "its summary checksum does not match"
    cursor = _Cursor(data, summary_start, summary_end)
    while cursor.pos < cursor.end:
        opcode = cursor.take(1)[0]
        length = cursor.u64()
        body = _Cursor(data, cursor.pos, cursor.pos + length)
        cursor.take(length)
        if opcode == OP_SCHEMA:
            schema = _schema(body)
            scan.schemas[schema.id] = schema
        elif opcode == OP_CHANNEL:
            channel = _channel(body)
            scan.channels[channel.id] = channel
        elif opcode == OP_CHUNK_INDEX:
            body.take(16)  # message start and end time (taken from the messages instead)
            offset, length = body.u64(), body.u64()
            body.take(body.u32())  # message index offsets per channel
            index_length = body.u64()
            if not len(MAGIC) <= offset < offset + length + index_length <= summary_start:
                return "a chunk index points outside the data section"
            chunks.append((offset, offset + length, offset + length + index_length))
    chunks.sort()
    if any(b[0] < a[2] for a, b in zip(chunks, chunks[1:], strict=False)):
        return "its chunk indexes overlap"  # each chunk would be checked again and again
    return "" if chunks else "unindexed"


class _SearchSpentError(Exception):
    """The bytes a linear read may check (EXAMINED_PER_BYTE times the file) are spent."""


def _verified(scan: McapScan, data: mmap.mmap, offset: int) -> ChunkRecords:
    """The records of the chunk at ``offset`` (:func:`decode_chunk`), its data counted in
    ``scan.examined``; _SearchSpentError instead when that would pass the linear read's bound."""
    head = _chunk_head(data, offset, scan.size)
    cost = head.end - head.start
    if scan.examined + cost > EXAMINED_PER_BYTE * scan.size:
        raise _SearchSpentError
    scan.examined += cost
    return _chunk_records(data, head)


def _add_chunk(
    scan: McapScan,
    data: mmap.mmap,
    offset: int,
    index: tuple[int, int] | None = None,
    records: ChunkRecords | None = None,
) -> ChunkInfo:
    """Check the chunk at ``offset`` and add it to ``scan`` (its records if it reads; else the
    messages lost, from the message index records at ``data[slice(*index)]`` if given).
    ``records``: the chunk's, verified already."""
    info = ChunkInfo(offset=offset, ok=True)
    try:
        if records is None:
            records = _verified(scan, data, offset)
    except _DamageError as error:
        info.ok, info.reason = False, str(error)
        if index is not None:
            info.lost = _message_index_counts(data, *index)
    else:
        for schema in records.schemas:
            scan.schemas.setdefault(schema.id, schema)
        for channel in records.channels:
            scan.channels.setdefault(channel.id, channel)
        _count_chunk(info, records)
    scan.chunks.append(info)
    return info


def _next_chunk(
    scan: McapScan, data: mmap.mmap, start: int, stop: int
) -> tuple[int, ChunkRecords] | None:
    """The offset and records of the first readable chunk record that starts in
    ``[start, stop)``, or None (_SearchSpentError when the read's bound is reached)."""
    size = scan.size
    pos = start
    while True:
        pos = data.find(bytes([OP_CHUNK]), pos, stop)
        if pos < 0:
            return None
        if pos + 9 + _CHUNK_FIXED + 8 <= size:
            length = int.from_bytes(data[pos + 1 : pos + 9], "little")
            if _CHUNK_FIXED + 8 <= length <= size - pos - 9:
                try:
                    return pos, _verified(scan, data, pos)
                except _DamageError:
                    pass
        pos += 1


def _scan_linear(scan: McapScan, data: mmap.mmap) -> None:
    """Read the data section record by record (see the module documentation). The chunk data
    checked, candidates included, is at most EXAMINED_PER_BYTE times the file: past that the
    rest is reported as not searched (only records made to pose as chunks get there)."""
    pos = len(MAGIC)
    try:
        _scan_records(scan, data, pos)
    except _SearchSpentError as spent:
        at = spent.args[0] if spent.args else pos
        if not scan.complete:
            scan.cut_at = at
        scan.problems.append(
            f"bytes {at} to {scan.size} not searched: too many records that pose as chunks "
            f"({scan.examined} bytes of chunk data checked, {EXAMINED_PER_BYTE} times the "
            "file's size at most)"
        )


def _scan_records(scan: McapScan, data: mmap.mmap, pos: int) -> None:
    size = scan.size
    in_step = True  # no damage met yet: records outside chunks can be trusted
    last_bad: ChunkInfo | None = None  # the messages it lost: from the index records after it
    lost: dict[int, int] | None = None
    ignored = 0
    found: tuple[int, ChunkRecords] | None = None  # a chunk verified while searching

    def settle() -> None:
        if last_bad is not None:
            last_bad.lost = lost or None

    def search(start: int, stop: int) -> tuple[int, ChunkRecords] | None:
        try:
            return _next_chunk(scan, data, start, stop)
        except _SearchSpentError:
            settle()
            raise _SearchSpentError(start) from None

    while True:
        if pos >= size:
            if not scan.complete:
                scan.cut_at = size
            break
        opcode = data[pos]
        length = int.from_bytes(data[pos + 1 : pos + 9], "little") if pos + 9 <= size else -1
        end = pos + 9 + length
        whole = opcode in _KNOWN_OPCODES and length >= 0 and end <= size
        if opcode == OP_DATA_END and length != 4 or opcode == OP_FOOTER and length != 20:
            whole = False
        if not whole:
            found = search(pos + 1, size)
            if found is None:
                if not scan.complete:
                    scan.cut_at = pos
                if opcode not in _KNOWN_OPCODES or (length >= 0 and end <= size):
                    scan.problems.append(f"bytes {pos} to {size} do not read as MCAP records")
                break
            scan.problems.append(f"bytes {pos} to {found[0]} do not read as MCAP records")
            settle()
            in_step, last_bad, pos = False, None, found[0]
            continue
        if opcode == OP_MESSAGE_INDEX:
            if last_bad is not None and lost is not None:
                counts = _message_index_counts(data, pos, end)
                if counts is None:
                    lost = None
                else:
                    for channel_id, n in counts.items():
                        lost[channel_id] = lost.get(channel_id, 0) + n
            pos = end
            continue
        settle()
        last_bad = None
        if opcode == OP_CHUNK:
            records = found[1] if found is not None and found[0] == pos else None
            found = None
            try:
                info = _add_chunk(scan, data, pos, records=records)
            except _SearchSpentError:
                raise _SearchSpentError(pos) from None
            if not info.ok:
                in_step = False
                # its length may be the damage: a whole chunk may start inside what it spans
                found = search(pos + 1, end)
                if found is not None:
                    scan.problems.append(f"bytes {pos} to {found[0]} do not read as MCAP records")
                    pos = found[0]
                    continue
                last_bad, lost = info, {}
        elif opcode in (OP_SCHEMA, OP_CHANNEL, OP_MESSAGE):
            if not in_step:
                ignored += 1
            else:
                try:
                    _loose_record(scan, opcode, _Cursor(data, pos + 9, end))
                except _DamageError as error:
                    scan.problems.append(f"record at offset {pos} does not read ({error})")
                    in_step = False
        elif opcode in (OP_DATA_END, OP_FOOTER):
            break
        pos = end
    settle()
    if ignored:
        scan.problems.append(
            f"{ignored} record(s) outside chunks after the damage were ignored (no checksum)"
        )


def _loose_record(scan: McapScan, opcode: int, body: _Cursor) -> None:
    if opcode == OP_SCHEMA:
        schema = _schema(body)
        scan.schemas.setdefault(schema.id, schema)
    elif opcode == OP_CHANNEL:
        channel = _channel(body)
        scan.channels.setdefault(channel.id, channel)
    else:
        channel_id, _sequence = body.u16(), body.u32()
        log_time, publish_time = body.u64(), body.u64()
        scan.loose.append(
            RawMessage(channel_id, log_time, publish_time, body.take(body.end - body.pos))
        )


def scan_file(path: Path) -> McapScan:
    """Check every chunk of an MCAP file and list what it holds (OSError if unreadable)."""
    with open_regular(path) as stream:
        size = stream.seek(0, 2)
        scan = McapScan(path=path, size=size, complete=False)
        if size <= len(MAGIC):
            scan.cut_at = size
            return scan
        with mmap.mmap(stream.fileno(), 0, access=mmap.ACCESS_READ) as data:
            chunks: list[tuple[int, int, int]] = []
            try:
                why = _read_summary(data, size, scan, chunks)
            except _DamageError as error:
                why = f"its summary is damaged ({error})"
            if why:
                scan.schemas.clear()
                scan.channels.clear()
                scan.complete = why == "unindexed"
                if why not in ("cut", "unindexed"):
                    scan.problems.append(f"{why}: read without its index")
                _scan_linear(scan, data)
            else:
                scan.complete = True
                for offset, index_start, index_end in chunks:
                    _add_chunk(scan, data, offset, (index_start, index_end))
    orphans = {k: n for k, n in scan.all_counts().items() if k not in scan.channels}
    scan.orphans = sum(orphans.values())
    if orphans:
        scan.problems.append(
            f"{scan.orphans} message(s) of channel(s) {sorted(orphans)} whose definition was "
            "in a lost chunk were dropped"
        )
    return scan


def iter_messages(
    scan: McapScan, topics: Collection[str] | None = None
) -> Iterator[tuple[Channel, RawMessage] | str]:
    """The verified messages of a scanned file in log-time order (file order among equal
    times), optionally only those of ``topics``. A chunk that no longer reads (the file
    changed since the scan) yields a string saying so instead."""
    wanted = {
        channel_id
        for channel_id, channel in scan.channels.items()
        if topics is None or channel.topic in topics
    }
    chunks = sorted(
        (c for c in scan.chunks if c.ok and wanted.intersection(c.counts)),
        key=lambda c: (c.start_ns, c.offset),
    )
    heap: list[tuple[int, int, int, RawMessage]] = [
        (m.log_time, -1, k, m) for k, m in enumerate(scan.loose) if m.channel_id in wanted
    ]
    heapq.heapify(heap)
    if not chunks:
        while heap:
            message = heapq.heappop(heap)[3]
            yield scan.channels[message.channel_id], message
        return
    with open_regular(scan.path) as stream:
        size = stream.seek(0, 2)
        with mmap.mmap(stream.fileno(), 0, access=mmap.ACCESS_READ) as data:
            i = 0
            while i < len(chunks) or heap:
                while i < len(chunks) and (not heap or chunks[i].start_ns <= heap[0][0]):
                    chunk = chunks[i]
                    i += 1
                    try:
                        records = decode_chunk(data, chunk.offset, size)
                    except _DamageError as error:
                        yield (
                            f"{scan.path}: chunk at offset {chunk.offset} no longer reads ({error})"
                        )
                        continue
                    for k, message in enumerate(records.messages):
                        if message.channel_id in wanted:
                            heapq.heappush(heap, (message.log_time, chunk.offset, k, message))
                if heap:
                    message = heapq.heappop(heap)[3]
                    yield scan.channels[message.channel_id], message
