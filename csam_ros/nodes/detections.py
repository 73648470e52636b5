"""detections: a camera's tag detections as the smoother's observations, in the robot's namespace.

Takes the camera's tags by one of two inputs (subscribed both; a frame that came by the other
already, at the same stamp, would be dropped as stale):

- ``detections`` (vision_msgs/Detection3DArray, relative: ``/<robot>/detections``): each
  detection's tag is the class id of its best-scoring hypothesis (``7`` or ``tag36h11:7``),
  its position that hypothesis' pose, in the array's frame (which must be ``camera_frame``);
  the stamp is the array's (a detection's own where the array has none);
- ``/tf`` in the apriltag_ros convention: every transform from ``camera_frame`` to a child
  frame ``<family>:<id>`` (e.g. ``tag36h11:7``) is a tag at that translation; transforms
  between other frames are not this node's and are ignored.

and publishes, per frame of detections (one stamp), one ``features``
(csam_msgs/FeatureObservations, label = tag id) and one ``rendezvous``
(csam_msgs/RendezvousObservations, tags listed in ``robot_tags``) message in
``<robot>/base_link``, stamped with the detections' stamp, each only when it has an
observation. The conversion (camera mounting ``camera_x``, ``camera_y``, ``camera_yaw``, the
camera frame's axes ``camera_axes``, the noise model ``sigma_range_base``,
``sigma_range_per_m``, ``sigma_bearing``, ``tag_family``) is
:mod:`csam_ros.core.model.detections`; docs/DETECTIONS.md says what a team publishes.

A detection that cannot be taken (a NaN pose, a tag name that does not parse or of another
family, behind the camera, the robot's own tag, a tag or robot seen twice in one frame, an
array in another frame than ``camera_frame``, a frame stamped at or before the last one
published) is dropped and counted by reason; the first drop of each reason is logged with its
tag. Counts go to ``/csam/status`` (``detections/<robot>``) every ``status_period`` s while
they change. Every callback is guarded: the node never dies of its input.
"""

from __future__ import annotations

import math
import sys
from collections.abc import Sequence
from typing import Any

import numpy as np
from rclpy.node import Node
from tf2_msgs.msg import TFMessage
from vision_msgs.msg import Detection3D, Detection3DArray

from csam_ros.core.exchange.validation import DropCounter
from csam_ros.core.model.detections import (
    OPTICAL,
    DetectionModel,
    frame_observations,
    parse_robot_tags,
)
from csam_ros.nodes.common import (
    ROBOT_PARAMETER,
    Declared,
    declare_each,
    declare_settings,
    guarded,
    publisher,
    run_node,
    steady_clock,
    subscribe,
    watch_parameters,
)
from csam_ros.ros.conversions import features_message, rendezvous_message, time_to_ns
from csam_ros.ros.diagnostics import node_status
from csam_ros.ros.topics import DETECTIONS, FEATURES, RENDEZVOUS, STATUS, TF

# drop reasons of the node: a detections array in another frame than the camera's; a frame
# stamped at or before the last one published (the smoother takes each stamp once, in order:
# a detector that splits one image's tags over several messages shows up here)
WRONG_FRAME = "wrong_frame"
STALE_STAMP = "stale_stamp"

Tag = tuple[str, tuple[float, float, float]]  # a tag's name and its position in the camera frame
# the node's own parameters (DetectionModel's fields are declared from their Settings)
DETECTIONS_PARAMETERS = (
    ROBOT_PARAMETER,
    Declared(
        "camera_frame",
        "",
        "the camera's frame: parent of the tag frames on /tf, frame of the detections arrays "
        "('': <robot>/camera_optical_frame, <robot>/camera_link for body axes)",
    ),
    Declared(
        "robot_tags",
        [""],
        "tags mounted on robots, '<tag id>:<robot>' each (e.g. '5:robot2'): their detections "
        "are rendezvous observations of that robot",
    ),
    Declared("status_period", 2.0, "s between /csam/status reports while counts change", 0.1),
)


class Detections(Node):
    """One robot's detections adapter (see the module docstring)."""

    def __init__(self, **node_options: Any) -> None:
        super().__init__("detections", **node_options)
        ns = self.get_namespace().strip("/")
        own = declare_each(self, DETECTIONS_PARAMETERS, {"robot": lambda _: ns or "robot1"})
        self.robot = own["robot"]
        self.model = declare_settings(self, DetectionModel)
        default_frame = (
            "camera_optical_frame" if self.model.camera_axes == OPTICAL else "camera_link"
        )
        self.camera_frame = own["camera_frame"] or f"{self.robot}/{default_frame}"
        self.robot_tags = parse_robot_tags(e for e in own["robot_tags"] if e)
        self.status_period = own["status_period"]
        self.drops = DropCounter()
        self.frames = 0  # frames with at least one tag of this camera
        self.features = 0  # observations published
        self.rendezvous = 0
        self.last_stamp_ns = -1  # of the last frame published
        self._logged: set[str] = set()
        self._reported: tuple | None = None
        self.features_pub = publisher(self, FEATURES)
        self.rendezvous_pub = publisher(self, RENDEZVOUS)
        self.status_pub = publisher(self, STATUS)
        subscribe(self, DETECTIONS, guarded(self, self.drops, self.on_detections))
        subscribe(self, TF, guarded(self, self.drops, self.on_tf))
        self.create_timer(self.status_period, self.publish_status, clock=steady_clock())
        watch_parameters(self, drops=self.drops)  # none is set live
        tags = ", ".join(f"{t}:{r}" for t, r in sorted(self.robot_tags.items())) or "none"
        self.get_logger().info(
            f"{self.robot}: tags seen by {self.camera_frame} ({self.model.camera_axes} axes) at "
            f"({self.model.camera_x}, {self.model.camera_y}, {self.model.camera_yaw} rad) in "
            f"base_link; robot tags: {tags}"
        )

    # -- input ----------------------------------------------------------------------------------

    def on_detections(self, msg: Detection3DArray) -> None:
        frames: dict[int, list[Tag]] = {}
        array_ns = time_to_ns(msg.header.stamp)
        for detection in msg.detections:
            frame = msg.header.frame_id or detection.header.frame_id
            if frame != self.camera_frame:
                self.drop(WRONG_FRAME, f"frame {frame!r}, not camera_frame {self.camera_frame!r}")
                continue
            stamp_ns = array_ns or time_to_ns(detection.header.stamp)
            frames.setdefault(stamp_ns, []).append(_best_tag(detection))
        for stamp_ns, tags in sorted(frames.items()):
            self.publish_frame(stamp_ns, tags)

    def on_tf(self, msg: TFMessage) -> None:
        frames: dict[int, list[Tag]] = {}
        for t in msg.transforms:
            if t.header.frame_id != self.camera_frame:
                continue  # another frame's transform: not a detection of this camera
            p = t.transform.translation
            frames.setdefault(time_to_ns(t.header.stamp), []).append(
                (t.child_frame_id, (p.x, p.y, p.z))
            )
        for stamp_ns, tags in sorted(frames.items()):
            self.publish_frame(stamp_ns, tags)

    # -- output ---------------------------------------------------------------------------------

    def publish_frame(self, stamp_ns: int, tags: Sequence[Tag]) -> None:
        """The observations of one frame of tags at ``stamp_ns``, each kind as one message."""
        if stamp_ns <= self.last_stamp_ns:
            for name, _ in tags:
                self.drop(
                    STALE_STAMP,
                    f"tag {name!r} at {stamp_ns} ns, not after the last frame "
                    f"({self.last_stamp_ns} ns; one message per image?)",
                )
            return
        self.frames += 1
        seen = frame_observations(
            stamp_ns / 1e9,
            [name for name, _ in tags],
            np.array([position for _, position in tags], dtype=float).reshape(-1, 3),
            self.model,
            self.robot_tags,
            self.robot,
        )
        for drop in seen.dropped:
            self.drop(drop.reason, f"tag {drop.tag!r}")
        f, r = seen.features, seen.rendezvous
        if len(f.labels):
            self.features_pub.publish(
                features_message(
                    self.robot,
                    stamp_ns,
                    f.labels,
                    f.ranges,
                    f.bearings,
                    f.sigma_range,
                    f.sigma_bearing,
                )
            )
            self.features += len(f.labels)
        if r.observed:
            self.rendezvous_pub.publish(
                rendezvous_message(
                    self.robot,
                    stamp_ns,
                    r.observed,
                    r.ranges,
                    r.bearings,
                    r.sigma_range,
                    r.sigma_bearing,
                )
            )
            self.rendezvous += len(r.observed)
        if len(f.labels) or r.observed:
            self.last_stamp_ns = stamp_ns

    def drop(self, reason: str, detail: str) -> None:
        """Count a dropped detection; the first of each reason is logged."""
        self.drops.add(reason)
        if reason not in self._logged:
            self._logged.add(reason)
            self.get_logger().warning(
                f"dropped a detection ({reason}): {detail}; further ones are counted in "
                f"/csam/status (detections/{self.robot})"
            )

    def publish_status(self) -> None:
        """Counts of frames, observations and drops by reason, when they changed."""
        counts = (self.frames, self.features, self.rendezvous, self.drops.total)
        if counts == self._reported:
            return
        self._reported = counts
        values = {
            "frames": self.frames,
            "features": self.features,
            "rendezvous": self.rendezvous,
            "dropped": self.drops.total,
            **{f"dropped/{k}": v for k, v in self.drops.as_dict().items()},
        }
        message = (
            f"{self.frames} frames, {self.features} feature and {self.rendezvous} "
            f"rendezvous observations, {self.drops.total} detections dropped"
        )
        array = node_status(
            f"detections/{self.robot}",
            self.robot,
            self.drops.total == 0,
            message,
            values,
            self.get_clock().now().to_msg(),
        )
        self.status_pub.publish(array)
        self.get_logger().info(message + (f" {self.drops.as_dict()}" if self.drops.total else ""))


def _best_tag(detection: Detection3D) -> Tag:
    """The class id and position of a detection's best-scoring hypothesis (no hypothesis: an
    name that does not parse)."""
    if not detection.results:
        return "(no hypothesis)", (math.nan, math.nan, math.nan)
    best = max(
        detection.results,
        key=lambda h: h.hypothesis.score if math.isfinite(h.hypothesis.score) else -math.inf,
    )
    p = best.pose.pose.position
    return best.hypothesis.class_id, (p.x, p.y, p.z)


def main(args: list[str] | None = None) -> int:
    return run_node(Detections, args, __doc__)


if __name__ == "__main__":
    sys.exit(main())
