"""The state services of the smoother and the merger (docs/ARCHITECTURE.md, section Services).

- ``~/save_state`` (csam_msgs/SaveState: a path): write the node's state file there, in the
  format its ``checkpoint_path`` or ``state_path`` has (:mod:`csam_ros.core.exchange.checkpoint`),
  atomically. The smoother's is what it accepted and its local map as they are; the merger's is
  the state of its last joined map, as a solve writes it to ``state_path`` (none before the first
  joined map).
- ``~/load_state`` (csam_msgs/LoadState: a path): replace the node's state by the file's, as a
  restart from that file would, and publish what it holds: the smoother its local map (the first
  update of a new session: the whole map), the merger its joined map (then it asks the smoothers
  for their maps, as a merger started from the file does). A file missing, malformed, of another
  kind or another robot is refused in one line and the state stays as it was.
- ``~/reset`` (std_srvs/Trigger): forget every input, map and count, as a start without a state
  file would. The smoother goes on in a new session (the merger takes its next map for a
  restart); the merger publishes an empty joined map and asks the smoothers for their maps
  again. With ``checkpoint_path`` or ``state_path`` set, the empty state is written there.
- ``~/pause`` (std_srvs/SetBool): true stops taking input, every message that comes is dropped
  and counted as ``paused`` (and the merger asks for no whole map); false takes input again.
  Paused, a node keeps its map and answers every service; a reset or a load leaves it paused.

Every reply's message is one line; a handler that fails answers ``success`` false, logs the
error and counts it (``callback_error``): the node never dies of a request.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path
from typing import Any, TypeVar

from csam_msgs.msg import JoinedMap
from csam_msgs.srv import LoadState, SaveState
from rclpy.node import Node
from std_srvs.srv import SetBool, Trigger
from visualization_msgs.msg import Marker, MarkerArray

from csam_ros.core.exchange.checkpoint import UNUSABLE_STATE, MergerState
from csam_ros.core.exchange.state_files import CheckpointError
from csam_ros.core.exchange.validation import CALLBACK_ERROR, DropCounter, LocalMapError
from csam_ros.core.merging.notices import StateMissing, StateResumed, StateUnusable
from csam_ros.core.merging.policy_inputs import joined_maps, read_state
from csam_ros.ros.topics import LOAD_STATE, PAUSE, RESET, SAVE_STATE
from csam_ros.solve_process import SolveProcess

# a drop reason: input that came while the node was paused (~/pause)
PAUSED = "paused"
UNCHANGED = "not loaded, the state is unchanged"

R = TypeVar("R")


def one_line(text: str) -> str:
    """``text`` on one line (an error's message may span several)."""
    return " ".join(text.split())


def answer(response: R, success: bool, message: str) -> R:
    """``response`` (any reply with ``success`` and ``message``) filled in."""
    response.success = success  # type: ignore[attr-defined]
    response.message = one_line(message)  # type: ignore[attr-defined]
    return response


def answering(node: Node, drops: DropCounter, handler: Callable[[Any, R], R]) -> Callable[..., R]:
    """``handler`` of a service that never takes the node down: an unexpected exception is
    logged, counted under ``callback_error`` in ``drops`` and answered ``success`` false."""

    @functools.wraps(handler)
    def call(request: Any, response: R) -> R:
        try:
            return handler(request, response)
        except Exception as error:  # noqa: BLE001 - the boundary of a node: nothing escapes
            drops.add(CALLBACK_ERROR)
            node.get_logger().error(f"{handler.__name__}: {type(error).__name__}: {error}")
            return answer(response, False, f"{type(error).__name__}: {error}")

    return call


def requested_path(request: Any) -> Path:
    """The path a request names; ValueError when it names none."""
    if not request.path.strip():
        raise ValueError("no path given")
    return Path(request.path)


class Pause:
    """``~/pause``: whether the node takes input, and the wrapper of its input callbacks that
    drops (and counts under ``paused``) what comes while it does not. ``on_change(paused)``
    is called with the new setting."""

    def __init__(
        self, drops: DropCounter, on_change: Callable[[bool], None] = lambda paused: None
    ) -> None:
        self.drops = drops
        self.on_change = on_change
        self.paused = False

    def taking(self, callback: Callable[..., Any]) -> Callable[..., Any]:
        """``callback``, dropping its message while paused."""

        @functools.wraps(callback)
        def call(*args: Any) -> Any:
            if self.paused:
                self.drops.add(PAUSED)
                return None
            return callback(*args)

        return call

    def on_pause(self, request: SetBool.Request, response: SetBool.Response) -> SetBool.Response:
        was, self.paused = self.paused, bool(request.data)
        self.on_change(self.paused)
        state = "paused: input is dropped" if self.paused else "taking input"
        return answer(response, True, state if was != self.paused else f"already {state}")


def _map_size(smoother: Any) -> str:
    return f"{len(smoother.map.stamps)} poses, {len(smoother.map.landmark_labels)} features"


class StateServices:
    """``~/save_state``, ``~/load_state``, ``~/reset`` and ``~/pause`` of ``node``, answered by
    the subclass's ``on_save``, ``on_load`` and ``on_reset``; ``pause_changed(paused)`` is told
    of a new pause setting."""

    def __init__(self, node: Any) -> None:
        self.node = node
        self.pause = Pause(node.drops, self.pause_changed)
        self.taking = self.pause.taking
        handlers: dict[str, tuple[type, Callable]] = {
            SAVE_STATE: (SaveState, self.on_save),
            LOAD_STATE: (LoadState, self.on_load),
            RESET: (Trigger, self.on_reset),
            PAUSE: (SetBool, self.pause.on_pause),
        }
        for name, (srv_type, handler) in handlers.items():
            node.create_service(srv_type, f"~/{name}", answering(node, node.drops, handler))

    def pause_changed(self, paused: bool) -> None:
        """A new pause setting (the node's own flag is :attr:`pause`)."""

    def on_save(self, request: SaveState.Request, response: SaveState.Response) -> Any:
        raise NotImplementedError

    def on_load(self, request: LoadState.Request, response: LoadState.Response) -> Any:
        raise NotImplementedError

    def on_reset(self, request: Trigger.Request, response: Trigger.Response) -> Any:
        raise NotImplementedError


class SmootherServices(StateServices):
    """The smoother's state services (module docstring); the state itself is the node's
    (:meth:`~csam_ros.nodes.smoother.Smoother.checkpoint`, ``load``, ``forget``)."""

    def on_save(self, request: SaveState.Request, response: SaveState.Response) -> Any:
        node = self.node
        try:
            path = requested_path(request)
            size = node.checkpoint().write(path)
        except (OSError, ValueError) as err:
            return answer(response, False, f"not saved: {err}")
        return answer(response, True, f"saved to {path}: {_map_size(node)} ({size} bytes)")

    def on_load(self, request: LoadState.Request, response: LoadState.Response) -> Any:
        node = self.node
        try:
            path = requested_path(request)
            node.load(path)
        except (CheckpointError, ValueError) as err:
            if isinstance(err, CheckpointError):
                node.drops.add(UNUSABLE_STATE)
            return answer(response, False, f"{UNCHANGED}: {err}")
        node.publish_status()
        loaded = f"loaded {path}: {_map_size(node)}, in session {node.sender.session}"
        return answer(response, True, loaded)

    def on_reset(self, request: Trigger.Request, response: Trigger.Response) -> Any:
        node = self.node
        node.forget()
        if node.checkpoint_path is not None:
            node.write_checkpoint(node.checkpoint_path)
        node.publish_status()
        node.get_logger().info(f"reset: starting empty in session {node.sender.session}")
        return answer(response, True, f"reset: empty, in session {node.sender.session}")


class MergerServices(StateServices):
    """The merger's state services (module docstring), and its start from ``state_path``.
    A part of the node: it takes the node's locks as the node does (the policy under
    ``_lock``; no solve runs while it holds ``_solve_lock``)."""

    def pause_changed(self, paused: bool) -> None:
        with self.node._lock:
            self.node.policy.paused = paused

    def resume(self, path: Path) -> bool:
        """Take up the state saved at ``path`` at the node's start (before any subscription);
        whether it was (a file that cannot be used is logged once: the merger starts empty)."""
        saved = read_state(path)
        if not isinstance(saved, MergerState):
            if isinstance(saved, StateUnusable):
                self.node.drops.add(UNUSABLE_STATE)
            self.node._note(saved)
            return False
        self._take_up(saved)
        self.node._note(StateResumed(path, len(saved.maps), saved.reference, saved.solves))
        return True

    def _take_up(self, saved: MergerState) -> None:
        """Forget everything held, then go on from ``saved``: subscribed to its robots."""
        node = self.node
        with node._lock:
            node.policy.reset()
            robots = [r for r in node.policy.take_up(saved) if r not in node.policy.robots]
        for robot in robots:
            node._subscribe(robot)

    @contextmanager
    def _quiet(self) -> Iterator[None]:
        """Give a running solve up and hold the solve lock: while inside, no solve runs (the
        one given up has published what it had) and no provisional map is due. On the way in
        the solve process is replaced by a new one, which holds no map and no warm start of
        what the merger is to forget."""
        node = self.node
        with node._lock:
            if node.policy.solving:
                node.solve_process.cancel()
            node._provisional_due = None
        with node._solve_lock:
            old = node.solve_process
            node.solve_process = SolveProcess(old.niceness)
            old.close()
            node.solve_process.start()
            yield

    def _publish_held(self) -> None:
        """Publish the joined map the merger holds with its robots' poses (an empty one when it
        holds none, which clears the latched joined maps and the markers), and the status."""
        node = self.node
        with node._lock:
            result, stamps = node.policy.last_result, dict(node.policy.local_map_stamps)
            robots, maps = tuple(node.policy.robots), node.policy.local_maps
        if result is not None:
            node.output.joined_map(result, stamps, robots, maps=maps)
        else:
            empty = JoinedMap()
            empty.header.stamp = node.get_clock().now().to_msg()
            clear = MarkerArray(markers=[Marker(action=Marker.DELETEALL)])
            output = node.output
            with output.lock:
                if not output.stopping.is_set():
                    output.joined_pub.publish(empty)
                    output.provisional_pub.publish(empty)
                    output.markers_pub.publish(clear)
        node.publish_status()

    def on_save(self, request: SaveState.Request, response: SaveState.Response) -> Any:
        node = self.node
        with node._lock:
            saved = node.policy.saved_state()
        if saved is None:
            return answer(response, False, "not saved: no joined map yet")
        state, inputs = saved
        try:
            path = requested_path(request)
            state = replace(state, maps=joined_maps(inputs))
            size = state.write(path)
        except (OSError, ValueError, LocalMapError) as err:
            return answer(response, False, f"not saved: {err}")
        return answer(
            response,
            True,
            f"saved to {path}: {len(state.maps)} local maps, reference {state.reference}, "
            f"{state.solves} solves ({size} bytes)",
        )

    def on_load(self, request: LoadState.Request, response: LoadState.Response) -> Any:
        try:
            path = requested_path(request)
        except ValueError as err:
            return answer(response, False, f"{UNCHANGED}: {err}")
        saved = read_state(path)
        if isinstance(saved, StateMissing):
            return answer(response, False, f"{UNCHANGED}: {path}: no such file")
        if not isinstance(saved, MergerState):
            self.node.drops.add(UNUSABLE_STATE)
            return answer(response, False, f"{UNCHANGED}: {saved.detail}")
        with self._quiet():
            self._take_up(saved)
        self._publish_held()
        loaded = StateResumed(path, len(saved.maps), saved.reference, saved.solves)
        message = str(loaded).replace("resumed from", "loaded")
        self.node.get_logger().info(message)
        return answer(response, True, message)

    def on_reset(self, request: Trigger.Request, response: Trigger.Response) -> Any:
        node = self.node
        message = "reset: no local map held"
        with self._quiet():
            with node._lock:
                node.policy.reset()
                robots = list(node.policy.robots)
            if node.state_path is not None:  # the empty state, as a reset merger's file
                try:
                    MergerState("", [], robots, {}, {}, {}, 0, {}).write(node.state_path)
                except OSError as err:
                    message += f"; the state file not written: {err}"
        self._publish_held()
        message += f"; {len(robots)} smoothers to ask for theirs"
        node.get_logger().info(message)
        return answer(response, True, message)
