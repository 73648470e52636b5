"""The nodes' parameters from a config file: the merger's and the smoothers' keys, checked
before any node starts."""

from __future__ import annotations

from pathlib import Path

import pytest

from csam_ros.core.model.config_file import load_document
from csam_ros.run.errors import RunError
from csam_ros.run.params import load_config_document, merger_params, smoother_params


def test_no_config_gives_the_merger_its_solve_period_and_the_smoothers_nothing() -> None:
    assert load_config_document(None) == {}
    assert merger_params({}) == {"solve_period": 0.5}
    assert smoother_params({}) == {}


def test_the_mrclam_config_splits_between_the_nodes() -> None:
    """config/mrclam.yaml's merger section as seconds, the local map section to the smoothers
    (never the offline-only batch_window)."""
    document = load_document("mrclam")
    merger = merger_params(document)
    for key, value in document["merger"].items():
        assert merger[key] == float(value) and isinstance(merger[key], float)
    smoother = smoother_params(document)
    assert "batch_window" not in smoother
    assert set(smoother) <= set(document["local_map"]) | set(document["csam"]) | set(
        document.get("input") or {}
    )
    assert smoother and not set(smoother) & set(merger)


@pytest.mark.parametrize(
    ("merger", "message"),
    [
        ({"solve_every": 1}, "merger: unknown key(s) ['solve_every']; allowed: "),
        ([1, 2], "merger: unknown key(s) ['(not a map)']"),
        ({"stale_after": -1}, "merger.stale_after: expected seconds >= 0, got -1"),
        ({"solve_period": True}, "merger.solve_period: expected seconds >= 0, got True"),
        ({"solve_period": "1"}, "merger.solve_period: expected seconds >= 0, got '1'"),
    ],
)
def test_a_bad_merger_section_is_a_run_error(merger: object, message: str) -> None:
    with pytest.raises(RunError) as raised:
        merger_params({"merger": merger})
    assert str(raised.value).startswith(message), raised.value


def test_a_bad_section_or_file_is_a_run_error_naming_it(tmp_path: Path) -> None:
    with pytest.raises(RunError, match="local_map"):
        smoother_params({"local_map": {"robust_kernel": "tukey"}})
    with pytest.raises(RunError, match="^--config: .*missing.yaml"):
        load_config_document(tmp_path / "missing.yaml")
    (tmp_path / "bad.yaml").write_text("csam: [\n")
    with pytest.raises(RunError, match="^--config: .*bad.yaml: not valid YAML"):
        load_config_document(tmp_path / "bad.yaml")
