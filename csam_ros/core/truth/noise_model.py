"""The noise model of robots with a range-bearing sensor and velocity odometry, as the noise
estimation (:mod:`csam_ros.core.truth.calibration`) fits it.

``sigma_range(r) = sigma_range + sigma_range_per_m * r``, one bearing sigma, white velocity
noise densities ``q`` per sqrt-second on ``(v, v_lat, omega)`` (the pose noise of an interval
of length ``t`` grows as ``q^2 t``), and factors by which measurements of other robots spread
more than those of landmarks.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
MAD_TO_SIGMA = 1.4826
# Smallest odometry noise density a fit may return [m/sqrt(s), rad/sqrt(s)]: a density the
# data drive to zero (MR.CLAM Dataset 4's first estimate of q_vlat: 6e-10) would make the
# odometry factors of short intervals singular.
DENSITY_FLOOR = 1e-3
# the values the estimation fits (the rendezvous factors come after, from its localisations)
ESTIMATED = ("sigma_range", "sigma_range_per_m", "sigma_bearing", "q_v", "q_vlat", "q_omega")


@dataclass(frozen=True)
class NoiseModel:
    """Sensor and odometry noise (module docstring): range sigma ``sigma_range +
    sigma_range_per_m * r`` [m], bearing sigma [rad], odometry densities ``q_v``, ``q_vlat``
    [m/sqrt(s)] and ``q_omega`` [rad/sqrt(s)]; measurements of other robots get the landmark
    sigmas times ``rendezvous_*_factor``."""

    sigma_range: float
    sigma_range_per_m: float
    sigma_bearing: float
    q_v: float
    q_vlat: float
    q_omega: float
    rendezvous_range_factor: float = 1.0
    rendezvous_bearing_factor: float = 1.0

    def __post_init__(self) -> None:
        for name, value in asdict(self).items():
            low_ok = value >= 0 if name == "sigma_range_per_m" else value > 0
            if not (np.isfinite(value) and low_ok):
                bound = ">= 0" if name == "sigma_range_per_m" else "> 0"
                raise ValueError(f"noise {name} must be finite and {bound}, got {value!r}")

    @classmethod
    def from_dict(cls, values: dict, defaults: NoiseModel | None = None) -> NoiseModel:
        """Build from a mapping (e.g. a config file's ``noise`` section); keys it leaves out
        come from ``defaults`` (all are required without)."""
        known = set(cls.__dataclass_fields__)
        unknown = set(values) - known
        if unknown:
            raise ValueError(f"unknown noise keys {sorted(unknown)}; known: {sorted(known)}")
        given = {k: float(v) for k, v in values.items()}
        if defaults is not None:
            return replace(defaults, **given)
        return cls(**given)

    def densities(self) -> FloatArray:
        """``(q_v, q_vlat, q_omega)``."""
        return np.array([self.q_v, self.q_vlat, self.q_omega])


# Where the estimation starts (deliberately not a data set's known values, so that re-running
# it does not feed its own output back in).
NEUTRAL_START = NoiseModel(
    sigma_range=0.1, sigma_range_per_m=0.0, sigma_bearing=0.02, q_v=0.02, q_vlat=0.01, q_omega=0.04
)


def robust_sigma(values: FloatArray) -> float:
    """Median absolute deviation about zero, scaled to a normal sigma."""
    return float(MAD_TO_SIGMA * np.median(np.abs(values))) if values.size else float("nan")
