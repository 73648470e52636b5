"""Rewriting a cut or partly damaged bag into a complete one (``csam bag recover``).

A recording killed by SIGKILL leaves an MCAP file without summary and footer, which rosbags'
Reader refuses ("File end magic is invalid"); a damaged chunk makes readers fail or, without
a CRC check, return corrupted messages. :func:`recover_bag` reads every message that still
verifies (see ``mcapfile``) and writes them into a new bag directory with summary, footer and
a metadata.yaml that counts them, keeping each topic's recorded definition (schema text and
type hash) and QoS. The source is never changed.
"""

from __future__ import annotations

import heapq
import os
import shutil
from dataclasses import dataclass, field
from pathlib import Path

from csam_ros.bag.mcapfile import McapScan
from csam_ros.bag.reader import (
    _iter_scan,
    _scan_bag,
    cut_summary,
    file_warnings,
    inspect_bag,
)
from csam_ros.bag.types import MessageDefinition, normalize_msgtype
from csam_ros.bag.writer import BagError, BagWriter


@dataclass
class RecoveryReport:
    """What :func:`recover_bag` wrote and what it could not."""

    source: Path
    out: Path
    messages: dict[str, int]  # per topic, as written to ``out``
    cut_files: list[Path] = field(default_factory=list)  # files that had no footer / index
    cut_reads: list[str] = field(default_factory=list)  # per cut file: messages and log time read
    skipped_chunks: list[str] = field(default_factory=list)  # one line per damaged chunk
    warnings: list[str] = field(default_factory=list)  # everything else found wrong
    dropped_topics: dict[str, str] = field(default_factory=dict)  # topic -> why not copied

    @property
    def message_count(self) -> int:
        return sum(self.messages.values())

    def lines(self) -> list[str]:
        """The report as printed by ``csam bag recover``."""
        lines = [f"recovered {self.message_count} message(s) of {self.source} into {self.out}/"]
        lines += [f"  {topic}: {n}" for topic, n in sorted(self.messages.items())]
        reads = self.cut_reads or [""] * len(self.cut_files)
        lines += [
            f"  {file}: cut short, read up to its last chunk" + (f": {read}" if read else "")
            for file, read in zip(self.cut_files, reads, strict=True)
        ]
        lines += [f"  {line}" for line in self.skipped_chunks + self.warnings]
        lines += [f"  {topic} not copied: {why}" for topic, why in self.dropped_topics.items()]
        return lines


def default_output(source: Path) -> Path:
    """``<bag>-recovered`` beside the bag (``<name>-recovered`` for an .mcap file)."""
    name = source.stem if source.is_file() else source.name
    return source.parent / f"{name}-recovered"


def _definitions(
    scans: list[McapScan], recorded_hashes: dict[str, str]
) -> tuple[dict[str, MessageDefinition], dict[str, str]]:
    """Each topic's recorded definition, and the topics whose definition did not survive."""
    definitions: dict[str, MessageDefinition] = {}
    dropped: dict[str, str] = {}
    for scan in scans:
        for channel in scan.channels.values():
            if channel.topic in definitions:
                continue
            schema = scan.schemas.get(channel.schema_id)
            why = ""
            if schema is None:
                why = "its schema was lost"
            elif channel.message_encoding != "cdr" or schema.encoding != "ros2msg":
                why = f"not a ROS 2 topic ({channel.message_encoding}, {schema.encoding})"
            else:
                try:
                    msgtype = normalize_msgtype(schema.name)
                    text = schema.data.decode("utf-8")
                except (ValueError, UnicodeDecodeError) as error:
                    why = f"its schema does not read ({error})"
                else:
                    type_hash = channel.metadata.get("topic_type_hash") or recorded_hashes.get(
                        channel.topic, ""
                    )
                    definitions[channel.topic] = MessageDefinition(msgtype, text, type_hash)
                    dropped.pop(channel.topic, None)
            if why:
                dropped.setdefault(channel.topic, why)
    return definitions, dropped


def recover_bag(
    source: str | os.PathLike[str], out: str | os.PathLike[str] | None = None
) -> RecoveryReport:
    """Write every readable message of bag ``source`` into the new bag ``out`` (default
    ``<source>-recovered``), complete, in log-time order. BagError if ``source`` cannot be
    read at all or ``out`` exists."""
    source = Path(source)
    info = inspect_bag(source)  # BagError for what cannot be read at all
    out = Path(out) if out is not None else default_output(source)
    if os.path.lexists(out):
        raise BagError(f"{out} already exists; not overwriting it")
    _, scans, listed = _scan_bag(source)
    hashes = {name: topic.type_hash for name, topic in info.topics.items()}
    definitions, dropped = _definitions(scans, hashes)
    if not definitions:
        raise BagError(f"{source}: no topic with a readable definition; nothing to recover")

    report = RecoveryReport(source=source, out=out, messages={}, dropped_topics=dropped)
    for scan in scans:
        if scan.cut_at is not None:
            report.cut_files.append(scan.path)
            report.cut_reads.append(cut_summary(scan, listed.get(scan.path)))
        elif not scan.complete:
            report.warnings.append(f"{scan.path}: its index was unreadable")
        report.skipped_chunks += [w for w in file_warnings(scan) if ": chunk at offset" in w]
        report.warnings += [f"{scan.path}: {problem}" for problem in scan.problems]

    changed: list[str] = []
    try:
        with BagWriter(out, flush_period_s=3600.0) as writer:
            for topic, definition in definitions.items():
                recorded = info.topics.get(topic)
                qos = recorded.offered_qos_profiles if recorded is not None else None
                try:
                    writer.add_topic(topic, definition.msgtype, qos, definition=definition)
                except (ValueError, LookupError) as error:
                    report.dropped_topics[topic] = f"cannot be written ({error})"
            streams = [_iter_scan(scan, set(writer.topics), changed.append) for scan in scans]
            for message in heapq.merge(*streams, key=lambda m: m.log_time_ns):
                writer.write(message.topic, message.log_time_ns, message.data)
                report.messages[message.topic] = report.messages.get(message.topic, 0) + 1
            for topic in writer.topics:
                report.messages.setdefault(topic, 0)
    except OSError as error:
        shutil.rmtree(out, ignore_errors=True)
        raise BagError(f"cannot write {out}: {error.strerror or error}") from None
    except BaseException:
        shutil.rmtree(out, ignore_errors=True)
        raise
    report.warnings += changed
    return report
