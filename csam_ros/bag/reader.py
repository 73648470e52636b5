"""Reading rosbag2 bags with MCAP storage, including bags whose recorder was killed.

A bag is a directory (metadata.yaml plus .mcap files) or a single .mcap file. A complete MCAP
file is read through its index in log-time order. A file cut short (no footer: the recorder
was killed) is read linearly up to its last complete chunk, then in log-time order. Every
chunk's CRC is checked first (``mcapfile``): a chunk that is damaged (CRC mismatch, failed
decompression) is skipped, never returned, and reported with the file, its offset and the
messages lost; ``inspect_bag`` lists these warnings, the readers pass them to ``on_damage``
(default: the ``csam_ros.bag`` logger). ``recover_bag`` (``csam bag recover``) rewrites such
a bag complete. Without metadata.yaml the .mcap files of the directory are read alone
(topics, types and QoS come from the MCAP schemas and channels); the files metadata.yaml
names must lie inside the bag directory.

``read_bag`` yields raw CDR bytes; ``read_bag_messages`` deserializes them into the rclpy
(rosidl generated) message classes, the same classes the nodes receive, so offline replay can
share the nodes' message conversion code.
"""

from __future__ import annotations

import heapq
import logging
import os
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, NamedTuple

import yaml
from mcap.records import Channel

from csam_ros.bag.mcapfile import MAGIC as MCAP_MAGIC
from csam_ros.bag.mcapfile import McapScan, iter_messages, scan_file
from csam_ros.bag.qos import QosDict, parse_qos_profiles
from csam_ros.bag.types import MessageTypes, message_class
from csam_ros.bag.writer import METADATA_FILE, BagError
from csam_ros.core.model import yaml_text
from csam_ros.core.model.regular_files import open_regular

LOGGER = logging.getLogger("csam_ros.bag")
MAX_METADATA_BYTES = 64 * 2**20  # a metadata.yaml larger than this is refused unread
DamageHandler = Callable[[str], None]
Decoder = Literal["rclpy", "rosbags"]


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
    truncated_files: list[Path] = field(default_factory=list)  # no footer or no readable index
    has_metadata: bool = False
    warnings: list[str] = field(default_factory=list)
    damaged_files: list[Path] = field(default_factory=list)  # skipped chunks or unreadable bytes
    skipped_chunks: int = 0


def _load_metadata(path: Path) -> dict[str, Any] | None:
    """metadata.yaml's ``rosbag2_bagfile_information``, or None if absent; BagError if bad
    (not a regular file, not YAML, or a section that is not a list where one is)."""
    meta = path / METADATA_FILE
    if not os.path.lexists(meta):
        return None
    try:
        with open_regular(meta) as stream:
            text = stream.read(MAX_METADATA_BYTES + 1)
        if len(text) > MAX_METADATA_BYTES:
            raise ValueError(f"more than {MAX_METADATA_BYTES} bytes")
        document = yaml_text.safe_load(text.decode("utf-8"))
        info = document["rosbag2_bagfile_information"]
        if not isinstance(info, dict):
            raise TypeError
    except OSError as error:
        raise BagError(f"cannot read {meta}: {error.strerror or error}") from None
    except (yaml.YAMLError, UnicodeDecodeError, KeyError, TypeError, ValueError) as error:
        cause = " ".join(str(error).split())
        raise BagError(f"{meta} is not a rosbag2 metadata file ({cause})") from None
    for key in ("files", "relative_file_paths", "topics_with_message_count"):
        if info.get(key) is not None and not isinstance(info[key], list):
            raise BagError(f"{meta}: {key} is {info[key]!r:.40}, not a list")
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
        names = metadata["relative_file_paths"]
        if not isinstance(names, list):
            raise BagError(f"{path / METADATA_FILE}: relative_file_paths is not a list of files")
        files = [_inside(path, name) for name in names]
        missing = [f.name for f in files if not os.path.lexists(f)]
        if missing:
            raise BagError(f"{path}: metadata.yaml names missing file(s) {', '.join(missing)}")
        seen: set[Path] = set()
        for file in files:
            if file.resolve() in seen:  # every message would be read and counted twice
                raise BagError(f"{path / METADATA_FILE} names {file.name} twice")
            seen.add(file.resolve())
        return files
    files = sorted(path.glob("*.mcap"))
    if not files:
        raise BagError(f"{path} holds no .mcap file")
    return files


def _inside(path: Path, name: Any) -> Path:
    """``path / name`` for a file name of metadata.yaml; BagError unless it is a relative path
    that stays inside the bag directory (symbolic links followed)."""
    if not isinstance(name, str) or not name:
        raise BagError(f"{path / METADATA_FILE}: file name {name!r} is not a path")
    file = path / name
    try:
        inside = file.resolve().is_relative_to(path.resolve())
    except (OSError, RuntimeError, ValueError):  # a loop of links, a NUL in the name
        inside = False
    if Path(name).is_absolute() or not inside:
        raise BagError(
            f"{path / METADATA_FILE} names {name}, outside the bag directory; not opening it"
        )
    return file


def _check_magic(file: Path) -> None:
    try:
        with open_regular(file) as stream:  # a FIFO would block here forever
            head = stream.read(len(MCAP_MAGIC))
    except OSError as error:
        raise BagError(f"cannot read {file}: {error.strerror or error}") from None
    if not head:
        raise BagError(f"{file} is empty")
    if head != MCAP_MAGIC[: len(head)] or len(head) < len(MCAP_MAGIC):
        raise BagError(f"{file} is not an MCAP file")


def _channel_qos(channel: Channel) -> list[QosDict]:
    try:
        return parse_qos_profiles(channel.metadata.get("offered_qos_profiles", ""))
    except (ValueError, TypeError):
        return []


def _scan(file: Path) -> McapScan:
    try:
        return scan_file(file)
    except OSError as error:
        raise BagError(f"cannot read {file}: {error.strerror or error}") from None


def _scan_bag(path: Path) -> tuple[dict[str, Any] | None, list[McapScan], dict[Path, int]]:
    """A bag's metadata.yaml (None without one), a scan of each of its files (all checked to
    be MCAP first) and the message count metadata.yaml lists for each file."""
    metadata = _load_metadata(path) if path.is_dir() else None
    files = _bag_files(path, metadata)
    for file in files:
        _check_magic(file)
    return metadata, [_scan(file) for file in files], _listed_counts(path, metadata)


def _lost(scan: McapScan, lost: dict[int, int] | None) -> str:
    if not lost:
        return "an unknown number of messages"
    return ", ".join(f"{n} message(s) of {scan.topic_of(k)}" for k, n in sorted(lost.items()))


def log_time_text(ns: int) -> str:
    """A log time [ns] as exact seconds, e.g. ``1795354445.656958706 s``."""
    return f"{ns // 10**9}.{ns % 10**9:09d} s"


def cut_summary(scan: McapScan, listed: int | None = None) -> str:
    """What a file cut short still gives: its readable messages (against ``listed``, the count
    metadata.yaml gives for the file, when that is more) and the log time they reach."""
    read = sum(scan.counts().values())
    text = f"{read} message(s)"
    if listed is not None and listed > read:
        text += f" of the {listed} in metadata.yaml"
    span = scan.span()
    if span is not None:
        text += (
            f", up to log time {log_time_text(span[1])} "
            f"({(span[1] - span[0]) * 1e-9:.3f} s after its first)"
        )
    return text


def _listed_counts(path: Path, metadata: dict[str, Any] | None) -> dict[Path, int]:
    """The message count of each file as metadata.yaml's ``files`` section gives it (written
    when the recording ended; an entry that does not read is left out)."""
    counts: dict[Path, int] = {}
    for entry in (metadata or {}).get("files") or []:
        try:
            counts[path / str(entry["path"])] = int(entry["message_count"])
        except (KeyError, TypeError, ValueError, OverflowError):
            continue
    return counts


def file_warnings(scan: McapScan, listed: int | None = None) -> list[str]:
    """One line for each thing wrong with a scanned file: cut short (the messages read and
    the log time they reach; ``listed``: metadata.yaml's count for the file), a skipped
    chunk (its offset, why, the messages lost), bytes that do not read, messages without a
    channel."""
    warnings = []
    if scan.cut_at is not None:
        chunks = sum(1 for c in scan.chunks if c.ok)
        warnings.append(
            f"{scan.path} is cut short (no MCAP footer: its recording was killed or the file "
            f"cut?); read {cut_summary(scan, listed)} in {chunks} complete chunk(s) up to byte "
            f"{scan.cut_at} of {scan.size}; `csam bag recover` rewrites it complete"
        )
    for chunk in scan.skipped:
        warnings.append(
            f"{scan.path}: chunk at offset {chunk.offset} skipped ({chunk.reason}); "
            f"{_lost(scan, chunk.lost)} lost"
        )
    warnings += [f"{scan.path}: {problem}" for problem in scan.problems]
    return warnings


def _scan_topics(scan: McapScan, add: Callable[[str, str, Channel, str, int], None]) -> None:
    counts = scan.counts()
    for channel_id, channel in scan.channels.items():
        schema = scan.schemas.get(channel.schema_id)
        add(
            channel.topic,
            schema.name if schema else "",
            channel,
            channel.metadata.get("topic_type_hash", ""),
            counts.get(channel_id, 0),
        )


def inspect_bag(path: str | os.PathLike[str]) -> BagInfo:
    """Topics, types, recorded QoS, counts and time span of a bag (directory or .mcap file).

    Raises BagError for a missing path, a directory without .mcap files, an empty or
    non-MCAP file, and unsupported storage."""
    path = Path(path)
    metadata, scans, listed = _scan_bag(path)
    warnings = [line for scan in scans for line in file_warnings(scan, listed.get(scan.path))]

    counts: dict[str, int] = {}
    types: dict[str, str] = {}
    qos: dict[str, list[QosDict]] = {}
    hashes: dict[str, str] = {}

    channels: dict[str, Channel] = {}

    def add(topic: str, msgtype: str, channel: Channel, type_hash: str, n: int) -> None:
        counts[topic] = counts.get(topic, 0) + n
        types.setdefault(topic, msgtype)
        channels.setdefault(topic, channel)
        hashes.setdefault(topic, type_hash)

    for scan in scans:
        _scan_topics(scan, add)
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
    for topic, channel in channels.items():  # QoS YAML is slow to parse: only when needed
        if topic not in qos:
            qos[topic] = _channel_qos(channel)
    topics = {
        name: TopicInfo(
            name, types.get(name, ""), qos.get(name, []), counts.get(name, 0), hashes.get(name, "")
        )
        for name in sorted(set(counts) | set(types))
    }
    total = sum(sum(scan.counts().values()) for scan in scans)
    spans = [span for span in (scan.span() for scan in scans) if span is not None]
    start = min((span[0] for span in spans), default=0)
    end = max((span[1] for span in spans), default=0)
    return BagInfo(
        path=path,
        files=[scan.path for scan in scans],
        topics=topics,
        message_count=total,
        start_ns=start,
        end_ns=end,
        truncated_files=[scan.path for scan in scans if not scan.complete],
        has_metadata=metadata is not None,
        warnings=warnings,
        damaged_files=[scan.path for scan in scans if scan.skipped or scan.problems],
        skipped_chunks=sum(len(scan.skipped) for scan in scans),
    )


def _iter_scan(
    scan: McapScan, topics: set[str] | None, on_damage: DamageHandler
) -> Iterator[BagMessage]:
    for item in iter_messages(scan, topics):
        if isinstance(item, str):
            on_damage(item)
            continue
        channel, message = item
        schema = scan.schemas.get(channel.schema_id)
        yield BagMessage(
            channel.topic, schema.name if schema else "", message.log_time, message.data
        )


def read_bag(
    path: str | os.PathLike[str],
    topics: Iterable[str] | None = None,
    *,
    on_damage: DamageHandler | None = None,
) -> Iterator[BagMessage]:
    """Yield every message (topic, msgtype, log_time_ns, raw CDR bytes) of a bag in log-time
    order, optionally only those of ``topics``. Reads killed recordings up to their last
    complete chunk; skips damaged chunks. What was cut or skipped is passed to ``on_damage``
    line by line before the first message (default: a warning of the ``csam_ros.bag``
    logger). Raises BagError for a bag that cannot be read at all."""
    path = Path(path)
    _, scans, listed = _scan_bag(path)
    report = on_damage if on_damage is not None else LOGGER.warning
    for scan in scans:
        for line in file_warnings(scan, listed.get(scan.path)):
            report(line)
    wanted = set(topics) if topics is not None else None
    streams = [_iter_scan(scan, wanted, report) for scan in scans]
    if len(streams) == 1:
        yield from streams[0]
    else:
        yield from heapq.merge(*streams, key=lambda m: m.log_time_ns)


def read_bag_messages(
    path: str | os.PathLike[str],
    topics: Iterable[str] | None = None,
    *,
    on_damage: DamageHandler | None = None,
    decoder: Decoder = "rclpy",
) -> Iterator[DecodedMessage]:
    """Like :func:`read_bag`, with each message deserialized into its rclpy message class
    (needs the message packages installed; rclpy is imported on first use), or with
    ``decoder="rosbags"`` into rosbags' message classes of the same installed definitions:
    the same fields and values, decoded in less than half the time and without rclpy (the
    conversions of :mod:`csam_ros.ros.conversions` read either).

    A topic recorded with another definition of its type than the installed one (its type
    hash differs) raises BagError when its first message is reached: its bytes would not
    decode, or decode wrongly. :func:`read_bag` still yields them raw, and readers that take
    the definition stored in the bag (rosbags, mcap) decode them."""
    recorded = {name: topic.type_hash for name, topic in inspect_bag(path).topics.items()}
    installed = MessageTypes()
    checked: set[str] = set()
    decode = installed.typestore.deserialize_cdr if decoder == "rosbags" else _rclpy_decoder()
    for message in read_bag(path, topics, on_damage=on_damage):
        if message.topic not in checked:
            expected = installed.definition(message.msgtype).type_hash
            if recorded.get(message.topic) not in ("", None, expected):
                raise BagError(
                    f"{message.topic}: recorded with another definition of {message.msgtype} "
                    f"({recorded[message.topic]}) than the installed one ({expected}); "
                    "it cannot be decoded here"
                )
            checked.add(message.topic)
        yield DecodedMessage(
            message.topic,
            message.msgtype,
            message.log_time_ns,
            decode(message.data, message.msgtype),
        )


def _rclpy_decoder() -> Callable[[bytes, str], Any]:
    from rclpy.serialization import deserialize_message

    classes: dict[str, type] = {}

    def decode(data: bytes, msgtype: str) -> Any:
        cls = classes.get(msgtype)
        if cls is None:
            cls = classes[msgtype] = message_class(msgtype)
        return deserialize_message(data, cls)

    return decode
