"""The message process: the markers and summary a solved joined map's build here would give,
a child that died or failed replaced by a build in the caller's process, then started again.
(Serialized bytes are compared after deserializing: CDR padding bytes are not defined.)"""

from __future__ import annotations

import os
import signal
from typing import Any

import pytest
from rclpy.serialization import deserialize_message, serialize_message
from visualization_msgs.msg import MarkerArray

from csam_ros.core.joining.pipeline import run_csam
from csam_ros.core.joining.result import CsamResult, MergerStats, RunSummary
from csam_ros.datasets.scenario import load_scenario
from csam_ros.datasets.simulation import simulate
from csam_ros.message_process import (
    MarkersAndSummary,
    MarkersRequest,
    MessageProcess,
    build_markers,
)
from csam_ros.ros.conversions import ns_to_time
from csam_ros.ros.markers import joined_map_markers

MARKERS_NS = 41_500_000_000
reported_failures: list[str] = []  # what the processes of these tests reported


@pytest.fixture(scope="module")
def result() -> CsamResult:
    return run_csam(simulate(load_scenario("map_joining"), seed=3))


def _request(result: CsamResult, with_summary: bool = True) -> MarkersRequest:
    summary = RunSummary(result, merger=MergerStats(dropped={}, solves=3))
    return MarkersRequest(result, MARKERS_NS, summary if with_summary else None)


def _same(a: MarkersAndSummary, b: MarkersAndSummary) -> bool:
    markers = [deserialize_message(m.markers, MarkerArray) for m in (a, b)]
    return markers[0] == markers[1] and a.summary_text == b.summary_text


@pytest.fixture
def messages() -> MessageProcess:
    reported_failures.clear()
    process = MessageProcess(on_failure=reported_failures.append)
    yield process
    process.close()


def _round_trip(message: Any) -> Any:
    return deserialize_message(serialize_message(message), type(message))


def test_the_child_builds_what_would_be_published_here(
    result: CsamResult, messages: MessageProcess
) -> None:
    out = messages.build(_request(result))
    assert messages.starts == 1 and messages.failures == 0
    markers = joined_map_markers(result, ns_to_time(MARKERS_NS))
    assert len(markers.markers) > 0
    assert deserialize_message(out.markers, MarkerArray) == _round_trip(markers)
    assert out.summary_text == RunSummary(result, merger=MergerStats(dropped={}, solves=3)).text()
    assert messages.build(_request(result, with_summary=False)).summary_text is None


def test_a_child_that_died_is_replaced_by_a_build_here_then_started_again(
    result: CsamResult, messages: MessageProcess
) -> None:
    request = _request(result)
    expected = build_markers(request)
    messages.start()
    os.kill(messages._process.pid, signal.SIGKILL)
    messages._process.join()
    assert _same(messages.build(request), expected)  # the dead child is seen, one started
    assert messages.starts == 2 and messages.failures == 0
    os.kill(messages._process.pid, signal.SIGKILL)
    messages._process.join(timeout=5)
    # a child killed between the liveness check and the request: built here, counted
    messages._process.is_alive = lambda: True  # type: ignore[method-assign]
    assert _same(messages.build(request), expected)
    assert messages.failures == 1 and "ended" in messages.last_error
    assert reported_failures == [f"{messages.last_error}: built in this process instead"]
    assert _same(messages.build(request), expected)
    assert messages.starts == 3 and messages.failures == 1


def test_a_failed_request_is_built_here_and_reported(
    result: CsamResult, messages: MessageProcess
) -> None:
    broken = MarkersRequest(result, "late")  # type: ignore[arg-type]
    with pytest.raises(Exception) as here:
        build_markers(broken)
    with pytest.raises(type(here.value)):
        messages.build(broken)  # the child's error, then the same one here
    assert messages.failures == 1 and messages.last_error.startswith(type(here.value).__name__)
    assert reported_failures == [f"{messages.last_error}: built in this process instead"]
    request = _request(result)
    assert _same(messages.build(request), build_markers(request))  # the same child
    assert messages.starts == 1
    messages.close()
    assert _same(messages.build(request), build_markers(request))  # closed: built here
    assert messages.starts == 1
