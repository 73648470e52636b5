"""A project module run as a command, as a user runs it (``python -m MODULE ARGS``).

test/conftest.py puts this folder on ``sys.path``, so a test imports it as ``module_runs``.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def module_output(*args: str | Path, timeout: float = 300.0) -> str:
    """What ``python -m ARGS`` printed, run from the repository; its output in the assertion
    when it fails."""
    done = subprocess.run(
        [sys.executable, "-m", *map(str, args)],
        capture_output=True,
        text=True,
        timeout=timeout,
        cwd=REPO,
    )
    assert done.returncode == 0, done.stdout + done.stderr
    return done.stdout
