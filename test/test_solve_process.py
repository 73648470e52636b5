"""The solve process: the same replies as a joiner in this process, maps sent only when
changed, and a child that died started again."""

from __future__ import annotations

import os
import signal
from dataclasses import replace

import numpy as np
import pytest
from growing_joins import maps_until

from csam_ros.core.csam import CsamConfig
from csam_ros.core.joiner import Joiner, JoinRequest
from csam_ros.core.map_arrays import robot_map_arrays
from csam_ros.core.simulation import simulate
from csam_ros.datasets.scenario import load_scenario
from csam_ros.solve_process import SolveProcess

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
