"""merger: joins every robot's local map by C-SAM and publishes the joined map.

Subscribes to ``/<robot>/local_map_updates`` and ``/<robot>/rendezvous_poses`` of every robot
found publishing local map updates (or of those in ``robots``; at most ``max_robots`` found at
once, named by ``robot_pattern``, one silent for ``forget_after`` s forgotten), holds each
robot's local map by applying its updates (:mod:`csam_ros.core.exchange.map_updates`) and asks
a smoother for its whole map (``/<robot>/smoother/resync``) when it holds none, an update does
not apply, or a whole map of another session came (its answer names its session). Every
message is checked whole when it arrives (``ros/map_messages.py``): a malformed one is dropped
and counted, and the robot's last valid inputs stay in use. With ``team_key_file``, only
messages signed with the team key are taken (:mod:`csam_ros.nodes.merger_auth`).

Its decisions are :class:`~csam_ros.core.merging.policy.MergerPolicy`'s: the reference, when to
solve, when the provisional map goes out, smoother restarts, stale robots and what
``/csam/status`` and ``/diagnostics`` say. A worker thread hands each solve to the solve process
(:mod:`csam_ros.solve_process`; one runs, one is pending; between solves, each new map to
prepare), then publishes ``/csam/joined_map``, ``/tf`` ``<reference>/map -> <robot>/map`` and
``/<robot>/pose`` (nodes/merger_output.py), and the message process writes ``summary_path``
and publishes ``/csam/markers``. A thread of its own publishes ``/csam/joined_map/provisional``.
``~/flush`` (the data has ended) solves the newest inputs at once, giving up a running solve of
older ones. With ``state_path`` set, the merger writes its state there after each solve and takes
it up when started with it (``MergerState``). ``~/save_state``, ``~/load_state``, ``~/reset`` and
``~/pause``: :mod:`csam_ros.nodes.state_services`.
"""

from __future__ import annotations

import sys
import threading
import time
from dataclasses import replace
from typing import Any

from csam_msgs.msg import LocalMapUpdate, RendezvousPoses
from rclpy.node import Node
from rclpy.subscription import Subscription
from rclpy.timer import Timer
from std_srvs.srv import Trigger

from csam_ros.core.exchange.validation import CALLBACK_ERROR, DropCounter, RefusedMessageError
from csam_ros.core.merging.notices import Notice
from csam_ros.core.merging.policy import MergerPolicy
from csam_ros.core.merging.policy_inputs import (
    Flushed,
    Found,
    MapTaken,
    ProvisionalMap,
    SolveInputs,
    arrival,
)
from csam_ros.core.merging.status import SharedDropCounter
from csam_ros.nodes.common import guarded, run_node, steady_clock, subscribe, watch_parameters
from csam_ros.nodes.merger_auth import SignedInputs
from csam_ros.nodes.merger_output import MergerOutput
from csam_ros.nodes.merger_parameters import declare_merger_parameters, live_merger_parameters
from csam_ros.nodes.merger_rendezvous import RendezvousInput
from csam_ros.nodes.merger_resync import ResyncClients
from csam_ros.nodes.state_services import MergerServices
from csam_ros.ros.conversions import time_to_ns
from csam_ros.ros.map_messages import map_update_from_message
from csam_ros.ros.merger_reports import log_notice
from csam_ros.ros.topics import FLUSH, LOCAL_MAP_UPDATES, MERGER_NODE, RENDEZVOUS_POSES
from csam_ros.solve_process import SolveProcess

DISCOVERY_PERIOD_S = 1.0  # s between looks at the ROS graph for new robots
SHUTDOWN_JOIN_S = 5.0  # s destroy_node waits for the solve worker to stop


class Merger(Node):
    """C-SAM merger node (see the module docstring). What it holds and decides is its
    :class:`~csam_ros.core.merging.policy.MergerPolicy`'s, read and written under ``_lock``;
    the node subscribes, publishes and runs the threads, timers and processes."""

    def __init__(self, **node_options: Any) -> None:
        super().__init__(MERGER_NODE, **node_options)
        params = declare_merger_parameters(self)
        self.config, self.state_path = params.config, params.state_path
        self.drops: DropCounter = SharedDropCounter()
        settings = params.settings
        self.policy = MergerPolicy(settings, time.monotonic, self.config, self.drops)
        # the solve worker's alone (and destroy_node's)
        self.solve_process = SolveProcess(params.solve_niceness)
        # the policy is read and written under _lock; one solve at a time holds _solve_lock;
        # publications of a solve hold _publish_lock (destroy_node waits on it)
        self._lock = threading.Lock()
        self.resyncs = ResyncClients(self, self.policy, self._lock, self._taken)
        self.rendezvous_input = RendezvousInput(self)
        self.signed = SignedInputs(self, params.team_key, self.drops)  # with a key: signed only
        self._robot_inputs: dict[str, tuple[Subscription, ...]] = {}
        self._wake = threading.Condition(self._lock)
        self._provisional_wake = threading.Condition(self._lock)
        self._solve_lock = threading.Lock()
        self._publish_lock = threading.Lock()
        self._requested = False  # the timer asked the worker for a solve
        self._new_maps = False  # maps arrived that the solve process may prepare
        # the newest provisional map decided on and not yet taken by the provisional thread
        self._provisional_due: ProvisionalMap | None = None
        self._writing_state = False  # the worker waits for the last solve's state write
        self._stopping = threading.Event()  # set under _lock
        self.state_services = MergerServices(self)  # ~/save_state, ~/load_state, ~/reset, ...
        taking = self.state_services.taking  # input dropped while paused
        self._on_map = guarded(self, self.drops, taking(self.on_local_map_update))
        self._on_rendezvous = guarded(self, self.drops, taking(self.on_rendezvous_poses))
        self.output = MergerOutput(
            self, params.summary_path, self._publish_lock, self._stopping, self.drops
        )
        resumed = self.state_path is not None and self.state_services.resume(self.state_path)
        for robot in settings.robots:  # listed robots' latched maps may come before discovery
            if robot not in self.policy.robots:
                self._subscribe(robot)
        if resumed:
            self.output.resumed(self.policy)
        self._solve_timer = self._timer(settings.solve_check_period, self.on_timer)
        self._timer(DISCOVERY_PERIOD_S, self.discover)
        provisional_period = settings.provisional_check_period
        self._provisional_timer = (
            self._timer(provisional_period, self.publish_provisional)
            if provisional_period is not None
            else None
        )
        self.create_service(Trigger, f"~/{FLUSH}", self.on_flush)
        self.solve_process.start()  # its imports overlap the wait for the first maps
        self.output.message_process.start()
        self._worker = threading.Thread(target=self._work, name="merger-solve", daemon=True)
        self._worker.start()
        self._provisional_worker = threading.Thread(
            target=self._publish_provisionals, name="merger-provisional", daemon=True
        )
        self._provisional_worker.start()
        live = live_merger_parameters(self.set_setting, self._provisional_timer is not None)
        watch_parameters(self, live, self.drops)

    def _timer(self, period: float, callback: Any) -> Timer:
        return self.create_timer(period, guarded(self, self.drops, callback), clock=steady_clock())

    def set_setting(self, name: str, value: Any) -> None:
        """Put a parameter set at run time into the policy's settings, and the solve and
        provisional timers' periods."""
        with self._lock:
            self.policy.settings = settings = replace(self.policy.settings, **{name: value})
        self._solve_timer.timer_period_ns = round(settings.solve_check_period * 1e9)
        provisional = settings.provisional_check_period
        if self._provisional_timer is not None and provisional is not None:
            self._provisional_timer.timer_period_ns = round(provisional * 1e9)

    def destroy_node(self) -> None:
        """Stop the solve worker and the solve process (a solve running is lost: nothing of it
        is published or counted), then destroy the node."""
        with self._lock:
            self._stopping.set()
            self._wake.notify_all()
            self._provisional_wake.notify_all()
            writing = self._writing_state
        if writing and self._worker is not threading.current_thread():
            self._worker.join(timeout=SHUTDOWN_JOIN_S)  # the last solve's state is written
        self.solve_process.close()
        if self._worker is not threading.current_thread():
            self._worker.join(timeout=SHUTDOWN_JOIN_S)
        if self._worker.is_alive():
            self.get_logger().warning("a solve is still running; its result is not published")
        if self._provisional_worker is not threading.current_thread():
            self._provisional_worker.join(timeout=SHUTDOWN_JOIN_S)
        self.output.message_process.close()
        with self._publish_lock:  # no publication is under way, and none starts from now on
            super().destroy_node()

    def _subscribe(self, robot: str) -> None:
        """Subscribe to ``robot``'s local map updates and rendezvous poses; publish its pose."""
        self.output.add_robot(robot)
        inputs = ((LOCAL_MAP_UPDATES, self._on_map), (RENDEZVOUS_POSES, self._on_rendezvous))
        self._robot_inputs[robot] = tuple(
            subscribe(self, t, self.signed.gate(robot, t.of(robot), on), t.of(robot))
            for t, on in inputs
        )
        self.resyncs.add(robot)
        with self._lock:
            self.policy.subscribed(robot)
        self.rendezvous_input.robot_found(robot)

    def discover(self) -> None:
        """Subscribe to every robot newly seen publishing local map updates on the ROS graph
        (``/<robot>/local_map_updates``), unless the allow-list or ``robot_pattern`` leaves it
        out or ``max_robots`` are joined (logged once)."""
        for name, types in self.get_topic_names_and_types():
            robot = LOCAL_MAP_UPDATES.robot_of(name)
            if robot is None or LOCAL_MAP_UPDATES.type_name not in types:
                continue
            with self._lock:
                found = self.policy.found(robot)
            if found is Found.LEAVE_OUT:
                self.get_logger().info(f"{robot} publishes a local map: not in robots or pattern")
            elif found is Found.TOO_MANY:
                self.get_logger().warning(f"{robot} publishes a local map: max_robots joined")
            elif found is Found.JOIN:
                self.get_logger().info(f"{robot} found: joining its local map")
                self._subscribe(robot)

    def forget_silent(self) -> None:
        """Unsubscribe from the robots found that were silent for ``forget_after`` s."""
        with self._lock:
            silent = self.policy.forget_silent()
        for robot in silent:
            self.get_logger().info(f"{robot}: no local map for forget_after s, forgotten")
            for subscription in self._robot_inputs.pop(robot, ()):
                self.destroy_subscription(subscription)
            self.resyncs.remove(robot)
            self.signed.remove(robot)

    def _refuse(self, robot: str, what: str, error: RefusedMessageError) -> None:
        with self._lock:
            notice = self.policy.refused(robot, what, error)
        self._note(notice)

    def _note(self, notice: Notice) -> None:
        log_notice(self.get_logger(), notice)

    def on_local_map_update(self, robot: str, msg: LocalMapUpdate) -> None:
        """Apply an update on ``robot``'s topic to the map held of it, and keep that map if
        it is valid (else the last valid one stays in use)."""
        try:
            update = map_update_from_message(msg, robot)
        except RefusedMessageError as error:
            self._refuse(robot, "local map update", error)
            return
        arrived = arrival(robot, self.policy.held.get(robot), update)  # only this thread holds
        answers = self.resyncs.ready(robot)
        with self._lock:
            taken = self.policy.map_arrived(robot, arrived, time_to_ns(msg.header.stamp), answers)
        self._taken(robot, taken)

    def _taken(self, robot: str, taken: MapTaken) -> None:
        """Act on what a map on ``robot``'s topic (or its smoother's answer) led to."""
        if taken.give_up_solve:
            with self._lock:
                self._solve_newest()
        for notice in taken.notices:
            self._note(notice)
        if taken.behind:
            self.resyncs.ask(robot, taken.behind)
        if taken.taken:
            with self._lock:  # the worker prepares it, or solves if it completes a round
                self._new_maps = True
                self._requested |= self.policy.solve_wanted(on_arrival=True)
                self._wake.notify()
            self.publish_provisional()

    def on_rendezvous_poses(self, robot: str, msg: RendezvousPoses) -> None:
        """Keep the valid rendezvous measurements on ``robot``'s topic (the last ones if none)."""
        self.rendezvous_input.arrived(robot, msg)

    def on_timer(self) -> None:
        """Wake the solve worker when a solve is to start; ask for the maps of robots none is
        held of (or whose update did not apply); publish the status."""
        with self._lock:
            wanted = list(self.policy.resyncs_wanted())
        for robot, reason in wanted:
            self.resyncs.ask(robot, reason)
        self.forget_silent()
        self.signed.expire()
        with self._lock:
            if self.policy.solve_wanted():
                self._requested = True
                self._wake.notify()
        self.publish_status()

    def on_flush(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        """Solve the newest inputs now (module docstring); the reply says what was done."""
        with self._lock:  # a solve running now is of older inputs, and no other starts
            newer = self.policy.flush()
            given_up = newer and self._solve_newest()
        response.success = True
        response.message = Flushed.of(newer, given_up).value
        return response

    def _solve_newest(self) -> bool:
        """Give up a running solve (of older inputs) and have the worker solve the newest;
        whether one was given up (call under the lock)."""
        given_up = self.policy.solving and self.solve_process.cancel()
        self._requested = True
        self._wake.notify()
        return given_up

    def _work(self) -> None:
        """The solve worker: one solve per request of the timer, and new maps handed to the
        solve process to prepare between solves, until the node stops."""
        while True:
            with self._lock:
                while not (self._requested or self._new_maps or self._stopping.is_set()):
                    self._wake.wait()
                if self._stopping.is_set():
                    return
                solve, self._requested, new_maps = self._requested, False, self._new_maps
                prepare = new_maps and not (solve or self.policy.solve_wanted())  # else solved
                self._new_maps = False
            try:
                if solve:
                    self.solve_pending()
                elif prepare:  # the maps it does not hold, while the solve waits for others
                    with self._solve_lock:  # the solve process of now (~/reset replaces it)
                        with self._lock:
                            sources = tuple(self.policy.sources.items())
                        self.solve_process.prepare(sources)
            except Exception as error:  # noqa: BLE001 - the worker outlives any one solve
                self.drops.add(CALLBACK_ERROR)
                self.get_logger().error(f"solve worker: {type(error).__name__}: {error}")

    def solve_pending(self) -> bool:
        """Solve on a snapshot of the inputs if they changed since the last one, in the calling
        thread (the worker's; tests call it to solve synchronously); whether a solve ran."""
        with self._solve_lock:
            with self._lock:
                start = None if self._stopping.is_set() else self.policy.start_solve()
            if start is None:
                return False
            if start.notice is not None:
                self._note(start.notice)
            try:
                self._solve(start.inputs)
            finally:
                with self._lock:
                    self.policy.solve_ended()
            return True

    def _solve(self, inputs: SolveInputs) -> None:
        """Join ``inputs`` in the solve process; record the result (or the failure) and
        publish it."""
        start = time.perf_counter()
        with self._lock:
            request = self.policy.join_request(inputs, self.state_path)
        reply = self.solve_process.join(request)
        seconds = time.perf_counter() - start
        if self._stopping.is_set():
            return
        with self._lock:
            notices = self.policy.solve_done(inputs, reply, seconds)
            self._writing_state = reply.state_pending  # only a solve that succeeded writes
            stats, maps = self.policy.stats(), self.policy.local_maps  # the newest maps held
        for notice in notices:
            self._note(notice)
        result = reply.result
        if result is None:
            return
        result.timing_s["merger_solve"] = seconds
        if not result.converged:
            for note in result.notes:
                if note.not_converged:
                    self.get_logger().warning(note.text)
        self.output.joined_map(result, dict(inputs.stamps), inputs.robots, stats, maps)
        try:
            written = self.solve_process.state_written()
        finally:
            with self._lock:
                self._writing_state = False
        if written is not None and written.error:
            self.get_logger().error(written.error)

    def publish_provisional(self) -> bool:
        """Have the provisional thread publish the provisional map if the policy says one is
        due now; whether one is to go out."""
        with self._lock:
            due = self.policy.provisional_due()
            if due is None:
                return False
            self._provisional_due = due
            self._provisional_wake.notify()
        return True

    def _publish_provisionals(self) -> None:
        """The provisional thread: builds and publishes the newest provisional map decided
        on (one not yet taken when a newer one is due is skipped), until the node stops."""
        publish = guarded(self, self.drops, self._publish_provisional)
        while True:
            with self._lock:
                while self._provisional_due is None and not self._stopping.is_set():
                    self._provisional_wake.wait()
                if self._stopping.is_set():
                    return
                due, self._provisional_due = self._provisional_due, None
            publish(due)

    def _publish_provisional(self, due: ProvisionalMap) -> None:
        with self._lock:
            if self.policy.joined_holds(due.stamps):  # a solved joined map holds them already
                return
        if self.output.provisional_map(due, self.policy.joined_holds):
            with self._lock:
                self.policy.provisional_published()

    def publish_status(self) -> None:
        """Publish the status (``/csam/status``, ``/diagnostics``): robots, counts, solves."""
        with self._lock:
            status = self.policy.status()
        self.output.status(status, self.get_clock().now().to_msg())


def main(args: list[str] | None = None) -> int:
    return run_node(Merger, args, __doc__)


if __name__ == "__main__":
    sys.exit(main())
