"""Waiting for a condition in tests that talk to other processes (import as ``waiting``)."""

from __future__ import annotations

import signal
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
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


@contextmanager
def no_hang(seconds: float = 10.0) -> Iterator[None]:
    """Fail with TimeoutError where the body blocks longer than ``seconds`` (SIGALRM: the
    main thread only), e.g. a reader that would wait forever on a FIFO."""

    def expired(signum: int, frame: Any) -> None:
        raise TimeoutError(f"blocked for more than {seconds} s")

    previous = signal.signal(signal.SIGALRM, expired)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)
