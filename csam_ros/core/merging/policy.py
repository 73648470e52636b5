"""The merger's decisions, without ROS: :class:`MergerPolicy`.

It holds what a live merger holds between messages (each robot's local map and rendezvous
measurements, the reference, the counts, the last result) and decides with it:

- the reference: ``reference`` (else the first of ``robots``) if it has a map, else the first
  robot heard from; kept once made. The first solve waits, up to ``reference_wait`` s after the
  first local map, for the configured reference's map and for the maps and rendezvous of every
  robot on the allow-list;
- when a solve starts: when the inputs changed since the last solve's snapshot (a map
  delivered again unchanged is no change), no solve runs (the node asks every
  ``solve_period`` s, and as a map completes a round), and either every robot's map is newer
  than the last solve's or ``solve_wait`` s passed since the first change: smoothers on one
  data clock send their maps within a second of each other, and a solve started on the first
  of them would keep the others waiting for the next; ``~/flush`` solves the newest inputs at
  once, and after it each robot's next local map gives up a running solve, once (a smoother's
  final map may come after the flush that asked for it; no more, so that a flush in the middle
  of a run does not keep solves from ending);
- when the provisional joined map goes out (the newest local maps placed by the last join):
  once every robot's map is newer than the last joined and provisional maps, or
  ``provisional_quiet`` s pass without another map (maps that arrive together go out in one),
  or ``provisional_period`` s after the first of them; at most every ``provisional_period`` s;
- restarts: a robot's new local map that starts later or holds fewer poses than its last one
  comes from a restarted smoother. It replaces the old one all the same (it is the robot's
  current truth, in a new frame); the restart and the poses lost are logged once and counted
  in the status and the summary;
- staleness: a robot without a new local map for ``stale_after`` s is reported stale; its
  last map stays joined;
- sessions: a robot's held map changes only by an update that applies to it and passes the
  checks; whole maps of another session, or older ones, wait for the smoother's answer
  (:meth:`MergerPolicy.resync_answered`), as :mod:`~csam_ros.core.merging.sessions` decides;
  an update older than the one held is counted and makes the merger ask the smoother;
- robots found: joined, turned away or forgotten as :mod:`~csam_ros.core.merging.discovery`
  decides (``robot_pattern``, ``max_robots``, ``forget_after``);
- when to ask a smoother for its whole map (``RESYNC_*``);
- the status content (:class:`~csam_ros.core.merging.status.MergerStatus`);
- the state services: the state of the last joined map to save (:meth:`MergerPolicy.saved_state`,
  its maps refined by :func:`joined_maps`), forgetting everything (:meth:`MergerPolicy.reset`)
  before going on from a saved state (:meth:`MergerPolicy.take_up`), and no resync request
  while paused (``paused``: the node drops what arrives).

Its clock is injected (a callable returning monotonic seconds). It is not thread-safe: the
node calls it under its lock. The inputs a solve takes (maps, sources, stamps, rendezvous)
are dicts replaced, never mutated, so that a solve's snapshot of them stays as it was taken.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Mapping
from dataclasses import replace
from math import inf
from pathlib import Path

from csam_ros.core.exchange.checkpoint import MergerState
from csam_ros.core.exchange.map_arrays import robot_map_arrays
from csam_ros.core.exchange.map_updates import HeldMap
from csam_ros.core.exchange.validation import (
    FAILED_SOLVE,
    REPLAYED_UPDATE,
    TOO_MANY_ROBOTS,
    DropCounter,
    RefusedMessageError,
)
from csam_ros.core.joining.config import CsamConfig
from csam_ros.core.joining.result import CsamResult, MergerStats
from csam_ros.core.merging.discovery import RobotDiscovery
from csam_ros.core.merging.joiner import JoinReply, JoinRequest, MapSource
from csam_ros.core.merging.notices import (
    Notice,
    ReferenceAbsent,
    ReferenceChosen,
    ReferenceKept,
    Refused,
    RowsDropped,
    SolveFailed,
    SolveGivenUp,
    smoother_restart,
)
from csam_ros.core.merging.policy_inputs import (
    BEHIND,
    NO_MAP_HELD,
    OLDER,
    RESYNC_FIRST_S,
    RESYNC_RETRY_S,
    RESYNC_TIMEOUT_S,
    SESSION_CHECK,
    UPDATE,
    Arrival,
    Found,
    MapTaken,
    MergerSettings,
    PendingMap,
    ProvisionalMap,
    SolveInputs,
    SolveStart,
    every_map_newer,
)
from csam_ros.core.merging.sessions import SessionPins, not_taken
from csam_ros.core.merging.status import MergerStatus, RobotStatus, outside_trajectory
from csam_ros.core.model.log import RendezvousLog
from csam_ros.core.smoothing.robot_map import RobotMap


class MergerPolicy:
    """The merger's state between messages and its decisions on it (module docstring)."""

    def __init__(
        self,
        settings: MergerSettings,
        clock: Callable[[], float],
        config: CsamConfig,
        drops: DropCounter | None = None,
    ) -> None:
        self.settings = settings
        self.clock = clock
        self.config = config  # what solves join with
        self.drops = drops if drops is not None else DropCounter()
        # the inputs: each robot's last valid local map, as its updates built it (held), what
        # it was built from (a held map, or a resumed map's arrays), its message's stamp, and
        # its rendezvous measurements
        self.local_maps: dict[str, RobotMap] = {}
        self.held: dict[str, HeldMap] = {}
        self.sources: dict[str, MapSource] = {}
        self.local_map_stamps: dict[str, int] = {}
        self.rendezvous: dict[str, RendezvousLog] = {}
        self.robots: list[str] = []  # subscribed to, in the order found
        self.discovery = RobotDiscovery()  # robots left out, turned away, forgotten
        self.heard: list[str] = []  # robots in the order their first local map arrived
        self.reference = ""  # made at the first solve, then kept
        self.map_arrival: dict[str, float] = {}  # clock s of each robot's last map
        self.resync_requests: dict[str, int] = {}
        self.dirty = False  # inputs changed since the last solve's snapshot
        self._changed_at: float | None = None  # clock s they first changed since
        self._solve_started_at = clock()  # clock s the last solve started (or none yet)
        self._solved_stamps: dict[str, int] = {}  # the local map stamps the last solve took
        self.solving = False  # a solve is running
        self.solves = 0
        self.solves_given_up = 0  # running solves given up by ~/flush for newer inputs
        self.solve_seconds = 0.0  # how long the last solve took
        self.last_error = ""  # why the last solve failed
        self.last_result: CsamResult | None = None
        self.restarts: dict[str, int] = {}
        self.restart_poses_lost: dict[str, int] = {}
        self.provisional_maps = 0  # provisional joined maps published
        self.paused = False  # ~/pause: nothing is taken, no whole map asked for
        self._joined: SolveInputs | None = None  # the inputs of the last joined map
        self._first_heard_at = 0.0  # clock s of the first local map
        self._late_reference_noted = False
        # why a robot's whole map is wanted (an update did not apply, or an older one came):
        # asked for until a map is taken
        self._behind: dict[str, str] = {}
        self._resync_next: dict[str, float] = {}  # clock s from which to ask again
        self.sessions = SessionPins()  # whole maps set aside until their smoother's answer
        # robots whose next local map gives up a running solve (after ~/flush)
        self._after_flush: frozenset[str] = frozenset()
        # the local map stamps the last joined map and the last provisional map used
        self._published_stamps: dict[str, int] = {}
        self._provisional_stamps: dict[str, int] = {}
        self._provisional_next = 0.0  # clock s from which the next one may go out
        self._unpublished_since: float | None = None  # clock s a map first waited

    # robots and resyncs

    @property
    def ignored(self) -> set[str]:
        """The robots found that the allow-list or ``robot_pattern`` leaves out."""
        return self.discovery.ignored

    def found(self, robot: str) -> Found | None:
        """What to do with ``robot``, seen publishing local map updates
        (:meth:`RobotDiscovery.found`); one turned away is counted."""
        found = self.discovery.found(robot, self.robots, self.settings, self.clock())
        if found is Found.TOO_MANY:
            self.drops.add(TOO_MANY_ROBOTS)
        return found

    def subscribed(self, robot: str) -> None:
        """``robot``'s topics are subscribed to: its map is asked for if none comes soon."""
        now = self.clock()
        self._resync_next[robot] = now + RESYNC_FIRST_S
        self.discovery.subscribed(robot, now)
        self.robots = [*self.robots, robot]

    def forget_silent(self) -> list[str]:
        """The robots found (not listed) that sent no local map for ``forget_after`` s
        (:meth:`RobotDiscovery.silent`): no longer subscribed to nor in the status (their maps
        stay joined). The node unsubscribes them."""
        silent = self.discovery.silent(self.robots, self.map_arrival, self.settings, self.clock())
        for robot in silent:
            for wanted in (self._behind, self._resync_next):
                wanted.pop(robot, None)
            self.sessions.forget(robot)
        self.robots = [r for r in self.robots if r not in silent]
        return silent

    def known_robots(self) -> tuple[str, ...]:
        """The robots a rendezvous measurement may name: the allow-list, else every robot
        subscribed to or heard from."""
        return self.settings.robots or (
            *self.robots,
            *(r for r in self.heard if r not in self.robots),
        )

    def resyncs_wanted(self) -> Iterator[tuple[str, str]]:
        """The robots whose whole map is wanted (none is held, an update did not apply or was
        older than the one held, or a whole map is set aside), with why, none while paused;
        :meth:`resync_due` says whether to ask now."""
        if self.paused:
            return
        for robot in self.robots:
            if robot not in self.held:
                yield robot, NO_MAP_HELD
            elif robot in self._behind:
                yield robot, self._behind[robot]
            elif self.sessions.check_wanted(robot, self.clock()):
                yield robot, SESSION_CHECK

    def resync_due(self, robot: str) -> bool:
        """Whether a request for ``robot``'s whole map may be made now (none stands)."""
        return self.clock() >= self._resync_next.get(robot, 0.0)

    def resync_asked(self, robot: str) -> None:
        """A request for ``robot``'s whole map was made: it stands ``RESYNC_TIMEOUT_S``."""
        self._resync_next[robot] = self.clock() + RESYNC_TIMEOUT_S
        self.resync_requests[robot] = self.resync_requests.get(robot, 0) + 1
        self.sessions.asked(robot, self.clock())

    def resync_refused(self, robot: str) -> None:
        """``robot``'s smoother had nothing to send: ask again after ``RESYNC_RETRY_S``."""
        self._resync_next[robot] = self.clock() + RESYNC_RETRY_S

    # inputs

    def map_arrived(
        self, robot: str, arrived: Arrival, stamp_ns: int, answers: bool = True
    ) -> MapTaken:
        """Take what an update on ``robot``'s topic (stamped ``stamp_ns``) built, when it is
        usable and the sessions allow (module docstring; ``answers``: whether the robot's
        smoother's resync service is there to ask): the map held of it and its new local
        map. A refused one is dropped and the last valid map (and the sequence it expects
        next) stays in use; a smoother restart is counted."""
        if arrived.behind:
            self._behind[robot] = BEHIND
            return MapTaken(behind=arrived.behind)
        if arrived.refused is not None:
            return MapTaken(notices=(self.refused(robot, UPDATE, arrived.refused),))
        if arrived.held is None or arrived.checked is None:
            if not arrived.older:
                return MapTaken()  # delivered again
            self._behind[robot] = OLDER
            detail = f"{robot}: an update older than update {self.held[robot].sequence} held"
            notice = self.refused(robot, UPDATE, RefusedMessageError(detail, REPLAYED_UPDATE))
            return MapTaken((notice,), behind=OLDER)
        aside = self._set_aside(robot, arrived.held, arrived.checked, stamp_ns, answers)
        if aside is not None:
            return aside
        return self._take(robot, arrived.held, arrived.checked, stamp_ns, arrived.whole)

    def _set_aside(
        self, robot: str, new: HeldMap, checked: RobotMap, stamp_ns: int, answers: bool
    ) -> MapTaken | None:
        """What became of ``new``, a map built by an update, if it is not to be taken now:
        dropped, or set aside for its smoother's answer (:meth:`SessionPins.arrived`); None:
        take it."""
        gone = not answers and self.stale(robot)
        held = self.held.get(robot)
        aside = self.sessions.arrived(robot, held, new, checked, stamp_ns, gone, self.clock())
        if aside is None:
            return None
        notices = () if aside.dropped is None else (self._dropped(robot, aside.dropped),)
        return MapTaken(notices, behind=SESSION_CHECK if aside.ask else "")

    def _dropped(self, robot: str, pending: PendingMap) -> Refused:
        """A whole map not taken, counted under its reason."""
        self.drops.add(pending.reason)
        return not_taken(robot, self.held[robot], pending.held, pending.reason)

    def _take(
        self, robot: str, new: HeldMap, checked: RobotMap, stamp_ns: int, whole: bool
    ) -> MapTaken:
        """Hold ``new`` (checked: ``checked``) as ``robot``'s map; a replay of its session set
        aside is counted."""
        self.held = {**self.held, robot: new}
        self._behind.pop(robot, None)
        if whole:
            self._resync_next.pop(robot, None)
        replay = self.sessions.taken(robot, new)
        dropped = () if replay is None else (self._dropped(robot, replay),)
        taken = self._map_taken(robot, new, checked, stamp_ns)
        return replace(taken, notices=(*dropped, *taken.notices))

    def resync_answered(self, robot: str, sent: bool, session: int, sequence: int) -> MapTaken:
        """``robot``'s smoother answered a resync request: its session is ``session``, and it
        ``sent`` its whole map as update ``sequence`` (else it has sent nothing yet). A map
        set aside is taken if it is the smoother's (:meth:`SessionPins.answered`), else
        dropped and counted; the update named is taken when it comes, whatever the map held."""
        answer = self.sessions.answered(robot, sent, session, sequence, self.clock())
        if answer is None:
            return MapTaken()
        pending, own = answer
        if own:
            return self._take(robot, pending.held, pending.checked, pending.stamp_ns, True)
        return MapTaken(notices=(self._dropped(robot, pending),))

    def smoother_absent(self, robot: str) -> MapTaken:
        """``robot``'s smoother's resync service is not there: a map of another session set
        aside is taken once the session held is stale (its smoother is gone)."""
        pending = self.sessions.released(robot, self.stale(robot))
        if pending is None:
            return MapTaken()
        return self._take(robot, pending.held, pending.checked, pending.stamp_ns, whole=True)

    def _map_taken(self, robot: str, held: HeldMap, new: RobotMap, stamp_ns: int) -> MapTaken:
        now = self.clock()
        old = self.local_maps.get(robot)
        tolerance = self.config.stamp_tolerance
        restart = None if old is None else smoother_restart(robot, old, new, tolerance)
        if restart is not None:
            self.restarts[robot] = self.restarts.get(robot, 0) + 1
            self.restart_poses_lost[robot] = self.restart_poses_lost.get(robot, 0) + restart.lost
        self.map_arrival[robot] = now
        if robot not in self.heard:
            if not self.heard:
                self._first_heard_at = now
            self.heard = [*self.heard, robot]
        self.local_maps = {**self.local_maps, robot: new}
        self.sources = {**self.sources, robot: held}
        self.local_map_stamps = {**self.local_map_stamps, robot: stamp_ns}
        self.inputs_changed()
        if self._unpublished_since is None:
            self._unpublished_since = now
        give_up = robot in self._after_flush
        self._after_flush -= {robot}
        notices = () if restart is None else (restart,)
        return MapTaken(notices, taken=True, give_up_solve=give_up)

    def rendezvous_arrived(
        self, robot: str, log: RendezvousLog, dropped: Mapping[str, int]
    ) -> list[Notice]:
        """Take ``log``, the valid measurements of a rendezvous message on ``robot``'s topic
        (``dropped``: the single ones left out, by reason), unless it has none and usable ones
        are held. What to log of it."""
        for reason, n in dropped.items():
            self.drops.add(reason, n)
        notices: list[Notice] = [RowsDropped(robot, dict(dropped))] if dropped else []
        if len(log.stamps) == 0 and robot in self.rendezvous:
            return notices  # a message with no usable measurement never replaces usable ones
        self.rendezvous = {**self.rendezvous, robot: log}
        self.inputs_changed()
        return notices

    def refused(self, robot: str, what: str, error: RefusedMessageError) -> Refused:
        """A message on ``robot``'s topic (``what``) refused by ``error``: counted."""
        self.drops.add(error.reason)
        return Refused(robot, what, error.reason, str(error))

    def inputs_changed(self) -> None:
        """The inputs changed (or are to be solved again as if they had)."""
        if not self.dirty:
            self._changed_at = self.clock()
        self.dirty = True

    def take_up(self, saved: MergerState) -> list[str]:
        """Go on from a saved merger state (on a policy just made, or :meth:`reset`); the
        robots it had subscribed to that are still to be (the allow-list's)."""
        now = self.clock()
        self.local_maps = dict(saved.maps)
        self.sources = {robot: robot_map_arrays(m) for robot, m in saved.maps.items()}
        self.local_map_stamps = dict(saved.map_stamps)
        self.rendezvous = dict(saved.rendezvous)
        self.heard = list(saved.heard)
        self.reference = saved.reference
        self.map_arrival = {robot: now for robot in saved.maps}
        self.restarts = dict(saved.restarts)
        self.restart_poses_lost = dict(saved.restart_poses_lost)
        self.solves = saved.solves
        for reason, n in saved.dropped.items():
            self.drops.add(reason, n)
        self.last_result = saved.result
        if saved.result is not None:  # the node publishes it at once
            self._published_stamps = dict(self.local_map_stamps)
            self._joined = SolveInputs(
                order=tuple(saved.heard),  # the reference first (state_after)
                sources=self.sources,
                logs=self.rendezvous,
                stamps=self.local_map_stamps,
                robots=tuple(saved.robots),
            )
        return [robot for robot in saved.robots if self.settings.admits(robot)]

    def reset(self) -> None:
        """Forget every map, measurement, result and count (``~/reset``, and before
        :meth:`take_up` on a merger that ran): as a policy just made that subscribed to the
        same robots (whose whole maps it asks for again); ``paused`` stays. Call with no solve
        running."""
        robots, ignored, paused = self.robots, self.ignored, self.paused
        self.drops.counts.clear()  # the node's counter, shared: cleared, never replaced
        vars(self).update(vars(MergerPolicy(self.settings, self.clock, self.config, self.drops)))
        self.discovery.ignored, self.paused = ignored, paused
        for robot in robots:
            self.subscribed(robot)

    def saved_state(self) -> tuple[MergerState, SolveInputs] | None:
        """The state of the last joined map (``~/save_state``), as a solve writes it to
        ``state_path``, but with the counts of now: its maps still to be filled in from its
        inputs (:func:`joined_maps`, outside the node's lock); None before the first."""
        inputs, result = self._joined, self.last_result
        if inputs is None or result is None:
            return None
        state = replace(
            self.state_after(inputs),
            solves=self.solves,
            rendezvous=dict(inputs.logs),
            result=result,
        )
        return state, inputs

    # solves

    def solve_wanted(self, on_arrival: bool = False) -> bool:
        """Whether a solve is to start: the inputs changed, none runs, and the maps that come
        together are in (:meth:`MergerSettings.solve_settled`). ``on_arrival`` (a local map
        just taken): only once every robot's map is new and ``solve_period`` s passed since
        the last solve started, so that the map that completes a round starts the solve at
        once instead of at the node's next look."""
        if not self.dirty or self.solving:
            return False
        every_map_new = every_map_newer(self.local_map_stamps, self._solved_stamps)
        if on_arrival:
            since = self.clock() - self._solve_started_at
            return every_map_new and since >= self.settings.solve_period
        waited = self.clock() - (self._changed_at if self._changed_at is not None else -inf)
        return self.settings.solve_settled(waited, every_map_new)

    def flush(self) -> bool:
        """``~/flush``: each robot heard from gives up a running solve with its next map;
        whether there are inputs newer than the last solve's (to solve at once)."""
        self._after_flush = frozenset(self.heard)
        return self.dirty

    def start_solve(self) -> SolveStart | None:
        """A solve of the inputs now, if they changed since the last one and the first solve
        need not wait (:meth:`_first_inputs_complete`, :meth:`_choose_reference`); it runs
        until :meth:`solve_ended`."""
        if not self.dirty:
            return None
        self.dirty = False
        if not self.heard:
            return None
        chosen = self._choose_reference() if self._first_inputs_complete() else None
        if chosen is None:
            self.dirty = True  # asked again at the next look
            return None
        _, notice = chosen
        self._changed_at, self._solved_stamps = None, dict(self.local_map_stamps)
        self._solve_started_at = self.clock()
        order, robots = self._order()
        inputs = SolveInputs(
            order=tuple(order),
            sources=self.sources,
            logs={r: self.rendezvous[r] for r in order if r in self.rendezvous},
            stamps=self.local_map_stamps,
            robots=robots,
        )
        self.solving = True
        return SolveStart(inputs, notice)

    def solve_ended(self) -> None:
        self.solving = False

    def solve_done(self, inputs: SolveInputs, reply: JoinReply, seconds: float) -> list[Notice]:
        """Record how the running solve of ``inputs`` went (``seconds`` long): the maps it
        could not use (dropped), and its result (the new joined map), or that it was given up
        for newer inputs, or failed (the last joined map stays). What to log of it."""
        notices: list[Notice] = []
        for refusal in reply.refused:
            self.drops.add(refusal.reason)
            notices.append(Refused(refusal.robot, UPDATE, refusal.reason, refusal.detail))
        if reply.cancelled:
            self.solves_given_up += 1
            notices.append(SolveGivenUp())
        elif reply.result is None:
            self.solve_seconds = seconds
            self.last_error = reply.error
            self.drops.add(FAILED_SOLVE)
            notices.append(SolveFailed(reply.error))
        else:
            self.last_error = ""
            self.solve_seconds = seconds
            self.solves += 1
            self.last_result = reply.result
            self._published_stamps = dict(inputs.stamps)
            self._joined = inputs
        return notices

    def stats(self) -> MergerStats:
        """What the merger counted so far, as the summary carries it."""
        return MergerStats(
            dropped=self.drops.as_dict(),
            solves=self.solves,
            restarts=dict(self.restarts),
            restart_poses_lost=dict(self.restart_poses_lost),
        )

    def join_request(self, inputs: SolveInputs, state_path: Path | None) -> JoinRequest:
        """The solve process's request to join ``inputs``, warm-started from the last result;
        with ``state_path``, the merger's state to write there after the join."""
        return JoinRequest(
            maps=tuple((r, inputs.sources[r]) for r in inputs.order),
            logs=inputs.logs,
            config=self.config,
            previous=self.last_result,
            state=self.state_after(inputs) if state_path is not None else None,
            state_path=state_path,
        )

    def state_after(self, inputs: SolveInputs) -> MergerState:
        """The merger's state as it will be once the solve of ``inputs`` is counted (its maps,
        rendezvous and result filled in by the solve)."""
        stats = self.stats()
        return MergerState(
            reference=inputs.order[0],
            heard=list(inputs.order),
            robots=list(inputs.robots),
            maps={},
            map_stamps={r: inputs.stamps[r] for r in inputs.order},
            rendezvous={},
            solves=stats.solves + 1,
            dropped=stats.dropped,
            restarts=stats.restarts,
            restart_poses_lost=stats.restart_poses_lost,
        )

    def _order(self) -> tuple[list[str], tuple[str, ...]]:
        """The robots heard from, the reference first (the order they are joined in), and
        those followed by every other robot subscribed to."""
        order = [self.reference] + [r for r in self.heard if r != self.reference]
        return order, (*order, *(r for r in self.robots if r not in order))

    def _first_inputs_complete(self) -> bool:
        """Whether the first solve may run: every listed robot's local map and rendezvous
        have come, or ``reference_wait`` has passed since the first map (a merger started
        beside running smoothers gets their latched inputs within moments, in any order; one
        solve then joins them all)."""
        if self.reference:
            return True
        waiting = [
            r for r in self.settings.robots if r not in self.local_maps or r not in self.rendezvous
        ]
        return not waiting or self.clock() - self._first_heard_at >= self.settings.reference_wait

    def _choose_reference(self) -> tuple[str, Notice | None] | None:
        """The configured reference if it has a map, else, once ``reference_wait`` has passed
        since the first map, the first robot heard from; kept once made. The reference and
        what to say of it, or None while there is none (call with a map heard)."""
        configured = self.settings.configured_reference
        if self.reference:
            late = configured and configured != self.reference and configured in self.local_maps
            if late and not self._late_reference_noted:
                self._late_reference_noted = True
                return self.reference, ReferenceKept(configured, self.reference)
            return self.reference, None
        absent = bool(configured) and configured not in self.local_maps
        wait = self.settings.reference_wait
        if absent and self.clock() - self._first_heard_at < wait:
            return None
        self.reference = configured if configured in self.local_maps else self.heard[0]
        if absent:
            return self.reference, ReferenceAbsent(configured, self.reference, wait)
        return self.reference, ReferenceChosen(self.reference, self.reference == configured)

    # provisional maps

    def provisional_due(self) -> ProvisionalMap | None:
        """The provisional map to publish now (module docstring), if one is due: the newest
        local maps when neither the last joined nor the last provisional map used them."""
        now = self.clock()
        settings = self.settings
        last, stamps = self.last_result, dict(self.local_map_stamps)
        if stamps in (self._published_stamps, self._provisional_stamps):
            self._unpublished_since = None
            return None
        waited = now - (now if self._unpublished_since is None else self._unpublished_since)
        quiet = now - max(self.map_arrival.values(), default=now)
        complete = every_map_newer(stamps, self._published_stamps, self._provisional_stamps)
        if (
            last is None
            or settings.provisional_period <= 0.0
            or now < self._provisional_next
            or (
                quiet < settings.provisional_quiet
                and waited < settings.provisional_period
                and not complete
            )
        ):
            return None
        order, robots = self._order()
        self._provisional_stamps = stamps
        self._unpublished_since = None
        self._provisional_next = now + settings.provisional_period
        maps = [self.local_maps[r] for r in order]
        return ProvisionalMap(last, maps, stamps, robots, self.config.stamp_tolerance)

    def joined_holds(self, stamps: Mapping[str, int]) -> bool:
        """Whether the last joined map holds the local maps of ``stamps`` already."""
        return stamps == self._published_stamps

    def provisional_published(self) -> None:
        self.provisional_maps += 1

    # status

    def seconds_since_map(self, robot: str, now: float | None = None) -> float | None:
        """s since ``robot``'s last local map at ``now`` (None: the clock's now); None when
        none came."""
        arrival = self.map_arrival.get(robot)
        if arrival is None:
            return None
        return (self.clock() if now is None else now) - arrival

    def stale(self, robot: str, now: float | None = None) -> bool:
        """Whether ``robot`` sent no local map for more than ``stale_after`` s (0: never) at
        ``now`` (None: the clock's now)."""
        since = self.seconds_since_map(robot, now)
        return since is not None and 0.0 < self.settings.stale_after < since

    def status(self) -> MergerStatus:
        """What ``/csam/status`` says now."""
        result = self.last_result
        now = self.clock()
        robots = []
        for robot in self.robots:
            r = result.robots.get(robot) if result is not None else None
            if robot not in self.local_maps:
                alignment = "pending: no local map received"
            elif r is None:
                alignment = "pending: not solved yet"
            else:
                alignment = r.alignment
            robots.append(
                RobotStatus(
                    robot=robot,
                    alignment=alignment,
                    stale=self.stale(robot, now),
                    seconds_since_map=self.seconds_since_map(robot, now),
                    poses=len(r.stamps) if r is not None else 0,
                    solve_seconds=self.solve_seconds,
                    restarts=self.restarts.get(robot, 0),
                    restart_poses_lost=self.restart_poses_lost.get(robot, 0),
                    update=self.held[robot].sequence if robot in self.held else 0,
                    resync_requests=self.resync_requests.get(robot, 0),
                    odometry_calibration=(
                        tuple(self.held[robot].map.odometry_calibration.tolist())
                        if robot in self.held
                        else ()
                    ),
                )
            )
        return MergerStatus(
            robots=tuple(robots),
            reference=self.reference,
            solves=self.solves,
            features=len(result.features) if result is not None else 0,
            associations=len(result.associations) if result is not None else 0,
            solve_seconds=self.solve_seconds,
            solving=self.solving,
            solves_given_up=self.solves_given_up,
            provisional_maps=self.provisional_maps,
            converged=result.converged if result is not None else None,
            dropped=self.drops.as_dict(),
            restarts=sum(self.restarts.values()),
            resync_requests=sum(self.resync_requests.values()),
            outside_trajectory=outside_trajectory(result),
            last_error=self.last_error,
        )

    # going back

    def copy(self) -> MergerPolicy:
        """This policy as it is now, to go back to with :meth:`restore`: its own dicts, lists,
        sets, discovery and session pins; the maps, results, settings, clock and drop counter
        shared (never changed in place, or meant to be shared)."""
        twin = object.__new__(MergerPolicy)
        vars(twin).update({name: _own(value) for name, value in vars(self).items()})
        return twin

    def restore(self, saved: MergerPolicy) -> None:
        """Go back to the state ``saved`` (a :meth:`copy`) holds; ``saved`` stays as it is."""
        vars(self).update(vars(saved.copy()))


def _own(value: object) -> object:
    """``value`` as a policy's copy holds it: containers and state objects copied, the rest
    shared."""
    if isinstance(value, dict | list | set):
        return type(value)(value)
    if isinstance(value, RobotDiscovery | SessionPins):
        return value.copy()
    return value
