"""The detections node's input type, built from vision_msg_defs/ where the wheels have no
vision_msgs, is the one of a ROS 2 Jazzy install (vision_msgs 4.1.1): so a detector built
against Jazzy's vision_msgs matches the node's subscription."""

from __future__ import annotations

from csam_ros.bag.types import MessageTypes

# vision_msgs/msg/Detection3DArray of vision_msgs 4.1.1 (Jazzy): its RIHS01 hash covers every
# type it holds (Detection3D, ObjectHypothesisWithPose, ObjectHypothesis, BoundingBox3D)
JAZZY_DETECTION3DARRAY = "RIHS01_793f5eab9595ac1c0da07873cc859db42eae51f0ee76056db8562515d830e018"


def test_detection3darray_hash_is_jazzys() -> None:
    definition = MessageTypes().definition("vision_msgs/msg/Detection3DArray")
    assert definition.type_hash == JAZZY_DETECTION3DARRAY


def test_the_python_type_is_the_built_one() -> None:
    from vision_msgs.msg import Detection3D, Detection3DArray

    assert Detection3DArray.get_fields_and_field_types() == {
        "header": "std_msgs/Header",
        "detections": "sequence<vision_msgs/Detection3D>",
    }
    assert Detection3D.get_fields_and_field_types() == {
        "header": "std_msgs/Header",
        "results": "sequence<vision_msgs/ObjectHypothesisWithPose>",
        "bbox": "vision_msgs/BoundingBox3D",
        "id": "string",
    }
