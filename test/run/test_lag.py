"""Lag from a local map to the joined map that includes it, and the merger's solve times:
closed-form cases on plain arrays, a small hand-written bag and a recorded live run (what a
live replay prints: test_cli)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from csam_ros.run import lag
from csam_ros.run.lag import (
    NOT_USED,
    LagStats,
    SolveStats,
    lag_stats,
    lags_over_run,
    map_lags,
    read_timeline,
)

REPO = Path(__file__).resolve().parents[2]
SECOND = 1_000_000_000


def test_each_map_waits_for_the_first_later_joined_map_that_uses_it_or_a_newer_one() -> None:
    # maps of stamps 10, 20, 30 arrive at 0, 1, 2; joined maps at 0.5 (used 10), 2.5 (used 30):
    # the map of stamp 20 was superseded before any solve and counts until 2.5
    lags = map_lags([0.0, 1.0, 2.0], [10.0, 20.0, 30.0], [0.5, 2.5], [10.0, 30.0])
    np.testing.assert_allclose(lags, [0.5, 1.5, 0.5])
    stats = lag_stats(
        {"r1": [0.0, 1.0, 2.0]}, {"r1": [10.0, 20.0, 30.0]}, [0.5, 2.5], {"r1": [10.0, 30.0]}
    )
    assert stats.count == 3 and stats.never_included == 0
    assert stats.mean == pytest.approx(2.5 / 3)
    assert stats.max == pytest.approx(1.5)
    assert stats.p95 == pytest.approx(0.5 + 0.9 * 1.0)  # sorted 0.5, 0.5, 1.5 at 0.95 * 2


def test_a_map_no_later_joined_map_uses_is_never_included() -> None:
    # stamp 40 is never used; the map at 3.0 arrives after the last joined map
    lags = map_lags([0.0, 1.0, 3.0], [10.0, 40.0, 10.0], [2.0], [30.0])
    np.testing.assert_allclose(lags, [2.0, np.nan, np.nan])
    stats = LagStats.of(lags)
    assert (stats.count, stats.never_included) == (1, 2)
    assert stats.mean == stats.p95 == stats.max == 2.0


def test_joined_maps_before_the_arrival_do_not_count() -> None:
    # a map republished with the stamp the joined map at 1.0 already used waits for the next
    lags = map_lags([0.0, 1.5], [5.0, 5.0], [1.0, 4.0], [5.0, 5.0])
    np.testing.assert_allclose(lags, [1.0, 2.5])
    # a joined map logged at the arrival itself counts (lag 0)
    np.testing.assert_allclose(map_lags([2.0], [5.0], [2.0], [5.0]), [0.0])


def test_joined_maps_without_the_robot_and_unsorted_times() -> None:
    # the joined map at 1.0 holds no map of this robot; the times come unsorted
    lags = map_lags([0.0, 0.5], [1.0, 2.0], [3.0, 1.0, 2.0], [2.0, NOT_USED, 1.0])
    np.testing.assert_allclose(lags, [2.0, 2.5])
    # a robot absent from used_stamps is in no joined map; lags pool over robots
    stats = lag_stats(
        {"a": [0.0], "b": [0.0, 1.0]}, {"a": [1.0], "b": [1.0, 2.0]}, [2.0], {"b": [2.0]}
    )
    assert (stats.count, stats.never_included) == (2, 1)
    assert stats.mean == pytest.approx(1.5) and stats.max == pytest.approx(2.0)


def test_no_joined_map_or_no_local_map() -> None:
    assert np.isnan(map_lags([0.0, 1.0], [1.0, 2.0], [], [])).all()
    empty = lag_stats({}, {}, [1.0], {})
    assert (empty.count, empty.never_included) == (0, 0) and np.isnan(empty.mean)
    with pytest.raises(ValueError):
        map_lags([0.0, 1.0], [1.0], [], [])


def test_chunked_comparison_matches_a_plain_loop(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(lag, "_CHUNK", 7)  # a few maps per chunk
    rng = np.random.default_rng(3)
    arrivals, stamps = rng.uniform(0, 10, 50), rng.uniform(0, 10, 50)
    times, used = rng.uniform(0, 10, 12), rng.uniform(0, 10, 12)
    expected = [
        min((t - a for t, u in zip(times, used, strict=True) if t >= a and u >= s), default=np.nan)
        for a, s in zip(arrivals, stamps, strict=True)
    ]
    np.testing.assert_allclose(map_lags(arrivals, stamps, times, used), expected)


def test_printouts() -> None:
    stats = LagStats(count=420, mean=0.8, p95=1.9, max=3.1, never_included=0)
    assert str(stats) == (
        "lag from a local map to the joined map that uses it: mean 0.80 s, p95 1.90 s, "
        "max 3.10 s (420 local maps)"
    )
    assert str(LagStats(4, 1.0, 1.0, 1.0, 2)).endswith("(4 local maps, 2 never included)")
    assert "no local map included (3 local maps)" in str(LagStats.of([np.nan] * 3))
    solves = SolveStats.of(5, [0.1, 0.3])
    assert (solves.seen, solves.mean, solves.max) == (2, pytest.approx(0.2), 0.3)
    assert str(solves) == (
        "merger: 5 solves, solve time mean 0.200 s, max 0.300 s (2 of them in /csam/status)"
    )
    assert str(SolveStats.of(0, [])) == "merger: 0 solves (no solve time in /csam/status)"


def test_lags_over_the_run_in_equal_spans() -> None:
    # maps at 0..9 s with lags growing 0.1 s per second, one never included; solves at 1 and 8
    arrivals = np.arange(10.0)
    lags = 0.5 + 0.1 * arrivals
    lags[3] = np.nan
    parts = lags_over_run(arrivals, lags, 3, solve_times=[1.0, 8.0], solve_seconds=[0.2, 0.6])
    assert [(p.start, p.end) for p in parts] == [(0.0, 3.0), (3.0, 6.0), (6.0, 9.0)]
    assert [p.lags.count + p.lags.never_included for p in parts] == [3, 3, 4]  # 9.0 in the last
    assert parts[1].lags.never_included == 1 and parts[1].lags.mean == pytest.approx(0.95)
    assert parts[2].lags.max == pytest.approx(1.4) and parts[0].lags.mean == pytest.approx(0.6)
    assert [p.solves.seen for p in parts] == [1, 0, 1]
    assert parts[2].solves.mean == pytest.approx(0.6)
    assert str(parts[0]) == (
        "      0 -      3 s     1 solves of  0.20 s      3 maps, lag mean  0.60 s, "
        "p95  0.69 s, max  0.70 s"
    )
    assert "no solve" in str(parts[1])
    assert str(lags_over_run([2.0], [np.nan], 1)[0]).endswith("1 maps, none included")
    assert lags_over_run([], [], 4) == []
    with pytest.raises(ValueError):
        lags_over_run([1.0], [1.0], 0)
    with pytest.raises(ValueError):
        lags_over_run([1.0], [1.0], 2, solve_times=[1.0])


def _write_run_bag(path: Path) -> None:
    """Local map updates of two robots, joined maps and merger status at known log times."""
    from csam_msgs.msg import BaseNode, JoinedMap, LocalMapUpdate
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

    from csam_ros.bag import BagWriter, msgtype_of
    from csam_ros.ros.conversions import ns_to_time
    from csam_ros.ros.topics import qos_of

    def local_map(robot: str, stamp_s: float) -> LocalMapUpdate:
        m = LocalMapUpdate(robot=robot)
        m.header.stamp = ns_to_time(int(stamp_s * SECOND))
        return m

    def joined(used: dict[str, float]) -> JoinedMap:
        nodes = [
            BaseNode(robot=r, alignment="aligned", local_map_stamp=ns_to_time(int(s * SECOND)))
            for r, s in used.items()
        ]
        nodes.append(BaseNode(robot="robot3", alignment="pending: no local map yet"))
        return JoinedMap(base_nodes=nodes)

    def status(solves: int, seconds: float) -> DiagnosticArray:
        values = [
            KeyValue(key="solves", value=str(solves)),
            KeyValue(key="solve_seconds", value=str(seconds)),
        ]
        smoother = DiagnosticStatus(name="smoother/robot1", values=values[1:])
        return DiagnosticArray(status=[smoother, DiagnosticStatus(name="merger", values=values)])

    t0 = 1_700_000_000 * SECOND
    messages = [
        (0.0, "/robot1/local_map_updates", local_map("robot1", 1.0)),
        (0.2, "/robot2/local_map_updates", local_map("robot2", 1.0)),
        (0.5, "/csam/status", status(0, 0.0)),
        (1.0, "/robot1/local_map_updates", local_map("robot1", 2.0)),
        (1.4, "/csam/joined_map", joined({"robot1": 2.0, "robot2": 1.0})),
        (1.5, "/csam/status", status(1, 0.25)),
        (2.0, "/robot2/local_map_updates", local_map("robot2", 3.0)),  # never joined
        (2.2, "/csam/joined_map/provisional", joined({"robot1": 2.0, "robot2": 3.0})),
        (2.5, "/csam/status", status(3, 0.75)),  # two solves, one time
    ]
    with BagWriter(path) as bag:
        for seconds, topic, message in messages:
            if topic not in bag.topics:
                bag.add_topic(topic, msgtype_of(message), qos_of(topic))
            bag.write(topic, t0 + int(seconds * SECOND), message)


def test_read_timeline_of_a_small_bag(tmp_path: Path) -> None:
    _write_run_bag(tmp_path / "bag")
    timeline = read_timeline(tmp_path / "bag")
    assert sorted(timeline.map_arrivals) == ["robot1", "robot2"]
    np.testing.assert_allclose(timeline.map_arrivals["robot1"], [0.0, 1.0])
    np.testing.assert_allclose(timeline.map_stamps["robot2"], [1.0, 3.0])
    np.testing.assert_allclose(timeline.joined_times, [1.4])
    np.testing.assert_allclose(timeline.used_stamps["robot2"], [1.0])
    stats = timeline.lag_stats()
    assert (stats.count, stats.never_included) == (3, 1)
    assert stats.max == pytest.approx(1.4) and stats.mean == pytest.approx((1.4 + 0.4 + 1.2) / 3)
    solves = timeline.solve_stats()
    assert (solves.solves, solves.seen) == (3, 2)
    assert solves.max == pytest.approx(0.75)
    assert timeline.solve_stats(solves=4).solves == 4  # the merger's own count, where known
    np.testing.assert_allclose(timeline.solve_times, [1.5, 2.5])
    arrivals, lags = timeline.map_lags()
    np.testing.assert_allclose(arrivals, [0.0, 0.2, 1.0, 2.0])
    np.testing.assert_allclose(lags, [1.4, 1.2, 0.4, np.nan])
    (whole,) = timeline.lags_over_run(1)
    assert (whole.lags.count, whole.lags.never_included) == (3, 1)
    assert whole.lags.mean == pytest.approx(stats.mean) and whole.lags.max == stats.max
    assert (whole.solves.seen, whole.solves.max) == (2, 0.75)
    np.testing.assert_allclose(timeline.provisional_times, [2.2])
    provisional = timeline.provisional_lag_stats()
    assert provisional is not None and (provisional.count, provisional.never_included) == (4, 0)
    assert provisional.mean == pytest.approx((1.4 + 1.2 + 0.4 + 0.2) / 4)
    assert str(provisional).startswith(
        "lag from a local map to the first joined or provisional map that uses it: mean 0.80 s"
    )


def test_read_timeline_of_a_recorded_live_run() -> None:
    """bags/map_joining is a recorded `csam demo --rate 8`: 26 local map updates per robot,
    10 solves, provisional maps between them."""
    timeline = read_timeline(REPO / "bags" / "map_joining")
    stats = timeline.lag_stats()
    assert stats.count + stats.never_included == 52
    assert stats.count >= 48  # at most the maps published after the last solve are left
    assert 0.0 <= stats.mean <= stats.p95 <= stats.max
    assert len(timeline.joined_times) == 10
    provisional = timeline.provisional_lag_stats()
    assert provisional is not None and provisional.count == stats.count
    assert provisional.mean <= stats.mean  # a provisional map comes first, or the solved one
    solves = timeline.solve_stats()
    assert solves.solves == 10 and 1 <= solves.seen <= 10
    assert 0.0 < solves.mean <= solves.max
