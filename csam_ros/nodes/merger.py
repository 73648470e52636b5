"""merger: joins every robot's local map by C-SAM and publishes the joined map.

Subscribes to ``/<robot>/local_map_updates`` and ``/<robot>/rendezvous_poses`` (transient
local) of every robot found on the ROS graph publishing local map updates (checked every
second), or only of those in ``robots`` when that allow-list is set (they are subscribed from
the start). It holds each robot's local map by applying its updates in turn
(:mod:`csam_ros.core.exchange.map_updates`); while it holds none of a robot, and when an update
does not apply to the one it holds (it missed one, or it restarted), it asks that robot's smoother
for the whole map (``/<robot>/smoother/resync``; one request at a time, see ``RESYNC_TIMEOUT_S``),
counted as ``resync_requests`` in ``/csam/status``. The
reference is ``reference`` (else the first of ``robots``) if it has a map, else the first
robot heard from; the choice is kept once made and named in ``/csam/status``, the joined map
and the summary. Smoothers' first maps come in any order, so the first solve waits up to
``reference_wait`` seconds after the first map for the configured reference's, and for the
maps and rendezvous of every robot on the allow-list. When a local
map or rendezvous part changes it re-solves (at most every ``solve_period`` wall-clock
seconds) with the core's :func:`~csam_ros.core.joining.join.join_maps`, then writes
``summary_path`` (when set) and publishes ``/csam/joined_map`` and ``/csam/markers``
(transient local), ``/tf`` ``<reference>/map -> <robot>/map`` of each aligned robot
(:func:`~csam_ros.ros.map_messages.robot_map_transforms`) and ``/csam/status``. A robot
without a new map for ``stale_after`` seconds is reported stale there; its last map stays
joined. A map delivered again unchanged starts no solve.

Solves run off the executor: a worker thread hands each to the merger's solve process
(:mod:`csam_ros.solve_process`), which refines each changed map to its sender's optimum and
joins them, so subscriptions, services and the status keep running during a solve, on a core's
share of their own. A solve works on a snapshot of the inputs taken under a lock (their dicts
are replaced, never mutated, when a message arrives). Input arriving during a
solve marks the inputs dirty again; the next solve starts after the current one ends, with
the newest inputs: at most one solve runs and one is pending. ``/csam/status`` says whether a
solve is running (``solving``) and how long the last one took (``solve_seconds``).
``~/flush`` (std_srvs/Trigger; called when the data has ended, after the smoothers' own
``~/flush``) solves the newest inputs at once: a running solve of older inputs is given up
(counted as ``solves_given_up``), since its result would be out of date when it came. After a
flush, each robot's next local map gives up a running solve once more (a smoother's final map
may come after the flush that asked for it); no more than that, so a flush in the middle of a
run does not keep solves from ending.

A join takes seconds to minutes on large maps. When local maps arrive that no joined map
holds, a thread of its own publishes ``/csam/joined_map/provisional`` once every robot's map
is newer than the last joined and provisional maps, or ``provisional_quiet`` wall-clock
seconds pass without another (maps that arrive together go out in one message), or
``provisional_period`` after the first of them, and at most every ``provisional_period``:
the newest local maps placed by the last join, unsolved
(:func:`~csam_ros.core.joining.warm_start.carried_forward`; what the next join starts from). Its
base nodes name the local maps it holds; it has no heading sigmas, and the features first seen since
the last join have NaN covariances.
``/csam/joined_map`` stays the solved joined map. A joined map, solved or provisional, is
serialized where it is made (its trajectories from their arrays,
:func:`~csam_ros.ros.map_messages.serialized_joined_map`: milliseconds) and published at once;
then a solved map's summary is written and its markers published, both built by the merger's
message process (:mod:`csam_ros.message_process`): a long run's markers and summary are over
half a second of Python that would otherwise hold up the executor.

The topic says which robot a message belongs to. Every message is checked whole when it
arrives (``ros/map_messages.py``); a malformed one, or one naming another robot than its
topic's, is dropped and counted once under its reason, and the robot's last valid local map
and rendezvous measurements stay in use. Single bad rendezvous measurements are dropped and
the rest of their message kept. A robot whose new local map starts later or holds fewer poses
than its last one has had its smoother restarted: the new map is its current truth and
replaces the old one, and the restart and the poses lost are logged once and counted in
``/csam/status`` and the summary.

With ``state_path`` set, the merger writes its state there (atomically) after each solve (once
its joined map is out; a node destroyed meanwhile lets the write end):
every robot's last local map and rendezvous measurements, the reference, its counts and the
joined map (:class:`~csam_ros.core.exchange.checkpoint.MergerState`). Started with such a file, it
takes that state up, publishes its joined map at once and goes on from it, also for robots
whose smoothers are gone; a file it cannot use is one logged error, and it starts empty.
"""

from __future__ import annotations

import sys
import threading
import time
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from csam_msgs.msg import LocalMapUpdate, RendezvousPoses
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.node import Node
from std_srvs.srv import Trigger

from csam_ros.core.exchange.checkpoint import CheckpointError, MergerState
from csam_ros.core.exchange.map_arrays import held_robot_map, robot_map_arrays
from csam_ros.core.exchange.map_updates import HeldMap, MissingBaseError, apply_update
from csam_ros.core.exchange.validation import (
    CALLBACK_ERROR,
    FAILED_SOLVE,
    DropCounter,
    LocalMapError,
    RefusedMessageError,
)
from csam_ros.core.joining.config import CsamConfig
from csam_ros.core.joining.result import CsamResult, MergerStats, RunSummary, write_summary_text
from csam_ros.core.joining.warm_start import carried_forward
from csam_ros.core.merging.joiner import JoinRequest, MapSource
from csam_ros.core.model.log import RendezvousLog
from csam_ros.core.smoothing.robot_map import RobotMap
from csam_ros.message_process import MarkersRequest, MessageProcess
from csam_ros.nodes.common import (
    declare,
    declare_settings,
    guarded,
    publisher,
    run_node,
    steady_clock,
    subscribe,
)
from csam_ros.ros.conversions import time_to_ns
from csam_ros.ros.map_messages import (
    map_update_from_message,
    rendezvous_log_from_message,
    robot_map_transforms,
    serialized_joined_map,
)
from csam_ros.ros.topics import (
    FLUSH,
    JOINED_MAP,
    LOCAL_MAP_UPDATES,
    MARKERS,
    MERGER_NODE,
    PROVISIONAL_MAP,
    RENDEZVOUS_POSES,
    RESYNC,
    STATUS,
    TF,
    smoother_service,
)
from csam_ros.solve_process import SolveProcess

DISCOVERY_PERIOD_S = 1.0  # s between looks at the ROS graph for new robots
PROVISIONAL_CHECKS = 4  # looks per provisional_quiet (or period) whether a provisional map is due
# asking a smoother for its whole local map (~/resync): a robot none is held of is asked this
# long after it was subscribed to (its first update, whole, usually comes first); a request
# stands this long before another is made (the whole map may take long on a slow link), and
# one the smoother could not serve (nothing sent yet) is made again after RESYNC_RETRY_S
RESYNC_FIRST_S = 3.0
RESYNC_TIMEOUT_S = 30.0
RESYNC_RETRY_S = 2.0
SHUTDOWN_JOIN_S = 5.0  # s destroy_node waits for the solve worker to stop


class SharedDropCounter(DropCounter):
    """A :class:`DropCounter` the executor and the solve worker may both count into."""

    def __init__(self) -> None:
        super().__init__()
        self._lock = threading.Lock()

    def add(self, reason: str, n: int = 1) -> None:
        with self._lock:
            super().add(reason, n)

    def reclassify(self, old: str, new: str) -> None:
        with self._lock:
            super().reclassify(old, new)

    @property
    def total(self) -> int:
        with self._lock:
            return sum(self.counts.values())

    def as_dict(self) -> dict[str, int]:
        with self._lock:
            return super().as_dict()


@dataclass(frozen=True)
class ProvisionalMap:
    """A provisional joined map decided on: the newest local maps (in the join's robot order)
    to be placed by ``last`` (:func:`~csam_ros.core.joining.warm_start.carried_forward`)."""

    last: CsamResult
    maps: list[RobotMap]
    stamps: dict[str, int]
    robots: tuple[str, ...]


@dataclass(frozen=True)
class SolveInputs:
    """What one solve works on, taken under the merger's lock: never changed afterwards."""

    order: tuple[str, ...]  # the robots joined, the reference first
    sources: Mapping[str, MapSource]  # each robot's map as held (refined by the solve)
    logs: Mapping[str, RendezvousLog]
    stamps: Mapping[str, int]
    robots: tuple[str, ...]  # every known robot, in the solve's order


class Merger(Node):
    """C-SAM merger node (see the module docstring)."""

    def __init__(self, **node_options: Any) -> None:
        super().__init__(MERGER_NODE, **node_options)
        # an empty list has no element type: ROS reads `robots:=[]` as a byte array, so the
        # parameter takes any type and is checked here
        allowed = self.declare_parameter(
            "robots",
            None,
            ParameterDescriptor(
                description="allow-list of robot names (empty or unset: every robot that "
                "publishes a local map); its first is the reference when `reference` is empty",
                dynamic_typing=True,
            ),
        ).value
        if allowed is not None and not (
            isinstance(allowed, list | tuple) and all(isinstance(r, str) and r for r in allowed)
        ):
            raise ValueError(f"parameter robots: expected a list of robot names, got {allowed!r}")
        self.allowed: list[str] = list(allowed or [])
        reference = declare(
            self, "reference", "", "reference robot if it has a map, else the first one heard"
        )
        self.configured_reference = reference or (self.allowed[0] if self.allowed else "")
        self.reference_wait = declare(
            self,
            "reference_wait",
            5.0,
            "wall-clock s the first solve waits, after the first local map, for the configured "
            "reference's and every listed robot's (0: none)",
            0.0,
        )
        self.stale_after = declare(
            self,
            "stale_after",
            30.0,
            "wall-clock s without a local map after which a robot is reported stale (0: never)",
            0.0,
        )
        summary = declare(self, "summary_path", "", "write summary.json here after each solve")
        self.summary_path = Path(summary) if summary else None
        state = declare(
            self,
            "state_path",
            "",
            "write the merger's state here after each solve and resume from it at start ('': off)",
        )
        self.state_path = Path(state) if state else None
        period = declare(
            self, "solve_period", 0.5, "minimum wall-clock seconds between solves", 0.0, 3600.0
        )
        self.provisional_period = declare(
            self,
            "provisional_period",
            1.0,
            "minimum wall-clock seconds between provisional joined maps (the newest local maps "
            "placed by the last join), and the most a new local map waits for one (0: none)",
            0.0,
            3600.0,
        )
        self.provisional_quiet = declare(
            self,
            "provisional_quiet",
            0.5,
            "wall-clock seconds without a new local map after which the provisional joined map "
            "goes out (local maps that arrive together go out in one); it goes out at once when "
            "every robot's map is new",
            0.0,
            3600.0,
        )
        niceness = declare(
            self,
            "solve_niceness",
            10,
            "how much lower the solve process's CPU priority is than the node's (nice; 0: the "
            "same): the node, and nodes beside it, take and publish messages first",
            0,
            19,
        )
        # online, a rendezvous stamp may reach the merger before the observed robot's map has
        # its pose: leave such a measurement out until the next solve instead of failing
        self.config = declare_settings(self, CsamConfig, CsamConfig(skip_missing_poses=True))
        # the last valid local map (and its message's stamp) and rendezvous measurements: each
        # dict is replaced, never mutated, so a solve's snapshot of them stays as it was taken
        self.local_maps: dict[str, RobotMap] = {}
        self.held: dict[str, HeldMap] = {}  # each robot's map as its updates built it
        # what each of local_maps was built from: a held map, or a resumed map's arrays
        self.sources: dict[str, MapSource] = {}
        self.resync_requests: dict[str, int] = {}
        self._behind: set[str] = set()  # robots an update of did not apply: resync until one does
        self._resync_clients: dict[str, Any] = {}
        self._resync_next: dict[str, float] = {}  # steady clock s from which to ask again
        self.robots: list[str] = []  # subscribed to, in the order found
        self.heard: list[str] = []  # robots in the order their first local map arrived
        self.reference = ""  # chosen at the first solve, then kept
        self._first_heard_at = 0.0  # steady clock s of the first local map
        self.map_arrival: dict[str, float] = {}  # steady clock s of each robot's last map
        self._ignored: set[str] = set()  # robots on the graph outside the allow-list
        self._late_reference_logged = False
        self.local_map_stamps: dict[str, int] = {}
        self.rendezvous: dict[str, RendezvousLog] = {}
        self.drops: DropCounter = SharedDropCounter()
        self.restarts: dict[str, int] = {}
        self.restart_poses_lost: dict[str, int] = {}
        self.dirty = False  # inputs changed since the last solve's snapshot
        self.solving = False  # a solve is running
        self.last_result: CsamResult | None = None
        # the solve worker's alone (and destroy_node's)
        self.solve_process = SolveProcess(niceness)
        self.message_process = MessageProcess(
            on_failure=lambda error: self.get_logger().warning(f"message process: {error}")
        )
        self.solves = 0
        self.solves_given_up = 0  # running solves given up by ~/flush for newer inputs
        self.solve_seconds = 0.0  # how long the last solve took
        self.provisional_maps = 0  # provisional joined maps published
        # the local map stamps the last joined map and the last provisional map used
        self._published_stamps: dict[str, int] = {}
        self._provisional_stamps: dict[str, int] = {}
        self._provisional_next = 0.0  # steady clock s from which the next one may go out
        # the newest provisional map decided on and not yet taken by the provisional thread
        self._provisional_due: ProvisionalMap | None = None
        self._unpublished_since: float | None = None  # steady clock s a map first waited
        self.last_error = ""
        # the node's state above is read and written under _lock; one solve at a time holds
        # _solve_lock; publications of a solve hold _publish_lock (destroy_node waits on it)
        self._lock = threading.Lock()
        self._wake = threading.Condition(self._lock)
        self._provisional_wake = threading.Condition(self._lock)
        self._solve_lock = threading.Lock()
        self._publish_lock = threading.Lock()
        self._requested = False  # the timer asked the worker for a solve
        # robots whose next local map gives up a running solve (~/flush, module docs)
        self._after_flush: frozenset[str] = frozenset()
        self._writing_state = False  # the worker waits for the last solve's state write
        self._stopping = False
        self._on_map = guarded(self, self.drops, self.on_local_map_update)
        self._on_rendezvous = guarded(self, self.drops, self.on_rendezvous_poses)
        resumed = self.state_path is not None and self.resume(self.state_path)
        for robot in self.allowed:  # listed robots' latched maps may come before discovery
            if robot not in self.robots:
                self._subscribe(robot)
        self.joined_pub = publisher(self, JOINED_MAP)
        self.provisional_pub = publisher(self, PROVISIONAL_MAP)
        self.markers_pub = publisher(self, MARKERS)
        self.status_pub = publisher(self, STATUS)
        self.tf_pub = publisher(self, TF)
        if resumed and self.last_result is not None:
            self._published_stamps = dict(self.local_map_stamps)
            self._publish(self.last_result, dict(self.local_map_stamps), tuple(self.robots))
        self.create_timer(
            max(period, 0.01), guarded(self, self.drops, self.on_timer), clock=steady_clock()
        )
        self.create_timer(
            DISCOVERY_PERIOD_S, guarded(self, self.drops, self.discover), clock=steady_clock()
        )
        if self.provisional_period > 0.0:
            self.create_timer(
                max(
                    min(self.provisional_period, self.provisional_quiet) / PROVISIONAL_CHECKS, 0.01
                ),
                guarded(self, self.drops, self.publish_provisional),
                clock=steady_clock(),
            )
        self.create_service(Trigger, f"~/{FLUSH}", self.on_flush)
        self.solve_process.start()  # its imports overlap the wait for the first maps
        self.message_process.start()
        self._worker = threading.Thread(target=self._work, name="merger-solve", daemon=True)
        self._worker.start()
        self._provisional_worker = threading.Thread(
            target=self._publish_provisionals, name="merger-provisional", daemon=True
        )
        self._provisional_worker.start()

    def destroy_node(self) -> None:
        """Stop the solve worker and the solve process (a solve running is lost: nothing of it
        is published or counted), then destroy the node."""
        with self._lock:
            self._stopping = True
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
        self.message_process.close()
        with self._publish_lock:  # no publication is under way, and none starts from now on
            super().destroy_node()

    def resume(self, path: Path) -> bool:
        """Take up the state saved at ``path`` (call before any subscription); whether it was
        (a file that cannot be used is logged once: the merger starts empty)."""
        if not path.exists():
            self.get_logger().info(f"no merger state at {path} yet: starting empty")
            return False
        try:
            saved = MergerState.read(path)
        except CheckpointError as err:
            self.get_logger().error(f"merger state not used, starting empty: {err}")
            return False
        except Exception as err:  # noqa: BLE001 - a node never dies of a bad file
            self.get_logger().error(
                f"merger state not used, starting empty: {path}: {type(err).__name__}: {err}"
            )
            return False
        now = time.monotonic()
        self.local_maps = dict(saved.maps)
        self.sources = {robot: robot_map_arrays(m) for robot, m in saved.maps.items()}
        self.local_map_stamps = dict(saved.map_stamps)
        self.rendezvous = dict(saved.rendezvous)
        self.heard = list(saved.heard)
        self.reference = saved.reference
        self.map_arrival = {robot: now for robot in saved.maps}
        self.restarts = dict(saved.restarts)
        self.restart_poses_lost = dict(saved.restart_poses_lost)
        self.solves = saved.solves
        for reason, n in saved.dropped.items():
            self.drops.add(reason, n)
        self.last_result = saved.result
        for robot in saved.robots:
            if not self.allowed or robot in self.allowed:
                self._subscribe(robot)
        self.get_logger().info(
            f"resumed from {path}: {len(saved.maps)} local maps, reference "
            f"{saved.reference or '(none yet)'}, {saved.solves} solves"
        )
        return True

    def _subscribe(self, robot: str) -> None:
        """Subscribe to ``robot``'s local map updates and rendezvous poses (the topic names
        it)."""
        subscribe(
            self, LOCAL_MAP_UPDATES, lambda m: self._on_map(robot, m), LOCAL_MAP_UPDATES.of(robot)
        )
        self._resync_clients[robot] = self.create_client(Trigger, smoother_service(robot, RESYNC))
        self._resync_next[robot] = time.monotonic() + RESYNC_FIRST_S
        subscribe(
            self,
            RENDEZVOUS_POSES,
            lambda m: self._on_rendezvous(robot, m),
            RENDEZVOUS_POSES.of(robot),
        )
        with self._lock:
            self.robots = [*self.robots, robot]

    def discover(self) -> None:
        """Subscribe to every robot newly seen publishing local map updates on the ROS graph
        (``/<robot>/local_map_updates``), unless an allow-list leaves it out (logged once)."""
        for name, types in self.get_topic_names_and_types():
            robot = LOCAL_MAP_UPDATES.robot_of(name)
            if robot is None or LOCAL_MAP_UPDATES.type_name not in types or robot in self.robots:
                continue
            if self.allowed and robot not in self.allowed:
                if robot not in self._ignored:
                    self._ignored.add(robot)
                    self.get_logger().info(f"{robot} publishes a local map but is not in robots")
                continue
            self.get_logger().info(f"{robot} found: joining its local map")
            self._subscribe(robot)

    def _refuse(self, robot: str, what: str, error: RefusedMessageError) -> None:
        self.drops.add(error.reason)
        self.get_logger().warning(f"dropped a {what} on {robot}'s topic ({error.reason}): {error}")

    def on_local_map_update(self, robot: str, msg: LocalMapUpdate) -> None:
        """Apply an update on ``robot``'s topic to the map held of it, and keep that map if
        it is valid (else the last valid one stays in use)."""
        try:
            held = apply_update(self.held.get(robot), map_update_from_message(msg, robot))
        except MissingBaseError as error:
            self._behind.add(robot)
            self._ask_resync(robot, str(error))
            return
        except RefusedMessageError as error:
            self._refuse(robot, "local map update", error)
            return
        except ValueError as error:  # it does not fit the map held
            self._refuse(robot, "local map update", LocalMapError(f"{robot}: {error}"))
            return
        if held is self.held.get(robot):
            return  # delivered again: nothing to solve
        self.held[robot] = held
        self._behind.discard(robot)
        if msg.base_sequence == 0:
            self._resync_next.pop(robot, None)  # a whole map came: a request no longer stands
        try:  # checked here; refined by the solve process
            new = held_robot_map(robot, held, refine=False)
        except RefusedMessageError as error:
            self._refuse(robot, "local map update", error)
            return
        with self._lock:
            old = self.local_maps.get(robot)
            if old is not None:
                self._note_restart(robot, old, new)
            self.map_arrival[robot] = time.monotonic()
            stamp = time_to_ns(msg.header.stamp)
            if robot not in self.heard:
                if not self.heard:
                    self._first_heard_at = time.monotonic()
                self.heard = [*self.heard, robot]
            self.local_maps = {**self.local_maps, robot: new}
            self.sources = {**self.sources, robot: held}
            self.local_map_stamps = {**self.local_map_stamps, robot: stamp}
            self.dirty = True
            if self._unpublished_since is None:
                self._unpublished_since = self.map_arrival[robot]
            if robot in self._after_flush:
                self._after_flush -= {robot}
                self._solve_newest()
        self.publish_provisional()

    def _note_restart(self, robot: str, old: RobotMap, new: RobotMap) -> None:
        """Log and count once a new map that starts later or holds fewer poses than the last.

        The new map replaces the old one all the same: it is the robot's current truth (a
        restarted smoother has a new frame G_r), while the old one is frozen history that its
        rendezvous measurements and later poses no longer refer to. What was lost is reported.
        """
        tolerance = self.config.stamp_tolerance
        later = new.stamps[0] > old.stamps[0] + tolerance
        if not (later or len(new.stamps) < len(old.stamps)):
            return
        gap = np.abs(old.stamps[:, None] - new.stamps[None, :]).min(axis=1) > tolerance
        lost = int(gap.sum())
        self.restarts[robot] = self.restarts.get(robot, 0) + 1
        self.restart_poses_lost[robot] = self.restart_poses_lost.get(robot, 0) + lost
        self.get_logger().warning(
            f"{robot}: smoother restarted: the new local map holds {len(new.stamps)} poses from "
            f"{new.stamps[0]:.3f} s, the last one held {len(old.stamps)} from "
            f"{old.stamps[0]:.3f} s to {old.stamps[-1]:.3f} s; {lost} poses of its history are "
            "lost and no longer joined"
        )

    def on_rendezvous_poses(self, robot: str, msg: RendezvousPoses) -> None:
        """Keep the valid rendezvous measurements on ``robot``'s topic (the last ones if none)."""
        robot_map = self.local_maps.get(robot)
        rows = DropCounter()
        try:
            log = rendezvous_log_from_message(
                msg,
                robot,
                # without an allow-list, a robot heard from later is joined then: its rows
                # stay, and the core leaves them out until its map is there
                self.allowed or None,
                robot_map.stamps if robot_map is not None else None,
                self.config.stamp_tolerance,
                rows,
            )
        except RefusedMessageError as error:
            self._refuse(robot, "rendezvous poses message", error)
            return
        for reason, n in rows.as_dict().items():
            self.drops.add(reason, n)
        if rows.total:
            self.get_logger().warning(
                f"dropped rendezvous measurements on {robot}'s topic: {rows.as_dict()}"
            )
        if len(log.stamps) == 0 and robot in self.rendezvous:
            return  # a message with no usable measurement never replaces usable ones
        with self._lock:
            self.rendezvous = {**self.rendezvous, robot: log}
            self.dirty = True

    def _ask_resync(self, robot: str, reason: str) -> None:
        """Ask ``robot``'s smoother for its whole local map, unless a request stands (see
        ``RESYNC_TIMEOUT_S``) or its service is not there yet."""
        now = time.monotonic()
        client = self._resync_clients.get(robot)
        if client is None or now < self._resync_next.get(robot, 0.0):
            return
        if not client.service_is_ready():
            return
        self._resync_next[robot] = now + RESYNC_TIMEOUT_S
        self.resync_requests[robot] = self.resync_requests.get(robot, 0) + 1
        self.get_logger().info(f"{robot}: asking for its whole local map ({reason})")
        future = client.call_async(Trigger.Request())
        future.add_done_callback(lambda done: self._on_resync_reply(robot, done))

    def _on_resync_reply(self, robot: str, future: Any) -> None:
        """A smoother that had sent nothing yet is asked again after ``RESYNC_RETRY_S``."""
        reply = future.result()
        if reply is not None and not reply.success:
            self._resync_next[robot] = time.monotonic() + RESYNC_RETRY_S

    def on_timer(self) -> None:
        """Wake the solve worker when the inputs changed and it is idle; ask for the maps of
        robots none is held of; publish the status."""
        for robot in self.robots:
            if robot not in self.held:
                self._ask_resync(robot, "no local map held yet")
            elif robot in self._behind:
                self._ask_resync(robot, "an update did not apply to the map held")
        with self._lock:
            if self.dirty and not self.solving:
                self._requested = True
                self._wake.notify()
        self.publish_status()

    def on_flush(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        """Solve the newest inputs now (module docstring); the reply says what was done."""
        with self._lock:  # a solve running now is of older inputs, and no other starts
            newer = self.dirty
            given_up = newer and self._solve_newest()
            self._after_flush = frozenset(self.heard)
        response.success = True
        if not newer:
            response.message = "the joined map (or the running solve) holds the newest inputs"
        elif given_up:
            response.message = "a solve of older inputs was given up: solving the newest"
        else:
            response.message = "solving the newest inputs"
        return response

    def _solve_newest(self) -> bool:
        """Give up a running solve (of older inputs) and have the worker solve the newest;
        whether one was given up (call under the lock)."""
        given_up = self.solving and self.solve_process.cancel()
        self._requested = True
        self._wake.notify()
        return given_up

    def _work(self) -> None:
        """The solve worker: one solve per request of the timer, until the node stops."""
        while True:
            with self._lock:
                while not (self._requested or self._stopping):
                    self._wake.wait()
                if self._stopping:
                    return
                self._requested = False
            try:
                self.solve_pending()
            except Exception as error:  # noqa: BLE001 - the worker outlives any one solve
                self.drops.add(CALLBACK_ERROR)
                self.get_logger().error(f"solve worker: {type(error).__name__}: {error}")

    def solve_pending(self) -> bool:
        """Solve on a snapshot of the inputs if they changed since the last one, in the calling
        thread (the worker's; tests call it to solve synchronously); whether a solve ran."""
        with self._solve_lock:
            with self._lock:
                if not self.dirty or self._stopping:
                    return False
                self.dirty = False
                if not self.heard:
                    return False
                if not (self._first_inputs_complete() and self._choose_reference()):
                    self.dirty = True  # the timer asks again
                    return False
                order, robots = self._order()
                inputs = SolveInputs(
                    order=tuple(order),
                    sources=self.sources,
                    logs={r: self.rendezvous[r] for r in order if r in self.rendezvous},
                    stamps=self.local_map_stamps,
                    robots=robots,
                )
                self.solving = True
            try:
                self._solve(inputs)
            finally:
                with self._lock:
                    self.solving = False
            return True

    def _order(self) -> tuple[list[str], tuple[str, ...]]:
        """The robots heard from, the reference first (the order they are joined in), and
        those followed by every other robot subscribed to (call under the lock)."""
        order = [self.reference] + [r for r in self.heard if r != self.reference]
        return order, (*order, *(r for r in self.robots if r not in order))

    def _first_inputs_complete(self) -> bool:
        """Whether the first solve may run: every listed robot's local map and rendezvous
        have come, or ``reference_wait`` has passed since the first map (a merger started
        beside running smoothers gets their latched inputs within moments, in any order; one
        solve then joins them all). Call under the lock."""
        if self.reference:
            return True
        waiting = [r for r in self.allowed if r not in self.local_maps or r not in self.rendezvous]
        return not waiting or time.monotonic() - self._first_heard_at >= self.reference_wait

    def _choose_reference(self) -> bool:
        """The configured reference if it has a map, else, once ``reference_wait`` has passed
        since the first map, the first robot heard from; kept once chosen. Whether there is
        one (call under the lock, with a map heard)."""
        configured = self.configured_reference
        if self.reference:
            late = configured and configured != self.reference and configured in self.local_maps
            if late and not self._late_reference_logged:
                self._late_reference_logged = True
                self.get_logger().warning(
                    f"{configured} came after {self.reference} was made the reference; "
                    f"{self.reference} stays the reference"
                )
            return True
        absent = configured and configured not in self.local_maps
        if absent and time.monotonic() - self._first_heard_at < self.reference_wait:
            return False
        self.reference = configured if configured in self.local_maps else self.heard[0]
        if absent:
            self.get_logger().warning(
                f"{configured} has no local map {self.reference_wait:g} s after the first one: "
                f"{self.reference}, the first robot heard from, is the reference"
            )
        else:
            how = "configured" if self.reference == configured else "first robot heard from"
            self.get_logger().info(f"reference robot: {self.reference} ({how})")
        return True

    def _solve(self, inputs: SolveInputs) -> None:
        """Join ``inputs`` in the solve process; record the result (or the failure) and
        publish it."""
        start = time.perf_counter()
        with self._lock:
            previous, stats = self.last_result, self.stats()
        state = None
        if self.state_path is not None:  # as it will be once this solve is counted
            state = MergerState(
                reference=inputs.order[0],
                heard=list(inputs.order),
                robots=list(inputs.robots),
                maps={},
                map_stamps={r: inputs.stamps[r] for r in inputs.order},
                rendezvous={},
                solves=stats.solves + 1,
                dropped=stats.dropped,
                restarts=stats.restarts,
                restart_poses_lost=stats.restart_poses_lost,
            )
        reply = self.solve_process.join(
            JoinRequest(
                maps=tuple((r, inputs.sources[r]) for r in inputs.order),
                logs=inputs.logs,
                config=self.config,
                previous=previous,
                state=state,
                state_path=self.state_path,
            )
        )
        seconds = time.perf_counter() - start
        if self._stopping:
            return
        for refusal in reply.refused:
            self._refuse(
                refusal.robot, "local map update", LocalMapError(refusal.detail, refusal.reason)
            )
        if reply.cancelled:
            with self._lock:
                self.solves_given_up += 1
            self.get_logger().info("a solve of older inputs was given up for the newest")
            return
        result = reply.result
        if result is None:
            with self._lock:
                self.solve_seconds = seconds
                self.last_error = reply.error
                self.drops.add(FAILED_SOLVE)
            self.get_logger().error(f"C-SAM failed, the last joined map stays: {reply.error}")
            return
        result.timing_s["merger_solve"] = seconds
        if not result.converged:
            for note in result.notes:
                if note.not_converged:
                    self.get_logger().warning(note.text)
        with self._lock:
            self.last_error = ""
            self.solve_seconds = seconds
            self.solves += 1
            self.last_result = result
            self._published_stamps = dict(inputs.stamps)
            self._writing_state = reply.state_pending
            stats = self.stats()
        self._publish(result, dict(inputs.stamps), inputs.robots, stats)
        try:
            written = self.solve_process.state_written()
        finally:
            with self._lock:
                self._writing_state = False
        if written is not None and written.error:
            self.get_logger().error(written.error)

    def publish_provisional(self) -> bool:
        """Have the provisional thread publish the newest local maps placed by the last join
        (module docs) when neither the last joined nor the last provisional map used them,
        and when it is time to; whether one is to go out."""
        with self._lock:
            now = time.monotonic()
            last, stamps = self.last_result, dict(self.local_map_stamps)
            if stamps in (self._published_stamps, self._provisional_stamps):
                self._unpublished_since = None
                return False
            waited = now - (now if self._unpublished_since is None else self._unpublished_since)
            quiet = now - max(self.map_arrival.values(), default=now)
            # every robot's map is newer than the last joined and provisional maps: no other
            # is to come that this one should wait for
            complete = all(
                stamp not in (self._published_stamps.get(r), self._provisional_stamps.get(r))
                for r, stamp in stamps.items()
            )
            if (
                last is None
                or self.provisional_period <= 0.0
                or now < self._provisional_next
                or (
                    quiet < self.provisional_quiet
                    and waited < self.provisional_period
                    and not complete
                )
            ):
                return False
            order, robots = self._order()
            maps = [self.local_maps[r] for r in order]
            self._provisional_stamps = stamps
            self._unpublished_since = None
            self._provisional_next = now + self.provisional_period
            self._provisional_due = ProvisionalMap(last, maps, stamps, robots)
            self._provisional_wake.notify()
        return True

    def _publish_provisionals(self) -> None:
        """The provisional thread: builds and publishes the newest provisional map decided
        on (one not yet taken when a newer one is due is skipped), until the node stops."""
        publish = guarded(self, self.drops, self._publish_provisional)
        while True:
            with self._lock:
                while self._provisional_due is None and not self._stopping:
                    self._provisional_wake.wait()
                if self._stopping:
                    return
                due, self._provisional_due = self._provisional_due, None
            publish(due)

    def _publish_provisional(self, due: ProvisionalMap) -> None:
        with self._lock:
            if due.stamps == self._published_stamps:  # a solved joined map holds them already
                return
        result = carried_forward(due.last, due.maps, self.config.stamp_tolerance)
        stamps = due.stamps
        joined_map = serialized_joined_map(result, max(stamps.values()), stamps, due.robots)
        with self._publish_lock:
            if self._stopping or stamps == self._published_stamps:
                return
            self.provisional_pub.publish(joined_map)
        with self._lock:
            self.provisional_maps += 1

    def _publish(
        self,
        result: CsamResult,
        stamps: dict[str, int],
        robots: tuple[str, ...],
        stats: MergerStats | None = None,
    ) -> None:
        """Publish a joined map and its transforms, then write the summary and publish the
        markers (the summary is written even when the node stops meanwhile: the map it
        describes is out)."""
        stamp_ns = max(stamps.values())
        joined_map = serialized_joined_map(result, stamp_ns, stamps, robots)
        transforms = robot_map_transforms(result, stamp_ns)
        with self._publish_lock:
            if self._stopping:
                return
            self.joined_pub.publish(joined_map)
            self.tf_pub.publish(transforms)
        summary = (
            RunSummary(result, merger=stats)
            if self.summary_path is not None and stats is not None
            else None
        )
        now_ns = self.get_clock().now().nanoseconds
        out = self.message_process.build(MarkersRequest(result, now_ns, summary))
        with self._publish_lock:
            if self.summary_path is not None and out.summary_text is not None:
                write_summary_text(self.summary_path, out.summary_text)
            if not self._stopping:
                self.markers_pub.publish(out.markers)

    def stats(self) -> MergerStats:
        """What the merger counted so far, as the summary carries it (call under the lock)."""
        return MergerStats(
            dropped=self.drops.as_dict(),
            solves=self.solves,
            restarts=dict(self.restarts),
            restart_poses_lost=dict(self.restart_poses_lost),
        )

    def publish_status(self) -> None:
        """Publish ``/csam/status``: per robot, and the merger's counts and solve state."""
        with self._lock:
            array = self._status()
        self.status_pub.publish(array)

    def _status(self) -> DiagnosticArray:
        """The status message of the node's state now (call under the lock)."""
        array = DiagnosticArray()
        array.header.stamp = self.get_clock().now().to_msg()
        result = self.last_result
        now = time.monotonic()
        for robot in self.robots:
            r = result.robots.get(robot) if result is not None else None
            arrival = self.map_arrival.get(robot)
            since = now - arrival if arrival is not None else None
            stale = since is not None and 0.0 < self.stale_after < since
            if robot not in self.local_maps:
                alignment = "pending: no local map received"
            elif r is None:
                alignment = "pending: not solved yet"
            else:
                alignment = r.alignment
            ok = alignment in ("reference", "aligned") and not stale
            values = {
                "alignment": alignment,
                "stale": stale,
                "seconds_since_map": round(since, 1) if since is not None else "",
                "poses": len(r.stamps) if r is not None else 0,
                "solve_seconds": round(self.solve_seconds, 4),
                "restarts": self.restarts.get(robot, 0),
                "restart_poses_lost": self.restart_poses_lost.get(robot, 0),
                "update": self.held[robot].sequence if robot in self.held else 0,
                "resync_requests": self.resync_requests.get(robot, 0),
            }
            array.status.append(
                DiagnosticStatus(
                    level=DiagnosticStatus.OK if ok else DiagnosticStatus.WARN,
                    name=f"merger/{robot}",
                    hardware_id=robot,
                    message=f"{alignment} (stale: no local map for {since:.0f} s)"
                    if stale
                    else alignment,
                    values=[KeyValue(key=k, value=str(v)) for k, v in values.items()],
                )
            )
        values = {
            "reference": self.reference,
            "solves": self.solves,
            "features": len(result.features) if result is not None else 0,
            "associations": len(result.associations) if result is not None else 0,
            "solve_seconds": round(self.solve_seconds, 4),
            "solving": self.solving,
            "solves_given_up": self.solves_given_up,
            "provisional_maps": self.provisional_maps,
            "converged": result.converged if result is not None else "",
            "dropped": self.drops.total,
            "restarts": sum(self.restarts.values()),
            "resync_requests": sum(self.resync_requests.values()),
            # rendezvous the last solve left out: stamped outside a robot's trajectory
            "outside_trajectory": _outside_trajectory(result),
            "last_error": self.last_error,
            **{f"dropped/{k}": v for k, v in self.drops.as_dict().items()},
        }
        level, message = (
            DiagnosticStatus.OK,
            f"{self.solves} solves, {values['associations']} associations",
        )
        if self.last_error:
            level = DiagnosticStatus.ERROR
        elif result is not None and not result.converged:
            level, message = DiagnosticStatus.WARN, f"{message}; the last solve did not converge"
        array.status.append(
            DiagnosticStatus(
                level=level,
                name="merger",
                message=message,
                values=[KeyValue(key=k, value=str(v)) for k, v in values.items()],
            )
        )
        return array


def _outside_trajectory(result: CsamResult | None) -> int:
    """Rendezvous measurements a solve left out as stamped outside a map's span."""
    report = result.rendezvous_filter.get("trajectory_span") if result is not None else None
    return report.total("outside_trajectory") if report is not None else 0


def main(args: list[str] | None = None) -> int:
    return run_node(Merger, args, __doc__)


if __name__ == "__main__":
    sys.exit(main())
