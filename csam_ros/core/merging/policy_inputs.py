"""What the merger's policy (:class:`~csam_ros.core.merging.policy.MergerPolicy`) takes and
gives: its settings, a local map's arrival, a solve's inputs, the provisional map, and the
merger's saved state read back."""

from __future__ import annotations

import re
from collections.abc import Mapping
from dataclasses import dataclass
from enum import Enum
from pathlib import Path

from csam_ros.core.exchange.checkpoint import MergerState
from csam_ros.core.exchange.map_arrays import held_robot_map
from csam_ros.core.exchange.map_updates import HeldMap, MapUpdate, MissingBaseError, apply_update
from csam_ros.core.exchange.state_files import CheckpointError
from csam_ros.core.exchange.validation import (
    LocalMapError,
    RefusedMessageError,
)
from csam_ros.core.joining.local_views import in_threads
from csam_ros.core.joining.result import CsamResult
from csam_ros.core.merging.joiner import MapSource, robot_map_of
from csam_ros.core.merging.notices import (
    Notice,
    StateMissing,
    StateUnusable,
)
from csam_ros.core.model.log import RendezvousLog
from csam_ros.core.smoothing.robot_map import RobotMap

PROVISIONAL_CHECKS = 4  # looks per provisional_quiet (or period) whether a provisional map is due
# asking a smoother for its whole local map (~/resync): a robot none is held of is asked this
# long after it was subscribed to (its first update, whole, usually comes first); a request
# stands this long before another is made (the whole map may take long on a slow link), and
# one the smoother could not serve (nothing sent yet) is made again after RESYNC_RETRY_S
RESYNC_FIRST_S = 3.0
RESYNC_TIMEOUT_S = 30.0
RESYNC_RETRY_S = 2.0
NO_MAP_HELD = "no local map held yet"
UPDATE = "local map update"  # what a refused map update is called
BEHIND = "an update did not apply to the map held"
OLDER = "an update older than the map held came"
SESSION_CHECK = "a whole map of another session, or an older one, came: is it the smoother's?"


@dataclass(frozen=True)
class MergerSettings:
    """The merger node's own parameters its decisions take (seconds of the wall clock)."""

    robots: tuple[str, ...] = ()  # the allow-list (empty: every robot found)
    reference: str = ""  # the configured reference ("": the first of robots)
    reference_wait: float = 5.0
    stale_after: float = 30.0  # 0: never stale
    solve_period: float = 0.5
    solve_wait: float = 1.0
    provisional_period: float = 1.0  # 0: no provisional maps
    provisional_quiet: float = 0.5
    max_robots: int = 64  # robots found and joined at once (the allow-list's always are)
    robot_pattern: str = ".*"  # a regular expression every robot's whole name must match
    forget_after: float = 300.0  # s a robot found (not listed) may be silent in the status

    @property
    def configured_reference(self) -> str:
        """``reference``, else the first of ``robots`` ("" when neither is set)."""
        return self.reference or (self.robots[0] if self.robots else "")

    def admits(self, robot: str) -> bool:
        """Whether ``robot`` is joined: on the allow-list (or there is none), and its name
        matches ``robot_pattern``."""
        listed = not self.robots or robot in self.robots
        return listed and re.fullmatch(self.robot_pattern, robot) is not None

    def listed(self, robot: str) -> bool:
        """Whether ``robot`` is on the allow-list."""
        return robot in self.robots

    def solve_settled(self, waited: float, every_map_new: bool) -> bool:
        """Whether a solve of changed inputs may start: every robot's local map is newer than
        the last solve's, or ``solve_wait`` s passed since the first change (local maps that
        arrive together are solved in one)."""
        return every_map_new or waited >= self.solve_wait

    @property
    def solve_check_period(self) -> float:
        """s between looks whether a solve is to start."""
        return max(self.solve_period, 0.01)

    @property
    def provisional_check_period(self) -> float | None:
        """s between looks whether a provisional map is due (None: there are none)."""
        if self.provisional_period <= 0.0:
            return None
        quickest = min(self.provisional_period, self.provisional_quiet)
        return max(quickest / PROVISIONAL_CHECKS, 0.01)


class Flushed(Enum):
    """What ``~/flush`` did (its reply's message)."""

    NOTHING_NEWER = "the joined map (or the running solve) holds the newest inputs"
    GAVE_UP = "a solve of older inputs was given up: solving the newest"
    SOLVING = "solving the newest inputs"

    @classmethod
    def of(cls, newer: bool, given_up: bool) -> Flushed:
        """With inputs ``newer`` than the last solve's, and a running solve ``given_up``."""
        if not newer:
            return cls.NOTHING_NEWER
        return cls.GAVE_UP if given_up else cls.SOLVING


class Found(Enum):
    """What to do with a robot newly seen publishing local map updates."""

    JOIN = "join"  # subscribe to it
    LEAVE_OUT = "leave out"  # not on the allow-list, or its name not of robot_pattern (said once)
    TOO_MANY = "too many"  # max_robots are joined: not now (said and counted once)


@dataclass(frozen=True)
class SolveInputs:
    """What one solve works on, taken from the policy: never changed afterwards."""

    order: tuple[str, ...]  # the robots joined, the reference first
    sources: Mapping[str, MapSource]  # each robot's map as held (refined by the solve)
    logs: Mapping[str, RendezvousLog]
    stamps: Mapping[str, int]
    robots: tuple[str, ...]  # every known robot, in the solve's order


@dataclass(frozen=True)
class SolveStart:
    """A solve to run now, and what making the reference for it has to say (if anything)."""

    inputs: SolveInputs
    notice: Notice | None = None


@dataclass(frozen=True)
class Arrival:
    """An update on a robot's topic applied to the map held of it (:func:`arrival`)."""

    held: HeldMap | None = None  # the map it built (None: it built none new)
    checked: RobotMap | None = None  # ``held`` checked (None: not usable, or none)
    behind: str = ""  # why it did not apply to the map held: the whole map is wanted
    refused: RefusedMessageError | None = None  # why it, or the map it built, is not usable
    whole: bool = False  # it was a complete update: a resync request no longer stands
    older: bool = False  # an update older than the one held (it built nothing new)


def arrival(robot: str, held: HeldMap | None, update: MapUpdate) -> Arrival:
    """``update`` on ``robot``'s topic applied to ``held``, the map held of it (never changed),
    and the map it builds checked (not refined: the solve process refines it); a map that
    fails the checks is not returned, so that it is never held. Pure: the node calls it
    outside its lock (only the executor changes what is held), then
    :meth:`MergerPolicy.map_arrived`, which decides whether a whole map is taken."""
    try:
        new = apply_update(held, update)
    except MissingBaseError as error:
        return Arrival(behind=str(error))
    except RefusedMessageError as error:
        return Arrival(refused=error)
    except ValueError as error:  # it does not fit the map held
        return Arrival(refused=LocalMapError(f"{robot}: {error}"))
    if new is held:  # delivered again (nothing to solve), or older than the one held
        return Arrival(older=held is not None and update.sequence < held.sequence)
    try:
        return Arrival(new, held_robot_map(robot, new, refine=False), whole=update.complete)
    except RefusedMessageError as error:
        return Arrival(refused=error)


@dataclass(frozen=True)
class PendingMap:
    """A whole map, checked, held aside until its robot's smoother says whether it is its own
    (:meth:`MergerPolicy.resync_answered`): one of another session than the map held, or of
    the same session but older."""

    held: HeldMap
    checked: RobotMap
    stamp_ns: int
    reason: str  # what it is counted as when it is not taken


@dataclass(frozen=True)
class MapTaken:
    """What an update on a robot's topic led to."""

    notices: tuple[Notice, ...] = ()  # a refusal, a smoother restart
    behind: str = ""  # why its whole map is wanted ("": it is not)
    taken: bool = False  # a new local map is held: a provisional map may be due
    give_up_solve: bool = False  # give up a running solve for the newest inputs (~/flush)


@dataclass(frozen=True)
class ProvisionalMap:
    """A provisional joined map decided on: the newest local maps (in the join's robot order)
    to be placed by ``last`` (:func:`~csam_ros.core.joining.warm_start.carried_forward`)."""

    last: CsamResult
    maps: list[RobotMap]
    stamps: dict[str, int]
    robots: tuple[str, ...]
    stamp_tolerance: float  # s: carried_forward's


def every_map_newer(stamps: Mapping[str, int], *used: Mapping[str, int]) -> bool:
    """Whether each robot's local map (its message stamp in ``stamps``) is none of the maps
    ``used`` (stamps a joined or provisional map took): no robot's newer map is still to come
    that a map should wait for."""
    return all(all(stamp != b.get(robot) for b in used) for robot, stamp in stamps.items())


def joined_maps(inputs: SolveInputs) -> dict[str, RobotMap]:
    """Each robot's map as the solve of ``inputs`` joined it, in the join's order: one built
    from updates refined to its sender's optimum, a saved one as it is (the joiner's maps,
    :class:`~csam_ros.core.merging.joiner.Joiner`). :class:`LocalMapError` when one is not
    usable (the solve joined that robot's previous map)."""
    maps = in_threads(lambda robot: robot_map_of(robot, inputs.sources[robot]), inputs.order)
    return dict(zip(inputs.order, maps, strict=True))


def read_state(path: Path) -> MergerState | StateMissing | StateUnusable:
    """The merger state saved at ``path``, or why there is none to take up."""
    if not path.exists():
        return StateMissing(path)
    try:
        return MergerState.read(path)
    except CheckpointError as err:
        return StateUnusable(str(err))
    except Exception as err:  # noqa: BLE001 - a node never dies of a bad file
        return StateUnusable(f"{path}: {type(err).__name__}: {err}")
