"""The smoother's frames by REP-105: ``map -> odom`` on ``/tf``, the correction of odometry.

The robot's driver (or the simulator, or the player) publishes ``odom -> base_link``; the
smoother publishes ``<robot>/map -> <robot>/odom`` (parameters ``map_frame``, ``odom_frame``)
so that ``base_link`` has one parent: the transform that takes the odometry pose at the latest
key pose's stamp to that key pose (:func:`~csam_ros.core.model.odometry_frame.map_to_odom`).
The odometry pose is the one each message carried, or the dead reckoning of the samples where
messages carry none (:class:`~csam_ros.core.model.odometry_frame.OdometryFrame`). It goes out
at ``tf_rate`` Hz of the steady clock stamped with the node's time (sim time under
``use_sim_time``), as slam_toolbox does, and at once when it changes; never twice with one
stamp, which tf2 would refuse.
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np
from nav_msgs.msg import Odometry
from rclpy.node import Node

from csam_ros.core.exchange.validation import DropCounter, OdometrySample, Pose
from csam_ros.core.model.motion import odometry_poses
from csam_ros.core.model.odometry_frame import OdometryFrame, map_to_odom
from csam_ros.nodes.common import Declared, declare_each, guarded, publisher, steady_clock
from csam_ros.ros.conversions import tf_message
from csam_ros.ros.topics import TF

# the smoother's frame parameters (REP-105), declared by :class:`MapToOdom`
FRAME_PARAMETERS = (
    Declared("map_frame", "", "the local map's frame", made_at_start="<robot>/map"),
    Declared(
        "odom_frame",
        "",
        "the odometry's frame (child of map_frame)",
        made_at_start="<robot>/odom",
    ),
    Declared(
        "base_frame",
        "",
        "the body frame (child of odom_frame)",
        made_at_start="<robot>/base_link",
    ),
    Declared(
        "tf_rate",
        20.0,
        "Hz: how often map_frame -> odom_frame goes out on /tf (0: with each local map)",
        0.0,
    ),
)


class MapToOdom:
    """A smoother's ``map -> odom`` transform: its frames, its odometry frame and its timer."""

    def __init__(self, node: Node, robot: str, drops: DropCounter) -> None:
        self.node = node
        own = declare_each(
            node,
            FRAME_PARAMETERS,
            {
                "map_frame": lambda _: f"{robot}/map",
                "odom_frame": lambda _: f"{robot}/odom",
                "base_frame": lambda _: f"{robot}/base_link",
            },
        )
        self.map_frame, self.odom_frame = own["map_frame"], own["odom_frame"]
        self.base_frame, rate = own["base_frame"], own["tf_rate"]
        self.reset()
        self._sent_ns = -1
        self._named: set[str] = set()  # frame names of the odometry already warned about
        self.publisher = publisher(node, TF)
        if rate > 0:
            node.create_timer(
                1.0 / rate, guarded(node, drops, self.broadcast), clock=steady_clock()
            )

    def reset(self) -> None:
        """Forget the odometry frame and the correction (a reset or loaded smoother); the stamp
        last sent stays, so no transform goes out twice with one stamp."""
        self.odometry = OdometryFrame()
        self.correction: np.ndarray | None = None
        self._changed = False

    def add(self, msg: Odometry, samples: Iterable[tuple[OdometrySample, Pose | None]]) -> None:
        """Accepted odometry samples (with the poses their messages carried) of ``msg``; say
        once when its frames are not this node's ``odom_frame`` and ``base_frame``."""
        for sample, pose in samples:
            self.odometry.add(sample[0], sample[1], pose)
        for name, expected in (
            (msg.header.frame_id, self.odom_frame),
            (msg.child_frame_id, self.base_frame),
        ):
            if name and name != expected and name not in self._named:
                self._named.add(name)
                self.node.get_logger().warning(
                    f"odometry in frame {name!r}, not {expected!r}: /tf {self.map_frame} -> "
                    f"{self.odom_frame} assumes the odometry's pose is in {self.odom_frame} "
                    "(parameters odom_frame, base_frame)"
                )

    def resume(self, stamps: np.ndarray, inputs: np.ndarray) -> None:
        """Continue the dead reckoning after a restart from the odometry accepted before it."""
        if len(stamps):
            self.odometry.add(float(stamps[-1]), inputs[-1], odometry_poses(stamps, inputs)[-1])

    def update(self, key_stamp: float, key_pose: np.ndarray) -> None:
        """A new latest key pose: the correction from the odometry pose at its stamp (none
        while no odometry sample reaches it), sent at once."""
        odometry = self.odometry.pose_at(key_stamp)
        if odometry is None:
            return
        self.odometry.forget_before(key_stamp)
        self.correction = map_to_odom(key_pose, odometry)
        self._changed = True
        self.broadcast()

    def broadcast(self) -> None:
        """Send the correction stamped now, when the clock moved on or the correction changed
        (then 1 ns after the last one at least: a stopped sim clock)."""
        if self.correction is None:
            return
        now_ns = self.node.get_clock().now().nanoseconds
        if now_ns <= self._sent_ns:
            if not self._changed:
                return
            now_ns = self._sent_ns + 1
        transform = (self.map_frame, self.odom_frame, self.correction)
        self.publisher.publish(tf_message([transform], now_ns))
        self._sent_ns, self._changed = now_ns, False
