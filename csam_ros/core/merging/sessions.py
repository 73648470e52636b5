"""Sessions pinned at the merger, without ROS: :class:`SessionPins`.

A robot's held map changes only by an update that applies to it and passes the checks. A whole
map of another session than the one held, or an older one of the same session, is set aside
(:class:`~csam_ros.core.merging.policy_inputs.PendingMap`) until the robot's smoother, asked for
its whole map, names its session and sequence (:meth:`SessionPins.answered`): taken if they are
the map's (the smoother restarted), else dropped and counted (``foreign_session``,
``replayed_update``). A map of another session is taken at once when the held one is stale and
its smoother's service is gone. The decisions are here; the merger's policy holds the maps,
counts what is dropped and takes what the decisions let through.
"""

from __future__ import annotations

from dataclasses import dataclass

from csam_ros.core.exchange.map_updates import HeldMap
from csam_ros.core.exchange.validation import FOREIGN_SESSION, REPLAYED_UPDATE
from csam_ros.core.merging.notices import Refused
from csam_ros.core.merging.policy_inputs import (
    RESYNC_RETRY_S,
    RESYNC_TIMEOUT_S,
    UPDATE,
    PendingMap,
)
from csam_ros.core.smoothing.robot_map import RobotMap


@dataclass(frozen=True)
class Aside:
    """A whole map not taken at once: the map dropped for it (the one set aside before it, of
    another session, or itself; None: none), and whether to ask its smoother now."""

    dropped: PendingMap | None = None
    ask: bool = False


def not_taken(robot: str, held: HeldMap, m: HeldMap, reason: str) -> Refused:
    """What to say of ``m``, a whole map of ``robot`` not taken (``reason``), ``held`` held."""
    why = (
        f"older than update {held.sequence} held"
        if reason == REPLAYED_UPDATE
        else f"of another session than {held.session}, which its smoother did not name"
    )
    detail = f"{robot}: whole map {m.sequence} of session {m.session} not taken: {why}"
    return Refused(robot, UPDATE, reason, detail)


class SessionPins:
    """Each robot's whole maps set aside and what its smoother said (module docstring). Its
    dicts but ``checked_at`` are replaced, never mutated; :meth:`copy` gives its own."""

    def __init__(self) -> None:
        self.pending: dict[str, PendingMap] = {}  # whole maps set aside
        self.vouched: dict[str, tuple[int, int]] = {}  # the last answer's (session, sequence)
        self.refuted: dict[str, tuple[int, float]] = {}  # the session refuted last, and when
        self.checked_at: dict[str, float] = {}  # when an answer about a map set aside was asked

    def copy(self) -> SessionPins:
        """These pins as they are now, in dicts of their own."""
        twin = SessionPins()
        twin.pending, twin.vouched = dict(self.pending), dict(self.vouched)
        twin.refuted, twin.checked_at = dict(self.refuted), dict(self.checked_at)
        return twin

    def check_due(self, robot: str, now: float) -> bool:
        """Whether the smoother may be asked about a map set aside at ``now`` (at most every
        ``RESYNC_RETRY_S``: another publisher's maps ask no more often)."""
        return now - self.checked_at.get(robot, -RESYNC_RETRY_S) >= RESYNC_RETRY_S

    def check_wanted(self, robot: str, now: float) -> bool:
        """Whether a map of ``robot`` is set aside and its smoother may be asked about it."""
        return robot in self.pending and self.check_due(robot, now)

    def asked(self, robot: str, now: float) -> None:
        """``robot``'s smoother was asked for its whole map at ``now``."""
        if robot in self.pending:
            self.checked_at[robot] = now

    def arrived(
        self,
        robot: str,
        held: HeldMap | None,
        new: HeldMap,
        checked: RobotMap,
        stamp_ns: int,
        gone: bool,
        now: float,
    ) -> Aside | None:
        """What becomes of ``new`` (checked: ``checked``, stamped ``stamp_ns``), a map built
        by an update of ``robot`` while ``held`` is held (``gone``: the held session is stale
        and no smoother answers): None to take it, else dropped or set aside."""
        if held is None or (new.session, new.sequence) == self.vouched.get(robot):
            return None
        if new.session == held.session:
            if new.sequence > held.sequence:
                return None
            reason = REPLAYED_UPDATE
        else:
            if gone:
                return None  # the old session is gone and no smoother answers for it
            refuted = self.refuted.get(robot, (-1, -RESYNC_TIMEOUT_S))
            if refuted[0] == new.session and now - refuted[1] < RESYNC_TIMEOUT_S:
                return Aside(PendingMap(new, checked, stamp_ns, FOREIGN_SESSION))
            reason = FOREIGN_SESSION
        old = self.pending.get(robot)
        replaced = old if old is not None and old.held.session != new.session else None
        self.pending = {**self.pending, robot: PendingMap(new, checked, stamp_ns, reason)}
        return Aside(replaced, ask=self.check_due(robot, now))

    def taken(self, robot: str, new: HeldMap) -> PendingMap | None:
        """``new`` is held of ``robot`` now: the answer it was is spent, and a map set aside
        of its session (older) is no longer; that one when it is a replay to count."""
        vouched = self.vouched.get(robot)
        if vouched is not None and (vouched[0] != new.session or new.sequence >= vouched[1]):
            self.vouched = {r: v for r, v in self.vouched.items() if r != robot}
        pending = self.pending.get(robot)
        if pending is None or pending.held.session != new.session:
            return None
        self.pending = {r: p for r, p in self.pending.items() if r != robot}
        return pending if pending.reason == REPLAYED_UPDATE else None

    def answered(
        self, robot: str, sent: bool, session: int, sequence: int, now: float
    ) -> tuple[PendingMap, bool] | None:
        """``robot``'s smoother answered at ``now`` (its ``session``; ``sent``: its whole map
        as update ``sequence``): the map set aside, if any, and whether it is the smoother's
        (its session, or that very update, for one of the session held)."""
        if sent:
            self.vouched = {**self.vouched, robot: (session, sequence)}
        pending = self.pending.get(robot)
        if pending is None:
            return None
        self.pending = {r: p for r, p in self.pending.items() if r != robot}
        m = pending.held
        own = (m.session, m.sequence) == (session, sequence) or (
            pending.reason == FOREIGN_SESSION and m.session == session and sent
        )
        if not own and pending.reason == FOREIGN_SESSION:
            self.refuted = {**self.refuted, robot: (m.session, now)}
        return pending, own

    def released(self, robot: str, stale: bool) -> PendingMap | None:
        """The map of another session set aside to take now that ``robot``'s smoother's
        service is gone, if the session held is ``stale``."""
        pending = self.pending.get(robot)
        if pending is None or pending.reason != FOREIGN_SESSION or not stale:
            return None
        self.pending = {r: p for r, p in self.pending.items() if r != robot}
        return pending

    def forget(self, robot: str) -> None:
        """``robot`` is no longer subscribed to: nothing of it is set aside."""
        self.pending.pop(robot, None)
        self.checked_at.pop(robot, None)
