"""Message type registry: full ``ros2msg`` definitions and type hashes for bag schemas.

Built on rosbags' ROS 2 Jazzy typestore, extended with the project's ``csam_msgs`` and with any
type whose ``.msg`` file is installed in an ament prefix (``<prefix>/share/<pkg>/msg``). The
definition text is the one rosbag2 stores in MCAP schemas: the type's own fields followed by
every dependency, each after a line of 80 ``=`` and ``MSG: pkg/Type``. Needs no rclpy.
"""

from __future__ import annotations

import importlib
import os
import re
import sys
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rosbags.interfaces import Nodetype
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore

CUSTOM_PACKAGE = "csam_msgs"
_MSGTYPE = re.compile(r"^([A-Za-z][A-Za-z0-9_]*)/(?:msg/)?([A-Za-z][A-Za-z0-9_]*)$")


class UnknownMessageTypeError(LookupError):
    """A message type whose definition cannot be found."""


@dataclass(frozen=True)
class MessageDefinition:
    """A type's full ``ros2msg`` definition text and its RIHS01 type description hash."""

    msgtype: str
    text: str
    type_hash: str


def normalize_msgtype(msgtype: str) -> str:
    """'pkg/Type' or 'pkg/msg/Type' -> 'pkg/msg/Type'; ValueError for anything else."""
    match = _MSGTYPE.match(msgtype)
    if match is None:
        raise ValueError(f"message type {msgtype!r} is not of the form 'package/msg/Type'")
    return f"{match.group(1)}/msg/{match.group(2)}"


def ament_prefixes() -> list[Path]:
    """Install prefixes to search: AMENT_PREFIX_PATH, then this interpreter's prefix."""
    prefixes = [Path(p) for p in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p]
    prefixes.append(Path(sys.prefix))
    return list(dict.fromkeys(prefixes))


def find_msg_file(msgtype: str) -> Path | None:
    """The installed ``.msg`` file of ``pkg/msg/Type``, or of csam_msgs in this source tree."""
    package, _, name = normalize_msgtype(msgtype).split("/")
    for prefix in ament_prefixes():
        candidate = prefix / "share" / package / "msg" / f"{name}.msg"
        if candidate.is_file():
            return candidate
    if package == CUSTOM_PACKAGE:
        candidate = Path(__file__).resolve().parents[2] / "msg_defs" / "msg" / f"{name}.msg"
        if candidate.is_file():
            return candidate
    return None


def _referenced_types(fields: list[tuple[str, Any]]) -> Iterator[str]:
    for _, (kind, detail) in fields:
        if kind in (Nodetype.ARRAY, Nodetype.SEQUENCE):
            kind, detail = detail[0]
        if kind == Nodetype.NAME:
            yield detail


class MessageTypes:
    """Definitions of the standard ROS 2 Jazzy types, csam_msgs and installed packages."""

    def __init__(self, extra_msg_files: Iterable[Path] = ()) -> None:
        self.typestore: Typestore = get_typestore(Stores.ROS2_JAZZY)
        self._cache: dict[str, MessageDefinition] = {}
        for path in extra_msg_files:
            self._register_file(
                Path(path), f"{Path(path).parent.parent.name}/msg/{Path(path).stem}"
            )

    def _register_file(self, path: Path, msgtype: str) -> None:
        self.typestore.register(get_types_from_msg(path.read_text(), msgtype))

    def _ensure(self, msgtype: str) -> None:
        """Register ``msgtype`` and everything it references, loading .msg files as needed."""
        pending = [msgtype]
        seen: set[str] = set()
        while pending:
            name = pending.pop()
            if name in seen:
                continue
            seen.add(name)
            if name not in self.typestore.fielddefs:
                path = find_msg_file(name)
                if path is None:
                    raise UnknownMessageTypeError(
                        f"message type {name!r} is neither a standard ROS 2 Jazzy type nor "
                        f"installed (no share/{name.split('/')[0]}/msg/{name.split('/')[2]}.msg "
                        "in AMENT_PREFIX_PATH)"
                    )
                self._register_file(path, name)
            pending.extend(_referenced_types(self.typestore.fielddefs[name][1]))

    def definition(self, msgtype: str) -> MessageDefinition:
        """Full ``ros2msg`` schema text and RIHS01 hash of ``msgtype``."""
        msgtype = normalize_msgtype(msgtype)
        cached = self._cache.get(msgtype)
        if cached is None:
            self._ensure(msgtype)
            text, _ = self.typestore.generate_msgdef(msgtype, ros_version=2)
            cached = MessageDefinition(msgtype, text, self.typestore.hash_rihs01(msgtype))
            self._cache[msgtype] = cached
        return cached

    def custom_types(self) -> list[str]:
        """Every csam_msgs type (from the installed share folder or msg_defs/msg)."""
        names = set()
        for prefix in ament_prefixes():
            names.update(p.stem for p in (prefix / "share" / CUSTOM_PACKAGE / "msg").glob("*.msg"))
        if not names:
            source = Path(__file__).resolve().parents[2] / "msg_defs" / "msg"
            names.update(p.stem for p in source.glob("*.msg"))
        return [f"{CUSTOM_PACKAGE}/msg/{name}" for name in sorted(names)]

    def register_custom_types(self) -> Typestore:
        """Register all csam_msgs types (e.g. for rosbags' readers) and return the typestore."""
        for msgtype in self.custom_types():
            self._ensure(msgtype)
        return self.typestore


def message_class(msgtype: str) -> type:
    """The rclpy (rosidl generated Python) class of ``pkg/msg/Type``."""
    package, _, name = normalize_msgtype(msgtype).split("/")
    try:
        module = importlib.import_module(f"{package}.msg")
        return getattr(module, name)
    except (ImportError, AttributeError):
        raise UnknownMessageTypeError(
            f"message type {msgtype!r} has no installed Python message class ({package}.msg.{name})"
        ) from None


def msgtype_of(message: object) -> str:
    """'pkg/msg/Type' of a rosidl generated message object."""
    cls = type(message)
    package = cls.__module__.split(".")[0]
    return f"{package}/msg/{cls.__name__}"
