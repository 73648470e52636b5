"""The markers and summary of the merger's solved joined maps built in a process of their own.

A joined map of a long run carries every robot's whole trajectory: on MR.CLAM Dataset 1 at
its end 28,000 poses and as many stamps. Its message is written from arrays in milliseconds
(:func:`~csam_ros.ros.map_messages.serialized_joined_map`) and goes out first, but its markers
take 0.26 s of Python to build and serialize and the summary's JSON 0.36 s. In the merger's
process that would hold the interpreter lock that the executor needs to take local maps and
publish. A :class:`MessageProcess` child builds them from the result (a pickle of numpy
arrays, a few milliseconds) and returns serialized CDR, which the merger publishes as it is
(``rclpy`` publishes ``bytes`` without touching them). A child that fails or dies is started
again at the next request; meanwhile the messages are built in the caller's process, so none
is lost.
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from multiprocessing.connection import Connection
from typing import Any

from rclpy.serialization import serialize_message

from csam_ros.core.joining.result import CsamResult, RunSummary
from csam_ros.ros.conversions import ns_to_time
from csam_ros.ros.markers import joined_map_markers
from csam_ros.solve_process import forkserver_context, stop_child


@dataclass(frozen=True)
class MarkersRequest:
    """What a solved joined map's markers (stamped ``stamp_ns``) and, with ``summary``, its
    summary text are built from."""

    result: CsamResult
    stamp_ns: int
    summary: RunSummary | None = None


@dataclass(frozen=True)
class MarkersAndSummary:
    """The serialized markers of a :class:`MarkersRequest` and its summary text (None when
    not asked for)."""

    markers: bytes
    summary_text: str | None = None


def build_markers(request: MarkersRequest) -> MarkersAndSummary:
    """Build and serialize what ``request`` asks for (in whichever process calls it)."""
    markers = joined_map_markers(request.result, ns_to_time(request.stamp_ns))
    return MarkersAndSummary(
        serialize_message(markers),
        None if request.summary is None else request.summary.text(),
    )


@dataclass(frozen=True)
class _Failed:
    error: str


def _serve(connection: Connection) -> None:
    """The child: one reply per request, until the parent closes its end or goes."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's to handle
    while True:
        try:
            request = connection.recv()
        except (EOFError, OSError):
            return
        try:
            reply: MarkersAndSummary | _Failed = build_markers(request)
        except Exception as err:  # noqa: BLE001 - the child outlives any one request
            reply = _Failed(f"{type(err).__name__}: {err}")
        try:
            connection.send(reply)
        except (EOFError, OSError):
            return


@dataclass
class MessageProcess:
    """A child process building the markers and summaries of one merger's solved joined maps
    (module docstring); thread safe, one request at a time. ``failures`` counts the requests
    the child did not answer (built in the caller's process instead), ``last_error`` says why
    the last one failed, and ``on_failure`` (when given) is told each time."""

    on_failure: Callable[[str], None] | None = field(default=None, repr=False)
    failures: int = 0
    last_error: str = ""
    starts: int = 0
    _process: Any = field(default=None, repr=False)
    _connection: Connection | None = field(default=None, repr=False)
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False)
    _closed: bool = False

    def start(self) -> None:
        """Start the child unless it runs (it imports while the caller goes on)."""
        with self._lock:
            if not self._closed:
                self._ensure_started()

    def build(self, request: MarkersRequest) -> MarkersAndSummary:
        """``request`` serialized by the child, or here if the child fails or is closed."""
        with self._lock:
            if not self._closed:
                self._ensure_started()
                assert self._connection is not None
                try:
                    self._connection.send(request)
                    reply = self._connection.recv()
                except (EOFError, OSError) as err:
                    self._stop_child()
                    reply = _Failed(f"the message process ended ({type(err).__name__})")
                if isinstance(reply, MarkersAndSummary):
                    return reply
                self.failures += 1
                self.last_error = reply.error
                if self.on_failure is not None:
                    self.on_failure(f"{reply.error}: built in this process instead")
        return build_markers(request)

    def close(self) -> None:
        """Stop the child for good (a later request is built in the caller's process)."""
        with self._lock:
            self._closed = True
            self._stop_child()

    def _ensure_started(self) -> None:
        if self._process is not None and self._process.is_alive():
            return
        self._stop_child()
        context = forkserver_context()
        mine, theirs = context.Pipe()
        process = context.Process(
            target=_serve, args=(theirs,), name="csam-merger-messages", daemon=True
        )
        process.start()
        theirs.close()
        self._process, self._connection = process, mine
        self.starts += 1

    def _stop_child(self) -> None:
        process, connection = self._process, self._connection
        self._process = self._connection = None
        stop_child(process, connection)
