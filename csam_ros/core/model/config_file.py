"""Parameter and scenario files (YAML), where they are found, and how their values are checked.

A name such as ``mrclam`` means ``<config dir>/mrclam.yaml``. The config directory is, first
found: ``$CSAM_CONFIG_DIR``; ``share/csam_ros/config`` under each prefix of
``$AMENT_PREFIX_PATH`` and under the Python environment's prefix (where ``colcon build`` and
``make`` install it); the ``config/`` folder of a source checkout.

A parameter dataclass declares each field with :func:`setting` (description, minimum, choices,
the node that takes it); :func:`from_mapping` checks a file section against those rules (a
:class:`Section` subclass by its ``from_dict``), and the nodes declare their ROS parameters from
the same fields.
"""

from __future__ import annotations

import math
import os
import sys
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any, ClassVar, Self, TypeVar

import yaml

from csam_ros.core.model import yaml_text

T = TypeVar("T")
CONFIG_DIR_VARIABLE = "CSAM_CONFIG_DIR"
_SHARE = Path("share") / "csam_ros" / "config"
_SOURCE_TREE = Path(__file__).resolve().parents[2] / "config"


class ConfigFileError(ValueError):
    """A parameter or scenario file that cannot be read; the message names the file."""


def _candidate_dirs() -> Iterator[Path]:
    if os.environ.get(CONFIG_DIR_VARIABLE):
        yield Path(os.environ[CONFIG_DIR_VARIABLE])
        return
    for prefix in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep):
        if prefix:
            yield Path(prefix) / _SHARE
    yield Path(sys.prefix) / _SHARE
    yield _SOURCE_TREE


def config_dir() -> Path:
    """The directory that named parameter and scenario files are looked up in."""
    for candidate in _candidate_dirs():
        if candidate.is_dir():
            return candidate
    return next(_candidate_dirs())


def resolve_config_path(name_or_path: str | Path) -> Path:
    """An existing file path, or the file a name stands for in :func:`config_dir`."""
    path = Path(name_or_path)
    if path.is_file():
        return path
    if path.suffix or len(path.parts) > 1:  # a file path, not a name
        raise ConfigFileError(f"{path}: no such file")
    directory = config_dir()
    candidate = directory / f"{name_or_path}.yaml"
    if candidate.is_file():
        return candidate
    raise ConfigFileError(
        f"{str(name_or_path)!r}: no such file and no {candidate.name} in {directory}"
    )


# The top-level sections of parameter and scenario files and who reads them: ``scenario``
# (datasets.scenario, the simulator), ``csam`` (core.joining.config.CsamConfig: the merger, the
# smoothers' rendezvous thinning), ``local_map`` (core.smoothing.local_map_config.LocalMapConfig:
# the smoothers), ``merger`` (the merger node's solve_period), ``mrclam`` (the MR.CLAM importer
# and calibration) and ``input`` (core.exchange.validation.InputBounds: bounds on sensor messages,
# in the smoothers and offline replay). Any other top-level key is an error, so that a misspelt
# section never leaves its settings at their defaults unnoticed.
SECTIONS = ("csam", "local_map", "merger", "mrclam", "scenario", "input")


def load_document(name_or_path: str | Path) -> dict[str, Any]:
    """The whole parsed YAML document of a parameter or scenario file (all top-level keys,
    each one of :data:`SECTIONS`)."""
    path = resolve_config_path(name_or_path)
    try:
        document = yaml_text.safe_load(path.read_bytes().decode("utf-8"))
    except (yaml.YAMLError, UnicodeDecodeError) as err:
        raise ConfigFileError(f"{path}: not valid YAML: {' '.join(str(err).split())}") from err
    except OSError as err:
        raise ConfigFileError(f"{path}: cannot read: {err.strerror or err}") from err
    if not isinstance(document, dict):
        raise ConfigFileError(f"{path}: expected a mapping, got {type(document).__name__}")
    unknown = sorted(str(key) for key in document if key not in SECTIONS)
    if unknown:
        raise ConfigFileError(
            f"{path}: unknown top-level section(s) {unknown}; known: {list(SECTIONS)}"
        )
    return document


SETTING = "setting"  # the dataclass field metadata key of a :class:`Setting`


@dataclass(frozen=True)
class Setting:
    """What a field of a parameter dataclass means and which values it takes."""

    description: str
    minimum: float | None = None  # numbers: the least value allowed
    exclusive: bool = False  # the minimum itself is not allowed
    choices: tuple[str, ...] = ()  # strings: the values allowed
    node: str | None = None  # the node that takes it as a ROS parameter (None: offline only)

    def check(self, value: Any, default: Any, where: str) -> Any:
        """``value`` converted to the type of ``default``; ValueError naming ``where``."""
        if isinstance(default, bool):
            if not isinstance(value, bool):
                raise ValueError(f"{where}: expected true/false, got {value!r}")
            return value
        if isinstance(default, str):
            if not isinstance(value, str) or (self.choices and value not in self.choices):
                allowed = ", ".join(repr(c) for c in self.choices) if self.choices else "a string"
                raise ValueError(f"{where}: {value!r} is not one of {allowed}")
            return value
        integral = isinstance(value, float) and value.is_integer()
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise ValueError(f"{where}: expected a number, got {value!r}")
        if isinstance(default, int) and not (isinstance(value, int) or integral):
            raise ValueError(f"{where}: expected a whole number, got {value!r}")
        if not math.isfinite(value):
            raise ValueError(f"{where}: must be finite, got {value!r}")
        if self.minimum is not None and (
            value <= self.minimum if self.exclusive else value < self.minimum
        ):
            bound = "greater than" if self.exclusive else "at least"
            raise ValueError(f"{where}: must be {bound} {self.minimum:g}, got {value!r}")
        return type(default)(value)

    @property
    def constraint(self) -> str:
        """The rule in words (empty when the type says all)."""
        if self.choices:
            return "one of " + ", ".join(repr(c) for c in self.choices)
        if self.minimum is None:
            return ""
        return f"{'>' if self.exclusive else '>='} {self.minimum:g}"


def setting(default: Any, description: str, **rules: Any) -> Any:
    """A dataclass field with its default and its :class:`Setting` (description and rules)."""
    return field(default=default, metadata={SETTING: Setting(description, **rules)})


def settings(cls: type) -> dict[str, tuple[Setting, Any]]:
    """Each field of a parameter dataclass: its Setting and its default."""
    return {f.name: (f.metadata[SETTING], f.default) for f in fields(cls)}


def from_mapping(cls: type[T], node: Mapping[str, Any] | None, source: str) -> T:
    """An instance of a parameter dataclass from a mapping of some of its fields, each value
    checked against its Setting; unknown keys and bad values are errors naming them."""
    if node is None:
        return cls()
    if not isinstance(node, Mapping):
        raise ValueError(f"{source}: expected a mapping, got {type(node).__name__}")
    known = settings(cls)
    unknown = sorted(set(node) - set(known))
    if unknown:
        raise ValueError(f"{source}: unknown key(s) {unknown}; allowed: {sorted(known)}")
    values = {}
    for key, value in node.items():
        rule, default = known[key]
        values[key] = rule.check(value, default, f"{source}.{key}")
    return cls(**values)


class Section:
    """Base of a parameter dataclass that is one section of a parameter file."""

    section: ClassVar[str] = ""  # the section's name in a parameter file

    @classmethod
    def from_dict(cls, node: Mapping[str, Any] | None, source: str | None = None) -> Self:
        """Build from a mapping (:func:`from_mapping`); unknown keys and bad values are errors
        naming them, after ``source`` (default: the section's name)."""
        return from_mapping(cls, node, source or cls.section)
