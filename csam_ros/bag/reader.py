"""Reading rosbag2 bags with MCAP storage, including bags whose recorder was killed.

A bag is a directory (metadata.yaml plus .mcap files) or a single .mcap file. A complete MCAP
file is read through its index in log-time order. A file cut short (no footer: the recorder
was killed) is read linearly up to its last complete chunk, then sorted by log time. Without
metadata.yaml the .mcap files of the directory are read alone (topics, types and QoS come
from the MCAP schemas and channels).

``read_bag`` yields raw CDR bytes; ``read_bag_messages`` deserializes them into the rclpy
(rosidl generated) message classes, the same classes the nodes receive, so offline replay can
share the nodes' message conversion code.
"""

from __future__ import annotations

import heapq
import os
import struct
from collections.abc import Callable, Collection, Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import yaml
from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap.records import Channel, Message, Schema
from mcap.stream_reader import StreamReader

from .qos import QosDict, parse_qos_profiles
from .types import MessageTypes, message_class
from .writer import METADATA_FILE, BagError

MCAP_MAGIC = b"\x89MCAP0\r\n"
_TRUNCATION_ERRORS = (McapError, struct.error, EOFError, ValueError)


class BagMessage(NamedTuple):
    """One recorded message: raw CDR bytes at log time ``log_time_ns``."""

    topic: str
    msgtype: str
    log_time_ns: int
    data: bytes


class DecodedMessage(NamedTuple):
    """One recorded message deserialized into its rclpy message class."""

    topic: str
    msgtype: str
    log_time_ns: int
    message: Any


@dataclass(frozen=True)
class TopicInfo:
    """A recorded topic."""

    name: str
    msgtype: str
    offered_qos_profiles: list[QosDict]
    message_count: int
    type_hash: str = ""  # RIHS01 hash of the recorded definition ("" if the bag has none)


@dataclass
class BagInfo:
    """What a bag holds, as far as it can be read."""

    path: Path
    files: list[Path]
    topics: dict[str, TopicInfo]
    message_count: int
    start_ns: int
    end_ns: int
    truncated_files: list[Path] = field(default_factory=list)
    has_metadata: bool = False
    warnings: list[str] = field(default_factory=list)


@dataclass
class _FileScan:
    messages: int = 0
    start_ns: int = 2**63 - 1
    end_ns: int = 0
    counts: dict[str, int] = field(default_factory=dict)
    types: dict[str, str] = field(default_factory=dict)
    qos: dict[str, list[QosDict]] = field(default_factory=dict)
    hashes: dict[str, str] = field(default_factory=dict)


def _load_metadata(path: Path) -> dict[str, Any] | None:
    """metadata.yaml's ``rosbag2_bagfile_information``, or None if absent; BagError if bad."""
    meta = path / METADATA_FILE
    if not meta.is_file():
        return None
    try:
        document = yaml.safe_load(meta.read_text(encoding="utf-8"))
        info = document["rosbag2_bagfile_information"]
        if not isinstance(info, dict):
            raise TypeError
    except (yaml.YAMLError, OSError, UnicodeDecodeError, KeyError, TypeError) as error:
        raise BagError(f"{meta} is not a rosbag2 metadata file ({error})") from None
    storage = info.get("storage_identifier", "mcap")
    if storage != "mcap":
        raise BagError(f"{path} uses storage {storage!r}; only mcap bags are supported")
    if info.get("compression_mode"):
        raise BagError(f"{path} uses rosbag2 {info['compression_mode']} compression (unsupported)")
    return info


def _bag_files(path: Path, metadata: dict[str, Any] | None) -> list[Path]:
    if not os.path.lexists(path):
        raise BagError(f"{path} does not exist")
    if path.is_file():
        return [path]
    if not path.is_dir():
        raise BagError(f"{path} is neither a bag directory nor an .mcap file")
    if metadata is not None and metadata.get("relative_file_paths"):
        files = [path / name for name in metadata["relative_file_paths"]]
        missing = [f.name for f in files if not f.is_file()]
        if missing:
            raise BagError(f"{path}: metadata.yaml names missing file(s) {', '.join(missing)}")
        return files
    files = sorted(path.glob("*.mcap"))
    if not files:
        raise BagError(f"{path} holds no .mcap file")
    return files


def _check_magic(file: Path) -> None:
    with file.open("rb") as stream:
        head = stream.read(len(MCAP_MAGIC))
    if not head:
        raise BagError(f"{file} is empty")
    if head != MCAP_MAGIC[: len(head)] or len(head) < len(MCAP_MAGIC):
        raise BagError(f"{file} is not an MCAP file")


def _is_complete(file: Path) -> bool:
    """Whether the file ends with an MCAP footer and its summary reads."""
    with file.open("rb") as stream:
        stream.seek(0, os.SEEK_END)
        if stream.tell() < 2 * len(MCAP_MAGIC):
            return False
        stream.seek(-len(MCAP_MAGIC), os.SEEK_END)
        if stream.read() != MCAP_MAGIC:
            return False
        stream.seek(0)
        try:
            make_reader(stream).get_summary()
        except _TRUNCATION_ERRORS:
            return False
    return True


def _channel_qos(channel: Channel) -> list[QosDict]:
    try:
        return parse_qos_profiles(channel.metadata.get("offered_qos_profiles", ""))
    except (ValueError, TypeError):
        return []


def _iter_linear(file: Path) -> Iterator[tuple[Schema | None, Channel, Message]]:
    """Every message of a file cut short, in file order, up to the last complete record."""
    schemas: dict[int, Schema] = {}
    channels: dict[int, Channel] = {}
    with file.open("rb") as stream:
        records = StreamReader(stream, skip_magic=False).records
        while True:
            try:
                record = next(records)
            except StopIteration:
                return
            except _TRUNCATION_ERRORS:
                return
            if isinstance(record, Schema):
                schemas[record.id] = record
            elif isinstance(record, Channel):
                channels[record.id] = record
            elif isinstance(record, Message):
                channel = channels.get(record.channel_id)
                if channel is not None:
                    yield schemas.get(channel.schema_id), channel, record


def _iter_file(file: Path, complete: bool, topics: Collection[str] | None) -> Iterator[BagMessage]:
    """Messages of one file in log-time order."""
    if complete:
        with file.open("rb") as stream:
            reader = make_reader(stream)
            for schema, channel, message in reader.iter_messages(
                topics=list(topics) if topics is not None else None, log_time_order=True
            ):
                yield BagMessage(
                    channel.topic, schema.name if schema else "", message.log_time, message.data
                )
        return
    selected = [
        BagMessage(channel.topic, schema.name if schema else "", message.log_time, message.data)
        for schema, channel, message in _iter_linear(file)
        if topics is None or channel.topic in topics
    ]
    selected.sort(key=lambda m: m.log_time_ns)
    yield from selected


def _scan_file(file: Path, complete: bool) -> _FileScan:
    """Per-topic counts, types, QoS and time span of one file: from the summary statistics
    of a complete file, else by reading it through."""
    scan = _FileScan()

    def add(channel: Channel, schema: Schema | None, n: int) -> None:
        scan.types.setdefault(channel.topic, schema.name if schema else "")
        scan.qos.setdefault(channel.topic, _channel_qos(channel))
        scan.hashes.setdefault(channel.topic, channel.metadata.get("topic_type_hash", ""))
        scan.counts[channel.topic] = scan.counts.get(channel.topic, 0) + n

    if complete:
        with file.open("rb") as stream:
            summary = make_reader(stream).get_summary()
        if summary is not None and summary.statistics is not None:
            stats = summary.statistics
            for channel_id, channel in summary.channels.items():
                schema = summary.schemas.get(channel.schema_id)
                add(channel, schema, stats.channel_message_counts.get(channel_id, 0))
            scan.messages = stats.message_count
            if stats.message_count:
                scan.start_ns, scan.end_ns = stats.message_start_time, stats.message_end_time
            return scan
    for schema, channel, message in _iter_records(file, complete):
        add(channel, schema, 1)
        scan.messages += 1
        scan.start_ns = min(scan.start_ns, message.log_time)
        scan.end_ns = max(scan.end_ns, message.log_time)
    return scan


def _iter_records(file: Path, complete: bool) -> Iterator[tuple[Schema | None, Channel, Message]]:
    """Every message of a file in file order (complete: through the mcap reader)."""
    if not complete:
        yield from _iter_linear(file)
        return
    with file.open("rb") as stream:
        yield from make_reader(stream).iter_messages()


def inspect_bag(path: str | os.PathLike[str]) -> BagInfo:
    """Topics, types, recorded QoS, counts and time span of a bag (directory or .mcap file).

    Raises BagError for a missing path, a directory without .mcap files, an empty or
    non-MCAP file, and unsupported storage."""
    path = Path(path)
    metadata = _load_metadata(path) if path.is_dir() else None
    files = _bag_files(path, metadata)
    for file in files:
        _check_magic(file)
    truncated = [file for file in files if not _is_complete(file)]
    scans = [_scan_file(file, file not in truncated) for file in files]
    warnings = [
        f"{file} is cut short (no MCAP footer): reading it up to its last complete chunk"
        for file in truncated
    ]

    counts: dict[str, int] = {}
    types: dict[str, str] = {}
    qos: dict[str, list[QosDict]] = {}
    hashes: dict[str, str] = {}
    for scan in scans:
        for topic, n in scan.counts.items():
            counts[topic] = counts.get(topic, 0) + n
        for topic, msgtype in scan.types.items():
            types.setdefault(topic, msgtype)
        for topic, profiles in scan.qos.items():
            qos.setdefault(topic, profiles)
        for topic, type_hash in scan.hashes.items():
            hashes.setdefault(topic, type_hash)
    if metadata is not None:  # metadata.yaml is authoritative for types and QoS
        for entry in metadata.get("topics_with_message_count") or []:
            try:
                topic_meta = entry["topic_metadata"]
                name = topic_meta["name"]
                types[name] = topic_meta["type"]
                qos[name] = parse_qos_profiles(topic_meta.get("offered_qos_profiles"))
                hashes[name] = str(topic_meta.get("type_description_hash") or hashes.get(name, ""))
            except (KeyError, TypeError, ValueError) as error:
                warnings.append(f"{path / METADATA_FILE}: ignored a topic entry ({error})")
            else:
                counts.setdefault(name, 0)
    topics = {
        name: TopicInfo(
            name, types.get(name, ""), qos.get(name, []), counts.get(name, 0), hashes.get(name, "")
        )
        for name in sorted(set(counts) | set(types))
    }
    total = sum(scan.messages for scan in scans)
    start = min((scan.start_ns for scan in scans if scan.messages), default=0)
    end = max((scan.end_ns for scan in scans if scan.messages), default=0)
    return BagInfo(
        path=path,
        files=files,
        topics=topics,
        message_count=total,
        start_ns=start,
        end_ns=end,
        truncated_files=truncated,
        has_metadata=metadata is not None,
        warnings=warnings,
    )


def read_bag(
    path: str | os.PathLike[str], topics: Iterable[str] | None = None
) -> Iterator[BagMessage]:
    """Yield every message (topic, msgtype, log_time_ns, raw CDR bytes) of a bag in log-time
    order, optionally only those of ``topics``. Reads killed recordings up to their last
    complete chunk. Raises BagError for a bag that cannot be read at all."""
    path = Path(path)
    metadata = _load_metadata(path) if path.is_dir() else None
    files = _bag_files(path, metadata)
    for file in files:
        _check_magic(file)
    wanted = set(topics) if topics is not None else None
    streams = [_iter_file(file, _is_complete(file), wanted) for file in files]
    if len(streams) == 1:
        yield from streams[0]
    else:
        yield from heapq.merge(*streams, key=lambda m: m.log_time_ns)


def read_bag_messages(
    path: str | os.PathLike[str], topics: Iterable[str] | None = None
) -> Iterator[DecodedMessage]:
    """Like :func:`read_bag`, with each message deserialized into its rclpy message class
    (needs the message packages installed; rclpy is imported on first use).

    A topic recorded with another definition of its type than the installed one (its type
    hash differs) raises BagError when its first message is reached: its bytes would not
    decode, or decode wrongly. :func:`read_bag` still yields them raw, and readers that take
    the definition stored in the bag (rosbags, mcap) decode them."""
    from rclpy.serialization import deserialize_message

    recorded = {name: topic.type_hash for name, topic in inspect_bag(path).topics.items()}
    installed = MessageTypes()
    classes: dict[str, type] = {}
    checked: set[str] = set()
    decode: Callable[[bytes, type], Any] = deserialize_message
    for message in read_bag(path, topics):
        if message.topic not in checked:
            expected = installed.definition(message.msgtype).type_hash
            if recorded.get(message.topic) not in ("", None, expected):
                raise BagError(
                    f"{message.topic}: recorded with another definition of {message.msgtype} "
                    f"({recorded[message.topic]}) than the installed one ({expected}); "
                    "it cannot be decoded here"
                )
            checked.add(message.topic)
        cls = classes.get(message.msgtype)
        if cls is None:
            cls = classes[message.msgtype] = message_class(message.msgtype)
        yield DecodedMessage(
            message.topic, message.msgtype, message.log_time_ns, decode(message.data, cls)
        )
