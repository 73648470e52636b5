"""RViz and Foxglove markers of a joined map: trajectories, features, covariance ellipses."""

from __future__ import annotations

import numpy as np
from builtin_interfaces.msg import Time
from geometry_msgs.msg import Point
from std_msgs.msg import ColorRGBA
from visualization_msgs.msg import Marker, MarkerArray

from csam_ros.core.joining.result import CsamResult
from csam_ros.core.model.chi_square import CHI2_2DOF_95

ELLIPSE_SEGMENTS = 24
PALETTE = [  # tab10
    (0.12, 0.47, 0.71),
    (1.0, 0.5, 0.05),
    (0.17, 0.63, 0.17),
    (0.84, 0.15, 0.16),
    (0.58, 0.4, 0.74),
    (0.55, 0.34, 0.29),
    (0.89, 0.47, 0.76),
    (0.5, 0.5, 0.5),
]


def robot_color(index: int, alpha: float = 1.0) -> ColorRGBA:
    r, g, b = PALETTE[index % len(PALETTE)]
    return ColorRGBA(r=r, g=g, b=b, a=alpha)


def ellipse_points(xy: np.ndarray, cov: np.ndarray, scale: float = CHI2_2DOF_95) -> np.ndarray:
    """Outline points ``(F, S, 2)`` of the ``scale``-level ellipses of ``F`` 2D Gaussians."""
    values, vectors = np.linalg.eigh(np.asarray(cov, dtype=float))
    radii = np.sqrt(np.clip(values, 0.0, None) * scale)  # (F, 2)
    angle = np.linspace(0.0, 2 * np.pi, ELLIPSE_SEGMENTS + 1)
    unit = np.stack([np.cos(angle), np.sin(angle)], -1)  # (S, 2)
    return xy[:, None, :] + np.einsum("fij,sj->fsi", vectors * radii[:, None, :], unit)


def _marker(frame: str, stamp: Time, ns: str, marker_id: int, kind: int) -> Marker:
    m = Marker()
    m.header.frame_id = frame
    m.header.stamp = stamp
    m.ns = ns
    m.id = marker_id
    m.type = kind
    m.action = Marker.ADD
    m.pose.orientation.w = 1.0
    return m


def _points(xy: np.ndarray) -> list[Point]:
    return [Point(x=float(x), y=float(y), z=0.0) for x, y in xy]


def joined_map_markers(result: CsamResult, stamp: Time) -> MarkerArray:
    """Markers of a C-SAM result in its reference frame."""
    frame = result.reference_frame
    array = MarkerArray()
    clear = Marker()
    clear.action = Marker.DELETEALL
    array.markers.append(clear)
    for i, (name, robot) in enumerate(result.robots.items()):
        poses = robot.poses_joined
        if poses is None or len(poses) < 2:
            continue
        m = _marker(frame, stamp, "trajectories", i, Marker.LINE_STRIP)
        m.scale.x = 0.05
        m.color = robot_color(i)
        m.points = _points(poses[:, :2])
        m.text = name
        array.markers.append(m)
    features = result.features
    if features:
        xy = np.array([f.xy for f in features], dtype=float)
        cov = np.array([f.cov for f in features], dtype=float)
        shared = np.array([len(f.members) > 1 for f in features])
        for k, (ns, mask, color) in enumerate(
            (
                ("features/shared", shared, ColorRGBA(r=0.9, g=0.1, b=0.1, a=1.0)),
                ("features/single", ~shared, ColorRGBA(r=0.2, g=0.2, b=0.2, a=1.0)),
            )
        ):
            if not mask.any():
                continue
            m = _marker(frame, stamp, ns, k, Marker.SPHERE_LIST)
            m.scale.x = m.scale.y = m.scale.z = 0.12
            m.color = color
            m.points = _points(xy[mask])
            array.markers.append(m)
        outline = ellipse_points(xy, cov)
        segments = np.stack([outline[:, :-1], outline[:, 1:]], axis=2).reshape(-1, 2)
        m = _marker(frame, stamp, "feature_covariance_95", 0, Marker.LINE_LIST)
        m.scale.x = 0.01
        m.color = ColorRGBA(r=0.1, g=0.1, b=0.6, a=0.8)
        m.points = _points(segments)
        array.markers.append(m)
    return array
