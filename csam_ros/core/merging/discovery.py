"""Which robots found the merger joins, without ROS: :class:`RobotDiscovery`.

A robot found publishing local map updates is joined if ``robot_pattern`` and the allow-list
admit it, while fewer than ``max_robots`` are joined (the allow-list's always are; the others
are counted once, ``too_many_robots``, and joined when room is made). One found (not listed)
that sends no map for ``forget_after`` s is forgotten (unsubscribed, out of the status; its
map stays joined), and may be found again ``forget_after`` s later. The settings are passed to
each call, as the merger's live parameters may change them.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

from csam_ros.core.merging.policy_inputs import Found, MergerSettings


class RobotDiscovery:
    """The robots left out, turned away and forgotten, and when each was subscribed to."""

    def __init__(self) -> None:
        self.ignored: set[str] = set()  # robots found outside the allow-list or the pattern
        self.turned_away: set[str] = set()  # robots found while max_robots were joined
        self.subscribed_at: dict[str, float] = {}  # clock s each robot was subscribed to
        self.forgotten: dict[str, float] = {}  # clock s each robot was forgotten

    def copy(self) -> RobotDiscovery:
        """This discovery as it is now, in sets and dicts of its own."""
        twin = RobotDiscovery()
        twin.ignored, twin.turned_away = set(self.ignored), set(self.turned_away)
        twin.subscribed_at, twin.forgotten = dict(self.subscribed_at), dict(self.forgotten)
        return twin

    def found(
        self, robot: str, robots: Sequence[str], settings: MergerSettings, now: float
    ) -> Found | None:
        """What to do with ``robot``, seen publishing at ``now`` while ``robots`` are
        subscribed to (None: nothing now, it is subscribed to, was left out or turned away
        already, or was forgotten less than ``forget_after`` s ago)."""
        if robot in robots or robot in self.ignored:
            return None
        if not settings.admits(robot):
            self.ignored.add(robot)
            return Found.LEAVE_OUT
        forgotten = self.forgotten.get(robot)
        if forgotten is not None and now - forgotten < settings.forget_after:
            return None
        if len(robots) >= settings.max_robots and not settings.listed(robot):
            if robot in self.turned_away:
                return None
            self.turned_away.add(robot)
            return Found.TOO_MANY
        self.turned_away.discard(robot)
        self.forgotten.pop(robot, None)
        return Found.JOIN

    def subscribed(self, robot: str, now: float) -> None:
        """``robot``'s topics were subscribed to at ``now``."""
        self.subscribed_at[robot] = now

    def silent(
        self,
        robots: Sequence[str],
        map_arrival: Mapping[str, float],
        settings: MergerSettings,
        now: float,
    ) -> list[str]:
        """Those of ``robots`` found (not listed) that sent no local map (last at
        ``map_arrival``) for ``forget_after`` s (0: never), or none since they were subscribed
        to: forgotten at ``now``."""
        after = settings.forget_after
        silent = [
            r
            for r in robots
            if not settings.listed(r)
            and 0.0 < after < now - map_arrival.get(r, self.subscribed_at.get(r, now))
        ]
        for robot in silent:
            self.forgotten[robot] = now
        return silent
