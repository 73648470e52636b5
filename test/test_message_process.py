"""The message process: the messages a joined map built here would be, a child that died
or failed replaced by a build in the caller's process, then started again. (Serialized bytes
are compared after deserializing: CDR padding bytes are not defined.)"""

from __future__ import annotations

import os
import signal
from typing import Any

import pytest
from csam_msgs.msg import JoinedMap
from rclpy.serialization import deserialize_message, serialize_message
from tf2_msgs.msg import TFMessage
from visualization_msgs.msg import MarkerArray

from csam_ros.core.csam import run_csam
from csam_ros.core.result import CsamResult, MergerStats, RunSummary
from csam_ros.core.simulation import simulate
from csam_ros.datasets.scenario import load_scenario
from csam_ros.message_process import (
    JoinedMapRequest,
    MessageProcess,
    SerializedJoinedMap,
    serialize_joined_map,
)
from csam_ros.ros.conversions import ns_to_time
from csam_ros.ros.map_messages import joined_map_message, robot_map_transforms
from csam_ros.ros.markers import joined_map_markers

STAMP_NS = 40_000_000_000
MARKERS_NS = 41_500_000_000
reported_failures: list[str] = []  # what the processes of these tests reported


@pytest.fixture(scope="module")
def result() -> CsamResult:
    return run_csam(simulate(load_scenario("map_joining"), seed=3))


def _request(result: CsamResult, solved: bool) -> JoinedMapRequest:
    stamps = {name: STAMP_NS - i for i, name in enumerate(result.robots)}
    return JoinedMapRequest(
        result,
        STAMP_NS,
        stamps,
        (*result.robots, "robot9"),  # one robot heard of without a map
        markers_stamp_ns=MARKERS_NS if solved else None,
        summary=RunSummary(result, merger=MergerStats(dropped={}, solves=3)) if solved else None,
    )


def _same(a: SerializedJoinedMap, b: SerializedJoinedMap) -> bool:
    return deserialize_message(a.joined_map, JoinedMap) == deserialize_message(
        b.joined_map, JoinedMap
    )


@pytest.fixture
def messages() -> MessageProcess:
    reported_failures.clear()
    process = MessageProcess(on_failure=reported_failures.append)
    yield process
    process.close()


def _round_trip(message: Any) -> Any:
    return deserialize_message(serialize_message(message), type(message))


def test_the_child_serializes_what_would_be_published_here(
    result: CsamResult, messages: MessageProcess
) -> None:
    request = _request(result, solved=True)
    out = messages.serialize(request)
    assert messages.starts == 1 and messages.failures == 0
    expected = joined_map_message(result, STAMP_NS, request.local_map_stamps, request.robots)
    assert len(expected.trajectories) == 2 and len(expected.base_nodes) == 3
    assert deserialize_message(out.joined_map, JoinedMap) == _round_trip(expected)
    markers = joined_map_markers(result, ns_to_time(MARKERS_NS))
    assert deserialize_message(out.markers, MarkerArray) == _round_trip(markers)
    transforms = robot_map_transforms(result, STAMP_NS)
    assert deserialize_message(out.transforms, TFMessage) == _round_trip(transforms)
    assert out.summary_text == RunSummary(result, merger=MergerStats(dropped={}, solves=3)).text()

    provisional = messages.serialize(_request(result, solved=False))
    assert deserialize_message(provisional.joined_map, JoinedMap) == _round_trip(expected)
    assert provisional.markers is provisional.transforms is provisional.summary_text is None


def test_a_child_that_died_is_replaced_by_a_build_here_then_started_again(
    result: CsamResult, messages: MessageProcess
) -> None:
    request = _request(result, solved=False)
    expected = serialize_joined_map(request)
    messages.start()
    os.kill(messages._process.pid, signal.SIGKILL)
    messages._process.join()
    assert _same(messages.serialize(request), expected)  # the dead child is seen, one started
    assert messages.starts == 2 and messages.failures == 0
    os.kill(messages._process.pid, signal.SIGKILL)
    messages._process.join(timeout=5)
    # a child killed between the liveness check and the request: built here, counted
    messages._process.is_alive = lambda: True  # type: ignore[method-assign]
    assert _same(messages.serialize(request), expected)
    assert messages.failures == 1 and "ended" in messages.last_error
    assert reported_failures == [f"{messages.last_error}: built in this process instead"]
    assert _same(messages.serialize(request), expected)
    assert messages.starts == 3 and messages.failures == 1


def test_a_failed_request_is_built_here_and_reported(
    result: CsamResult, messages: MessageProcess
) -> None:
    robots = tuple(result.robots)
    broken = JoinedMapRequest(result, STAMP_NS, dict.fromkeys(robots, "late"), robots)
    with pytest.raises(Exception) as here:
        serialize_joined_map(broken)
    with pytest.raises(type(here.value)):
        messages.serialize(broken)  # the child's error, then the same one here
    assert messages.failures == 1 and messages.last_error.startswith(type(here.value).__name__)
    assert reported_failures == [f"{messages.last_error}: built in this process instead"]
    request = _request(result, solved=False)
    assert _same(messages.serialize(request), serialize_joined_map(request))  # the same child
    assert messages.starts == 1
    messages.close()
    assert _same(messages.serialize(request), serialize_joined_map(request))  # closed: built here
    assert messages.starts == 1
