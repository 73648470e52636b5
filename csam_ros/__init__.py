"""csam_ros: collaborative multi-robot SLAM by square-root information smoothing (C-SAM)."""

__version__ = "0.1.0"
