"""csam bandwidth: bytes per topic and per tenth of a run, counted from a bag's raw messages."""

from __future__ import annotations

from pathlib import Path

import pytest

from csam_ros.bag import BagWriter, read_bag
from csam_ros.cli import main
from csam_ros.run.bandwidth import PARTS, measure_bandwidth

SECOND = 1_000_000_000


@pytest.fixture
def bag(tmp_path: Path) -> Path:
    """robot1 sends a local map update that grows each second for 10 s, robot2 one
    status-sized message per second; a global topic spans the run."""
    from csam_msgs.msg import LocalMapUpdate, RendezvousPoses
    from std_msgs.msg import String

    path = tmp_path / "traffic"
    with BagWriter(path) as writer:
        writer.add_topic("/robot1/local_map_updates", "csam_msgs/msg/LocalMapUpdate")
        writer.add_topic("/robot2/rendezvous_poses", "csam_msgs/msg/RendezvousPoses")
        writer.add_topic("/chatter", "std_msgs/msg/String")
        for second in range(11):
            m = LocalMapUpdate()
            m.pose_stamps = [k * SECOND for k in range(100 * second)]
            writer.write("/robot1/local_map_updates", second * SECOND, m)
            writer.write("/chatter", second * SECOND, String(data="x" * 10))
        writer.write("/robot2/rendezvous_poses", 5 * SECOND, RendezvousPoses())
    return path


def test_bytes_are_the_recorded_messages_summed_per_topic_and_part(bag: Path) -> None:
    bandwidth = measure_bandwidth(bag)
    sizes: dict[str, list[tuple[int, int]]] = {}
    for m in read_bag(bag):
        sizes.setdefault(m.topic, []).append((m.log_time_ns, len(m.data)))
    assert set(bandwidth.topics) == set(sizes)
    assert bandwidth.seconds == pytest.approx(10.0)
    for name, entries in sizes.items():
        traffic = bandwidth.topics[name]
        assert traffic.messages == len(entries)
        assert traffic.bytes == sum(n for _, n in entries) == sum(traffic.bytes_by_part)
        assert traffic.largest == max(n for _, n in entries)
    local_map = bandwidth.topics["/robot1/local_map_updates"]
    assert local_map.robot == "robot1" and bandwidth.topics["/chatter"].robot is None
    # one message per second, the last (t = 10 s) in the last tenth with the one at 9 s
    assert local_map.bytes_by_part[:-1] == [n for _, n in sizes["/robot1/local_map_updates"][:9]]
    to_base = bandwidth.to_base_by_part("robot1")
    assert len(to_base) == PARTS and to_base == sorted(to_base)  # grows with the map
    assert to_base[0] == pytest.approx(local_map.bytes_by_part[0] * 8e-3)  # 1 s parts
    assert bandwidth.robots() == ["robot1", "robot2"]


def test_the_command_prints_topics_and_growth(bag: Path, capsys) -> None:
    assert main(["bandwidth", str(bag)]) == 0
    out = capsys.readouterr().out
    assert "/robot1/local_map_updates" in out and "/chatter" in out
    rows = [line.split() for line in out.splitlines() if line.strip().startswith("robot")]
    assert [r[0] for r in rows[1:]] == ["robot1", "robot2"] and len(rows[1]) == 1 + PARTS


def test_a_missing_bag_is_one_line(tmp_path: Path, capsys) -> None:
    assert main(["bandwidth", str(tmp_path / "nothing")]) != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "nothing" in err[0]
