"""Readers of data sets and scenario files into core data (no ROS)."""
