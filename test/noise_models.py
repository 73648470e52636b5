"""Noise models for tests, given by their sigmas and odometry densities."""

from __future__ import annotations

from csam_ros.core.truth.noise_model import NoiseModel


def noise_model(
    sigmas: tuple[float, float, float],
    densities: tuple[float, float, float],
    rendezvous_factors: tuple[float, float] = (1.0, 1.0),
) -> NoiseModel:
    """``sigmas``: range [m], range per metre of range, bearing [rad]; ``densities``: ``q_v``,
    ``q_vlat`` [m/sqrt(s)], ``q_omega`` [rad/sqrt(s)]; ``rendezvous_factors``: range, bearing."""
    return NoiseModel(*sigmas, *densities, *rendezvous_factors)
