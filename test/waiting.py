"""Waiting for a condition in tests that talk to other processes (import as ``waiting``)."""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any


def wait_until(
    condition: Callable[[], Any], timeout_s: float = 15.0, step: Callable[[], Any] | None = None
) -> bool:
    """Call ``step`` (by default: sleep 20 ms) until ``condition()`` holds or ``timeout_s``
    passes; whether it held."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            return False
        if step is None:
            time.sleep(0.02)
        else:
            step()
    return True
