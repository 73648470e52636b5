"""What a live merger's solves share, and one solve on it (docs/METHOD.md section 6.4).

A :class:`Joiner` keeps, between solves, each robot's local map refined to its sender's optimum
(the next refine starting from it: :func:`~csam_ros.core.exchange.map_arrays.refine_start`),
the local views (:class:`~csam_ros.core.joining.local_views.LocalViewCache`) and the last result,
the warm start of the next join. :meth:`Joiner.join` takes a :class:`JoinRequest`: each robot's map
source (a map built from updates, refined here once; or a map as saved, joined as it is), or
``None`` for the source of the last request, so that a caller in another process sends a map only
when it changed. A join may be given up part-way (:class:`JoinCancelled`, raised inside the
``cancellable`` context the joiner was made with): the joiner keeps the maps it took and its warm
start, and the reply says it was cancelled. A request may carry the merger's state, written by
:meth:`Joiner.write_state` after the reply (the joined map goes out first). :meth:`Joiner.prepare`
takes map sources ahead of their join, with what a join derives from each map alone. The merger node
runs a joiner in a process of its own (:mod:`csam_ros.solve_process`); nothing here knows of ROS.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable, Mapping
from contextlib import AbstractContextManager
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from csam_ros.core.exchange.checkpoint import MergerState
from csam_ros.core.exchange.local_map_checks import LocalMapArrays
from csam_ros.core.exchange.map_arrays import Refined, checked_robot_map, held_robot_map
from csam_ros.core.exchange.map_updates import HeldMap
from csam_ros.core.exchange.validation import LocalMapError
from csam_ros.core.joining.config import CsamConfig
from csam_ros.core.joining.join import join_maps
from csam_ros.core.joining.local_views import LocalViewCache, in_threads
from csam_ros.core.joining.result import CsamResult
from csam_ros.core.model.log import RendezvousLog
from csam_ros.core.smoothing.robot_map import RobotMap

# a robot's local map as the merger holds it: built from updates (refined when joined), or
# as a saved merger state held it (joined as it is)
MapSource = HeldMap | LocalMapArrays


class JoinCancelled(BaseException):
    """A join given up part-way. Not an :class:`Exception`: no handler of the core's may take
    it for a failure of one part and go on."""


@dataclass(frozen=True)
class JoinRequest:
    """One solve: the robots' map sources in the join's order (the reference first)."""

    maps: tuple[tuple[str, MapSource | None], ...]  # None: the source of the last request
    logs: Mapping[str, RendezvousLog]
    config: CsamConfig
    previous: CsamResult | None = None  # when given, the warm start instead of the last result
    # the merger's state to write after a successful join (Joiner.write_state), its maps,
    # rendezvous and result filled in here
    state: MergerState | None = None
    state_path: Path | None = None


@dataclass(frozen=True)
class PrepareRequest:
    """Robots' new map sources, to be taken and prepared before the join that uses them."""

    maps: tuple[tuple[str, MapSource], ...]


@dataclass(frozen=True)
class Refusal:
    """A map source that could not be refined (its robot's last map is joined instead)."""

    robot: str
    reason: str
    detail: str


@dataclass(frozen=True)
class JoinReply:
    """A solve's outcome: the result, or why there is none."""

    result: CsamResult | None
    error: str = ""  # "<exception type>: <message>" of a failed join
    refused: tuple[Refusal, ...] = ()
    cancelled: bool = False  # the join was given up (JoinCancelled): no result, no failure
    state_pending: bool = False  # the request's state is to be written (Joiner.write_state)


@dataclass(frozen=True)
class StateWritten:
    """How writing the merger's state after a join went."""

    error: str = ""  # why it could not be written ("": written)
    seconds: float = 0.0


def robot_map_of(robot: str, source: MapSource, last: Refined | None = None) -> RobotMap:
    """``robot``'s map as a join takes it: one built from updates refined to its sender's
    optimum (from where ``last``, its map refined before, leads), a saved one as it is.
    :class:`LocalMapError` when it is not usable."""
    if isinstance(source, HeldMap):
        return held_robot_map(robot, source, last=last)
    return checked_robot_map(robot, source)


class Joiner:
    """The joins of one merger, each warm-started from the last (module docstring)."""

    def __init__(
        self,
        cancellable: Callable[[], AbstractContextManager[object]] = contextlib.nullcontext,
    ) -> None:
        self.maps: dict[str, RobotMap] = {}  # each robot's last usable map, refined
        self._refined: dict[str, Refined] = {}  # where each robot's next refine starts
        self.local_views = LocalViewCache()
        self.previous: CsamResult | None = None
        self._refused: list[Refusal] = []  # by prepare, to go with the next join's reply
        self._state: tuple[MergerState, Path] | None = None  # what write_state writes
        # entered around the join itself (not the maps' refinement or the state write): a
        # JoinCancelled raised within gives the join up
        self.cancellable = cancellable

    def join(self, request: JoinRequest) -> JoinReply:
        """Join the request's maps. A failed join raises nothing: the reply says why (an
        exception, or a result holding a non-finite number)."""
        self._state = None
        if request.previous is not None:
            self.previous = request.previous
        # refined in threads, one per core (their factorisations release the interpreter lock)
        taken = in_threads(lambda item: self._take(*item), request.maps)
        refused = (*self._refused, *(r for r in taken if r is not None))
        self._refused = []
        order = [robot for robot, _ in request.maps]
        config = request.config
        try:
            missing = [robot for robot in order if robot not in self.maps]
            if missing:
                raise ValueError(f"no usable map held of {', '.join(missing)}")
            maps = [self.maps[robot] for robot in order]
            with self.cancellable():
                result = join_maps(
                    maps,
                    dict(request.logs),
                    config,
                    previous=self.previous if config.warm_start else None,
                    last=self.previous,
                    cache=self.local_views,
                )
            fault = non_finite(result)
            if fault:
                raise ValueError(f"the joined map has non-finite numbers ({fault})")
        except JoinCancelled as cancelled:
            return JoinReply(None, f"cancelled: {cancelled}", refused, cancelled=True)
        except Exception as err:  # noqa: BLE001 - the caller reports a failed solve
            return JoinReply(None, f"{type(err).__name__}: {err}", refused)
        self.previous = result
        if request.state is not None and request.state_path is not None:
            state = replace(
                request.state,
                maps=dict(zip(order, maps, strict=True)),
                rendezvous=dict(request.logs),
                result=result,
            )
            self._state = (state, request.state_path)
        return JoinReply(result, refused=refused, state_pending=self._state is not None)

    def prepare(self, request: PrepareRequest) -> None:
        """Take the request's map sources as a join would, and compute what joins derive from
        each map alone (:meth:`~csam_ros.core.joining.local_views.LocalViewCache.prepare`), so
        that the join that uses them does not: a live merger prepares a map when it arrives,
        while it waits for the others. Refusals go with the next join's reply."""
        taken = in_threads(lambda item: self._take(*item), request.maps)
        self._refused.extend(r for r in taken if r is not None)
        self.local_views.prepare(
            [self.maps[robot] for robot, _ in request.maps if robot in self.maps]
        )

    def write_state(self) -> StateWritten | None:
        """Write the state of the last join's request (None when it had none to write)."""
        if self._state is None:
            return None
        (state, path), self._state = self._state, None
        start = time.perf_counter()
        try:
            state.write(path)
        except (OSError, ValueError) as err:
            return StateWritten(f"merger state not written to {path}: {err}")
        return StateWritten(seconds=time.perf_counter() - start)

    def _take(self, robot: str, source: MapSource | None) -> Refusal | None:
        """Hold ``robot``'s map of ``source`` (None: keep the last); a refusal if it is not
        usable (the robot's last map stays, else a map built from updates is held as it
        came). Never raises: every source of a request is taken, whatever one of them is.
        Called for several robots at once (each thread holds its own robot's map)."""
        if source is None:
            return None
        try:
            self.maps[robot] = robot_map_of(robot, source, self._refined.get(robot))
            if isinstance(source, HeldMap):
                self._refined[robot] = Refined(self.maps[robot], source.map)
            else:
                self._refined.pop(robot, None)
            return None
        except LocalMapError as error:
            if robot not in self.maps and isinstance(source, HeldMap):
                with contextlib.suppress(LocalMapError):
                    self.maps[robot] = held_robot_map(robot, source, refine=False)
            return Refusal(robot, error.reason, str(error))


def non_finite(result: CsamResult) -> str:
    """The first part of a result holding a non-finite number ("" when none)."""
    for name, r in result.robots.items():
        for part in ("base_node", "base_node_cov", "poses_joined", "sigma_phi_joined"):
            value = getattr(r, part)
            if value is not None and not np.all(np.isfinite(np.asarray(value, dtype=float))):
                return f"{name} {part}"
    for f in result.features:
        if not (np.all(np.isfinite(f.xy)) and np.all(np.isfinite(f.cov))):
            return f"feature {'+'.join(f.members)}"
    return ""
