"""ROS 2 side: topic declarations and conversions between messages and core data."""
