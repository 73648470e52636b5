"""All nodes in one process on one executor: simulator, one smoother per robot, merger.

The joined map the merger publishes must equal the core's C-SAM result on the same
measurements (within the online tolerance), bad input at the node boundary must be dropped and
counted in /csam/status without changing the result, and a separate process must receive the
transient-local joined map and markers after they were published.
"""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
from node_group import simulation_taken, simulator_node, smoothers_and_merger
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter

from csam_ros.core.joining.pipeline import run_csam
from csam_ros.core.joining.result import CsamResult, MergerStats, RunSummary
from csam_ros.datasets.scenario import load_scenario
from csam_ros.datasets.simulation import simulate

SCENARIO = "map_joining"
SEED = 4


def _nodes(
    context,
    robots: list[str],
    extra_smoother: list[Parameter] | None = None,
    summary_path: Path | None = None,
):

    smoothers, merger = smoothers_and_merger(context, robots, extra_smoother, summary_path)
    simulator = simulator_node(context, SCENARIO, SEED, Parameter("min_subscribers", value=1))
    return simulator, smoothers, merger


def _run_to_the_end(executor, spin, simulator, smoothers, merger) -> CsamResult:
    assert spin(executor, lambda: simulation_taken(simulator, smoothers), 60)
    # let reliable messages in flight arrive, then flush every smoother like `csam demo` does
    spin(executor, lambda: False, 1.0)
    for s in smoothers.values():
        s.solve_and_publish(converge=True)
    final = {r: s.published_ns for r, s in smoothers.items()}

    def merged_final() -> bool:
        result = merger.policy.last_result
        if result is None:
            return False
        return all(
            r in result.robots and len(result.robots[r].stamps) == len(s.map.stamps)
            for r, s in smoothers.items()
        ) and set(merger.policy.local_maps) == set(final)

    assert spin(executor, merged_final, 60)
    spin(executor, lambda: False, 0.3)
    assert merger.policy.last_result is not None
    return merger.policy.last_result


@pytest.fixture(scope="module")
def core_result() -> CsamResult:
    return run_csam(simulate(load_scenario(SCENARIO), seed=SEED))


def test_nodes_in_one_process_give_the_core_result(
    ros_context, spin, core_result, tmp_path
) -> None:
    robots = [r.name for r in load_scenario(SCENARIO).robots]
    summary_path = tmp_path / "summary.json"
    simulator, smoothers, merger = _nodes(ros_context, robots, summary_path=summary_path)
    executor = SingleThreadedExecutor(context=ros_context)
    for n in (simulator, merger, *smoothers.values()):
        executor.add_node(n)
    try:
        result = _run_to_the_end(executor, spin, simulator, smoothers, merger)

        def summary_written() -> bool:  # by the message process, after the result is out
            if not summary_path.exists():
                return False
            written = RunSummary.read(summary_path)  # the merger's last solve
            return written.to_dict() == RunSummary(result, merger=written.merger).to_dict()

        assert spin(executor, summary_written, 30)
        written = RunSummary.read(summary_path)
        assert written.merger == MergerStats(merger.drops.as_dict(), merger.policy.solves)
        assert written.merger.solves >= 1
        for name, expected in core_result.robots.items():
            got = result.robots[name]
            assert got.alignment == expected.alignment
            np.testing.assert_allclose(got.stamps, expected.stamps, atol=1e-9)
            np.testing.assert_allclose(got.poses_local, expected.poses_local, atol=1e-6)
            np.testing.assert_allclose(got.poses_joined, expected.poses_joined, atol=1e-6)
            np.testing.assert_allclose(
                got.sigma_phi_joined, expected.sigma_phi_joined, rtol=1e-5, atol=1e-9
            )
        pairs = {(a.a, a.b) for a in result.associations}
        assert pairs == {(a.a, a.b) for a in core_result.associations}
        assert len(pairs) > 0

        # a separate process receives the latched joined map and markers after the fact
        script = textwrap.dedent(
            """
            import sys, time, rclpy
            from csam_msgs.msg import JoinedMap
            from visualization_msgs.msg import MarkerArray
            from csam_ros.ros.topics import LATCHED
            rclpy.init()
            node = rclpy.create_node("late_listener")
            got = {}
            node.create_subscription(JoinedMap, "/csam/joined_map",
                                     lambda m: got.__setitem__("map", len(m.features)), LATCHED)
            node.create_subscription(MarkerArray, "/csam/markers",
                                     lambda m: got.__setitem__("markers", len(m.markers)), LATCHED)
            deadline = time.monotonic() + 20
            while len(got) < 2 and time.monotonic() < deadline:
                rclpy.spin_once(node, timeout_sec=0.1)
            print(got)
            sys.exit(0 if len(got) == 2 and got["map"] > 0 and got["markers"] > 1 else 1)
            """
        )
        listener = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE)
        assert spin(executor, lambda: listener.poll() is not None, 40)
        assert listener.returncode == 0, listener.stdout.read()
    finally:
        for n in (simulator, merger, *smoothers.values()):
            n.destroy_node()
        executor.shutdown()


def test_bad_input_is_dropped_counted_and_changes_nothing(ros_context, spin, core_result) -> None:
    from csam_msgs.msg import (
        FeatureObservation,
        FeatureObservations,
        RendezvousObservation,
        RendezvousObservations,
    )
    from diagnostic_msgs.msg import DiagnosticArray

    from csam_ros.ros.conversions import ns_to_time
    from csam_ros.ros.topics import RELIABLE

    robots = [r.name for r in load_scenario(SCENARIO).robots]
    simulator, smoothers, merger = _nodes(
        ros_context, robots, [Parameter("field_of_view_deg", value=240.0)]
    )
    injector = ros_context and __import__("rclpy").create_node("injector", context=ros_context)
    status: dict[str, dict[str, str]] = {}

    def on_status(msg: DiagnosticArray) -> None:
        for s in msg.status:
            status[s.name] = {kv.key: kv.value for kv in s.values}

    injector.create_subscription(DiagnosticArray, "/csam/status", on_status, 50)
    features = injector.create_publisher(FeatureObservations, "/robot1/features", RELIABLE)
    rendezvous = injector.create_publisher(RendezvousObservations, "/robot1/rendezvous", RELIABLE)
    executor = SingleThreadedExecutor(context=ros_context)
    for n in (simulator, merger, injector, *smoothers.values()):
        executor.add_node(n)

    def scan(stamp_ns: int, **fields) -> FeatureObservations:
        msg = FeatureObservations()
        msg.header.stamp = ns_to_time(stamp_ns)
        values = {
            "label": 999_999,
            "range": 1.0,
            "bearing": 0.1,
            "sigma_range": 0.01,
            "sigma_bearing": 0.012,
            **fields,
        }
        msg.observations = [FeatureObservation(**values)]
        return msg

    try:
        assert spin(executor, lambda: features.get_subscription_count() > 0, 10)
        late = 10**15  # far in the future: accepted stamps would break the result if used
        bad = [
            scan(late, range=float("nan")),
            scan(late + 1, range=-1.0),
            scan(late + 2, bearing=3.0),  # outside +-120 degrees
            FeatureObservations(),  # empty
        ]
        for msg in bad:
            features.publish(msg)
        spin(executor, lambda: False, 0.5)
        wrong_robot = RendezvousObservations()
        wrong_robot.header.stamp = ns_to_time(late + 3)
        wrong_robot.observations = [
            RendezvousObservation(
                observed_robot="robot9",
                range=1.0,
                bearing=0.0,
                sigma_range=0.01,
                sigma_bearing=0.01,
            )
        ]
        rendezvous.publish(wrong_robot)
        spin(executor, lambda: False, 0.5)
        result = _run_to_the_end(executor, spin, simulator, smoothers, merger)
        # stamps going backwards and duplicates: replay the first scan after the run
        first = simulator.messages[[m.topic for m in simulator.messages].index("/robot1/features")]
        features.publish(first.message)
        features.publish(first.message)
        last = [m for m in simulator.messages if m.topic == "/robot1/features"][-1]
        features.publish(last.message)  # the same stamp again: a duplicate
        spin(executor, lambda: False, 0.5)
        smoothers["robot1"].publish_status()
        assert spin(
            executor, lambda: "dropped/stamp_backwards" in status.get("smoother/robot1", {}), 10
        )
        counts = status["smoother/robot1"]
        assert counts["dropped/not_finite"] == "1"
        assert counts["dropped/non_positive_range"] == "1"
        assert counts["dropped/outside_field_of_view"] == "1"
        assert counts["dropped/empty"] == "1"
        assert counts["dropped/unknown_robot"] == "1"
        assert int(counts["dropped/stamp_backwards"]) == 2  # the repeated scan twice
        assert counts["dropped/duplicate"] == "1"
        for name, expected in core_result.robots.items():
            np.testing.assert_allclose(
                result.robots[name].poses_joined, expected.poses_joined, atol=1e-6
            )
    finally:
        for n in (simulator, merger, injector, *smoothers.values()):
            n.destroy_node()
        executor.shutdown()
