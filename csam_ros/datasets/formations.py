"""Formations of many robots for benchmarks and tests: N robots each drive one loop around a
centre of their own, neighbouring centres 3.5 m apart, in a ``ring`` (robot i meets i-1 and
i+1, the last the first) or a ``chain`` (no wrap, neighbours turning in opposite directions);
each observes only its neighbours, every ``rendezvous_every`` samples
(``python -m csam_ros.bench.many_robots`` runs them)."""

from __future__ import annotations

import numpy as np

from csam_ros.core.model import se2
from csam_ros.datasets.simulation import (
    RangeBearingSensor,
    RobotSpec,
    Scenario,
    Segment,
    feature_grid,
)

LAYOUTS = ("ring", "chain")
NEIGHBOUR_DISTANCE = 3.5  # m between neighbouring loop centres
LOOP_RADIUS = 2.4  # m
SPEED = 0.5  # m/s
SAMPLE_TIME = 0.5  # s
RENDEZVOUS_EVERY = 4  # samples between observations of the neighbours
FEATURE_SPACING = 1.5  # m
SENSOR = RangeBearingSensor(max_range=4.0, field_of_view=float(np.deg2rad(240.0)))
ODOMETRY_SIGMA = (0.02, 0.01, float(np.deg2rad(0.6)))
CSAM_SECTION = {"chi2_gate": 9.21}


def robot_name(i: int, n: int) -> str:
    """``robot01`` ... (zero-padded: the names sort in the scenario's order)."""
    return f"robot{i + 1:0{len(str(n))}d}"


def neighbours(n: int, layout: str) -> list[list[int]]:
    """The robots each robot meets: i-1 and i+1, wrapping round in a ring."""
    if layout not in LAYOUTS:
        raise ValueError(f"layout must be one of {LAYOUTS}, got {layout!r}")
    ring = layout == "ring"
    return [
        sorted({j % n if ring else j for j in (i - 1, i + 1) if ring or 0 <= j < n} - {i})
        for i in range(n)
    ]


def many_robot_scenario(
    n: int,
    layout: str,
    duration: float = 30.0,
    seed: int = 1,
    rendezvous_every: int = RENDEZVOUS_EVERY,
) -> Scenario:
    """``n`` robots looping around centres on a ring or a chain (module docs); ``duration``
    seconds each, a multiple of the sample time; each observes its neighbours at every
    ``rendezvous_every``-th sample."""
    if n < 2:
        raise ValueError(f"need at least 2 robots, got {n}")
    if rendezvous_every < 1:
        raise ValueError(f"rendezvous_every must be >= 1, got {rendezvous_every}")
    index = np.arange(n)
    omega = SPEED / LOOP_RADIUS
    if layout == "ring":
        theta = 2 * np.pi * index / n
        radius = NEIGHBOUR_DISTANCE / (2 * np.sin(np.pi / n))
        centres = radius * np.column_stack([np.cos(theta), np.sin(theta)])
        phase, turn = theta, np.ones(n)  # the formation turns as one: every pair alike
    else:
        centres = np.column_stack([NEIGHBOUR_DISTANCE * index, np.zeros(n)])
        odd = index % 2 == 1  # the mirror image of its left neighbour
        phase, turn = np.where(odd, np.pi, 0.0), np.where(odd, -1.0, 1.0)
    starts = centres + LOOP_RADIUS * np.column_stack([np.cos(phase), np.sin(phase)])
    headings = se2.wrap_angle(phase + turn * np.pi / 2)
    low = centres.min(axis=0) - LOOP_RADIUS - SENSOR.max_range
    high = centres.max(axis=0) + LOOP_RADIUS + SENSOR.max_range
    features = feature_grid(
        tuple((low + high) / 2), tuple(high - low), FEATURE_SPACING, 0.25, np.random.default_rng(5)
    )
    met = neighbours(n, layout)
    robots = tuple(
        RobotSpec(
            name=robot_name(i, n),
            start_pose=(float(starts[i, 0]), float(starts[i, 1]), float(headings[i])),
            program=(Segment(duration, SPEED, float(turn[i] * omega)),),
            odometry_sigma=ODOMETRY_SIGMA,
            feature_sensor=SENSOR,
            rendezvous_sensor=SENSOR,
            observes=tuple(robot_name(j, n) for j in met[i]),
            rendezvous_every=rendezvous_every,
        )
        for i in range(n)
    )
    description = f"{n} robots looping on a {layout}, each meeting its neighbours"
    if rendezvous_every != RENDEZVOUS_EVERY:
        every = "sample" if rendezvous_every == 1 else f"{rendezvous_every} samples"
        description += f", observing them every {every}"
    return Scenario(f"{layout}{n}", SAMPLE_TIME, features, robots, seed, description)
