"""rosbag2 bags (metadata.yaml + MCAP, cdr, ros2msg schemas) written and read without rosbag2.

- :class:`BagWriter`: write a new bag from serialized bytes or rclpy messages, no node needed;
  survives SIGKILL up to its last flushed chunk.
- :func:`read_bag` / :func:`read_bag_messages`: messages in log-time order, raw or
  deserialized to rclpy message classes; :func:`inspect_bag`: topics, types, recorded QoS.
- :func:`recover_bag`: rewrite a cut (killed) or partly damaged bag into a complete one.
- :class:`MessageTypes`: full message definitions and type hashes (rosbags' typestore plus
  csam_msgs and installed packages).
"""

from csam_ros.bag.qos import parse_qos_profiles, publisher_qos, qos_to_dict, subscription_qos
from csam_ros.bag.reader import (
    BagInfo,
    BagMessage,
    DecodedMessage,
    TopicInfo,
    inspect_bag,
    read_bag,
    read_bag_messages,
)
from csam_ros.bag.recover import RecoveryReport, recover_bag
from csam_ros.bag.types import (
    MessageDefinition,
    MessageTypes,
    UnknownMessageTypeError,
    message_class,
    msgtype_of,
)
from csam_ros.bag.writer import BagError, BagWriter

__all__ = [
    "BagError",
    "BagInfo",
    "BagMessage",
    "BagWriter",
    "DecodedMessage",
    "MessageDefinition",
    "MessageTypes",
    "RecoveryReport",
    "TopicInfo",
    "UnknownMessageTypeError",
    "inspect_bag",
    "message_class",
    "msgtype_of",
    "parse_qos_profiles",
    "publisher_qos",
    "qos_to_dict",
    "read_bag",
    "read_bag_messages",
    "recover_bag",
    "subscription_qos",
]
