"""Tag detections to range-bearing observations: the camera conventions, the noise model, the
labels and robot tags, every drop reason, and the inverse a simulated camera uses."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from csam_ros.core.model import detections as det
from csam_ros.core.model.detections import DetectionModel, frame_observations

ROBOT_TAGS = {5: "robot2", 6: "robot2", 9: "robot1", 11: "robot3"}


def _observe(model: DetectionModel, tags: list[str], positions: list[list[float]]):
    return frame_observations(12.5, tags, positions, model, ROBOT_TAGS, "robot1")


def test_optical_axes_level_camera_in_front_of_the_centre() -> None:
    # optical: x right, y down, z forward; the camera 0.1 m ahead of the centre, looking forward
    model = DetectionModel(camera_x=0.1, sigma_range_base=0.01, sigma_range_per_m=0.02)
    seen = _observe(model, ["tag36h11:3", "tag36h11:4"], [[0.0, -0.3, 2.0], [-1.0, 0.4, 1.0]])
    f = seen.features
    np.testing.assert_array_equal(f.labels, [3, 4])
    np.testing.assert_array_equal(f.stamps, [12.5, 12.5])
    # the second tag is 1 m to the left (-x) and 1 m ahead: (1.1, 1.0) from the centre
    np.testing.assert_allclose(f.ranges, [2.1, math.hypot(1.1, 1.0)], rtol=1e-15)
    np.testing.assert_allclose(f.bearings, [0.0, math.atan2(1.0, 1.1)], atol=1e-15)
    np.testing.assert_allclose(f.sigma_range, 0.01 + 0.02 * f.ranges, rtol=1e-15)
    np.testing.assert_array_equal(f.sigma_bearing, [0.01, 0.01])
    assert seen.rendezvous.observed == [] and seen.dropped == []


def test_camera_yaw_and_offset_place_the_tag_in_base_link() -> None:
    # a camera on the left side (y = 0.2) looking left (yaw pi/2): 3 m ahead of it is
    # (0, 3.2) in base_link; 0.5 m to its right (optical +x) is towards the robot's front
    model = DetectionModel(camera_y=0.2, camera_yaw=math.pi / 2)
    f = _observe(model, ["tag36h11:1"], [[0.5, 0.0, 3.0]]).features
    np.testing.assert_allclose(f.ranges, [math.hypot(0.5, 3.2)], rtol=1e-15)
    np.testing.assert_allclose(f.bearings, [math.atan2(3.2, 0.5)], rtol=1e-15)


def test_body_axes_take_x_forward_y_left() -> None:
    model = DetectionModel(camera_axes=det.BODY, camera_x=-0.2)
    f = _observe(model, ["7"], [[1.2, -1.0, 5.0]]).features  # z (up) is ignored
    np.testing.assert_allclose(f.ranges, [math.hypot(1.0, -1.0)], rtol=1e-15)
    np.testing.assert_allclose(f.bearings, [-math.pi / 4], rtol=1e-15)


def test_robot_tags_become_rendezvous_of_their_robot() -> None:
    model = DetectionModel()
    seen = _observe(
        model,
        ["tag36h11:5", "tag36h11:2", "11", "tag36h11:6"],
        [[0, 0, 2.0], [0, 0, 3.0], [0, 0, 4.0], [0.1, 0, 2.0]],
    )
    assert seen.rendezvous.observed == ["robot2", "robot3"]
    np.testing.assert_allclose(seen.rendezvous.ranges, [2.0, 4.0])
    np.testing.assert_allclose(seen.rendezvous.sigma_range, model.sigma_range([2.0, 4.0]))
    np.testing.assert_array_equal(seen.features.labels, [2])
    # a second tag of robot2 in the same frame: one measurement of a robot per frame
    assert seen.dropped == [det.Drop(det.DUPLICATE_ROBOT, "tag36h11:6")]


@pytest.mark.parametrize(
    ("name", "family", "expected"),
    [
        ("tag36h11:7", "tag36h11", 7),
        ("7", "tag36h11", 7),
        ("tag36h11:007", "tag36h11", 7),
        ("tag16h5:7", "", 7),
        ("tag16h5:7", "tag36h11", det.UNKNOWN_TAG_FAMILY),
        ("tag36h11:", "tag36h11", det.UNPARSEABLE_TAG),
        (":7", "tag36h11", det.UNPARSEABLE_TAG),
        ("tag36h11:-3", "tag36h11", det.UNPARSEABLE_TAG),
        ("tag36h11:1e3", "tag36h11", det.UNPARSEABLE_TAG),
        ("tag36h11:\u0663", "tag36h11", det.UNPARSEABLE_TAG),  # an Arabic-Indic digit
        ("tag36h11:" + "9" * 20, "tag36h11", det.UNPARSEABLE_TAG),  # beyond int64
        ("camera_link", "tag36h11", det.UNPARSEABLE_TAG),
        ("", "tag36h11", det.UNPARSEABLE_TAG),
    ],
)
def test_tag_names(name: str, family: str, expected: int | str) -> None:
    assert det.parse_tag(name, family) == expected


def test_every_bad_detection_is_dropped_with_its_reason_and_the_rest_kept() -> None:
    nan, inf = math.nan, math.inf
    tags = [
        ("tag36h11:1", [0.0, 0.0, 1.0]),  # kept
        ("tag36h11:2", [nan, 0.0, 1.0]),
        ("tag36h11:3", [0.0, inf, 1.0]),  # not finite even where the height is ignored
        ("tag36h11:4", [0.0, 0.0, 0.0]),  # in the camera's plane: behind
        ("tag36h11:5x", [0.0, 0.0, 1.0]),
        ("tag25h9:6", [0.0, 0.0, 1.0]),
        ("tag36h11:1", [0.5, 0.0, 1.0]),  # seen again in this frame
        ("tag36h11:9", [0.0, 0.0, 2.0]),  # robot1's own tag
        ("tag36h11:8", [0.2, 0.1, -3.0]),  # behind
        ("tag36h11:10", [0.0, 0.0, 1.5]),  # kept
    ]
    seen = _observe(DetectionModel(), [t for t, _ in tags], [p for _, p in tags])
    np.testing.assert_array_equal(seen.features.labels, [1, 10])
    np.testing.assert_allclose(seen.features.ranges, [1.0, 1.5])
    assert [(d.reason, d.tag) for d in seen.dropped] == [
        (det.NOT_FINITE, "tag36h11:2"),
        (det.NOT_FINITE, "tag36h11:3"),
        (det.BEHIND_CAMERA, "tag36h11:4"),
        (det.UNPARSEABLE_TAG, "tag36h11:5x"),
        (det.UNKNOWN_TAG_FAMILY, "tag25h9:6"),
        (det.DUPLICATE_TAG, "tag36h11:1"),
        (det.OWN_TAG, "tag36h11:9"),
        (det.BEHIND_CAMERA, "tag36h11:8"),
    ]


def test_an_empty_frame_gives_nothing() -> None:
    seen = frame_observations(1.0, [], np.zeros((0, 3)), DetectionModel(), {}, "robot1")
    assert len(seen.features.labels) == 0 and seen.rendezvous.observed == []
    assert seen.dropped == []
    with pytest.raises(ValueError, match="2 tags but 1 positions"):
        frame_observations(1.0, ["1", "2"], [[0, 0, 1.0]], DetectionModel(), {}, "robot1")


def test_robot_tags_parse_and_refuse_malformed_entries() -> None:
    assert det.parse_robot_tags(["5:robot2", " 6 : robot2", "9:robot1"]) == {
        5: "robot2",
        6: "robot2",
        9: "robot1",
    }
    for bad in ["5", "robot2:5", "5:", ":robot2", "-5:robot2", "5:a/b"]:
        with pytest.raises(ValueError, match="not '<tag id>:<robot>'"):
            det.parse_robot_tags([bad])
    with pytest.raises(ValueError, match="tag 5 is given twice"):
        det.parse_robot_tags(["5:robot2", "5:robot3"])


def test_the_model_refuses_bad_settings_by_name() -> None:
    assert DetectionModel.from_dict({"camera_x": 0.3}).camera_x == 0.3
    with pytest.raises(ValueError, match="sigma_range_base: must be greater than 0"):
        DetectionModel.from_dict({"sigma_range_base": 0.0})
    with pytest.raises(ValueError, match="camera_axes"):
        DetectionModel.from_dict({"camera_axes": "fisheye"})
    with pytest.raises(ValueError, match="camera_yaw: must be finite"):
        DetectionModel.from_dict({"camera_yaw": math.nan})
    with pytest.raises(ValueError, match="unknown key"):
        DetectionModel.from_dict({"camera_z": 0.1})


@given(
    st.sampled_from([det.OPTICAL, det.BODY]),
    st.floats(-0.5, 0.5),
    st.floats(-0.5, 0.5),
    st.floats(-math.pi, math.pi),
    st.lists(
        st.tuples(st.floats(0.05, 20.0), st.floats(-1.5, 1.5), st.floats(-2, 2)),
        min_size=1,
        max_size=8,
    ),
)
def test_camera_positions_invert_the_conversion(
    axes: str,
    camera_x: float,
    camera_y: float,
    camera_yaw: float,
    rows: list[tuple[float, float, float]],
) -> None:
    """A point at (range, angle from the camera's axis, height) seen by the camera: its
    position from camera_positions converts back to its range and bearing."""
    model = DetectionModel(
        camera_x=camera_x, camera_y=camera_y, camera_yaw=camera_yaw, camera_axes=axes
    )
    distance, angle, height = (np.array(c) for c in zip(*rows, strict=True))
    camera = model.camera_pose
    points = camera[:2] + distance[:, None] * np.stack(
        [np.cos(camera_yaw + angle), np.sin(camera_yaw + angle)], axis=-1
    )
    ranges = np.hypot(points[:, 0], points[:, 1])
    bearings = np.arctan2(points[:, 1], points[:, 0])
    positions = det.camera_positions(ranges, bearings, model, height)
    forward = positions[:, 2] if axes == det.OPTICAL else positions[:, 0]
    np.testing.assert_allclose(forward, distance * np.cos(angle), atol=1e-9)
    tags = [str(k) for k in range(len(rows))]
    seen = frame_observations(0.0, tags, positions, model, {}, "robot1")
    assert seen.dropped == []
    np.testing.assert_allclose(seen.features.ranges, ranges, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(
        np.angle(np.exp(1j * (seen.features.bearings - bearings))), 0.0, atol=1e-9
    )
