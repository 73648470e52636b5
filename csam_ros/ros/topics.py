"""Every topic of a run, declared once: name, message type, QoS, and whether a live run records it.

A topic is global (``/csam/status``) or a robot's (``odom`` is ``/<robot>/odom``; a smoother in
the robot's namespace uses the relative name). Nodes, the importers' bag writer and the live run
take names, types and QoS from here; a new topic is one more declaration.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

from csam_msgs.msg import (
    FeatureObservations,
    FeaturePoints,
    FeaturesTruth,
    JoinedMap,
    LocalMap,
    LocalMapUpdate,
    RendezvousObservations,
    RendezvousPoses,
)
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseWithCovarianceStamped
from nav_msgs.msg import Odometry, Path
from rclpy.qos import (
    DurabilityPolicy,
    HistoryPolicy,
    QoSProfile,
    ReliabilityPolicy,
    qos_profile_sensor_data,
)
from rosgraph_msgs.msg import Clock
from tf2_msgs.msg import TFMessage
from vision_msgs.msg import Detection3DArray
from visualization_msgs.msg import MarkerArray

SENSOR_DATA = qos_profile_sensor_data
# Subscribing to sensor data: best effort like its publishers, but a deep queue so that a burst
# (a bag played as fast as possible) is buffered rather than overwritten.
SENSOR_DATA_BUFFERED = QoSProfile(
    depth=10000, reliability=ReliabilityPolicy.BEST_EFFORT, history=HistoryPolicy.KEEP_LAST
)
RELIABLE = QoSProfile(
    depth=1000, reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST
)
LATCHED = QoSProfile(
    depth=1,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
    history=HistoryPolicy.KEEP_LAST,
)
SHALLOW = QoSProfile(depth=10)  # reliable, volatile: only the latest values matter
LATEST = QoSProfile(depth=1)  # reliable, volatile: only the newest value is wanted


@dataclass(frozen=True)
class Topic:
    """One topic: ``name`` is absolute (global) or a robot's relative suffix (per robot)."""

    name: str
    msgtype: type
    qos: QoSProfile  # what its publishers offer
    subscription: QoSProfile | None = None  # what its subscribers ask for, where different
    recorded: bool = True  # a live run records it
    sensor: bool = False  # a measurement stream the smoothers read (and a replay plays)

    @property
    def per_robot(self) -> bool:
        return not self.name.startswith("/")

    @property
    def subscription_qos(self) -> QoSProfile:
        return self.subscription or self.qos

    @property
    def type_name(self) -> str:
        """The message type as the ROS graph names it, e.g. ``csam_msgs/msg/LocalMap``."""
        return f"{self.msgtype.__module__.split('.')[0]}/msg/{self.msgtype.__name__}"

    def robot_of(self, name: str) -> str | None:
        """The robot whose instance of this per-robot topic ``name`` is (``/<robot>/<topic>``,
        one namespace level), else None."""
        parts = name.split("/")
        if len(parts) == 3 and parts[0] == "" and parts[1] and parts[2] == self.name:
            return parts[1]
        return None

    def of(self, robot: str | None = None) -> str:
        """The absolute name: of ``robot`` for a per-robot topic, else the global name."""
        if self.per_robot:
            if not robot:
                raise ValueError(f"topic {self.name!r} is per robot: name the robot")
            return f"/{robot}/{self.name}"
        if robot:
            raise ValueError(f"topic {self.name} is global, not of robot {robot!r}")
        return self.name


ODOM = Topic("odom", Odometry, SENSOR_DATA, SENSOR_DATA_BUFFERED, sensor=True)
FEATURES = Topic("features", FeatureObservations, RELIABLE, sensor=True)
# Cartesian feature observations with their covariance (2D SLAM files; sensors give range-bearing)
FEATURE_POINTS = Topic("feature_points", FeaturePoints, RELIABLE, sensor=True)
RENDEZVOUS = Topic("rendezvous", RendezvousObservations, RELIABLE, sensor=True)
GROUND_TRUTH = Topic("ground_truth", Odometry, SENSOR_DATA)
# a detector's tags in the camera frame, for the detections node (nodes/detections.py), which
# publishes them as features and rendezvous; read best effort, so any publisher matches
DETECTIONS = Topic(
    "detections", Detection3DArray, SENSOR_DATA, SENSOR_DATA_BUFFERED, recorded=False
)
FEATURES_TRUTH = Topic("/sim/features_truth", FeaturesTruth, LATCHED)
# the whole local map, for a look on the robot (published only while subscribed, not recorded)
LOCAL_MAP = Topic("local_map", LocalMap, LATCHED, recorded=False)
# what the merger joins: the local map's changes (csam_ros/core/exchange/map_updates.py); every one
# is kept (reliable, deep), a receiver that missed one asks the smoother for a resync
LOCAL_MAP_UPDATES = Topic("local_map_updates", LocalMapUpdate, RELIABLE)
RENDEZVOUS_POSES = Topic("rendezvous_poses", RendezvousPoses, LATCHED)
# the local trajectory, for a look on the robot (published only while subscribed, not recorded)
PATH = Topic("path", Path, LATCHED, recorded=False)
JOINED_MAP = Topic("/csam/joined_map", JoinedMap, LATCHED)
# the newest local maps placed by the last join, while the next one runs (nodes/merger.py)
PROVISIONAL_MAP = Topic("/csam/joined_map/provisional", JoinedMap, LATCHED)
MARKERS = Topic("/csam/markers", MarkerArray, LATCHED)
STATUS = Topic("/csam/status", DiagnosticArray, SHALLOW)
# the merger's status as ROS's diagnostics tools read it (csam/<robot> per robot, csam)
DIAGNOSTICS = Topic("/diagnostics", DiagnosticArray, SHALLOW)
# each joined robot's latest pose in <reference>/map with its covariance, from the merger
POSE = Topic("pose", PoseWithCovarianceStamped, LATEST)
# REP-105 frames: <reference>/map -> <robot>/map (merger), <robot>/map -> <robot>/odom
# (smoothers), <robot>/odom -> <robot>/base_link (the robot's driver, or the simulator or
# player); reliable and volatile with a deep queue, as tf2's broadcasters
TF = Topic("/tf", TFMessage, QoSProfile(depth=100))
CLOCK = Topic("/clock", Clock, SHALLOW)

# what each robot sends to the base station (the merger subscribes to these)
MERGER_INPUTS: tuple[Topic, ...] = (LOCAL_MAP_UPDATES, RENDEZVOUS_POSES)
# what the merger publishes for each robot (recorded where it is published, the base station)
MERGER_ROBOT_OUTPUTS: tuple[Topic, ...] = (POSE,)

TOPICS: tuple[Topic, ...] = (
    ODOM,
    FEATURES,
    FEATURE_POINTS,
    RENDEZVOUS,
    GROUND_TRUTH,
    DETECTIONS,
    FEATURES_TRUTH,
    LOCAL_MAP,
    LOCAL_MAP_UPDATES,
    RENDEZVOUS_POSES,
    PATH,
    JOINED_MAP,
    PROVISIONAL_MAP,
    MARKERS,
    STATUS,
    DIAGNOSTICS,
    POSE,
    TF,
    CLOCK,
)
# the services (std_srvs/Trigger): the smoother's solve to convergence and publish, the
# merger's solve the newest maps at once (the data has ended); the smoother's resend of the
# whole local map as one update
FLUSH = "flush"
RESYNC = "resync"
# the state services of the smoother and the merger (nodes/state_services.py): write the state
# file (csam_msgs/SaveState), replace the state by a file's (csam_msgs/LoadState), forget
# everything held (std_srvs/Trigger), stop and resume taking input (std_srvs/SetBool)
SAVE_STATE = "save_state"
LOAD_STATE = "load_state"
RESET = "reset"
PAUSE = "pause"
MERGER_NODE = "merger"


def smoother_service(robot: str, service: str) -> str:
    """The absolute name of ``robot``'s smoother service (the node is ``/<robot>/smoother``)."""
    return f"/{robot}/smoother/{service}"


def merger_service(service: str) -> str:
    """The absolute name of the merger's service (the node is ``/merger``)."""
    return f"/{MERGER_NODE}/{service}"


_GLOBAL = {t.name: t for t in TOPICS if not t.per_robot}
_PER_ROBOT = {t.name: t for t in TOPICS if t.per_robot}


def parse(name: str) -> tuple[Topic, str | None] | None:
    """The declaration of an absolute topic name and its robot (None for a global topic);
    None when no declaration matches."""
    if name in _GLOBAL:
        return _GLOBAL[name], None
    robot, _, suffix = name.removeprefix("/").rpartition("/")
    if name.startswith("/") and robot and "/" not in robot and suffix in _PER_ROBOT:
        return _PER_ROBOT[suffix], robot
    return None


def declaration(name: str) -> Topic:
    """The declaration of an absolute topic name; ValueError naming it when there is none."""
    found = parse(name)
    if found is None:
        raise ValueError(f"{name!r} is not a declared topic (csam_ros/ros/topics.py)")
    return found[0]


def qos_of(name: str) -> QoSProfile:
    """The QoS a topic is published with in a live run."""
    return declaration(name).qos


def robot_topics(robots: Iterable[str], topics: Iterable[Topic]) -> list[str]:
    """The absolute names of per-robot ``topics`` for each robot, robot by robot."""
    topics = [t for t in topics if t.per_robot]
    return [t.of(r) for r in robots for t in topics]


def sensor_topics(robots: Iterable[str]) -> list[str]:
    """The measurement topics of the robots: what smoothers read and a replay plays."""
    return robot_topics(robots, (t for t in TOPICS if t.sensor))


def recorded_topics(robots: Iterable[str]) -> list[str]:
    """Every topic a live run of these robots records."""
    recorded = [t for t in TOPICS if t.recorded]
    return robot_topics(robots, recorded) + [t.name for t in recorded if not t.per_robot]


def base_station_topics(robots: Iterable[str]) -> list[str]:
    """What the base station records when every robot is on a host of its own: what reaches
    it anyway (the merger's inputs), what the merger publishes for each robot, and the global
    topics. Each robot records the rest of its own topics (:func:`robot_host_topics`), so its
    raw data never crosses its link."""
    recorded = [t for t in TOPICS if t.recorded]
    at_base = MERGER_INPUTS + MERGER_ROBOT_OUTPUTS
    return robot_topics(robots, at_base) + [t.name for t in recorded if not t.per_robot]


def robot_host_topics(robot: str) -> list[str]:
    """What a robot's own host records: its recorded topics that the base station does not
    (:func:`base_station_topics`)."""
    at_base = MERGER_INPUTS + MERGER_ROBOT_OUTPUTS
    return robot_topics([robot], [t for t in TOPICS if t.recorded and t not in at_base])
