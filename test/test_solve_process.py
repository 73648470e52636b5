"""The solve process: the same replies as a joiner in this process, maps sent only when
changed, a child that died started again, a join cancelled."""

from __future__ import annotations

import multiprocessing
import os
import signal
import threading
import time
from dataclasses import replace

import numpy as np
import pytest
from growing_joins import largest_difference, maps_until

from csam_ros.core.exchange.checkpoint import MergerState
from csam_ros.core.exchange.map_arrays import robot_map_arrays
from csam_ros.core.joining.config import CsamConfig
from csam_ros.core.merging.joiner import JoinCancelled, Joiner, JoinReply, JoinRequest
from csam_ros.datasets.scenario import load_scenario
from csam_ros.datasets.simulation import simulate
from csam_ros.solve_process import CANCEL_SIGNAL, SolveProcess, _Cancellation

CONFIG = CsamConfig(skip_missing_poses=True)


def _requests() -> list[JoinRequest]:
    """Two solves of the map-joining run; the second with robot2's map grown, robot1's the
    same object."""
    log = simulate(load_scenario("map_joining"), 1)
    end = max(r.odometry.stamps.max() for r in log.robots.values())
    requests, sources = [], {}
    for t in (0.6 * end, end):
        maps, logs = maps_until(log, t)
        for m in maps:
            if m.name not in sources or m.name != "robot1":
                sources[m.name] = robot_map_arrays(m)
        requests.append(JoinRequest(tuple(sources.items()), logs, CONFIG))
    return requests


@pytest.fixture
def process() -> SolveProcess:
    solver = SolveProcess()
    yield solver
    solver.close()


def test_replies_equal_a_joiner_here_and_unchanged_maps_are_not_sent(process) -> None:
    first, second = _requests()
    here = Joiner()
    for request, unchanged in ((first, [False, False]), (second, [True, False])):
        assert [source is None for _, source in process.stripped(request).maps] == unchanged
        expected = here.join(request).result
        reply = process.join(request)
        assert reply.error == "" and reply.result is not None and expected is not None
        for name, robot in expected.robots.items():
            np.testing.assert_array_equal(
                reply.result.robots[name].poses_joined, robot.poses_joined
            )
        assert [f.members for f in reply.result.features] == [f.members for f in expected.features]
    assert process.starts == 1
    # the child holds its last result as the warm start; another one is sent
    assert process.stripped(replace(second, previous=reply.result)).previous is None
    assert process.stripped(replace(second, previous=expected)).previous is expected


def test_prepared_maps_are_not_sent_again_and_join_as_sent_with_it(process) -> None:
    first, second = _requests()
    here = Joiner()
    here.join(first)
    expected = here.join(second).result
    assert process.join(first).result is not None
    process.prepare(second.maps)
    assert all(source is None for _, source in process.stripped(second).maps)
    reply = process.join(second)
    assert reply.error == "" and reply.result is not None and expected is not None
    assert largest_difference(reply.result, expected) < 1e-12
    process.close()
    process.prepare(second.maps)  # closed: nothing sent, nothing started
    assert process.starts == 1


def test_the_state_is_written_after_the_reply(process, tmp_path) -> None:
    """A request with the merger's state: the reply says a write follows, state_written
    waits for it; a join not waited for lets the write end first."""
    first, second = _requests()
    order = [robot for robot, _ in first.maps]
    state = MergerState(order[0], order, order, {}, {r: 1 for r in order}, {}, 1, {})
    path = tmp_path / "merger.npz"
    reply = process.join(replace(first, state=state, state_path=path))
    assert reply.result is not None and reply.state_pending
    written = process.state_written()
    assert written is not None and written.error == "" and path.exists()
    assert process.state_written() is None  # waited for once
    saved = MergerState.read(path)
    assert saved.result is not None and largest_difference(saved.result, reply.result) < 1e-12
    again = process.join(replace(second, state=replace(state, solves=2), state_path=path))
    assert again.state_pending
    assert process.join(second).result is not None  # the write ended before it was sent
    assert not process.state_written() and MergerState.read(path).solves == 2


def test_a_child_that_died_is_an_error_then_started_again(process) -> None:
    first, second = _requests()
    assert process.join(first).result is not None
    pid = process.pid
    os.kill(pid, signal.SIGKILL)
    lost = process.join(second)  # lost if it was sent before the death was seen
    assert lost.result is not None or lost.error.startswith("the solve process ended")
    reply = lost if lost.result is not None else process.join(second)
    assert reply.error == "" and reply.result is not None
    assert process.starts == 2 and process.pid != pid


def test_a_cancelled_join_is_a_reply_saying_so_and_the_next_as_without_it(process) -> None:
    """Cancelled while its request waits for the child (stopped), the join is given up as
    it begins; the child keeps the maps and warm start, and the next join of the same
    request equals a joiner's here that never saw the cancelled one."""
    first, second = _requests()
    here = Joiner()
    here.join(first)
    expected = here.join(second).result
    assert process.join(first).result is not None
    pid = process.pid
    replies: list[JoinReply] = []
    os.kill(pid, signal.SIGSTOP)
    try:
        worker = threading.Thread(target=lambda: replies.append(process.join(second)))
        worker.start()
        deadline = time.monotonic() + 20
        while not process.cancel():  # the join is under way from the parent's side
            assert time.monotonic() < deadline
            time.sleep(0.01)
    finally:
        os.kill(pid, signal.SIGCONT)
    worker.join(60)
    assert replies[0].cancelled and replies[0].result is None
    assert process.stripped(second).maps == tuple((r, None) for r, _ in second.maps)
    reply = process.join(second)
    assert not reply.cancelled and reply.result is not None and expected is not None
    assert largest_difference(reply.result, expected) < 1e-12
    assert not process.cancel()  # no join under way
    assert process.starts == 1 and process.pid == pid


def test_the_cancel_signal_raises_only_inside_the_join_it_names() -> None:
    """In the child, the signal gives a join up wherever it computes, and only the request
    it names; outside a join it does nothing."""
    cancelled = multiprocessing.Value("q", 0, lock=False)
    previous = signal.getsignal(CANCEL_SIGNAL)
    try:
        cancellation = _Cancellation(cancelled)
        cancellation.request = 1
        os.kill(os.getpid(), CANCEL_SIGNAL)  # named none: nothing
        cancelled.value = 1
        os.kill(os.getpid(), CANCEL_SIGNAL)  # outside a join: nothing
        with pytest.raises(JoinCancelled), cancellation.cancellable():
            pass  # the request named on entry
        cancellation.request = 2
        with cancellation.cancellable():
            os.kill(os.getpid(), CANCEL_SIGNAL)  # another request named: nothing
            time.sleep(0.05)
        cancelled.value = 2
        with pytest.raises(JoinCancelled), cancellation.cancellable():
            os.kill(os.getpid(), CANCEL_SIGNAL)
            time.sleep(5)  # the handler raises here, as soon as the signal comes
        assert not cancellation.armed
    finally:
        signal.signal(CANCEL_SIGNAL, previous)


def test_the_child_runs_at_the_niceness_asked() -> None:
    process = SolveProcess(niceness=7)
    try:
        assert process.join(JoinRequest((), {}, CONFIG)).error  # the child is serving
        mine = os.getpriority(os.PRIO_PROCESS, 0)
        assert os.getpriority(os.PRIO_PROCESS, process.pid) == min(mine + 7, 19)
    finally:
        process.close()
