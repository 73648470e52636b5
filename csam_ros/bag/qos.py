"""QoS profiles as rosbag2 stores them (metadata version 9: a list of plain dicts per topic).

``qos_to_dict`` reads rclpy QoSProfile objects by attribute (no rclpy import); the functions
that build rclpy profiles import rclpy when called. The adaptation rules follow rosbag2: a
recorder subscribes reliable / transient local only if every publisher offers it, a player
publishes with the recorded policies when all recorded publishers agree.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from typing import Any

import yaml

from csam_ros.core.model import yaml_text

QosDict = dict[str, Any]

INFINITE_NS = 2**63 - 1  # RMW_DURATION_INFINITE, written as sec 9223372036 nsec 854775807
_POLICY_KEYS = ("history", "reliability", "durability", "liveliness")
_DURATION_KEYS = ("deadline", "lifespan", "liveliness_lease_duration")
_KEYS = {"depth", "avoid_ros_namespace_conventions", *_POLICY_KEYS, *_DURATION_KEYS}
# rmw enum numbers, as rosbag2 metadata version 8 wrote them
_POLICY_NAMES = {
    "history": ("system_default", "keep_last", "keep_all", "unknown"),
    "reliability": ("system_default", "reliable", "best_effort", "unknown", "best_available"),
    "durability": ("system_default", "transient_local", "volatile", "unknown", "best_available"),
    "liveliness": (
        "system_default",
        "automatic",
        "manual_by_node",
        "manual_by_topic",
        "unknown",
        "best_available",
    ),
}
RECORDER_DEPTH = 1000  # a subscription's queue: deep, so a busy recorder does not lose messages
PLAYER_DEPTH = 1000  # a volatile publisher's queue on replay (reliable at --rate 0 needs room)


def _duration_dict(nanoseconds: int) -> dict[str, int]:
    return {"sec": nanoseconds // 1_000_000_000, "nsec": nanoseconds % 1_000_000_000}


def qos_to_dict(profile: Any) -> QosDict:
    """An rclpy QoSProfile (or a rosbag2 QoS dict, checked) as a rosbag2 metadata dict."""
    if isinstance(profile, Mapping):
        missing = _KEYS - set(profile)
        if missing:
            raise ValueError(f"QoS dict lacks {sorted(missing)}: {dict(profile)}")
        result = {key: profile[key] for key in profile}
        for key, names in _POLICY_NAMES.items():
            value = result[key]
            if isinstance(value, int) and 0 <= value < len(names):
                result[key] = names[value]
            elif not isinstance(value, str):
                raise ValueError(f"QoS {key} must be a policy name, got {value!r}")
        return result
    try:
        result: QosDict = {
            "history": profile.history.name.lower(),
            "depth": int(profile.depth),
            "reliability": profile.reliability.name.lower(),
            "durability": profile.durability.name.lower(),
            "deadline": _duration_dict(profile.deadline.nanoseconds),
            "lifespan": _duration_dict(profile.lifespan.nanoseconds),
            "liveliness": profile.liveliness.name.lower(),
            "liveliness_lease_duration": _duration_dict(
                profile.liveliness_lease_duration.nanoseconds
            ),
            "avoid_ros_namespace_conventions": bool(profile.avoid_ros_namespace_conventions),
        }
    except AttributeError:
        raise TypeError(
            f"expected an rclpy QoSProfile or a rosbag2 QoS dict, got {type(profile).__name__}"
        ) from None
    for key in _DURATION_KEYS:  # rclpy reports "default" (0) where the middleware means infinite
        if result[key] == {"sec": 0, "nsec": 0}:
            result[key] = _duration_dict(INFINITE_NS)
    return result


def qos_list(qos: Any) -> list[QosDict]:
    """None, one profile, or a sequence of profiles -> list of rosbag2 QoS dicts."""
    if qos is None:
        return []
    if isinstance(qos, Mapping) or not isinstance(qos, Sequence):
        return [qos_to_dict(qos)]
    return [qos_to_dict(item) for item in qos]


def parse_qos_profiles(value: Any) -> list[QosDict]:
    """offered_qos_profiles as found in metadata.yaml (v9 list or v8 YAML string) or MCAP
    channel metadata (YAML string); invalid entries raise ValueError."""
    if value is None or value == "":
        return []
    if isinstance(value, str):
        try:
            value = yaml_text.safe_load(value)
        except yaml.YAMLError as error:
            raise ValueError(f"offered_qos_profiles is not valid YAML: {error}") from None
        if value is None:
            return []
    if not isinstance(value, list):
        raise ValueError(f"offered_qos_profiles must be a list, got {type(value).__name__}")
    return [qos_to_dict(item) for item in value]


def dump_qos_profiles(profiles: Iterable[QosDict]) -> str:
    """The YAML string rosbag2 puts in MCAP channel metadata 'offered_qos_profiles'."""
    profiles = list(profiles)
    return yaml.safe_dump(profiles, sort_keys=False).strip() if profiles else ""


def _common(profiles: Sequence[QosDict], key: str, value: str) -> bool:
    return bool(profiles) and all(str(p[key]).lower() == value for p in profiles)


def subscription_qos(offered: Sequence[Any]) -> Any:
    """rclpy QoSProfile a recorder subscribes with: compatible with every offered profile,
    keeping reliable and transient local when all publishers offer them."""
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

    dicts = qos_list(list(offered))
    reliable = not dicts or _common(dicts, "reliability", "reliable")
    transient = _common(dicts, "durability", "transient_local")
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=RECORDER_DEPTH,
        reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if transient else DurabilityPolicy.VOLATILE,
    )


def publisher_qos(recorded: Sequence[QosDict]) -> Any:
    """rclpy QoSProfile a player republishes a topic with: the recorded reliability and
    durability when every recorded publisher agrees (reliable, volatile when none recorded).
    Transient local keeps the recorded depth (late joiners get that many samples; 1 when the
    middleware reported none); volatile topics get a deep queue for fast replay."""
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

    best_effort = _common(recorded, "reliability", "best_effort")
    transient = _common(recorded, "durability", "transient_local")
    depth = max([int(p["depth"]) for p in recorded] + [1]) if transient else PLAYER_DEPTH
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=depth,
        reliability=ReliabilityPolicy.BEST_EFFORT if best_effort else ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if transient else DurabilityPolicy.VOLATILE,
    )
