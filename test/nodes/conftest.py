"""Fixtures of the merger's node tests."""

from __future__ import annotations

import pytest
from merger_harness import RunMessages, run_messages


@pytest.fixture(scope="module")
def good() -> RunMessages:
    """The smoothers' messages of a whole simulated run (map_joining)."""
    return run_messages()
