"""The bag of ``csam simulate`` (run/simulate.py): what the simulator node publishes, stamped
with its own stamps, the same bytes on every run, read by rosbags and by mcap."""

from __future__ import annotations

from pathlib import Path

import pytest
from rclpy.parameter import Parameter

from csam_ros.bag import MessageTypes, inspect_bag, qos_to_dict, read_bag, read_bag_messages
from csam_ros.ros.conversions import time_to_ns
from csam_ros.run.errors import RunError
from csam_ros.run.simulate import simulate_to_bag

SCENARIO = "map_joining"
SEED = 3
GENERATED = ("/clock", "/tf")  # not in the node's message list: made at each stamp


@pytest.fixture(scope="module")
def simulated(tmp_path_factory: pytest.TempPathFactory) -> Path:
    bag = tmp_path_factory.mktemp("simulated") / "bag"
    simulate_to_bag(SCENARIO, bag, SEED)
    return bag


def test_the_bag_holds_what_the_simulator_node_publishes(simulated: Path, ros_context) -> None:
    """Every message of the node's list (the node made in this process, never spun), at its
    stamp, on the node's topics with their types and QoS; its odom -> base_link transforms
    on /tf and a /clock at every stamp."""
    from csam_ros.nodes.simulator import Simulator

    overrides = [Parameter("scenario", value=SCENARIO), Parameter("seed", value=SEED)]
    node = Simulator(context=ros_context, parameter_overrides=overrides)
    try:
        published = [(m.stamp_ns, m.topic, m.message) for m in node.messages]
        transforms = [t for t in node.odometry_tf if t is not None]
        offered = {
            topic: (p.msg_type, qos_to_dict(p.qos_profile))
            for topic, p in [
                *node.topic_publishers.items(),
                ("/tf", node.tf),
                ("/clock", node.clock),
            ]
        }
    finally:
        node.destroy_node()
    read = list(read_bag_messages(simulated))
    assert [(m.log_time_ns, m.topic, m.message) for m in read if m.topic not in GENERATED] == (
        published
    )
    for m in read:
        if hasattr(m.message, "header"):
            assert time_to_ns(m.message.header.stamp) == m.log_time_ns, m.topic
    tf = [m for m in read if m.topic == "/tf"]
    assert [t for m in tf for t in m.message.transforms] == transforms
    assert all(
        time_to_ns(t.header.stamp) == m.log_time_ns for m in tf for t in m.message.transforms
    )
    clock = [m for m in read if m.topic == "/clock"]
    assert [m.log_time_ns for m in clock] == sorted({stamp for stamp, _, _ in published})
    assert all(time_to_ns(m.message.clock) == m.log_time_ns for m in clock)
    topics = inspect_bag(simulated).topics
    assert set(topics) == set(offered)
    for name, (msg_type, qos) in offered.items():
        info = topics[name]
        assert info.msgtype == f"{msg_type.__module__.split('.')[0]}/msg/{msg_type.__name__}"
        [recorded] = info.offered_qos_profiles
        for policy in ("history", "depth", "reliability", "durability"):
            assert recorded[policy] == qos[policy], (name, policy)


def test_the_same_seed_gives_the_same_bytes_and_another_seed_other_data(
    simulated: Path, tmp_path: Path
) -> None:
    again = tmp_path / "bag"
    simulate_to_bag(SCENARIO, again, SEED)
    for name in ("bag_0.mcap", "metadata.yaml"):
        assert (again / name).read_bytes() == (simulated / name).read_bytes(), name
    other = tmp_path / "other" / "bag"
    simulate_to_bag(SCENARIO, other, SEED + 1)
    odometry = [[m.data for m in read_bag(b, ["/robot2/odom"])] for b in (simulated, other)]
    assert len(odometry[0]) == len(odometry[1]) > 0 and odometry[0] != odometry[1]


def test_rosbags_and_mcap_read_every_message(simulated: Path) -> None:
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory
    from rosbags.highlevel import AnyReader

    counts = {name: t.message_count for name, t in inspect_bag(simulated).topics.items()}
    expected = [(m.topic, m.log_time_ns) for m in read_bag(simulated)]
    assert len(expected) == sum(counts.values())
    store = MessageTypes().register_custom_types()
    with AnyReader([simulated], default_typestore=store) as reader:
        assert {c.topic: c.msgcount for c in reader.connections} == counts
        rows = list(reader.messages())
        for connection, _, raw in rows:
            reader.deserialize(raw, connection.msgtype)
    assert sorted((c.topic, t) for c, t, _ in rows) == sorted(expected)
    with (simulated / "bag_0.mcap").open("rb") as stream:
        mcap = make_reader(stream, decoder_factories=[DecoderFactory()], validate_crcs=True)
        decoded = [(c.topic, m.log_time) for _, c, m, _ in mcap.iter_decoded_messages()]
    assert sorted(decoded) == sorted(expected)


def test_bad_options_are_refused_before_anything_is_written(tmp_path: Path) -> None:
    with pytest.raises(RunError, match="--seed: expected 0..2147483647, got -1"):
        simulate_to_bag(SCENARIO, tmp_path / "bag", -1)
    assert not (tmp_path / "bag").exists()
    (tmp_path / "bag").mkdir()
    with pytest.raises(RunError, match="exists: a simulation never overwrites a bag"):
        simulate_to_bag(SCENARIO, tmp_path / "bag")
    assert list((tmp_path / "bag").iterdir()) == []
