"""Scenario files: YAML under a top-level ``scenario:`` key, loaded into a
:class:`~csam_ros.datasets.simulation.Scenario`.

Layout (see ``config/map_joining.yaml`` for a commented example)::

    scenario:
      name: map_joining
      seed: 1                  # noise seed of a run (override with simulate(seed=...))
      sample_time: 0.5         # s, one pose and one scan per sample
      world:
        seed: 7                # the features are drawn once from this seed: a fixed world
        areas:                 # jittered grids of point features
          - {center: [x, y], size: [w, h], spacing: 1.0, jitter: 0.25}
        points: [[x, y], ...]  # optional explicit features
      defaults:                # every robot inherits these unless it overrides them
        odometry_sigma: {v: 0.02, v_lat: 0.01, omega_deg: 0.3}
        feature_sensor: {max_range: 4.0, field_of_view_deg: 240,
                         sigma_range: 0.01, sigma_bearing: 0.012}   # min_range: 0.1
        rendezvous_sensor: {...same keys...}   # or null: this robot observes no robot
        rendezvous_every: 1
        odometry_stress: {turn_driving: 1.5, distance: 0.9, resample_hz: 8}  # optional:
                               # reported odometry miscalibrated (datasets/odometry_stress.py)
      robots:
        - name: robot1
          start: {x: 0.0, y: 0.0, phi_deg: 0.0}
          observes: [robot2]   # optional; default every other robot
          program:             # constant (v, omega) segments
            - {duration: 10.0, v: 0.4, omega_deg: 0.0}

Other top-level keys (for example ``csam:`` with the joining parameters) are left to their
own loaders. Unknown keys inside ``scenario:`` are errors naming the key, so a typo never
silently falls back to a default.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import fields
from pathlib import Path
from typing import Any

import numpy as np

from csam_ros.core.model.config_file import ConfigFileError, load_document, resolve_config_path
from csam_ros.datasets.odometry_stress import OdometryStress
from csam_ros.datasets.simulation import (
    RangeBearingSensor,
    RobotSpec,
    Scenario,
    Segment,
    feature_grid,
)


class ScenarioError(ConfigFileError):
    """A scenario file that cannot be used; the message names the file and key."""


def _check_keys(node: Mapping[str, Any], allowed: set[str], where: str) -> None:
    unknown = sorted(set(node) - allowed)
    if unknown:
        raise ScenarioError(f"{where}: unknown key(s) {unknown}; allowed: {sorted(allowed)}")


def _mapping(node: Any, where: str) -> Mapping[str, Any]:
    if not isinstance(node, Mapping):
        raise ScenarioError(f"{where}: expected a mapping, got {type(node).__name__}")
    return node


def _number(node: Mapping[str, Any], key: str, where: str, default: float | None = None) -> float:
    if key not in node:
        if default is None:
            raise ScenarioError(f"{where}: missing key {key!r}")
        return default
    value = node[key]
    if isinstance(value, bool) or not isinstance(value, int | float) or not np.isfinite(value):
        raise ScenarioError(f"{where}.{key}: expected a finite number, got {value!r}")
    return float(value)


def _pair(node: Mapping[str, Any], key: str, where: str) -> tuple[float, float]:
    value = node.get(key)
    if (
        not isinstance(value, list | tuple)
        or len(value) != 2
        or not all(isinstance(v, int | float) and not isinstance(v, bool) for v in value)
    ):
        raise ScenarioError(f"{where}.{key}: expected [a, b] numbers, got {value!r}")
    return float(value[0]), float(value[1])


_SENSOR_KEYS = {"max_range", "min_range", "field_of_view_deg", "sigma_range", "sigma_bearing"}


def _sensor(node: Any, where: str, base: RangeBearingSensor | None) -> RangeBearingSensor | None:
    if node is None:
        return None
    node = _mapping(node, where)
    _check_keys(node, _SENSOR_KEYS, where)
    base = base or RangeBearingSensor()
    fov = _number(node, "field_of_view_deg", where, float(np.rad2deg(base.field_of_view)))
    sensor = RangeBearingSensor(
        max_range=_number(node, "max_range", where, base.max_range),
        field_of_view=float(np.deg2rad(fov)),
        sigma_range=_number(node, "sigma_range", where, base.sigma_range),
        sigma_bearing=_number(node, "sigma_bearing", where, base.sigma_bearing),
        min_range=_number(node, "min_range", where, base.min_range),
    )
    if not 0 <= sensor.min_range < sensor.max_range or not 0 < fov <= 360:
        raise ScenarioError(
            f"{where}: need 0 <= min_range < max_range and field_of_view_deg in (0, 360]"
        )
    if sensor.sigma_range <= 0 or sensor.sigma_bearing <= 0:
        raise ScenarioError(f"{where}: sensor sigmas must be positive")
    return sensor


def _odometry_sigma(node: Any, where: str) -> tuple[float, float, float]:
    node = _mapping(node, where)
    _check_keys(node, {"v", "v_lat", "omega_deg"}, where)
    sigma = (
        _number(node, "v", where),
        _number(node, "v_lat", where),
        float(np.deg2rad(_number(node, "omega_deg", where))),
    )
    if min(sigma) <= 0:
        raise ScenarioError(f"{where}: odometry sigmas must be positive, got {node}")
    return sigma


_ROBOT_KEYS = {
    "name",
    "odometry_stress",
    "start",
    "program",
    "observes",
    "odometry_sigma",
    "feature_sensor",
    "rendezvous_sensor",
    "rendezvous_every",
}


def _robot(node: Any, where: str, defaults: Mapping[str, Any]) -> RobotSpec:
    node = _mapping(node, where)
    _check_keys(node, _ROBOT_KEYS, where)
    merged = {**defaults, **node}
    name = merged.get("name")
    if not isinstance(name, str) or not name or "/" in name:
        raise ScenarioError(f"{where}.name: expected a robot name without '/', got {name!r}")
    where = f"{where} ({name})"
    start = _mapping(merged.get("start"), f"{where}.start")
    _check_keys(start, {"x", "y", "phi_deg"}, f"{where}.start")
    start_pose = (
        _number(start, "x", f"{where}.start"),
        _number(start, "y", f"{where}.start"),
        float(np.deg2rad(_number(start, "phi_deg", f"{where}.start"))),
    )
    program_node = merged.get("program")
    if not isinstance(program_node, list) or not program_node:
        raise ScenarioError(f"{where}.program: expected a non-empty list of segments")
    program = []
    for k, seg in enumerate(program_node):
        sw = f"{where}.program[{k}]"
        seg = _mapping(seg, sw)
        _check_keys(seg, {"duration", "v", "omega_deg"}, sw)
        program.append(
            Segment(
                duration=_number(seg, "duration", sw),
                v=_number(seg, "v", sw),
                omega=float(np.deg2rad(_number(seg, "omega_deg", sw, 0.0))),
            )
        )
    observes = merged.get("observes")
    if observes is not None and (
        not isinstance(observes, list) or not all(isinstance(o, str) for o in observes)
    ):
        raise ScenarioError(f"{where}.observes: expected a list of robot names")
    every = merged.get("rendezvous_every", 1)
    if not isinstance(every, int) or isinstance(every, bool) or every < 1:
        raise ScenarioError(f"{where}.rendezvous_every: expected an integer >= 1, got {every!r}")
    if "odometry_sigma" not in merged:
        raise ScenarioError(f"{where}: missing odometry_sigma (in the robot or in defaults)")
    feature_sensor = _sensor(merged.get("feature_sensor", {}), f"{where}.feature_sensor", None)
    if feature_sensor is None:
        raise ScenarioError(f"{where}.feature_sensor: a robot needs a feature sensor")
    return RobotSpec(
        name=name,
        start_pose=start_pose,
        program=tuple(program),
        odometry_sigma=_odometry_sigma(merged["odometry_sigma"], f"{where}.odometry_sigma"),
        feature_sensor=feature_sensor,
        rendezvous_sensor=_sensor(
            merged.get("rendezvous_sensor", {}), f"{where}.rendezvous_sensor", None
        ),
        observes=tuple(observes) if observes is not None else None,
        rendezvous_every=every,
        odometry_stress=_odometry_stress(merged.get("odometry_stress"), f"{where}.odometry_stress"),
    )


def _odometry_stress(node: Any, where: str) -> OdometryStress | None:
    """``odometry_stress: {turn_driving: 1.5, distance: 0.9, resample_hz: 8}`` (the robot's
    reported odometry miscalibrated, csam_ros.datasets.odometry_stress); None: absent."""
    if node is None:
        return None
    node = _mapping(node, where)
    names = {f.name for f in fields(OdometryStress)}
    _check_keys(node, names, where)
    try:
        return OdometryStress(**{k: _number(node, k, where) for k in node})
    except ValueError as err:
        raise ScenarioError(f"{where}: {err}") from None


def _world(node: Any, where: str) -> np.ndarray:
    node = _mapping(node, where)
    _check_keys(node, {"seed", "areas", "points"}, where)
    seed = node.get("seed", 0)
    if not isinstance(seed, int) or isinstance(seed, bool):
        raise ScenarioError(f"{where}.seed: expected an integer, got {seed!r}")
    rng = np.random.default_rng(seed)
    parts = []
    for k, area in enumerate(node.get("areas") or []):
        aw = f"{where}.areas[{k}]"
        area = _mapping(area, aw)
        _check_keys(area, {"center", "size", "spacing", "jitter"}, aw)
        try:
            parts.append(
                feature_grid(
                    _pair(area, "center", aw),
                    _pair(area, "size", aw),
                    _number(area, "spacing", aw),
                    _number(area, "jitter", aw, 0.0),
                    rng,
                )
            )
        except ValueError as err:
            raise ScenarioError(f"{aw}: {err}") from err
    points = node.get("points") or []
    if points:
        arr = np.asarray(points, dtype=float)
        if arr.ndim != 2 or arr.shape[1] != 2 or not np.all(np.isfinite(arr)):
            raise ScenarioError(f"{where}.points: expected a list of [x, y]")
        parts.append(arr)
    if not parts:
        raise ScenarioError(f"{where}: no features (give areas or points)")
    return np.concatenate(parts)


def scenario_from_dict(document: Mapping[str, Any], source: str = "<dict>") -> Scenario:
    """Build a scenario from a parsed YAML document (the mapping holding ``scenario:``)."""
    root = _mapping(document, source)
    if "scenario" not in root:
        raise ScenarioError(f"{source}: missing top-level key 'scenario'")
    where = f"{source}: scenario"
    node = _mapping(root["scenario"], where)
    _check_keys(
        node, {"name", "description", "seed", "sample_time", "world", "defaults", "robots"}, where
    )
    defaults = _mapping(node.get("defaults") or {}, f"{where}.defaults")
    _check_keys(defaults, _ROBOT_KEYS - {"name", "start", "program"}, f"{where}.defaults")
    robots_node = node.get("robots")
    if not isinstance(robots_node, list) or not robots_node:
        raise ScenarioError(f"{where}.robots: expected a non-empty list")
    robots = tuple(_robot(r, f"{where}.robots[{k}]", defaults) for k, r in enumerate(robots_node))
    names = [r.name for r in robots]
    if len(set(names)) != len(names):
        raise ScenarioError(f"{where}.robots: duplicate robot names in {names}")
    for r in robots:
        unknown = sorted(set(r.observes or ()) - set(names))
        if unknown:
            raise ScenarioError(f"{where}.robots ({r.name}).observes: unknown robots {unknown}")
    seed = node.get("seed", 0)
    if not isinstance(seed, int) or isinstance(seed, bool):
        raise ScenarioError(f"{where}.seed: expected an integer, got {seed!r}")
    sample_time = _number(node, "sample_time", where)
    if sample_time <= 0:
        raise ScenarioError(f"{where}.sample_time: must be positive")
    return Scenario(
        name=str(node.get("name", "unnamed")),
        sample_time=sample_time,
        features=_world(node.get("world"), f"{where}.world"),
        robots=robots,
        seed=seed,
        description=str(node.get("description", "")),
    )


def load_scenario(name_or_path: str | Path) -> Scenario:
    """Load a scenario by file path or by name (``map_joining`` -> ``config/map_joining.yaml``)."""
    path = resolve_config_path(name_or_path)
    return scenario_from_dict(load_document(path), str(path))
