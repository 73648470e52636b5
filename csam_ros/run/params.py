"""The nodes' parameters from a config file's sections, checked before any node starts."""

from __future__ import annotations

from pathlib import Path

from csam_ros.run.errors import RunError

MERGER_KEYS = {
    "solve_period",
    "solve_wait",
    "stale_after",
    "provisional_period",
    "provisional_quiet",
}  # s


def load_config_document(path: Path | None) -> dict:
    """The sections of a run's config file (``--config``; None: no file, no sections)."""
    if path is None:
        return {}
    from csam_ros.core.model.config_file import ConfigFileError, load_document

    try:
        return load_document(path)
    except (ConfigFileError, OSError) as err:
        raise RunError(f"--config: {err}") from None


def node_params(document: dict, section: str, cls: type, node: str) -> dict:
    """The keys given in a file section that ``node`` takes as parameters (the dataclass
    fields whose Setting names it), checked and typed as declared."""
    from csam_ros.core.model.config_file import settings

    given = document.get(section)
    try:
        config = cls.from_dict(given, section)
    except ValueError as err:
        raise RunError(str(err)) from None
    return {
        name: getattr(config, name)
        for name, (rule, _) in settings(cls).items()
        if rule.node == node and name in (given or {})
    }


def merger_params(document: dict) -> dict:
    """The merger's parameters: its fields of the ``csam:`` section and the ``merger:``
    section's ``solve_period``, ``solve_wait``, ``stale_after``, ``provisional_period`` and
    ``provisional_quiet`` (seconds)."""
    from csam_ros.core.joining.config import MERGER, CsamConfig

    csam = node_params(document, "csam", CsamConfig, MERGER)
    merger = document.get("merger") or {}
    unknown = sorted(set(merger) - MERGER_KEYS) if isinstance(merger, dict) else ["(not a map)"]
    if unknown:
        raise RunError(f"merger: unknown key(s) {unknown}; allowed: {sorted(MERGER_KEYS)}")
    seconds = {"solve_period": 0.5, **merger}
    for key, value in seconds.items():
        if isinstance(value, bool) or not isinstance(value, int | float) or not value >= 0:
            raise RunError(f"merger.{key}: expected seconds >= 0, got {value!r}")
    return {**csam, **{key: float(value) for key, value in seconds.items()}}


def smoother_params(document: dict) -> dict:
    """The smoothers' parameters: their fields of the ``local_map:`` section (all but the
    offline-only ``batch_window``), of the ``csam:`` section (the rendezvous thinning) and the
    ``input:`` section (bounds on sensor messages)."""
    from csam_ros.core.exchange.validation import InputBounds
    from csam_ros.core.joining.config import CsamConfig
    from csam_ros.core.smoothing.local_map_config import SMOOTHER, LocalMapConfig

    return {
        **node_params(document, "local_map", LocalMapConfig, SMOOTHER),
        **node_params(document, "csam", CsamConfig, SMOOTHER),
        **node_params(document, "input", InputBounds, SMOOTHER),
    }
