"""Parameter and scenario files (YAML) and where they are found.

A name such as ``mrclam`` means ``<config dir>/mrclam.yaml``. The config directory is, first
found: ``$CSAM_CONFIG_DIR``; ``share/csam_ros/config`` under each prefix of
``$AMENT_PREFIX_PATH`` and under the Python environment's prefix (where ``colcon build`` and
``make`` install it); the ``config/`` folder of a source checkout.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import yaml

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
    directory = config_dir()
    candidate = directory / f"{name_or_path}.yaml"
    if candidate.is_file():
        return candidate
    raise ConfigFileError(
        f"{str(name_or_path)!r}: no such file and no {candidate.name} in {directory}"
    )


def load_document(name_or_path: str | Path) -> dict[str, Any]:
    """The whole parsed YAML document of a parameter or scenario file (all top-level keys)."""
    path = resolve_config_path(name_or_path)
    try:
        document = yaml.safe_load(path.read_text())
    except (yaml.YAMLError, UnicodeDecodeError) as err:
        raise ConfigFileError(f"{path}: not valid YAML: {err}") from err
    if not isinstance(document, dict):
        raise ConfigFileError(f"{path}: expected a mapping, got {type(document).__name__}")
    return document
