"""The simulator of one robot's host: the same scenario and seed, only that robot's topics,
and /clock from one simulator of the run."""

from __future__ import annotations

import pytest
from rclpy.parameter import Parameter

SCENARIO = "map_joining"


def _simulator(context, **params):
    from csam_ros.nodes.simulator import Simulator

    overrides = [Parameter("scenario", value=SCENARIO), Parameter("seed", value=3)]
    overrides += [Parameter(k, value=v) for k, v in params.items()]
    return Simulator(context=context, parameter_overrides=overrides)


def _messages(simulator) -> list[tuple[int, str, object]]:
    return [(m.stamp_ns, m.topic, m.message) for m in simulator.messages]


def _by_key(messages: list[tuple[int, str, object]]) -> dict[tuple[int, str], object]:
    keyed = {(stamp, topic): message for stamp, topic, message in messages}
    assert len(keyed) == len(messages)  # one message per topic and stamp
    return keyed


def test_simulators_per_robot_emit_the_single_simulators_messages(ros_context) -> None:
    every = _simulator(ros_context)
    first = _simulator(ros_context, emit_robots=["robot1"])
    second = _simulator(ros_context, emit_robots=["robot2"], publish_clock=False)
    try:
        assert every.robots == ["robot1", "robot2"]
        assert first.robots == ["robot1"] and second.robots == ["robot2"]
        topics = {t for _, t, _ in _messages(second)}
        assert topics and all(t.startswith("/robot2/") for t in topics)
        assert {t for _, t, _ in _messages(first)} >= {"/sim/features_truth", "/robot1/odom"}
        assert all(not t.startswith("/robot2/") for _, t, _ in _messages(first))
        # together they publish exactly what one simulator of every robot publishes
        assert _by_key(_messages(first) + _messages(second)) == _by_key(_messages(every))
        assert first.clock is not None and second.clock is None
    finally:
        for s in (every, first, second):
            s.destroy_node()


def test_an_unknown_robot_to_emit_is_refused(ros_context) -> None:
    with pytest.raises(ValueError, match="emit_robots: \\['robot9'\\] not in scenario"):
        _simulator(ros_context, emit_robots=["robot9"])
