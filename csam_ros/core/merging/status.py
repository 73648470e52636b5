"""The merger's status as typed data (what ``/csam/status`` says; the node turns it into a
DiagnosticArray), and the drop counter the merger's threads share."""

from __future__ import annotations

import threading
from dataclasses import dataclass
from enum import Enum

from csam_ros.core.exchange.validation import DropCounter
from csam_ros.core.joining.alignment import joined
from csam_ros.core.joining.result import CsamResult


class Health(Enum):
    """How a status entry stands (a diagnostic level)."""

    OK = "ok"
    WARN = "warn"
    ERROR = "error"


@dataclass(frozen=True)
class RobotStatus:
    """One robot's entry: its alignment in the last joined map, whether it went quiet, and
    its counts."""

    robot: str
    alignment: str  # the last result's, or "pending: ..." when not joined yet
    stale: bool  # no local map for more than stale_after s
    seconds_since_map: float | None  # None: no map yet
    poses: int  # in the last joined map
    solve_seconds: float  # how long the last solve took
    restarts: int
    restart_poses_lost: int
    update: int  # the sequence of the update the map held was built by (0: none held)
    resync_requests: int
    # its local map's odometry calibration: s, k_d, k_s and their sigmas; () not estimated
    odometry_calibration: tuple[float, ...] = ()

    @property
    def health(self) -> Health:
        is_joined = joined(self.alignment)
        return Health.OK if is_joined and not self.stale else Health.WARN

    @property
    def message(self) -> str:
        if self.stale and self.seconds_since_map is not None:
            return f"{self.alignment} (stale: no local map for {self.seconds_since_map:.0f} s)"
        return self.alignment


@dataclass(frozen=True)
class MergerStatus:
    """The merger's entry (its counts and solve state) and every subscribed robot's, in the
    order they were found."""

    robots: tuple[RobotStatus, ...]
    reference: str
    solves: int
    features: int
    associations: int
    solve_seconds: float
    solving: bool
    solves_given_up: int
    provisional_maps: int
    converged: bool | None  # None: nothing solved yet
    dropped: dict[str, int]  # by reason
    restarts: int
    resync_requests: int
    outside_trajectory: int  # rendezvous the last solve left out: outside a trajectory
    last_error: str  # why the last solve failed ("": it did not)

    @property
    def health(self) -> Health:
        if self.last_error:
            return Health.ERROR
        return Health.WARN if self.converged is False else Health.OK

    @property
    def message(self) -> str:
        message = f"{self.solves} solves, {self.associations} associations"
        if self.converged is False and not self.last_error:
            return f"{message}; the last solve did not converge"
        return message


def outside_trajectory(result: CsamResult | None) -> int:
    """Rendezvous measurements a solve left out as stamped outside a map's span."""
    report = result.rendezvous_filter.get("trajectory_span") if result is not None else None
    return report.total("outside_trajectory") if report is not None else 0


class SharedDropCounter(DropCounter):
    """A :class:`DropCounter` the executor and the solve worker may both count into."""

    def __init__(self) -> None:
        super().__init__()
        self._lock = threading.Lock()

    def add(self, reason: str, n: int = 1) -> None:
        with self._lock:
            super().add(reason, n)

    def reclassify(self, old: str, new: str) -> None:
        with self._lock:
            super().reclassify(old, new)

    @property
    def total(self) -> int:
        with self._lock:
            return sum(self.counts.values())

    def as_dict(self) -> dict[str, int]:
        with self._lock:
            return super().as_dict()
