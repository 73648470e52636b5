"""The merger's joins in a process of its own, so that its executor keeps a core's share.

A solve is seconds of Python and numpy. In a thread of the merger it shares one interpreter
with the executor, which then takes input, publishes provisional maps and status at the pace
the interpreter lock allows. :class:`SolveProcess` runs a :class:`~csam_ros.core.joiner.Joiner`
in a child process started from a fork server (a clean process that imported the core once:
the merger has threads, which a fork would not copy). The child keeps the joiner's state
between solves, so a request carries a robot's map only when it changed, and the warm start
only when the child does not hold it. A child that dies is started again at the next solve,
which then sends everything.
"""

from __future__ import annotations

import multiprocessing
import signal
import threading
from dataclasses import replace
from multiprocessing.connection import Connection
from typing import Any

from csam_ros.core.joiner import Joiner, JoinReply, JoinRequest, MapSource
from csam_ros.core.result import CsamResult

# what the fork server imports once, so that a child starts at once
PRELOAD = ["csam_ros.core.joiner"]


def _serve(connection: Connection) -> None:
    """The child: one reply per request, until the parent closes its end or goes."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's to handle
    joiner = Joiner()
    while True:
        try:
            request = connection.recv()
        except (EOFError, OSError):
            return
        try:
            reply = joiner.join(request)
        except Exception as err:  # noqa: BLE001 - the child outlives any one request
            reply = JoinReply(None, f"{type(err).__name__}: {err}")
        try:
            connection.send(reply)
        except (EOFError, OSError):
            return


class SolveProcess:
    """A child process joining maps for one merger (module docstring): started by
    :meth:`start` (else by the first :meth:`join`), again by a join after it died, stopped
    by :meth:`close`."""

    def __init__(self) -> None:
        self._process: Any = None
        self._connection: Connection | None = None
        self._lock = threading.Lock()  # join and close may come from different threads
        self._sent: dict[str, MapSource] = {}  # the source of each robot the child holds
        self._previous: CsamResult | None = None  # the result the child holds as warm start
        self._closed = False
        self.starts = 0

    @property
    def pid(self) -> int | None:
        """The child's process id (None when none runs)."""
        return self._process.pid if self._process is not None else None

    def start(self) -> None:
        """Start the child unless it runs: it imports the core while the caller goes on."""
        with self._lock:
            self._ensure_started()

    def join(self, request: JoinRequest) -> JoinReply:
        """``request`` joined by the child (started first if need be); a failed join or a
        child that died is a reply with an error, never an exception."""
        with self._lock:
            if self._closed:
                return JoinReply(None, "the solve process is closed")
            self._ensure_started()
            connection = self._connection
            assert connection is not None
            stripped = self.stripped(request)
        try:
            connection.send(stripped)
            reply: JoinReply = connection.recv()
        except (EOFError, OSError) as err:
            self._stop_child()
            return JoinReply(None, f"the solve process ended ({type(err).__name__})")
        with self._lock:
            self._sent.update({robot: source for robot, source in request.maps})
            if reply.result is not None:
                self._previous = reply.result
        return reply

    def stripped(self, request: JoinRequest) -> JoinRequest:
        """``request`` without what the child holds: the maps it was sent last (``None``)
        and its warm start."""
        maps = tuple(
            (robot, None if self._sent.get(robot) is source else source)
            for robot, source in request.maps
        )
        previous = None if request.previous is self._previous else request.previous
        return replace(request, maps=maps, previous=previous)

    def close(self) -> None:
        """Stop the child, at once if it is solving (its solve is lost), for good."""
        with self._lock:
            self._closed = True
        self._stop_child()

    def _stop_child(self) -> None:
        with self._lock:
            process, connection = self._process, self._connection
            self._process = self._connection = None
        if process is not None and process.is_alive():
            process.kill()
        if process is not None:
            process.join()
        if connection is not None:
            connection.close()

    def _ensure_started(self) -> None:
        if self._process is None or not self._process.is_alive():
            self._start()

    def _start(self) -> None:
        context = multiprocessing.get_context("forkserver")
        context.set_forkserver_preload(PRELOAD)  # read when the fork server starts
        mine, theirs = context.Pipe()
        process = context.Process(
            target=_serve, args=(theirs,), name="csam-merger-solve", daemon=True
        )
        process.start()
        theirs.close()
        self._process, self._connection = process, mine
        self._sent, self._previous = {}, None
        self.starts += 1
