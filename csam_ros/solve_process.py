"""The merger's joins in a process of its own, so that its executor keeps a core's share.

A solve is seconds of Python and numpy. In a thread of the merger it shares one interpreter
with the executor, which then takes input, publishes provisional maps and status at the pace
the interpreter lock allows. :class:`SolveProcess` runs a
:class:`~csam_ros.core.merging.joiner.Joiner` in a child process started from a fork server (a
clean process that imported the core once: the merger has threads, which a fork would not copy).
The child keeps the joiner's state between solves, so a request carries a robot's map only when it
changed, and the warm start only when the child does not hold it. A child that dies is started
again at the next solve, which then sends everything. Between solves the merger sends each new map
as it arrives (:meth:`SolveProcess.prepare`), so that the child refines and factors it while it
waits for the others. A join's state (when asked for) is written
after its reply: :meth:`SolveProcess.state_written` waits for it. :meth:`SolveProcess.cancel` gives
the running join up (a signal
the child turns into :class:`~csam_ros.core.merging.joiner.JoinCancelled` while it joins): the child
keeps its maps and warm start, and the join's reply says it was cancelled.
"""

from __future__ import annotations

import contextlib
import multiprocessing
import os
import signal
import threading
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import replace
from multiprocessing.connection import Connection
from types import FrameType
from typing import Any

from csam_ros.core.joining.result import CsamResult
from csam_ros.core.merging.joiner import (
    JoinCancelled,
    Joiner,
    JoinReply,
    JoinRequest,
    MapSource,
    PrepareRequest,
    StateWritten,
)

# what the fork server imports once, so that a child starts at once (this module's and
# csam_ros.message_process's)
PRELOAD = ["csam_ros.core.merging.joiner", "csam_ros.message_process"]
CANCEL_SIGNAL = signal.SIGUSR1


def forkserver_context() -> Any:
    """The multiprocessing context of the merger's children: a fork server (the merger has
    threads, which a fork would not copy) that imported :data:`PRELOAD` once."""
    context = multiprocessing.get_context("forkserver")
    context.set_forkserver_preload(PRELOAD)  # read when the fork server starts
    return context


def stop_child(process: Any, connection: Connection | None) -> None:
    """Kill a child ``process`` (None: none) if it runs, reap it and close its pipe end."""
    if process is not None and process.is_alive():
        process.kill()
    if process is not None:
        process.join()
    if connection is not None:
        connection.close()


class _Cancellation:
    """In the child: the requests are numbered from 1 as they come; ``cancelled`` (shared
    with the parent) holds the number of the one to give up. Entering :meth:`cancellable`
    for it, or :data:`CANCEL_SIGNAL` coming while inside, raises :class:`JoinCancelled`; at
    any other time the signal does nothing (a request or reply on the pipe is never cut)."""

    def __init__(self, cancelled: Any) -> None:
        self.cancelled = cancelled  # a multiprocessing.Value("q")
        self.request = 0  # the number of the request being served
        self.armed = False
        signal.signal(CANCEL_SIGNAL, self._on_signal)

    def _on_signal(self, signum: int, frame: FrameType | None) -> None:
        if self.armed and self.cancelled.value == self.request:
            self.armed = False
            raise JoinCancelled("given up by the merger")

    @contextmanager
    def cancellable(self) -> Iterator[None]:
        if self.cancelled.value == self.request:
            raise JoinCancelled("given up by the merger")
        self.armed = True
        try:
            yield
        finally:
            self.armed = False


def _serve(connection: Connection, cancelled: Any, niceness: int) -> None:
    """The child: one reply per request, until the parent closes its end or goes."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's to handle
    os.nice(niceness)
    cancellation = _Cancellation(cancelled)
    joiner = Joiner(cancellation.cancellable)
    while True:
        try:
            request = connection.recv()
        except (EOFError, OSError):
            return
        cancellation.request += 1
        if isinstance(request, PrepareRequest):
            with contextlib.suppress(Exception):  # the child outlives it; the join says more
                joiner.prepare(request)
            try:
                connection.send(None)  # prepared
            except (EOFError, OSError):
                return
            continue
        try:
            reply = joiner.join(request)
        except Exception as err:  # noqa: BLE001 - the child outlives any one request
            reply = JoinReply(None, f"{type(err).__name__}: {err}")
        try:
            connection.send(reply)
            if reply.state_pending:  # after the reply: the joined map goes out first
                connection.send(joiner.write_state())
        except (EOFError, OSError):
            return


class SolveProcess:
    """A child process joining maps for one merger (module docstring): started by
    :meth:`start` (else by the first :meth:`join`), again by a join after it died, stopped
    by :meth:`close`. It runs ``niceness`` below the caller's priority: on a busy machine the
    nodes that take and publish messages come first, the solves get the rest."""

    def __init__(self, niceness: int = 0) -> None:
        self.niceness = niceness
        self._process: Any = None
        self._connection: Connection | None = None
        self._lock = threading.Lock()  # join and close may come from different threads
        self._sent: dict[str, MapSource] = {}  # the source of each robot the child holds
        self._previous: CsamResult | None = None  # the result the child holds as warm start
        self._closed = False
        self._joining = False  # a request is with the child
        self._state_pending = False  # the child writes the state of the last join
        self._requests = 0  # requests sent to the child (its numbering)
        self._cancelled: Any = None  # shared with the child: the request it is to give up
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
        self.state_written()  # a state write not waited for ends first
        with self._lock:
            if self._closed:
                return JoinReply(None, "the solve process is closed")
            self._ensure_started()
            connection = self._connection
            assert connection is not None
            stripped = self.stripped(request)
            self._joining = True
            self._requests += 1
        try:
            connection.send(stripped)
            reply: JoinReply = connection.recv()
        except (EOFError, OSError) as err:
            self._stop_child()
            return JoinReply(None, f"the solve process ended ({type(err).__name__})")
        finally:
            with self._lock:
                self._joining = False
        with self._lock:
            self._sent.update({robot: source for robot, source in request.maps})
            if reply.result is not None:
                self._previous = reply.result
            self._state_pending = reply.state_pending
        return reply

    def prepare(self, maps: Sequence[tuple[str, MapSource]]) -> None:
        """Send the child the sources of ``maps`` it does not hold, and wait while it takes
        them and computes what a join derives from each map alone
        (:meth:`~csam_ros.core.merging.joiner.Joiner.prepare`): work the next join then does
        not do. A map it refuses is in that join's reply. Call it from the thread that joins;
        a child that died is started again by the next join."""
        self.state_written()
        with self._lock:
            new = tuple((robot, s) for robot, s in maps if self._sent.get(robot) is not s)
            if self._closed or not new:
                return
            self._ensure_started()
            connection = self._connection
            assert connection is not None
            self._requests += 1
        try:
            connection.send(PrepareRequest(new))
            connection.recv()
        except (EOFError, OSError):
            self._stop_child()
            return
        with self._lock:
            self._sent.update(new)

    def state_written(self) -> StateWritten | None:
        """Wait for the state write of the last join (None when it asked for none, or it
        was waited for already)."""
        with self._lock:
            connection = self._connection
            if not self._state_pending or connection is None:
                return None
        try:
            written: StateWritten = connection.recv()
        except (EOFError, OSError) as err:
            self._stop_child()
            written = StateWritten(f"merger state not written: the solve process ended ({err!r})")
        with self._lock:
            self._state_pending = False
        return written

    def cancel(self) -> bool:
        """Give up the running join, if any: its :meth:`join` returns a reply that says it
        was cancelled, unless the join was already ending. Whether a join was running."""
        with self._lock:
            if not self._joining or self._process is None:
                return False
            self._cancelled.value = self._requests
            with contextlib.suppress(ProcessLookupError):  # it has just ended
                os.kill(self._process.pid, CANCEL_SIGNAL)
            return True

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
        stop_child(process, connection)

    def _ensure_started(self) -> None:
        if self._process is None or not self._process.is_alive():
            self._start()

    def _start(self) -> None:
        context = forkserver_context()
        mine, theirs = context.Pipe()
        cancelled = context.Value("q", 0, lock=False)
        process = context.Process(
            target=_serve,
            args=(theirs, cancelled, self.niceness),
            name="csam-merger-solve",
            daemon=True,
        )
        process.start()
        theirs.close()
        self._process, self._connection, self._cancelled = process, mine, cancelled
        self._sent, self._previous, self._requests = {}, None, 0
        self._state_pending = False  # a new child writes no state it was not asked for
        self.starts += 1
