"""One function call computed in a forked child process while the caller goes on.

A fork copies the caller's imported modules and its data, so the child starts at once and the
call's arguments need no pickling; only its outcome (value or exception) comes back, pickled
through a pipe. A process with other threads is never forked (a fork copies no thread, and a
lock another thread held would stay locked in the child): there, and where fork is missing,
the call runs in the caller when it is made.
"""

from __future__ import annotations

import contextlib
import os
import pickle
import signal
import sys
import threading
from collections.abc import Callable
from typing import Any, Generic, TypeVar

T = TypeVar("T")


def can_fork() -> bool:
    """Whether this process may fork: it has the call and no thread but the main one."""
    return hasattr(os, "fork") and threading.active_count() == 1


class Forked(Generic[T]):
    """``function(*args)`` computed in a forked child; :meth:`result` waits for it.

    An exception the call raised is raised again by :meth:`result` (as a ``RuntimeError``
    naming it if it cannot be pickled). Ctrl-C is the caller's to handle: the child ignores it
    and is killed by :meth:`close`."""

    def __init__(self, function: Callable[..., T], *args: Any) -> None:
        self._pid: int | None = None
        self._stream: Any = None
        self._outcome: tuple[bool, Any] | None = None
        if not can_fork():
            self._outcome = _call(function, args)
            return
        read_end, write_end = os.pipe()
        pid = os.fork()
        if pid == 0:  # the child: compute, send, and leave without running the caller's code
            os.close(read_end)
            signal.signal(signal.SIGINT, signal.SIG_IGN)
            outcome = _call(function, args)
            with os.fdopen(write_end, "wb") as stream:
                try:
                    pickle.dump(outcome, stream)
                except Exception as err:  # noqa: BLE001  (an unpicklable value or exception)
                    pickle.dump((False, RuntimeError(f"{type(err).__name__}: {err}")), stream)
            sys.stdout.flush()
            sys.stderr.flush()
            os._exit(0)
        os.close(write_end)
        self._pid, self._stream = pid, os.fdopen(read_end, "rb")

    def result(self) -> T:
        """The call's value, once its child has sent it; or its exception, raised here."""
        if self._outcome is None:
            try:
                self._outcome = pickle.load(self._stream)
            except EOFError:
                self._outcome = (False, RuntimeError("its process ended without a word"))
            finally:
                self._reap(kill=False)
        done, value = self._outcome
        if not done:
            raise value
        return value

    def close(self) -> None:
        """Stop the child if it is still computing (the caller no longer wants the result)."""
        self._reap(kill=True)

    def _reap(self, kill: bool) -> None:
        if self._stream is not None:
            self._stream.close()
            self._stream = None
        if self._pid is not None:
            if kill:
                with contextlib.suppress(ProcessLookupError):
                    os.kill(self._pid, signal.SIGKILL)
            os.waitpid(self._pid, 0)
            self._pid = None


def _call(function: Callable[..., Any], args: tuple[Any, ...]) -> tuple[bool, Any]:
    try:
        return True, function(*args)
    except Exception as err:  # noqa: BLE001  (raised again in the caller)
        return False, err
