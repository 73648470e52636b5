"""The pure core of csam_ros (no ROS imports), in layers; each imports only those before it:

``model`` -> ``sam`` -> ``smoothing`` -> ``joining`` -> ``exchange`` -> ``merging``, and
``truth`` (ground truth, calibration, evaluation) beside ``exchange`` on top of ``joining``.
docs/ARCHITECTURE.md states the rule; test/test_layers.py checks it.
"""
