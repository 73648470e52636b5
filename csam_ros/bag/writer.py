"""Writing rosbag2 directories with MCAP storage, without rosbag2.

A bag is a new directory holding ``metadata.yaml`` (rosbag2 metadata version 9, as ROS 2
Jazzy writes it) and ``<name>_0.mcap`` (profile ``ros2``, message encoding ``cdr``, schema
encoding ``ros2msg`` with the full definition text, channel metadata
``offered_qos_profiles`` and ``topic_type_hash``, zstd-compressed chunks).

Made to survive being killed: chunks are closed and written at least every
``flush_period_s`` seconds of writing (and whenever ``chunk_size`` bytes are pending), and
``metadata.yaml`` is rewritten atomically after every flush, so a bag cut off by SIGKILL
reads up to its last flushed chunk and its metadata.yaml counts exactly those messages.
"""

from __future__ import annotations

import operator
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml
from mcap.writer import CompressionType
from mcap.writer import Writer as McapWriter

from csam_ros import __version__
from csam_ros.bag.qos import QosDict, dump_qos_profiles, qos_list
from csam_ros.bag.types import MessageDefinition, MessageTypes, msgtype_of, normalize_msgtype
from csam_ros.closing import Closing

METADATA_FILE = "metadata.yaml"
METADATA_VERSION = 9
ROS_DISTRO = "jazzy"
DEFAULT_CHUNK_SIZE = 786_432  # bytes, rosbag2's MCAP default
DEFAULT_FLUSH_PERIOD_S = 1.0
_NEVER = 2**62  # hand to mcap as chunk size: this class decides when a chunk ends


class BagError(Exception):
    """A bag that cannot be written or read; the message names the path and the cause."""


@dataclass
class _Topic:
    name: str
    msgtype: str
    channel_id: int
    offered_qos_profiles: list[QosDict]
    type_hash: str
    message_count: int = 0
    flushed_count: int = field(default=0)


# libyaml's emitter where PyYAML has it: the same text, a quarter of the time (metadata.yaml is
# written again at every flush, once a second while recording)
_SafeDumper = getattr(yaml, "CSafeDumper", yaml.SafeDumper)


class _PlainDumper(_SafeDumper):  # type: ignore[misc, valid-type]
    """YAML without anchors and aliases, as rosbag2 writes it."""

    def ignore_aliases(self, data: Any) -> bool:
        return True


def _dump_yaml(document: Any) -> str:
    return yaml.dump(document, Dumper=_PlainDumper, sort_keys=False)


def _write_text_atomically(path: Path, text: str) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text, encoding="utf-8")
    os.replace(tmp, path)


class BagWriter(Closing):
    """Writes a new rosbag2 bag directory; never overwrites an existing path.

    Usable without any ROS node: ``add_topic`` then ``write`` serialized CDR bytes (or rclpy
    message objects, serialized with rclpy), ``close`` at the end (or use ``with``)::

        with BagWriter("bags/run1") as bag:
            bag.add_topic("/robot1/odom", "nav_msgs/msg/Odometry", qos_profile)
            bag.write("/robot1/odom", stamp_ns, odometry_message)
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        *,
        chunk_size: int = DEFAULT_CHUNK_SIZE,
        flush_period_s: float = DEFAULT_FLUSH_PERIOD_S,
        compression: bool = True,
        types: MessageTypes | None = None,
    ) -> None:
        self.path = Path(path)
        if chunk_size <= 0:
            raise ValueError(f"chunk_size must be positive, got {chunk_size}")
        if flush_period_s <= 0:
            raise ValueError(f"flush_period_s must be positive, got {flush_period_s}")
        if os.path.lexists(self.path):
            raise BagError(f"{self.path} already exists; not overwriting it")
        try:
            self.path.mkdir(parents=True)
            self._file = (self.path / f"{self.path.name}_0.mcap").open("xb")
        except OSError as error:
            raise BagError(f"cannot create bag {self.path}: {error.strerror or error}") from None
        self.mcap_path = Path(self._file.name)
        self.chunk_size = chunk_size
        self.flush_period_s = flush_period_s
        self.types = types or MessageTypes()
        self._mcap = McapWriter(
            self._file,
            chunk_size=_NEVER,
            compression=CompressionType.ZSTD if compression else CompressionType.NONE,
        )
        self._mcap.start(profile="ros2", library=f"csam_ros-{__version__} (mcap-python)")
        self._topics: dict[str, _Topic] = {}
        self._schemas: dict[tuple[str, str], int] = {}  # (type, definition text) -> schema id
        self._pending_bytes = 0
        self._pending_messages = 0
        self._last_flush = time.monotonic()
        self._start_ns: int | None = None
        self._end_ns = 0
        self._flushed_span: tuple[int, int] | None = None
        self.closed = False
        self._write_metadata(final=False)

    # -- topics and messages --------------------------------------------------------------

    @property
    def topics(self) -> dict[str, str]:
        """Topic name -> message type of every added topic."""
        return {name: topic.msgtype for name, topic in self._topics.items()}

    @property
    def message_count(self) -> int:
        """Messages written so far (flushed to disk or not)."""
        return sum(topic.message_count for topic in self._topics.values())

    def add_topic(
        self,
        topic: str,
        msgtype: str,
        qos: Any = None,
        *,
        definition: MessageDefinition | None = None,
    ) -> None:
        """Register ``topic`` with its type and offered QoS: an rclpy QoSProfile, a rosbag2
        QoS dict, a sequence of these (one per publisher), or None (none known).
        ``definition`` (default: the installed one) is the type's definition text and hash to
        store, e.g. the one recorded in another bag whose messages are copied."""
        self._check_open()
        if not topic.startswith("/"):
            raise ValueError(f"topic {topic!r} must be an absolute name starting with '/'")
        if topic in self._topics:
            raise BagError(f"topic {topic} is already in bag {self.path}")
        msgtype = normalize_msgtype(msgtype)
        if definition is None:
            definition = self.types.definition(msgtype)
        profiles = qos_list(qos)
        schema_id = self._schemas.get((msgtype, definition.text))
        if schema_id is None:
            schema_id = self._mcap.register_schema(
                name=msgtype, encoding="ros2msg", data=definition.text.encode()
            )
            self._schemas[msgtype, definition.text] = schema_id
        channel_id = self._mcap.register_channel(
            topic=topic,
            message_encoding="cdr",
            schema_id=schema_id,
            metadata={
                "offered_qos_profiles": dump_qos_profiles(profiles),
                "topic_type_hash": definition.type_hash,
            },
        )
        # (listed in metadata.yaml from the next flush, with the first of its messages on disk:
        # rewriting it per topic cost a 64-robot team's 260 topics two minutes)
        self._topics[topic] = _Topic(topic, msgtype, channel_id, profiles, definition.type_hash)

    def write(self, topic: str, stamp_ns: int, message: Any) -> None:
        """Append one message at log time ``stamp_ns`` (integer nanoseconds): serialized CDR
        bytes, or an rclpy message object of the topic's type."""
        self._check_open()
        entry = self._topics.get(topic)
        if entry is None:
            raise BagError(f"topic {topic} was not added to bag {self.path} (add_topic first)")
        try:
            stamp_ns = operator.index(stamp_ns)
        except TypeError:
            raise TypeError(
                f"stamp_ns must be an integer (nanoseconds), got {type(stamp_ns).__name__}"
            ) from None
        if not 0 <= stamp_ns < 2**63:
            raise ValueError(f"stamp_ns {stamp_ns} for topic {topic} is outside 0..2^63-1")
        if isinstance(message, bytes | bytearray | memoryview):
            data = bytes(message)
        else:
            actual = msgtype_of(message)
            if actual != entry.msgtype:
                raise TypeError(f"topic {topic} holds {entry.msgtype}, got a {actual} message")
            from rclpy.serialization import serialize_message

            data = serialize_message(message)
        self._mcap.add_message(
            channel_id=entry.channel_id, log_time=stamp_ns, data=data, publish_time=stamp_ns
        )
        entry.message_count += 1
        self._start_ns = stamp_ns if self._start_ns is None else min(self._start_ns, stamp_ns)
        self._end_ns = max(self._end_ns, stamp_ns)
        self._pending_bytes += len(data)
        self._pending_messages += 1
        if (
            self._pending_bytes >= self.chunk_size
            or time.monotonic() - self._last_flush >= self.flush_period_s
        ):
            self.flush()

    def flush(self) -> None:
        """Close the current chunk, write it to the file and refresh metadata.yaml (nothing to
        do when no message was written since the last flush)."""
        self._check_open()
        if self._pending_messages == 0:
            self._last_flush = time.monotonic()
            return
        self._mcap.flush()
        self._file.flush()
        self._pending_bytes = 0
        self._pending_messages = 0
        self._last_flush = time.monotonic()
        for topic in self._topics.values():
            topic.flushed_count = topic.message_count
        if self._start_ns is not None:
            self._flushed_span = (self._start_ns, self._end_ns)
        self._write_metadata(final=False)

    def close(self) -> None:
        """Finish the MCAP file (summary, footer) and write the final metadata.yaml."""
        if self.closed:
            return
        info = self._bag_information(final=True)
        self._mcap.add_metadata(
            "rosbag2",
            {
                "serialized_metadata": _dump_yaml(info),
                "ROS_DISTRO": ROS_DISTRO,
            },
        )
        self._mcap.finish()
        self._file.close()
        self.closed = True
        self._write_metadata(final=True)

    # -- metadata.yaml --------------------------------------------------------------------

    def _check_open(self) -> None:
        if self.closed:
            raise BagError(f"bag {self.path} is closed")

    def _bag_information(self, final: bool) -> dict[str, Any]:
        """The ``rosbag2_bagfile_information`` mapping; before close it describes what is on
        disk (flushed chunks) only."""
        if final:
            counts = {name: t.message_count for name, t in self._topics.items()}
            span = (self._start_ns, self._end_ns) if self._start_ns is not None else None
        else:
            counts = {name: t.flushed_count for name, t in self._topics.items()}
            span = self._flushed_span
        start, end = span if span is not None else (0, 0)
        starting_time = {"nanoseconds_since_epoch": start}
        duration = {"nanoseconds": end - start}
        total = sum(counts.values())
        return {
            "version": METADATA_VERSION,
            "storage_identifier": "mcap",
            "duration": duration,
            "starting_time": starting_time,
            "message_count": total,
            "topics_with_message_count": [
                {
                    "topic_metadata": {
                        "name": t.name,
                        "type": t.msgtype,
                        "serialization_format": "cdr",
                        "offered_qos_profiles": t.offered_qos_profiles,
                        "type_description_hash": t.type_hash,
                    },
                    "message_count": counts[name],
                }
                for name, t in self._topics.items()
            ],
            "compression_format": "",
            "compression_mode": "",
            "relative_file_paths": [self.mcap_path.name],
            "files": [
                {
                    "path": self.mcap_path.name,
                    "starting_time": starting_time,
                    "duration": duration,
                    "message_count": total,
                }
            ],
            "custom_data": None,
            "ros_distro": ROS_DISTRO,
        }

    def _write_metadata(self, final: bool) -> None:
        document = {"rosbag2_bagfile_information": self._bag_information(final)}
        _write_text_atomically(self.path / METADATA_FILE, _dump_yaml(document))
