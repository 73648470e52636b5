"""Signed merger inputs: with a team key, a smoother signs its local map updates and
rendezvous poses, and the merger takes only those it can verify.

The signature of a message is HMAC-SHA256 under the team key over its type's name and the
message serialized (:func:`canonical_bytes`: every field in order, little-endian at its
declared width, lengths before sequences and strings; CDR's alignment padding is not
deterministic, so a message deserialized does not serialize to the bytes it came as). The
message names its robot, which the merger checks against the topic's. The message types
have no field for it: it travels, as hex, on a sibling topic (:data:`SIGNATURE_TOPICS`:
``/<robot>/local_map_updates_hmac``, ``/<robot>/rendezvous_poses_hmac``), published just
before the message. It keeps out messages of peers without the key (another
team on a shared network, a stray test publisher), not a key holder; the full answer is SROS2
(DDS Security), where Fast DDS is built with it (its PyPI wheels are not).
"""

from __future__ import annotations

import hashlib
import hmac
import re
import struct
from pathlib import Path
from typing import Any

import numpy as np
from rclpy.node import Node
from std_msgs.msg import String

from csam_ros.ros.topics import LATCHED, LOCAL_MAP_UPDATES, RELIABLE, RENDEZVOUS_POSES, Topic

MIN_KEY_BYTES = 16
# each signed topic's sibling: the signatures of its messages (a latched one's latched, so that
# a receiver that comes late gets the signature of the message it gets)
SIGNATURE_TOPICS: dict[str, Topic] = {
    LOCAL_MAP_UPDATES.name: Topic(f"{LOCAL_MAP_UPDATES.name}_hmac", String, RELIABLE),
    RENDEZVOUS_POSES.name: Topic(f"{RENDEZVOUS_POSES.name}_hmac", String, LATCHED),
}


class TeamKeyError(ValueError):
    """A team key file that cannot be used (named, with why)."""


def read_team_key(path: str | Path) -> bytes:
    """The team key in the file at ``path`` (its bytes, a trailing newline left out), at least
    :data:`MIN_KEY_BYTES` long; :class:`TeamKeyError` naming the file otherwise."""
    try:
        key = Path(path).read_bytes().rstrip(b"\r\n")
    except OSError as error:
        raise TeamKeyError(f"team_key_file {path}: {error.strerror or error}") from None
    if len(key) < MIN_KEY_BYTES:
        raise TeamKeyError(
            f"team_key_file {path}: {len(key)} bytes, at least {MIN_KEY_BYTES} are needed"
        )
    return key


def signature(key: bytes, msg: Any) -> str:
    """The signature (hex) of ``msg``."""
    kind = f"{type(msg).__module__.split('.')[0]}/msg/{type(msg).__name__}"  # as the graph
    digest = hmac.new(key, kind.encode() + b"\0", hashlib.sha256)
    digest.update(canonical_bytes(msg))
    return digest.hexdigest()


# numbers by their ROS type: numpy's little-endian type
_NUMBERS = {
    "boolean": "<u1",
    "octet": "<u1",
    "char": "<u1",
    "byte": "<u1",
    "float": "<f4",
    "double": "<f8",
    "int8": "<i1",
    "uint8": "<u1",
    "int16": "<i2",
    "uint16": "<u2",
    "int32": "<i4",
    "uint32": "<u4",
    "int64": "<i8",
    "uint64": "<u8",
}
_SEQUENCE = re.compile(r"sequence<([^,>]+)(?:, \d+)?>|([^\[]+)\[(\d*)\]")


def canonical_bytes(msg: Any) -> bytes:
    """``msg``'s fields in declaration order as bytes that depend only on their values."""
    out: list[bytes] = []
    _encode(msg, "", out)
    return b"".join(out)


def _encode(value: Any, ros_type: str, out: list[bytes]) -> None:
    fields = getattr(type(value), "get_fields_and_field_types", None)
    if fields is not None:  # a message
        for name, field_type in fields().items():
            _encode(getattr(value, name), field_type, out)
        return
    sequence = _SEQUENCE.fullmatch(ros_type)
    if sequence is not None:
        element = (sequence.group(1) or sequence.group(2)).strip()
        out.append(struct.pack("<Q", len(value)))
        if element in _NUMBERS:
            out.append(np.asarray(value).astype(_NUMBERS[element]).tobytes())
        else:
            for item in value:
                _encode(item, element, out)
    elif ros_type in _NUMBERS:
        if isinstance(value, bytes):
            value = value[0]
        elif isinstance(value, str):
            value = ord(value)
        out.append(np.asarray(value).astype(_NUMBERS[ros_type]).tobytes())
    else:  # string, wstring, string<=N
        text = str(value).encode()
        out.append(struct.pack("<Q", len(text)) + text)


class SignedPublisher:
    """A publisher of a signed topic whose every message goes out after its signature; any
    other attribute is the publisher's (``wait_for_all_acked``, ...)."""

    def __init__(self, node: Node, publisher: Any, key: bytes) -> None:
        self.publisher = publisher
        self.key = key
        topic = SIGNATURE_TOPICS[publisher.topic_name.rsplit("/", 1)[-1]]
        self.signatures = node.create_publisher(String, f"{publisher.topic_name}_hmac", topic.qos)

    def publish(self, msg: Any) -> None:
        self.signatures.publish(String(data=signature(self.key, msg)))
        self.publisher.publish(msg)

    def __getattr__(self, name: str) -> Any:
        return getattr(self.publisher, name)
