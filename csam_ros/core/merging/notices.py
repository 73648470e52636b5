"""What the merger's policy has the node log, as typed data: each notice has a level and the
text of its log line (:class:`~csam_ros.core.merging.policy.MergerPolicy` makes them; the
node only writes them out)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar, Literal

from csam_ros.core.model.stamps import matching_stamp
from csam_ros.core.smoothing.robot_map import RobotMap

Level = Literal["info", "warning", "error"]  # the name of the logger's method


@dataclass(frozen=True)
class ReferenceChosen:
    """The reference is made: the configured one (it has a map), or the first robot heard
    from (none is configured)."""

    level: ClassVar[Level] = "info"
    robot: str
    configured: bool

    def __str__(self) -> str:
        how = "configured" if self.configured else "first robot heard from"
        return f"reference robot: {self.robot} ({how})"


@dataclass(frozen=True)
class ReferenceAbsent:
    """The configured reference had no map ``wait`` s after the first one: the first robot
    heard from is the reference instead."""

    level: ClassVar[Level] = "warning"
    configured: str
    reference: str
    wait: float

    def __str__(self) -> str:
        return (
            f"{self.configured} has no local map {self.wait:g} s after the first one: "
            f"{self.reference}, the first robot heard from, is the reference"
        )


@dataclass(frozen=True)
class ReferenceKept:
    """The configured reference's map came after another robot was made the reference."""

    level: ClassVar[Level] = "warning"
    configured: str
    reference: str

    def __str__(self) -> str:
        return (
            f"{self.configured} came after {self.reference} was made the reference; "
            f"{self.reference} stays the reference"
        )


@dataclass(frozen=True)
class SmootherRestart:
    """A robot's new local map starts later or holds fewer poses than its last one: its
    smoother restarted, and ``lost`` poses of its history are no longer joined."""

    level: ClassVar[Level] = "warning"
    robot: str
    poses: int
    first: float  # s: the new map's first stamp
    old_poses: int
    old_first: float
    old_last: float
    lost: int

    def __str__(self) -> str:
        return (
            f"{self.robot}: smoother restarted: the new local map holds {self.poses} poses from "
            f"{self.first:.3f} s, the last one held {self.old_poses} from "
            f"{self.old_first:.3f} s to {self.old_last:.3f} s; {self.lost} poses of its history "
            "are lost and no longer joined"
        )


@dataclass(frozen=True)
class Refused:
    """A message on a robot's topic (``what``), or the map it built, is not usable: dropped
    and counted under ``reason``; the robot's last valid one stays in use."""

    level: ClassVar[Level] = "warning"
    robot: str
    what: str  # "local map update", "rendezvous poses message"
    reason: str
    detail: str

    def __str__(self) -> str:
        return f"dropped a {self.what} on {self.robot}'s topic ({self.reason}): {self.detail}"


@dataclass(frozen=True)
class RowsDropped:
    """Single rendezvous measurements of a message dropped (the rest kept), by reason."""

    level: ClassVar[Level] = "warning"
    robot: str
    counts: dict[str, int]

    def __str__(self) -> str:
        return f"dropped rendezvous measurements on {self.robot}'s topic: {self.counts}"


@dataclass(frozen=True)
class SolveGivenUp:
    """A running solve of older inputs was given up for the newest (after ``~/flush``)."""

    level: ClassVar[Level] = "info"

    def __str__(self) -> str:
        return "a solve of older inputs was given up for the newest"


@dataclass(frozen=True)
class SolveFailed:
    """A solve failed: the last joined map stays."""

    level: ClassVar[Level] = "error"
    error: str

    def __str__(self) -> str:
        return f"C-SAM failed, the last joined map stays: {self.error}"


@dataclass(frozen=True)
class StateMissing:
    """No merger state is saved at ``path`` yet: the merger starts empty."""

    level: ClassVar[Level] = "info"
    path: Path

    def __str__(self) -> str:
        return f"no merger state at {self.path} yet: starting empty"


@dataclass(frozen=True)
class StateUnusable:
    """The merger state file cannot be used (``detail`` says why): the merger starts empty."""

    level: ClassVar[Level] = "error"
    detail: str

    def __str__(self) -> str:
        return f"merger state not used, starting empty: {self.detail}"


@dataclass(frozen=True)
class StateResumed:
    """The merger took up the state saved at ``path``."""

    level: ClassVar[Level] = "info"
    path: Path
    maps: int
    reference: str
    solves: int

    def __str__(self) -> str:
        return (
            f"resumed from {self.path}: {self.maps} local maps, reference "
            f"{self.reference or '(none yet)'}, {self.solves} solves"
        )


Notice = (
    ReferenceChosen
    | ReferenceAbsent
    | ReferenceKept
    | SmootherRestart
    | Refused
    | RowsDropped
    | SolveGivenUp
    | SolveFailed
    | StateMissing
    | StateUnusable
    | StateResumed
)


def smoother_restart(
    robot: str, old: RobotMap, new: RobotMap, tolerance: float
) -> SmootherRestart | None:
    """The restart that ``new`` replacing ``old`` as ``robot``'s map shows, if any: it starts
    more than ``tolerance`` s later, or holds fewer poses. The poses lost are those of ``old``
    with no pose of ``new`` within ``tolerance``."""
    later = new.stamps[0] > old.stamps[0] + tolerance
    if not (later or len(new.stamps) < len(old.stamps)):
        return None
    return SmootherRestart(
        robot=robot,
        poses=len(new.stamps),
        first=float(new.stamps[0]),
        old_poses=len(old.stamps),
        old_first=float(old.stamps[0]),
        old_last=float(old.stamps[-1]),
        lost=int((matching_stamp(new.stamps, old.stamps, tolerance) < 0).sum()),
    )
