"""What a run's topics carried: bytes per robot, per topic and per tenth of the run, from a bag.

The bytes are the serialized (CDR) messages as recorded, without the DDS and UDP/IP headers
around them. What a robot sends to the base station is its ``local_map_updates`` and
``rendezvous_poses`` (the merger's inputs, :data:`~csam_ros.ros.topics.MERGER_INPUTS`); every
subscriber at the base (merger, recorder) receives its own copy.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from csam_ros.bag import read_bag
from csam_ros.ros.topics import MERGER_INPUTS, parse

PARTS = 10  # the run is cut into tenths


@dataclass
class TopicTraffic:
    """One recorded topic: its robot (None for a global topic), messages and bytes, in all
    and per part of the run."""

    topic: str
    robot: str | None
    messages: int = 0
    bytes: int = 0
    largest: int = 0
    bytes_by_part: list[int] = field(default_factory=lambda: [0] * PARTS)


@dataclass
class Bandwidth:
    """The traffic of every topic of a bag over ``[start_ns, end_ns]``."""

    start_ns: int
    end_ns: int
    topics: dict[str, TopicTraffic]

    @property
    def seconds(self) -> float:
        return max(self.end_ns - self.start_ns, 1) * 1e-9

    def robots(self) -> list[str]:
        return sorted({t.robot for t in self.topics.values() if t.robot is not None})

    def to_base_by_part(self, robot: str) -> list[float]:
        """kbit/s the robot sent to the base station (:data:`MERGER_INPUTS`) in each part."""
        names = {t.of(robot) for t in MERGER_INPUTS}
        part_s = self.seconds / PARTS
        return [
            sum(self.topics[n].bytes_by_part[i] for n in names if n in self.topics) * 8e-3 / part_s
            for i in range(PARTS)
        ]


def measure_bandwidth(bag: Path, on_damage: Callable[[str], None] | None = None) -> Bandwidth:
    """Read every message of ``bag`` once (raw bytes, nothing decoded)."""
    sizes: list[tuple[str, int, int]] = []
    for message in read_bag(bag, on_damage=on_damage):
        sizes.append((message.topic, message.log_time_ns, len(message.data)))
    if not sizes:
        return Bandwidth(0, 0, {})
    start = min(t for _, t, _ in sizes)
    end = max(t for _, t, _ in sizes)
    span = max(end - start, 1)
    topics: dict[str, TopicTraffic] = {}
    for name, stamp, size in sizes:
        traffic = topics.get(name)
        if traffic is None:
            found = parse(name)
            traffic = topics[name] = TopicTraffic(name, found[1] if found else None)
        traffic.messages += 1
        traffic.bytes += size
        traffic.largest = max(traffic.largest, size)
        traffic.bytes_by_part[min((stamp - start) * PARTS // span, PARTS - 1)] += size
    return Bandwidth(start, end, topics)


def bandwidth_lines(bandwidth: Bandwidth) -> list[str]:
    """The report ``csam bandwidth`` prints."""
    if not bandwidth.topics:
        return ["the bag holds no messages"]
    seconds = bandwidth.seconds
    lines = [
        f"{seconds:,.1f} s of log time; serialized message bytes (no DDS or IP headers)",
        f"  {'topic':<28} {'messages':>9} {'kB':>11} {'largest kB':>11} {'kbit/s':>9}",
    ]
    ordered = sorted(bandwidth.topics.values(), key=lambda t: (t.robot is None, t.robot, t.topic))
    for t in ordered:
        lines.append(
            f"  {t.topic:<28} {t.messages:>9,} {t.bytes / 1e3:>11,.1f} {t.largest / 1e3:>11,.1f} "
            f"{t.bytes * 8e-3 / seconds:>9,.1f}"
        )
    inputs = " + ".join(t.name for t in MERGER_INPUTS)
    lines.append(f"to the base station ({inputs}), kbit/s by tenth of the run:")
    lines.append(
        f"  {'robot':<10}" + "".join(f"{f'{10 * i}-{10 * i + 10}%':>9}" for i in range(PARTS))
    )
    for robot in bandwidth.robots():
        lines.append(
            f"  {robot:<10}" + "".join(f"{v:>9,.1f}" for v in bandwidth.to_base_by_part(robot))
        )
    return lines
