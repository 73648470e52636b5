"""Tag detections of a camera to the smoother's range-bearing observations (no ROS).

The ``detections`` node (csam_ros/nodes/detections.py) hands this module, frame by frame, each
detected tag's name and its position in the camera frame; it gets back feature observations
(labelled with the tag id), rendezvous observations (tags mounted on robots) and the
detections it dropped, each with its reason.

Camera convention. Positions come in the camera frame ``camera_axes`` names: ``optical`` (the
default), the REP-103 camera optical frame that camera drivers stamp images with and
apriltag_ros publishes tag poses in: x right, y down, z forward; or ``body``, a
``camera_link``: x forward, y left, z up. The camera sits at ``(camera_x, camera_y)`` in
``base_link`` with its viewing axis at heading ``camera_yaw``, level (no roll or pitch): a
tag's height is ignored, its position projected onto the ground plane. A tag whose forward
coordinate is not positive is behind the camera and dropped.

Noise model. ``sigma_range = sigma_range_base + sigma_range_per_m * range`` and a constant
``sigma_bearing``, of the range and bearing published (from the robot centre, in
``base_link``).

Labels. A tag is named ``<family>:<id>`` (apriltag_ros's child frames, e.g. ``tag36h11:7``) or
by its bare id (``7``, as a detector's class id); only ``tag_family``'s tags are taken (an
empty ``tag_family`` takes every family, whose ids then share one label space). A tag whose id
the robot tags map to a robot becomes a rendezvous observation of that robot; every other tag
is a feature labelled with its id.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
from numpy.typing import ArrayLike, NDArray

from csam_ros.core.model import se2
from csam_ros.core.model.config_file import Section, setting
from csam_ros.core.model.log import FeatureLog, RendezvousLog

DETECTIONS_NODE = "detections"  # the node that takes DetectionModel's fields as parameters
OPTICAL = "optical"  # x right, y down, z forward (REP-103 *_optical_frame)
BODY = "body"  # x forward, y left, z up (a camera_link)
_MAX_ID = 2**63 - 1  # labels are int64

# why a detection was dropped
NOT_FINITE = "not_finite"  # a NaN or infinite coordinate
UNPARSEABLE_TAG = "unparseable_tag"  # neither '<family>:<id>' nor '<id>' (or no hypothesis)
UNKNOWN_TAG_FAMILY = "unknown_tag_family"  # a family other than tag_family
BEHIND_CAMERA = "behind_camera"  # forward coordinate <= 0
OWN_TAG = "own_tag"  # a tag mounted on the observing robot itself
DUPLICATE_TAG = "duplicate_tag"  # a tag id seen again in the same frame
DUPLICATE_ROBOT = "duplicate_robot"  # a second tag of one robot in the same frame


@dataclass(frozen=True)
class DetectionModel(Section):
    """Where the camera is on the robot, which frame its detections are in, and the noise
    model of the observations made of them (the ``detections`` node's parameters)."""

    section: ClassVar[str] = DETECTIONS_NODE  # names the node's parameters in errors

    camera_x: float = setting(
        0.0, "m: the camera's position in base_link, forward of the centre", node=DETECTIONS_NODE
    )
    camera_y: float = setting(
        0.0, "m: the camera's position in base_link, left of the centre", node=DETECTIONS_NODE
    )
    camera_yaw: float = setting(
        0.0,
        "rad: heading of the camera's viewing axis in base_link, counter-clockwise from forward",
        node=DETECTIONS_NODE,
    )
    camera_axes: str = setting(
        OPTICAL,
        "axes of the camera frame detections are in: optical (x right, y down, z forward; "
        "REP-103 *_optical_frame, apriltag_ros) or body (x forward, y left, z up; camera_link)",
        choices=(OPTICAL, BODY),
        node=DETECTIONS_NODE,
    )
    sigma_range_base: float = setting(
        0.02,
        "m: sigma_range at range 0 (sigma_range = sigma_range_base + sigma_range_per_m * range)",
        minimum=0.0,
        exclusive=True,
        node=DETECTIONS_NODE,
    )
    sigma_range_per_m: float = setting(
        0.02,
        "m per m: growth of sigma_range with the range",
        minimum=0.0,
        node=DETECTIONS_NODE,
    )
    sigma_bearing: float = setting(
        0.01, "rad: sigma of every bearing", minimum=0.0, exclusive=True, node=DETECTIONS_NODE
    )
    tag_family: str = setting(
        "tag36h11",
        "family of the tags taken, as in '<family>:<id>' ('': every family, ids shared)",
        node=DETECTIONS_NODE,
    )

    @property
    def camera_pose(self) -> NDArray[np.float64]:
        """The camera's planar pose ``(x, y, yaw)`` in base_link."""
        return np.array([self.camera_x, self.camera_y, self.camera_yaw])

    def sigma_range(self, ranges: ArrayLike) -> NDArray[np.float64]:
        """The range sigma of observations at ``ranges``."""
        return self.sigma_range_base + self.sigma_range_per_m * np.asarray(ranges, dtype=float)


@dataclass(frozen=True)
class Drop:
    """A detection left out, why, and the tag it named (for the log)."""

    reason: str
    tag: str


@dataclass
class FrameObservations:
    """What one frame of detections gives: features, rendezvous and what was dropped."""

    features: FeatureLog
    rendezvous: RendezvousLog
    dropped: list[Drop]


def parse_tag(name: str, family: str) -> int | str:
    """The id of the tag named ``name`` (``<family>:<id>`` or ``<id>``), or the reason it is
    not taken (:data:`UNPARSEABLE_TAG`, :data:`UNKNOWN_TAG_FAMILY`)."""
    tag_family, colon, number = name.rpartition(":")
    if not (number.isascii() and number.isdigit()) or (colon and not tag_family):
        return UNPARSEABLE_TAG
    if colon and family and tag_family != family:
        return UNKNOWN_TAG_FAMILY
    tag_id = int(number)
    return tag_id if tag_id <= _MAX_ID else UNPARSEABLE_TAG


def parse_robot_tags(entries: Iterable[str]) -> dict[int, str]:
    """Tag id -> robot from entries ``'<id>:<robot>'`` (e.g. ``'5:robot2'``; a robot may
    carry several tags); ValueError naming a malformed or repeated entry."""
    tags: dict[int, str] = {}
    for entry in entries:
        number, colon, robot = entry.partition(":")
        number, robot = number.strip(), robot.strip()
        if not colon or not robot or "/" in robot or not (number.isascii() and number.isdigit()):
            raise ValueError(f"robot_tags: {entry!r} is not '<tag id>:<robot>', e.g. '5:robot2'")
        if int(number) in tags:
            raise ValueError(f"robot_tags: tag {int(number)} is given twice")
        tags[int(number)] = robot
    return tags


def planar_positions(positions: ArrayLike, model: DetectionModel) -> NDArray[np.float64]:
    """Camera-frame positions ``(K, 3)`` as ``(forward, left)`` ``(K, 2)`` of a level camera."""
    p = np.asarray(positions, dtype=float).reshape(-1, 3)
    if model.camera_axes == OPTICAL:
        return np.stack([p[:, 2], -p[:, 0]], axis=-1)
    return p[:, :2].copy()


def camera_positions(
    ranges: ArrayLike, bearings: ArrayLike, model: DetectionModel, heights: ArrayLike = 0.0
) -> NDArray[np.float64]:
    """The inverse of the conversion: the camera-frame positions ``(K, 3)`` of points at
    ``ranges`` and ``bearings`` from the robot centre, ``heights`` above the camera (a
    simulated camera's detections)."""
    r = np.asarray(ranges, dtype=float).reshape(-1)
    b = np.asarray(bearings, dtype=float).reshape(-1)
    up = np.broadcast_to(np.asarray(heights, dtype=float), r.shape)
    body = np.stack([r * np.cos(b), r * np.sin(b)], axis=-1)
    forward, left = se2.inverse_transform_point(model.camera_pose, body).T
    if model.camera_axes == OPTICAL:
        return np.stack([-left, -up, forward], axis=-1)
    return np.stack([forward, left, up], axis=-1)


def frame_observations(
    stamp: float,
    tags: Sequence[str],
    positions: ArrayLike,
    model: DetectionModel,
    robot_tags: Mapping[int, str],
    robot: str,
) -> FrameObservations:
    """The observations of ``robot`` at ``stamp`` [s] from one frame of detections: tag
    ``tags[k]`` at ``positions[k]`` (camera frame, m), in order; what is not taken is in
    ``dropped`` (its reason, see the module docstring)."""
    p = np.asarray(positions, dtype=float).reshape(-1, 3)
    if len(p) != len(tags):
        raise ValueError(f"{len(tags)} tags but {len(p)} positions")
    planar = planar_positions(p, model)
    with np.errstate(invalid="ignore"):  # rows that are not finite are dropped below
        body = se2.transform_point(model.camera_pose, planar)
        ranges = np.hypot(body[:, 0], body[:, 1])
        bearings = se2.wrap_angle(np.arctan2(body[:, 1], body[:, 0]))
    dropped: list[Drop] = []
    features: list[tuple[int, int]] = []  # (row, label)
    rendezvous: list[tuple[int, str]] = []  # (row, observed robot)
    seen_tags: set[int] = set()
    seen_robots: set[str] = set()
    for k, name in enumerate(tags):
        tag = parse_tag(name, model.tag_family)
        reason = ""
        if isinstance(tag, str):
            reason = tag
        elif not np.isfinite(p[k]).all():
            reason = NOT_FINITE
        elif planar[k, 0] <= 0:
            reason = BEHIND_CAMERA
        elif tag in seen_tags:
            reason = DUPLICATE_TAG
        elif robot_tags.get(tag) == robot:
            reason = OWN_TAG
        elif tag in robot_tags and robot_tags[tag] in seen_robots:
            reason = DUPLICATE_ROBOT
        if reason:
            dropped.append(Drop(reason, name))
            continue
        seen_tags.add(tag)
        if tag in robot_tags:
            seen_robots.add(robot_tags[tag])
            rendezvous.append((k, robot_tags[tag]))
        else:
            features.append((k, tag))
    f_rows = np.array([k for k, _ in features], dtype=np.int64)
    r_rows = np.array([k for k, _ in rendezvous], dtype=np.int64)
    return FrameObservations(
        FeatureLog(
            np.full(len(f_rows), float(stamp)),
            np.array([label for _, label in features], dtype=np.int64),
            ranges[f_rows],
            bearings[f_rows],
            model.sigma_range(ranges[f_rows]),
            np.full(len(f_rows), model.sigma_bearing),
        ),
        RendezvousLog(
            np.full(len(r_rows), float(stamp)),
            [name for _, name in rendezvous],
            ranges[r_rows],
            bearings[r_rows],
            model.sigma_range(ranges[r_rows]),
            np.full(len(r_rows), model.sigma_bearing),
        ),
        dropped,
    )
