"""Parameters at start and while the nodes run: a node started with ``--params-file`` answers
with the file's values; a parameter set while it runs (the SetParameters service, as ``ros2
param set`` calls it) is applied when the node can apply it live, else refused with the
reason; a parameter given that the node has none of is refused in one logged line, counted."""

from __future__ import annotations

import signal
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from parameter_services import Parameters, client_node
from rclpy.executors import SingleThreadedExecutor
from rclpy.time import Time
from waiting import wait_until

from csam_ros.nodes.common import START_ONLY, UNKNOWN_PARAMETER
from csam_ros.ros.merger_reports import status_array
from csam_ros.run.params_files import CONFIG_DIR

TEAM = CONFIG_DIR / "team.params.yaml"


@pytest.fixture
def client(ros_context: Any) -> Iterator[tuple[Any, SingleThreadedExecutor]]:
    with client_node(ros_context) as made:
        yield made


def test_nodes_started_with_the_team_file_answer_with_its_values_and_apply_or_refuse_sets(
    nodes: Any, client: tuple[Any, SingleThreadedExecutor]
) -> None:
    """A smoother and the merger as processes, as on a real team's computers."""
    smoother = nodes.start("smoother", "--ros-args", "-r", "__ns:=/robot1", "--params-file", TEAM)
    # provisional maps off at start: turning them on needs a restart
    merger = nodes.start(
        "merger", "--ros-args", "--params-file", TEAM, "-p", "provisional_period:=0.0"
    )
    at_smoother = Parameters(*client, "/robot1/smoother")
    at_merger = Parameters(*client, "/merger")

    assert at_smoother.get("robot", "robots", "publish_period", "use_sim_time") == [
        "robot1",
        ["robot1", "robot2"],
        1.0,
        False,
    ]
    assert at_merger.get("robots", "solve_period", "chi2_gate", "provisional_period") == [
        ["robot1", "robot2"],
        0.5,
        9.21,
        0.0,
    ]

    assert at_merger.set("solve_period", 2.0).successful
    assert at_merger.set("stale_after", 10.0).successful
    refused = at_merger.set("chi2_gate", 30.0)
    assert not refused.successful
    assert refused.reason.startswith(f"chi2_gate {START_ONLY}"), refused.reason
    assert "solve_period" in refused.reason  # what can be set instead
    refused = at_merger.set("provisional_period", 1.0)
    assert not refused.successful and "off at start" in refused.reason, refused.reason
    assert at_merger.get("solve_period", "stale_after", "chi2_gate", "provisional_period") == [
        2.0,
        10.0,
        9.21,
        0.0,
    ]

    assert at_smoother.set("publish_period", 2.5).successful
    refused = at_smoother.set("robust_kernel", "cauchy")
    assert not refused.successful
    assert refused.reason.startswith(f"robust_kernel {START_ONLY}"), refused.reason
    refused = at_smoother.set("publish_period", 0.0)
    assert not refused.successful and "greater than 0" in refused.reason, refused.reason
    assert at_smoother.get("publish_period", "robust_kernel") == [2.5, ""]

    for process in (smoother, merger):
        assert nodes.stop(process, signal.SIGINT) == 0, nodes.output(process)
    for process in (smoother, merger):
        assert "unknown parameter" not in nodes.output(process)


def test_a_parameter_set_at_run_time_takes_effect_in_the_node(
    ros_context: Any, client: tuple[Any, SingleThreadedExecutor]
) -> None:
    """In-process nodes, set through their services: the merger's settings and timers, the
    smoother's publish timer."""
    from csam_ros.nodes.merger import Merger
    from csam_ros.nodes.smoother import Smoother

    node, executor = client
    smoother = Smoother(context=ros_context, namespace="robot1")
    merger = Merger(context=ros_context)
    try:
        executor.add_node(smoother)
        executor.add_node(merger)
        at_smoother = Parameters(node, executor, "/robot1/smoother")
        at_merger = Parameters(node, executor, "/merger")

        assert at_smoother.set("publish_period", 0.25).successful
        assert smoother.publish_period == 0.25
        assert smoother.publish_timer.timer_period_ns == 250_000_000

        for name, value in [
            ("solve_period", 3.0),
            ("stale_after", 7.0),
            ("reference_wait", 0.0),
            ("provisional_period", 4.0),
            ("provisional_quiet", 2.0),
        ]:
            assert at_merger.set(name, value).successful, name
            assert getattr(merger.policy.settings, name) == value, name
        settings = merger.policy.settings
        assert merger._solve_timer.timer_period_ns == 3_000_000_000
        assert merger._provisional_timer.timer_period_ns == round(
            settings.provisional_check_period * 1e9
        )
        assert merger.policy.stale("robot1", 0.0) is False  # none heard
        merger.policy.map_arrival["robot1"] = 0.0
        assert merger.policy.stale("robot1", 7.5) and not merger.policy.stale("robot1", 6.5)

        before = merger.config
        refused = at_merger.set("warm_start", True)
        assert not refused.successful and START_ONLY in refused.reason
        assert merger.config == before
        refused = at_merger.set("use_sim_time", True)
        assert not refused.successful and START_ONLY in refused.reason
        assert not merger.get_parameter("use_sim_time").value
    finally:
        for made in (smoother, merger):
            executor.remove_node(made)
            made.destroy_node()


def _params_file(path: Path, sections: dict[str, dict[str, Any]]) -> Path:
    import yaml

    path.write_text(
        yaml.safe_dump({key: {"ros__parameters": values} for key, values in sections.items()})
    )
    return path


def test_unknown_parameters_given_are_refused_and_counted(tmp_path: Path) -> None:
    """Known ones are taken, unknown ones counted under unknown_parameter (and /csam/status)."""
    import rclpy
    from rclpy.context import Context

    from csam_ros.nodes.merger import Merger
    from csam_ros.nodes.smoother import Smoother

    path = _params_file(
        tmp_path / "bad.params.yaml",
        {
            "/**/smoother": {"publish_perod": 2.0, "publish_period": 3.0},
            "merger": {"solve_periode": 1.0, "chi2_gate": 30.0, "gate": 1.0},
        },
    )
    context = Context()
    rclpy.init(args=["csam", "--ros-args", "--params-file", str(path)], context=context)
    made = []
    try:
        made.append(Smoother(context=context, namespace="robot1"))
        made.append(Merger(context=context))
        smoother, merger = made
        assert smoother.publish_period == 3.0 and merger.config.chi2_gate == 30.0
        assert smoother.drops.as_dict() == {UNKNOWN_PARAMETER: 1}
        assert merger.drops.as_dict() == {UNKNOWN_PARAMETER: 2}
        (merger_status,) = [
            s
            for s in status_array(merger.policy.status(), Time().to_msg()).status
            if s.name == "merger"
        ]
        status = {kv.key: kv.value for kv in merger_status.values}
        assert status[f"dropped/{UNKNOWN_PARAMETER}"] == "2", status
    finally:
        for node in made:
            node.destroy_node()
        rclpy.try_shutdown(context=context)


def test_an_unknown_parameter_is_one_logged_line_naming_it(nodes: Any, tmp_path: Path) -> None:
    path = _params_file(tmp_path / "bad.params.yaml", {"/**/smoother": {"publish_perod": 2.0}})
    smoother = nodes.start("smoother", "--ros-args", "-r", "__ns:=/robot1", "--params-file", path)

    def said() -> list[str]:
        text = "".join(
            Path(p).read_text(errors="replace")
            for p in (smoother.stdout_path, smoother.stderr_path)
        )
        return [line for line in text.splitlines() if "unknown parameter" in line]

    assert wait_until(lambda: said() or smoother.poll() is not None, 60.0)
    assert nodes.stop(smoother, signal.SIGINT) == 0, nodes.output(smoother)
    lines = said()
    assert len(lines) == 1, lines
    assert "publish_perod (did you mean publish_period?)" in lines[0]
    assert "/robot1/smoother" in lines[0]
