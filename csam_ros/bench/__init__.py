"""Benchmarks: run each module with ``python -m csam_ros.bench.<name>``."""
