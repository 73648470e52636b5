"""What a run says about input it cannot use: an error (one line, exit code 2 in the ``csam``
command) or a warning printed once (e.g. a bag cut short)."""

from __future__ import annotations

import sys


class RunError(Exception):
    """Input a run cannot use (an option, a file, a config): said as one line."""


_warned: set[str] = set()


def warn(line: str) -> None:
    """Print a warning about the input once, e.g. a bag cut short or with a damaged chunk
    (what was read and what was lost)."""
    if line not in _warned:
        _warned.add(line)
        print(f"warning: {line}", file=sys.stderr)
