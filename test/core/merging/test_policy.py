"""The merger's decisions without ROS: :class:`MergerPolicy` on real local maps of a simulated
run, with a fake clock (nothing sleeps). Each test fails if the rule it names is removed."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import pytest
from growing_joins import maps_until
from log_slices import robot_log_between

from csam_ros.core.exchange.checkpoint import MergerState
from csam_ros.core.exchange.map_arrays import robot_map_arrays
from csam_ros.core.exchange.map_updates import MapUpdate, UpdateSender
from csam_ros.core.exchange.validation import (
    FAILED_SOLVE,
    FOREIGN_SESSION,
    MALFORMED_LOCAL_MAP,
    REPLAYED_UPDATE,
    TOO_MANY_ROBOTS,
    DropCounter,
)
from csam_ros.core.joining.config import CsamConfig
from csam_ros.core.joining.join import join_maps
from csam_ros.core.joining.pipeline import robot_map_from_local_map
from csam_ros.core.joining.result import CsamResult
from csam_ros.core.merging.joiner import JoinReply, Refusal
from csam_ros.core.merging.notices import (
    ReferenceAbsent,
    ReferenceChosen,
    ReferenceKept,
    Refused,
    RowsDropped,
    SmootherRestart,
    SolveFailed,
    SolveGivenUp,
)
from csam_ros.core.merging.policy import MergerPolicy
from csam_ros.core.merging.policy_inputs import (
    BEHIND,
    NO_MAP_HELD,
    OLDER,
    RESYNC_FIRST_S,
    RESYNC_RETRY_S,
    RESYNC_TIMEOUT_S,
    SESSION_CHECK,
    Flushed,
    Found,
    MapTaken,
    MergerSettings,
    SolveStart,
    arrival,
)
from csam_ros.core.merging.status import Health
from csam_ros.core.model.log import MultiRobotLog, RendezvousLog
from csam_ros.core.model.rendezvous import required_stamps
from csam_ros.core.smoothing.local_map_build import build_local_map
from csam_ros.core.smoothing.robot_map import RobotMap
from csam_ros.datasets.scenario import load_scenario
from csam_ros.datasets.simulation import simulate

CONFIG = CsamConfig(skip_missing_poses=True)
ROBOTS = ("robot1", "robot2")
S = 10**9  # ns per s: local map message stamps


class FakeClock:
    """Monotonic seconds that move only when a test moves them."""

    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now

    def advance(self, seconds: float) -> None:
        self.now += seconds


@dataclass(frozen=True)
class Run:
    """Local maps of a simulated run: at 20 s and at its end, robot2's restarted at 12 s, the
    rendezvous logs and a join of the maps at 20 s."""

    early: dict[str, RobotMap]
    late: dict[str, RobotMap]
    restarted: RobotMap
    logs: dict[str, RendezvousLog]
    joined: CsamResult


@pytest.fixture(scope="module")
def run() -> Run:
    log: MultiRobotLog = simulate(load_scenario("map_joining"), 1)
    early, logs = maps_until(log, 20.0)
    late, _ = maps_until(log, 40.0)
    robot2 = robot_log_between(log.robots["robot2"], start=12.0, end=40.0)
    stamps = required_stamps({n: r.rendezvous for n, r in log.robots.items()})["robot2"]
    kept = stamps[(stamps >= robot2.odometry.stamps[0]) & (stamps <= robot2.odometry.stamps[-1])]
    restarted = robot_map_from_local_map(build_local_map(robot2, kept))
    return Run(
        early={m.name: m for m in early},
        late={m.name: m for m in late},
        restarted=restarted,
        logs=logs,
        joined=join_maps(early, logs, CONFIG),
    )


class Merger:
    """A policy fed as the node feeds it: each robot's maps as its smoother's updates."""

    def __init__(self, **settings: object) -> None:
        self.clock = FakeClock()
        self.drops = DropCounter()
        self.policy = MergerPolicy(MergerSettings(**settings), self.clock, CONFIG, self.drops)
        self.senders: dict[str, UpdateSender] = {}
        for robot in ROBOTS:
            self.policy.subscribed(robot)

    def send(self, m: RobotMap, stamp_s: float = 1.0, session: int = 1) -> MapTaken:
        """``m`` sent as its robot's next update (a new session: a complete one)."""
        sender = self.senders.get(m.name)
        if sender is None or sender.session != session:
            sender = self.senders[m.name] = UpdateSender(session)
        update = sender.update(robot_map_arrays(m))
        arrived = arrival(m.name, self.policy.held.get(m.name), update)
        return self.policy.map_arrived(m.name, arrived, int(stamp_s * S))

    def restart(self, m: RobotMap, stamp_s: float = 1.0, session: int = 2) -> MapTaken:
        """``m`` sent as the first update of its robot's restarted smoother (a new
        ``session``): set aside until the smoother's answer to the resync request it makes
        names that session."""
        aside = self.send(m, stamp_s, session)
        assert aside.behind == SESSION_CHECK and not aside.taken
        self.policy.resync_asked(m.name)
        return self.policy.resync_answered(m.name, True, session, 1)

    def rendezvous(self, robot: str, log: RendezvousLog) -> None:
        assert self.policy.rendezvous_arrived(robot, log, {}) == []

    def solve(self, result: CsamResult) -> SolveStart:
        """Start a solve and end it with ``result``."""
        start = self.policy.start_solve()
        assert start is not None
        self.policy.solve_done(start.inputs, JoinReply(result), 1.5)
        self.policy.solve_ended()
        return start


def _all_in(merger: Merger, run: Run, maps: dict[str, RobotMap] | None = None) -> None:
    for robot in ROBOTS:
        merger.send((maps or run.early)[robot])
        merger.rendezvous(robot, run.logs[robot])


# the reference


def test_the_configured_reference_is_made_the_reference(run: Run) -> None:
    merger = Merger(reference="robot2")
    _all_in(merger, run)  # robot1 heard first
    start = merger.policy.start_solve()
    assert start is not None and start.inputs.order == ("robot2", "robot1")
    assert start.notice == ReferenceChosen("robot2", configured=True)
    assert merger.policy.reference == "robot2"


def test_without_reference_the_first_listed_robot_is_the_reference(run: Run) -> None:
    merger = Merger(robots=("robot2", "robot1"))
    _all_in(merger, run)
    start = merger.policy.start_solve()
    assert start is not None and start.inputs.order == ("robot2", "robot1")


def test_with_nothing_configured_the_first_robot_heard_from_is_the_reference(run: Run) -> None:
    merger = Merger()
    merger.send(run.early["robot2"])
    merger.send(run.early["robot1"])
    start = merger.policy.start_solve()
    assert start is not None and start.inputs.order == ("robot2", "robot1")
    assert start.notice == ReferenceChosen("robot2", configured=False)


def test_an_absent_configured_reference_is_awaited_reference_wait(run: Run) -> None:
    merger = Merger(reference="robot1", reference_wait=5.0)
    merger.send(run.early["robot2"])
    merger.clock.advance(4.75)
    assert merger.policy.start_solve() is None
    assert merger.policy.dirty and merger.policy.reference == ""  # asked again later
    merger.clock.advance(0.25)
    start = merger.policy.start_solve()
    assert start is not None and start.inputs.order == ("robot2",)
    assert start.notice == ReferenceAbsent("robot1", "robot2", 5.0)


def test_the_reference_is_kept_once_made(run: Run) -> None:
    merger = Merger(reference="robot1", reference_wait=0.0)
    merger.send(run.early["robot2"])
    merger.solve(run.joined)
    merger.send(run.early["robot1"])  # the configured reference comes late
    start = merger.solve(run.joined)
    assert start.inputs.order == ("robot2", "robot1")
    assert start.notice == ReferenceKept("robot1", "robot2")
    merger.send(run.late["robot1"], 2.0)
    assert merger.solve(run.joined).notice is None  # said once
    assert merger.policy.reference == "robot2"


def test_the_first_solve_waits_for_every_listed_robots_map_and_rendezvous(run: Run) -> None:
    merger = Merger(robots=ROBOTS, reference_wait=5.0)
    merger.send(run.early["robot1"])
    merger.rendezvous("robot1", run.logs["robot1"])
    merger.send(run.early["robot2"])
    assert merger.policy.start_solve() is None  # robot2's rendezvous has not come
    merger.rendezvous("robot2", run.logs["robot2"])
    start = merger.policy.start_solve()
    assert start is not None and start.inputs.order == ROBOTS
    assert set(start.inputs.logs) == set(ROBOTS)


def test_the_first_solve_waits_no_longer_than_reference_wait(run: Run) -> None:
    merger = Merger(robots=ROBOTS, reference_wait=5.0)
    merger.send(run.early["robot1"])
    assert merger.policy.start_solve() is None
    merger.clock.advance(5.0)
    start = merger.policy.start_solve()
    assert start is not None and start.inputs.order == ("robot1",)
    assert start.inputs.robots == ROBOTS  # robot2 subscribed to, not heard from


# when a solve starts


def test_a_solve_starts_only_when_the_inputs_changed(run: Run) -> None:
    merger = Merger()
    assert merger.policy.start_solve() is None and not merger.policy.solve_wanted()
    _all_in(merger, run)
    assert merger.policy.solve_wanted()
    start = merger.policy.start_solve()
    assert start is not None and merger.policy.solving
    assert not merger.policy.solve_wanted()  # none while one runs
    merger.rendezvous("robot2", run.logs["robot2"])  # arrives during the solve
    assert not merger.policy.solve_wanted()
    merger.policy.solve_done(start.inputs, JoinReply(run.joined), 1.0)
    merger.policy.solve_ended()
    merger.clock.advance(merger.policy.settings.solve_wait)  # no robot's map is new
    assert merger.policy.solve_wanted()  # the newer inputs next
    assert merger.policy.start_solve() is not None
    merger.policy.solve_ended()
    assert merger.policy.start_solve() is None and not merger.policy.solve_wanted()
    merger.policy.inputs_changed()
    merger.clock.advance(merger.policy.settings.solve_wait)
    assert merger.policy.solve_wanted()


def test_a_solve_waits_for_the_maps_that_come_together(run: Run) -> None:
    """After a solve, a new map of one robot waits up to solve_wait s for the other robots'
    (smoothers on one data clock send theirs within a second); it starts at once when every
    robot's map is new."""
    merger = Merger(solve_wait=1.0)
    _all_in(merger, run)
    merger.solve(run.joined)
    merger.send(run.late["robot1"], 2.0)
    assert merger.policy.dirty and not merger.policy.solve_wanted()
    merger.clock.advance(0.5)
    assert not merger.policy.solve_wanted()
    merger.send(run.late["robot2"], 2.0)  # every robot's map is new: no more to wait for
    assert merger.policy.solve_wanted()
    merger.solve(run.joined)
    merger.send(run.early["robot1"], 3.0)
    merger.clock.advance(0.99)
    assert not merger.policy.solve_wanted()
    merger.clock.advance(0.01)  # robot2's map is not coming: solved without it
    assert merger.policy.solve_wanted()
    assert Merger(solve_wait=0.0).policy.settings.solve_settled(0.0, every_map_new=False)


def test_the_map_that_completes_a_round_starts_the_solve_at_once(run: Run) -> None:
    """On a map's arrival a solve is wanted only when every robot's map is new, and at least
    solve_period s after the last solve started (or the policy was made)."""
    merger = Merger(solve_wait=1.0, solve_period=0.5)
    _all_in(merger, run)
    assert not merger.policy.solve_wanted(on_arrival=True)  # made just now
    merger.clock.advance(0.5)
    assert merger.policy.solve_wanted(on_arrival=True)
    merger.solve(run.joined)
    merger.send(run.late["robot1"], 2.0)
    merger.clock.advance(2.0)  # past solve_wait: the node's look would start it
    assert merger.policy.solve_wanted() and not merger.policy.solve_wanted(on_arrival=True)
    merger.send(run.late["robot2"], 2.0)
    assert merger.policy.solve_wanted(on_arrival=True)
    merger.solve(run.joined)
    merger.send(run.early["robot1"], 3.0)
    merger.send(run.early["robot2"], 3.0)
    assert merger.policy.solve_wanted() and not merger.policy.solve_wanted(on_arrival=True)
    merger.clock.advance(0.5)  # solve_period after the last start
    assert merger.policy.solve_wanted(on_arrival=True)


def test_a_map_delivered_again_starts_no_solve(run: Run) -> None:
    merger = Merger()
    sender = UpdateSender(3)
    update = sender.update(robot_map_arrays(run.early["robot1"]))
    taken = merger.policy.map_arrived("robot1", arrival("robot1", None, update), S)
    assert taken.taken and merger.policy.start_solve() is not None
    merger.policy.solve_ended()
    held = merger.policy.held["robot1"]
    again = merger.policy.map_arrived("robot1", arrival("robot1", held, update), 2 * S)
    assert again == MapTaken() and merger.policy.held["robot1"] is held
    assert not merger.policy.dirty and merger.policy.local_map_stamps == {"robot1": S}


def test_after_a_flush_each_robots_next_map_gives_up_a_running_solve_once(run: Run) -> None:
    merger = Merger()
    _all_in(merger, run)
    assert merger.policy.flush()  # inputs newer than the last solve's: solved at once
    merger.solve(run.joined)
    assert not merger.policy.flush()  # the joined map holds the newest inputs
    assert merger.send(run.late["robot1"], 2.0).give_up_solve
    assert not merger.send(run.late["robot1"], 3.0).give_up_solve  # once only
    assert merger.send(run.late["robot2"], 2.0).give_up_solve
    assert not merger.restart(run.early["robot2"], 3.0).give_up_solve


def test_without_a_flush_a_map_gives_up_no_solve(run: Run) -> None:
    merger = Merger()
    merger.send(run.early["robot1"])
    merger.policy.flush()
    assert not merger.send(run.early["robot2"]).give_up_solve  # not heard at the flush
    assert not merger.send(run.late["robot2"], 2.0).give_up_solve


def test_flush_replies() -> None:
    assert Flushed.of(newer=False, given_up=False) is Flushed.NOTHING_NEWER
    assert Flushed.of(newer=True, given_up=True) is Flushed.GAVE_UP
    assert Flushed.of(newer=True, given_up=False) is Flushed.SOLVING


def test_periods_of_the_nodes_looks() -> None:
    assert MergerSettings(solve_period=0.0).solve_check_period == 0.01
    assert MergerSettings(solve_period=2.0).solve_check_period == 2.0
    settings = MergerSettings(provisional_period=1.0, provisional_quiet=0.5)
    assert settings.provisional_check_period == 0.125
    assert MergerSettings(provisional_period=0.0).provisional_check_period is None


def test_what_a_solve_ends_with_is_recorded(run: Run) -> None:
    merger = Merger()
    _all_in(merger, run)
    start = merger.policy.start_solve()
    assert start is not None
    refused = (Refusal("robot2", MALFORMED_LOCAL_MAP, "robot2: bad"),)
    failed = JoinReply(None, "ValueError: no", refused)
    assert merger.policy.solve_done(start.inputs, failed, 2.0) == [
        Refused("robot2", "local map update", MALFORMED_LOCAL_MAP, "robot2: bad"),
        SolveFailed("ValueError: no"),
    ]
    assert merger.drops.as_dict() == {FAILED_SOLVE: 1, MALFORMED_LOCAL_MAP: 1}
    assert (merger.policy.last_error, merger.policy.solve_seconds) == ("ValueError: no", 2.0)
    assert merger.policy.solves == 0 and merger.policy.last_result is None
    given_up = JoinReply(None, "cancelled", cancelled=True)
    assert merger.policy.solve_done(start.inputs, given_up, 3.0) == [SolveGivenUp()]
    assert merger.policy.solves_given_up == 1 and merger.policy.solve_seconds == 2.0
    assert merger.policy.solve_done(start.inputs, JoinReply(run.joined), 4.0) == []
    assert merger.policy.solves == 1 and merger.policy.last_result is run.joined
    assert merger.policy.last_error == "" and merger.policy.solve_seconds == 4.0
    assert merger.policy.stats().solves == 1


def test_a_join_request_is_warm_started_and_carries_the_state_to_write(run: Run, tmp_path) -> None:
    merger = Merger()
    _all_in(merger, run)
    first = merger.solve(run.joined)
    assert merger.policy.join_request(first.inputs, None).state is None
    merger.send(run.late["robot2"], 2.0)
    start = merger.policy.start_solve()
    assert start is not None
    request = merger.policy.join_request(start.inputs, tmp_path / "state.npz")
    assert request.previous is run.joined
    assert [robot for robot, _ in request.maps] == list(ROBOTS)
    assert request.maps[1][1] is merger.policy.held["robot2"]
    assert request.state is not None and request.state.solves == 2  # once this one counts
    assert request.state.map_stamps == {"robot1": S, "robot2": 2 * S}


# provisional maps


def _provisional_merger(run: Run, **settings: object) -> Merger:
    """Both robots' maps joined; no map newer than the joined map."""
    merger = Merger(**settings)
    _all_in(merger, run)
    merger.solve(run.joined)
    assert merger.policy.provisional_due() is None
    return merger


def test_no_provisional_map_before_a_joined_one(run: Run) -> None:
    merger = Merger(provisional_quiet=0.5)
    _all_in(merger, run)
    merger.clock.advance(10.0)
    assert merger.policy.provisional_due() is None


def test_a_provisional_map_goes_out_after_provisional_quiet(run: Run) -> None:
    merger = _provisional_merger(run, provisional_quiet=0.5, provisional_period=1.0)
    merger.send(run.late["robot2"], 2.0)
    merger.clock.advance(0.25)
    assert merger.policy.provisional_due() is None
    merger.clock.advance(0.25)
    due = merger.policy.provisional_due()
    assert due is not None and due.last is run.joined
    assert due.stamps == {"robot1": S, "robot2": 2 * S} and due.robots == ROBOTS
    assert [m.name for m in due.maps] == list(ROBOTS)
    assert due.maps[1] is merger.policy.local_maps["robot2"]
    assert np.array_equal(due.maps[1].stamps, run.late["robot2"].stamps)
    merger.clock.advance(10.0)
    assert merger.policy.provisional_due() is None  # those maps went out


def test_a_provisional_map_waits_no_longer_than_provisional_period(run: Run) -> None:
    merger = _provisional_merger(run, provisional_quiet=0.5, provisional_period=1.0)
    maps = [run.early["robot2"], run.late["robot2"]]
    for k in range(1, 5):  # a new map every 0.25 s: never quiet
        merger.send(maps[k % 2], 1.0 + k)
        merger.clock.advance(0.25)
        due = merger.policy.provisional_due()
        assert (due is not None) == (k == 4), k  # 1 s after the first of them


def test_a_provisional_map_goes_out_at_once_when_every_robots_map_is_new(run: Run) -> None:
    merger = _provisional_merger(run, provisional_quiet=600.0, provisional_period=600.0)
    merger.send(run.late["robot2"], 2.0)
    merger.clock.advance(1.0)
    assert merger.policy.provisional_due() is None
    merger.send(run.late["robot1"], 2.0)
    due = merger.policy.provisional_due()
    assert due is not None and due.stamps == {"robot1": 2 * S, "robot2": 2 * S}


def test_provisional_maps_go_out_at_most_every_provisional_period(run: Run) -> None:
    merger = _provisional_merger(run, provisional_quiet=0.0, provisional_period=1.0)
    merger.send(run.late["robot2"], 2.0)
    assert merger.policy.provisional_due() is not None
    merger.send(run.early["robot2"], 3.0)
    merger.clock.advance(0.75)
    assert merger.policy.provisional_due() is None
    merger.clock.advance(0.25)
    assert merger.policy.provisional_due() is not None


def test_no_provisional_map_of_maps_a_joined_map_holds(run: Run) -> None:
    merger = _provisional_merger(run, provisional_quiet=0.5)
    merger.send(run.late["robot2"], 2.0)
    start = merger.policy.start_solve()
    assert start is not None
    assert not merger.policy.joined_holds(start.inputs.stamps)
    merger.policy.solve_done(start.inputs, JoinReply(run.joined), 1.0)
    assert merger.policy.joined_holds(start.inputs.stamps)
    merger.clock.advance(10.0)
    assert merger.policy.provisional_due() is None


def test_no_provisional_maps_with_provisional_period_zero(run: Run) -> None:
    merger = _provisional_merger(run, provisional_quiet=0.0, provisional_period=0.0)
    merger.send(run.late["robot1"], 2.0)
    merger.send(run.late["robot2"], 2.0)
    merger.clock.advance(10.0)
    assert merger.policy.provisional_due() is None


# restarts


def test_a_grown_map_is_no_restart(run: Run) -> None:
    merger = Merger()
    merger.send(run.early["robot2"])
    assert merger.send(run.late["robot2"], 2.0).notices == ()
    assert merger.policy.restarts == {}


def test_a_map_that_starts_later_is_a_restart_counted_with_the_poses_lost(run: Run) -> None:
    merger = Merger()
    old, new = run.early["robot2"], run.restarted
    assert len(new.stamps) > len(old.stamps)  # more poses, from a later start
    merger.send(old)
    taken = merger.restart(new, 2.0)
    lost = int(np.sum(old.stamps < new.stamps[0] - CONFIG.stamp_tolerance))
    assert lost > 0
    (restart,) = taken.notices
    assert isinstance(restart, SmootherRestart) and restart.lost == lost
    assert (restart.poses, restart.old_poses) == (len(new.stamps), len(old.stamps))
    assert taken.taken  # taken all the same
    assert np.array_equal(merger.policy.local_maps["robot2"].stamps, new.stamps)
    assert merger.policy.restarts == {"robot2": 1}
    assert merger.policy.restart_poses_lost == {"robot2": lost}
    assert merger.policy.stats().restarts == {"robot2": 1}


def test_a_map_with_fewer_poses_is_a_restart(run: Run) -> None:
    merger = Merger()
    merger.send(run.late["robot2"])
    (restart,) = merger.restart(run.early["robot2"], 2.0).notices
    assert isinstance(restart, SmootherRestart) and restart.lost > 0
    assert merger.policy.restarts == {"robot2": 1}


# staleness and status


def test_a_robot_without_a_new_map_for_stale_after_is_stale(run: Run) -> None:
    merger = Merger(stale_after=30.0)
    merger.send(run.early["robot1"])
    merger.clock.advance(30.0)
    assert not merger.policy.stale("robot1") and merger.policy.seconds_since_map("robot1") == 30
    merger.clock.advance(0.5)
    assert merger.policy.stale("robot1")
    assert not merger.policy.stale("robot2")  # no map yet: pending, not stale
    merger.send(run.late["robot1"], 2.0)
    assert not merger.policy.stale("robot1")
    never = Merger(stale_after=0.0)
    never.send(run.early["robot1"])
    never.clock.advance(1e6)
    assert not never.policy.stale("robot1")


def test_the_status_says_each_robots_state_and_the_counts(run: Run) -> None:
    merger = Merger(stale_after=5.0)
    merger.send(run.early["robot1"])
    status = merger.policy.status()
    assert [r.alignment for r in status.robots] == [
        "pending: not solved yet",
        "pending: no local map received",
    ]
    assert all(r.health is Health.WARN for r in status.robots)
    assert status.health is Health.OK and status.converged is None and status.reference == ""
    merger.rendezvous("robot2", run.logs["robot2"])
    calibration = np.array([[1.01, 0.65, 0.98], [0.01, 0.02, 0.03]])
    merger.send(replace(run.early["robot2"], odometry_calibration=calibration))
    merger.solve(run.joined)
    merger.clock.advance(6.0)
    merger.drops.add("robot_mismatch", 2)
    status = merger.policy.status()
    robot1, robot2 = status.robots
    assert (robot1.alignment, robot2.alignment) == ("reference", "aligned")
    assert robot1.stale and robot1.health is Health.WARN and robot1.seconds_since_map == 6.0
    assert robot1.message == "reference (stale: no local map for 6 s)"
    assert robot1.poses == len(run.joined.robots["robot1"].stamps) and robot1.update == 1
    assert robot1.solve_seconds == 1.5
    assert robot1.odometry_calibration == ()
    assert robot2.odometry_calibration == tuple(calibration.reshape(-1).tolist())
    assert status.solves == 1 and status.reference == "robot1"
    assert status.features == len(run.joined.features)
    assert status.associations == len(run.joined.associations)
    assert status.dropped == {"robot_mismatch": 2}
    assert status.message == f"1 solves, {status.associations} associations"
    merger.send(run.late["robot1"], 2.0)
    start = merger.policy.start_solve()
    assert start is not None and merger.policy.status().solving
    merger.policy.solve_done(start.inputs, JoinReply(None, "ValueError: no"), 1.0)
    status = merger.policy.status()
    assert status.health is Health.ERROR and status.last_error == "ValueError: no"


# resyncs and robots found


def test_a_robot_none_is_held_of_is_asked_for_its_map_after_a_while(run: Run) -> None:
    merger = Merger()
    assert list(merger.policy.resyncs_wanted()) == [(r, NO_MAP_HELD) for r in ROBOTS]
    assert not merger.policy.resync_due("robot1")
    merger.clock.advance(RESYNC_FIRST_S)
    assert merger.policy.resync_due("robot1")
    merger.policy.resync_asked("robot1")
    merger.clock.advance(RESYNC_TIMEOUT_S - 1.0)
    assert not merger.policy.resync_due("robot1")  # the request stands
    merger.policy.resync_refused("robot1")  # nothing to send yet
    merger.clock.advance(RESYNC_RETRY_S)
    assert merger.policy.resync_due("robot1")
    merger.policy.resync_asked("robot1")
    merger.send(run.early["robot1"])  # a whole map: no request stands
    assert merger.policy.resync_due("robot1")
    assert list(merger.policy.resyncs_wanted()) == [("robot2", NO_MAP_HELD)]
    assert merger.policy.resync_requests == {"robot1": 2}


def test_an_update_that_does_not_apply_asks_for_the_whole_map(run: Run) -> None:
    merger = Merger()
    merger.send(run.early["robot2"])
    merger.policy.start_solve()
    merger.policy.solve_ended()
    sender = UpdateSender(9)
    sender.update(robot_map_arrays(run.early["robot2"]))  # never arrives
    update = sender.update(robot_map_arrays(run.late["robot2"]))
    taken = merger.policy.map_arrived(
        "robot2", arrival("robot2", merger.policy.held["robot2"], update), 2 * S
    )
    assert taken.behind and not taken.taken and not merger.policy.dirty
    assert list(merger.policy.resyncs_wanted()) == [("robot1", NO_MAP_HELD), ("robot2", BEHIND)]
    merger.policy.resync_answered("robot2", True, 9, 1)  # the smoother's session, its answer
    merger.send(run.late["robot2"], 3.0, session=9)  # the whole map, sent again
    assert list(merger.policy.resyncs_wanted()) == [("robot1", NO_MAP_HELD)]


def test_robots_found_are_joined_unless_an_allow_list_leaves_them_out() -> None:
    merger = Merger(robots=ROBOTS)
    assert merger.policy.found("robot1") is None  # subscribed to already
    assert merger.policy.found("robot9") is Found.LEAVE_OUT
    assert merger.policy.found("robot9") is None  # said once
    assert merger.policy.ignored == {"robot9"}
    anyone = MergerPolicy(MergerSettings(), FakeClock(), CONFIG)
    assert anyone.found("robot9") is Found.JOIN


def test_an_unusable_map_is_dropped_once_and_the_last_one_kept(run: Run) -> None:
    merger = Merger()
    merger.send(run.early["robot2"])
    merger.policy.start_solve()
    merger.policy.solve_ended()
    kept, held = merger.policy.local_maps["robot2"], merger.policy.held["robot2"]
    arrays = robot_map_arrays(run.late["robot2"])
    poses = arrays.poses.copy()
    poses[3, 0] = np.nan
    update = merger.senders["robot2"].update(replace(arrays, poses=poses))
    arrived = arrival("robot2", merger.policy.held["robot2"], update)
    taken = merger.policy.map_arrived("robot2", arrived, 2 * S)
    (refusal,) = taken.notices
    assert isinstance(refusal, Refused) and refusal.reason == MALFORMED_LOCAL_MAP
    assert merger.drops.as_dict() == {MALFORMED_LOCAL_MAP: 1}
    assert not taken.taken and not merger.policy.dirty
    assert merger.policy.local_maps["robot2"] is kept
    assert arrived.held is None and merger.policy.held["robot2"] is held  # never stored


def test_a_refused_message_and_dropped_rows_are_counted(run: Run) -> None:
    merger = Merger()
    merger.rendezvous("robot1", run.logs["robot1"])
    none = np.zeros(0)
    empty = RendezvousLog(none, [], none, none, none, none)
    merger.policy.start_solve()
    notices = merger.policy.rendezvous_arrived("robot1", empty, {"unknown_robot": 2})
    assert notices == [RowsDropped("robot1", {"unknown_robot": 2})]
    assert merger.policy.rendezvous["robot1"] is run.logs["robot1"]  # the usable ones stay
    assert merger.drops.as_dict() == {"unknown_robot": 2}


# resuming and going back


def test_a_saved_state_is_taken_up(run: Run) -> None:
    saved = MergerState(
        reference="robot2",
        heard=["robot2", "robot1"],
        robots=["robot2", "robot1", "robot9"],
        maps=dict(run.early),
        map_stamps={"robot1": S, "robot2": S},
        rendezvous=dict(run.logs),
        solves=4,
        dropped={"robot_mismatch": 1},
        restarts={"robot1": 1},
        restart_poses_lost={"robot1": 3},
        result=run.joined,
    )
    merger = Merger(robots=ROBOTS)
    assert merger.policy.take_up(saved) == ["robot2", "robot1"]  # robot9 is not listed
    policy = merger.policy
    assert (policy.reference, policy.heard, policy.solves) == ("robot2", ["robot2", "robot1"], 4)
    assert policy.last_result is run.joined and merger.drops.as_dict() == {"robot_mismatch": 1}
    assert policy.joined_holds({"robot1": S, "robot2": S})  # its joined map goes out at once
    assert policy.provisional_due() is None and policy.stats().restart_poses_lost == {"robot1": 3}
    policy.inputs_changed()
    start = policy.start_solve()
    assert start is not None and start.inputs.order == ("robot2", "robot1")


def test_a_copy_is_a_state_to_go_back_to(run: Run) -> None:
    merger = Merger()
    _all_in(merger, run)
    merger.solve(run.joined)
    saved = merger.policy.copy()
    merger.restart(run.restarted, 2.0)
    merger.policy.resync_asked("robot1")
    assert merger.policy.restarts and saved.restarts == {}
    merger.policy.restore(saved)
    assert merger.policy.local_maps == saved.local_maps and merger.policy.restarts == {}
    assert merger.policy.local_maps["robot2"] is saved.local_maps["robot2"]
    assert len(merger.policy.local_maps["robot2"].stamps) == len(run.early["robot2"].stamps)
    assert merger.policy.last_result is run.joined and not merger.policy.dirty
    assert merger.policy.resync_requests == {} and merger.policy.drops is merger.drops
    assert merger.restart(run.restarted, 2.0, session=3).taken
    assert merger.policy.restarts == {"robot2": 1}  # counted again from the state gone back to
    assert saved.restarts == {}  # the copy stays as it was


# sessions: a robot's held map changes only by an update that applies to it and passes the checks


def _whole(m: RobotMap, session: int, sequence: int = 1) -> MapUpdate:
    """``m`` as whole map ``sequence`` of ``session``."""
    keyed = UpdateSender(session).update(robot_map_arrays(m)).changes
    return MapUpdate(session, sequence, 0, 0, keyed)


def _arrive(merger: Merger, robot: str, update: MapUpdate, answers: bool = True) -> MapTaken:
    arrived = arrival(robot, merger.policy.held.get(robot), update)
    return merger.policy.map_arrived(robot, arrived, 5 * S, answers)


def test_a_whole_map_of_another_session_waits_for_its_smoother_to_name_it(run: Run) -> None:
    """Another publisher's whole map (3 poses, a new session) is set aside, asked about once,
    and dropped when the smoother names the session held; the held map never changed."""
    merger = Merger()
    merger.send(run.late["robot1"])
    held, kept = merger.policy.held["robot1"], merger.policy.local_maps["robot1"]
    foreign = _whole(run.early["robot1"], session=77)
    aside = _arrive(merger, "robot1", foreign)
    assert aside.behind == SESSION_CHECK and not aside.taken and not aside.notices
    assert merger.policy.held["robot1"] is held and merger.policy.local_maps["robot1"] is kept
    assert ("robot1", SESSION_CHECK) in list(merger.policy.resyncs_wanted())
    merger.policy.resync_asked("robot1")
    assert ("robot1", SESSION_CHECK) not in list(merger.policy.resyncs_wanted())
    (dropped,) = merger.policy.resync_answered("robot1", True, 1, 2).notices
    assert isinstance(dropped, Refused) and dropped.reason == FOREIGN_SESSION
    assert merger.drops.as_dict() == {FOREIGN_SESSION: 1}
    assert merger.policy.held["robot1"] is held and merger.policy.local_maps["robot1"] is kept
    # the same session again, soon after: dropped at once, nothing asked
    again = _arrive(merger, "robot1", replace(foreign, sequence=2))
    assert again.behind == "" and [n.reason for n in again.notices] == [FOREIGN_SESSION]
    assert merger.drops.as_dict() == {FOREIGN_SESSION: 2}
    assert merger.policy.local_maps["robot1"] is kept and merger.policy.restarts == {}


def test_a_restarted_smoothers_map_is_taken_in_either_order_of_map_and_answer(run: Run) -> None:
    for answer_first in (False, True):
        merger = Merger()
        merger.send(run.early["robot2"])
        if answer_first:  # asked because its next update did not apply
            merger.policy.resync_answered("robot2", True, 5, 1)
        taken = _arrive(merger, "robot2", _whole(run.restarted, session=5))
        if not answer_first:
            assert not taken.taken
            taken = merger.policy.resync_answered("robot2", True, 5, 1)
        assert taken.taken and merger.policy.held["robot2"].session == 5
        assert merger.policy.restarts == {"robot2": 1} and merger.drops.as_dict() == {}


def test_a_newer_map_of_the_same_restarted_session_replaces_the_one_set_aside(run: Run) -> None:
    """The smoother's resync answer (whole map 2 of its new session) may come before its
    reply: the first whole map set aside is replaced, uncounted, and the answer takes it."""
    merger = Merger()
    merger.send(run.early["robot2"])
    _arrive(merger, "robot2", _whole(run.restarted, session=5))
    _arrive(merger, "robot2", _whole(run.restarted, session=5, sequence=2))
    assert merger.policy.resync_answered("robot2", True, 5, 2).taken
    assert merger.policy.held["robot2"].sequence == 2 and merger.drops.as_dict() == {}
    # a third session's map set aside is replaced by a fourth's: the third is counted
    _arrive(merger, "robot2", _whole(run.early["robot2"], session=6))
    (replaced,) = _arrive(merger, "robot2", _whole(run.early["robot2"], session=8)).notices
    assert replaced.reason == FOREIGN_SESSION and merger.drops.as_dict() == {FOREIGN_SESSION: 1}


def test_a_foreign_map_is_taken_when_the_held_session_is_stale_and_no_smoother_answers(
    run: Run,
) -> None:
    merger = Merger(stale_after=10.0)
    merger.send(run.early["robot2"])
    foreign = _whole(run.restarted, session=5)
    assert not _arrive(merger, "robot2", foreign, answers=False).taken  # not stale yet
    assert not merger.policy.smoother_absent("robot2").taken
    merger.clock.advance(11.0)
    assert merger.policy.smoother_absent("robot2").taken  # the old session is gone
    assert merger.policy.held["robot2"].session == 5
    stale = Merger(stale_after=10.0)
    stale.send(run.early["robot2"])
    stale.clock.advance(11.0)
    assert not _arrive(stale, "robot2", foreign).taken  # its smoother is there to ask
    assert _arrive(stale, "robot2", replace(foreign, sequence=2), answers=False).taken


def test_an_old_whole_map_of_the_session_held_rolls_nothing_back(run: Run) -> None:
    merger = Merger()
    merger.send(run.early["robot2"])
    old = _whole(run.early["robot2"], session=1, sequence=1)
    merger.send(run.late["robot2"], 2.0)  # update 2
    held = merger.policy.held["robot2"]
    assert not _arrive(merger, "robot2", old).taken
    assert merger.policy.held["robot2"] is held
    (dropped,) = merger.policy.resync_answered("robot2", True, 1, 3).notices
    assert dropped.reason == REPLAYED_UPDATE and merger.drops.as_dict() == {REPLAYED_UPDATE: 1}
    assert merger.policy.held["robot2"] is held
    # the smoother's whole map may come before its answer: the replay is counted then
    assert not _arrive(merger, "robot2", old).taken
    taken = _arrive(merger, "robot2", _whole(run.late["robot2"], session=1, sequence=3))
    assert taken.taken and [n.reason for n in taken.notices] == [REPLAYED_UPDATE]
    assert merger.drops.as_dict() == {REPLAYED_UPDATE: 2}
    assert merger.policy.resync_answered("robot2", True, 1, 3) == MapTaken()


def test_an_update_older_than_the_held_one_asks_and_the_answer_is_taken(run: Run) -> None:
    """A whole map of the session held with sequence 2^32-1 is newer, and taken; the real
    updates after it are then older: each is counted and asks the smoother, whose answer
    names the update it sent, which is taken although older."""
    merger = Merger()
    merger.send(run.early["robot2"])
    sender = merger.senders["robot2"]
    assert _arrive(merger, "robot2", _whole(run.early["robot2"], 1, 2**32 - 1)).taken
    real = sender.update(robot_map_arrays(run.late["robot2"]))
    older = _arrive(merger, "robot2", real)
    assert older.behind == OLDER and [n.reason for n in older.notices] == [REPLAYED_UPDATE]
    assert ("robot2", OLDER) in list(merger.policy.resyncs_wanted())
    answer = sender.resend()
    assert answer is not None
    merger.policy.resync_answered("robot2", True, 1, answer.sequence)
    assert _arrive(merger, "robot2", answer).taken
    assert merger.policy.held["robot2"].sequence == answer.sequence
    assert ("robot2", OLDER) not in list(merger.policy.resyncs_wanted())
    assert not _arrive(merger, "robot2", answer).taken  # the answered update, delivered again


@pytest.mark.parametrize("bad", ["unknown kernel", "nan information"])
def test_a_delta_refused_leaves_the_held_map_and_the_next_sequence(run: Run, bad: str) -> None:
    merger = Merger()
    merger.send(run.early["robot2"])
    held = merger.policy.held["robot2"]
    update = UpdateSender(1)
    update.update(robot_map_arrays(run.early["robot2"]))
    good = update.update(robot_map_arrays(run.late["robot2"]))
    c = good.changes
    changes = (
        replace(c, robust_kernel="tukey")
        if bad == "unknown kernel"
        else replace(c, odometry_sqrt_information=np.full_like(c.odometry_sqrt_information, np.nan))
    )
    assert good.base_sequence == held.sequence
    refused = _arrive(merger, "robot2", replace(good, changes=changes))
    assert [n.reason for n in refused.notices] == [MALFORMED_LOCAL_MAP] and not refused.taken
    assert merger.policy.held["robot2"] is held
    assert _arrive(merger, "robot2", good).taken  # the real next update applies
    assert merger.policy.held["robot2"].sequence == good.sequence


# robots found: bounded


def test_at_most_max_robots_are_joined_and_the_others_counted_once() -> None:
    policy = MergerPolicy(MergerSettings(max_robots=2), FakeClock(), CONFIG)
    for robot in ("a1", "a2"):
        assert policy.found(robot) is Found.JOIN
        policy.subscribed(robot)
    assert policy.found("a3") is Found.TOO_MANY and policy.found("a3") is None
    assert policy.drops.as_dict() == {TOO_MANY_ROBOTS: 1}
    listed = MergerPolicy(MergerSettings(robots=("r1", "r2"), max_robots=1), FakeClock(), CONFIG)
    listed.subscribed("r1")
    assert listed.found("r2") is Found.JOIN  # the allow-list's always are
    pattern = MergerPolicy(MergerSettings(robot_pattern="robot[0-9]+"), FakeClock(), CONFIG)
    assert pattern.found("robot12") is Found.JOIN
    assert pattern.found("robot12x") is Found.LEAVE_OUT and pattern.ignored == {"robot12x"}


def test_a_robot_found_that_stays_silent_is_forgotten_and_may_come_back(run: Run) -> None:
    clock = FakeClock()
    policy = MergerPolicy(MergerSettings(max_robots=2, forget_after=60.0), clock, CONFIG)
    for robot in ROBOTS:
        policy.subscribed(robot)
    sender = UpdateSender(1)
    update = sender.update(robot_map_arrays(run.early["robot1"]))
    policy.map_arrived("robot1", arrival("robot1", None, update), S)
    assert policy.found("robot3") is Found.TOO_MANY
    clock.advance(60.5)
    assert policy.forget_silent() == ["robot1", "robot2"]
    assert policy.robots == [] and [r.robot for r in policy.status().robots] == []
    assert "robot1" in policy.local_maps and policy.known_robots() == ("robot1",)
    assert policy.found("robot3") is Found.JOIN  # room was made
    assert policy.found("robot2") is None  # forgotten a moment ago
    clock.advance(60.0)
    assert policy.found("robot2") is Found.JOIN
    listed = MergerPolicy(MergerSettings(robots=ROBOTS, forget_after=1.0), clock, CONFIG)
    listed.subscribed("robot1")
    clock.advance(10.0)
    assert listed.forget_silent() == []  # listed robots are expected: stale, not forgotten
