"""A scenario straight to a bag (``csam simulate``): what the simulator node publishes, with no
DDS and no nodes, so that a team of any size is one command and ``csam replay BAG --offline``
joins it.

The messages are the simulator node's (``csam_ros/nodes/simulator.py``: the core's simulation
of the scenario and seed, every robot's ``odom`` with its integrated pose, ``features``,
``rendezvous`` and ``ground_truth``, and ``/sim/features_truth``), each logged at its own stamp,
as a recorder under sim time logs what the node paces out. At each stamp the bag first holds
``/clock`` at that stamp, then the messages of that stamp in the node's order, then one ``/tf``
with the ``<robot>/odom -> <robot>/base_link`` of that stamp's odometry. The same scenario and
seed give the same bytes (under the same bag name, which the .mcap file carries): each message
is written with its alignment padding zeroed (rclpy's serializer leaves whatever was in memory
there), and chunks end by size only, never by the time writing took.
"""

from __future__ import annotations

from itertools import groupby
from pathlib import Path
from typing import TYPE_CHECKING

from csam_ros.bag import BagWriter, MessageTypes, msgtype_of
from csam_ros.run.errors import RunError

if TYPE_CHECKING:
    from csam_ros.datasets.simulation import Scenario
    from csam_ros.ros.conversions import StampedMessage

# seconds between chunk flushes: longer than any write, so that a chunk ends by its size only
FLUSH_BY_SIZE_ONLY_S = 1e9
MAX_SEED = 2**31 - 1  # the simulator node's seed parameter's range


def simulator_messages(scenario: Scenario, seed: int | None = None) -> list[StampedMessage]:
    """The messages the simulator node publishes of ``scenario`` with ``seed`` (None: the
    scenario's) on the sensor, truth and features-truth topics, in its order."""
    from csam_ros.datasets.simulation import simulate
    from csam_ros.ros.conversions import log_to_messages
    from csam_ros.ros.topics import FEATURES_TRUTH, TOPICS, robot_topics

    log = simulate(scenario, seed)
    emitted = {*robot_topics([r.name for r in scenario.robots], TOPICS), FEATURES_TRUTH.name}
    return [m for m in log_to_messages(log, with_poses=True) if m.topic in emitted]


def simulated_bag_messages(scenario: Scenario, seed: int | None = None) -> list[StampedMessage]:
    """Everything :func:`write_simulated_bag` writes, in order (module docs): the node's
    messages with ``/clock`` and ``/tf`` at each stamp."""
    from rosgraph_msgs.msg import Clock
    from tf2_msgs.msg import TFMessage

    from csam_ros.ros.conversions import OdometryTransforms, StampedMessage, ns_to_time
    from csam_ros.ros.topics import CLOCK, ODOM, TF

    transforms = OdometryTransforms()
    out: list[StampedMessage] = []
    for stamp_ns, group in groupby(simulator_messages(scenario, seed), lambda m: m.stamp_ns):
        out.append(StampedMessage(stamp_ns, CLOCK.name, Clock(clock=ns_to_time(stamp_ns))))
        tf = TFMessage()
        for m in group:
            out.append(m)
            robot = ODOM.robot_of(m.topic)
            if robot is not None:
                transform = transforms.transform(robot, m.message)  # type: ignore[arg-type]
                if transform is not None:
                    tf.transforms.append(transform)
        if tf.transforms:
            out.append(StampedMessage(stamp_ns, TF.name, tf))
    return out


def write_simulated_bag(messages: list[StampedMessage], path: Path) -> int:
    """Write ``messages`` as a new bag at ``path``, each at its stamp in CDR with zeroed
    padding, each topic with the QoS its publisher offers in a live run; the message count."""
    from rclpy.serialization import serialize_message

    from csam_ros.ros.topics import qos_of

    types = MessageTypes()
    store = types.register_custom_types()
    with BagWriter(path, flush_period_s=FLUSH_BY_SIZE_ONLY_S, types=types) as bag:
        for m in messages:
            msgtype = msgtype_of(m.message)
            if m.topic not in bag.topics:
                bag.add_topic(m.topic, msgtype, qos_of(m.topic))
            # the same values, read back and written again by rosbags, which zeroes the padding
            values = store.deserialize_cdr(serialize_message(m.message), msgtype)
            bag.write(m.topic, m.stamp_ns, bytes(store.serialize_cdr(values, msgtype)))
    return len(messages)


def simulate_to_bag(scenario_name: str | Path, out: Path, seed: int | None = None) -> list[str]:
    """``csam simulate``: the scenario (a name in config/ or a YAML file) with ``seed`` (None:
    the scenario's) as a new bag ``out``; what was written, as lines to print."""
    from csam_ros.datasets.scenario import load_scenario

    if seed is not None and not 0 <= seed <= MAX_SEED:
        raise RunError(f"--seed: expected 0..{MAX_SEED}, got {seed}")
    if out.exists():
        raise RunError(f"{out} exists: a simulation never overwrites a bag")
    scenario = load_scenario(scenario_name)
    messages = simulated_bag_messages(scenario, seed)
    count = write_simulated_bag(messages, out)
    seconds = (messages[-1].stamp_ns - messages[0].stamp_ns) / 1e9 if messages else 0.0
    return [
        f"wrote {count} messages of {len(scenario.robots)} robot(s) to {out}",
        f"  scenario {scenario.name}, seed {scenario.seed if seed is None else seed}, "
        f"{seconds:.1f} s of sim time",
    ]
