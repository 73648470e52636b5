"""smoother: square-root smoothing of one robot's local map, in the robot's namespace.

Subscribes to ``odom``, ``features`` and ``rendezvous`` (relative names: run it with
``-r __ns:=/robot1``) and to every peer's ``/<peer>/rendezvous`` so that it holds a pose at the
stamp of every rendezvous measurement that involves its robot. Every ``publish_period`` seconds
(of the node's clock, so sim time under ``use_sim_time``) when new data arrived, and when asked
through ``~/flush`` (std_srvs/Trigger; the reply's message is the published local map's stamp in
nanoseconds), it publishes:

- ``local_map_updates``: what changed in the local map since the last update
  (:mod:`csam_ros.core.exchange.map_updates`; poses that moved beyond ``update_tolerance_m`` or
  ``update_tolerance_rad``, features and rendezvous poses beyond ``update_key_tolerance``,
  every one exactly after ``~/flush``; a flush with no new data since the last sends nothing
  again). The first update of a run is the whole map; ``~/resync`` (std_srvs/Trigger)
  publishes the whole map again as one update for a receiver that missed one, at once (also
  while the last update is unacknowledged), and answers with the session and that update's
  sequence (``session S sequence N``: by it a receiver tells a restart, a new session, from
  another publisher's map). While a reliable subscriber has not acknowledged the last update
  (a slow link), the next is deferred (``deferred_updates``): the one sent once all is
  acknowledged holds every change since, so a slow link carries fewer, larger updates instead
  of a queue it cannot drain. An update after ``~/flush`` is never deferred;
- ``rendezvous_poses`` when its measurements changed (latched);
- ``/tf`` ``<robot>/map -> <robot>/odom`` (REP-105; :mod:`csam_ros.nodes.smoother_frames`):
  the correction of the odometry at its latest key pose, also every 1/``tf_rate`` s;
- ``local_map`` (the whole map with covariances) and ``path``, only while something
  subscribes to them (they are for a look on the robot, and grow with the run).
Every field of every sensor message is checked against the ``input:`` bounds
(:class:`~csam_ros.core.exchange.validation.InputBounds`, the same checks as offline replay); bad
input is dropped and counted (``/csam/status``), and every callback is guarded, so an unexpected
error is logged and counted as ``callback_error``: the node keeps running with what it accepted.

With ``checkpoint_path`` set, every publication also writes a checkpoint there atomically
(:class:`~csam_ros.core.exchange.checkpoint.SmootherCheckpoint`: what the node accepted, its solved
local map, its filters' and thinning's state and its counts), and a smoother started with a
checkpoint of its robot resumes from it: it publishes the same local map at once and goes on.
What came while it was down is lost: the step of its odometry stamps across the restart is
logged, and the odometry samples missed are counted as ``lost_while_down`` (``/csam/status``,
with ``restarts`` and ``lost_seconds``). A checkpoint that cannot be read, or of another
robot, is one logged error: the node starts empty.

With ``team_key_file`` set, it signs its local map updates and rendezvous poses, for a merger
given the same key (:mod:`csam_ros.ros.signing`).

Its state services (:mod:`csam_ros.nodes.state_services`, docs/ARCHITECTURE.md): ``~/save_state``
writes such a checkpoint to a path, ``~/load_state`` takes one up as a restart from it would
and publishes its map, ``~/reset`` forgets everything as a start without one would (both in a
new update session: the merger takes the new map for a restart), ``~/pause`` drops the input
(``paused``) until resumed.
"""

from __future__ import annotations

import os
import pathlib
import sys
import time
from typing import Any

import numpy as np
from csam_msgs.msg import (
    FeatureObservations,
    FeaturePoints,
    RendezvousObservations,
    RendezvousPoses,
)
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Odometry, Path
from rclpy.duration import Duration
from rclpy.node import Node
from std_srvs.srv import Trigger

from csam_ros.core.exchange.checkpoint import (
    LOST_WHILE_DOWN,
    UNUSABLE_STATE,
    FilterState,
    SmootherCheckpoint,
    ThinningState,
    missed_samples,
    odometry_period,
)
from csam_ros.core.exchange.map_arrays import robot_map_arrays
from csam_ros.core.exchange.map_updates import UpdateSender, UpdateTolerance, resync_answer
from csam_ros.core.exchange.measurement_filter import MeasurementFilter
from csam_ros.core.exchange.state_files import CheckpointError
from csam_ros.core.exchange.validation import (
    ODOMETRY_DEFAULT_SIGMAS,
    InputBounds,
)
from csam_ros.core.joining.config import CsamConfig
from csam_ros.core.joining.pipeline import robot_map_from_local_map
from csam_ros.core.joining.rendezvous_filters import select_rendezvous
from csam_ros.core.model.log import RendezvousLog
from csam_ros.core.smoothing.local_map import LocalMap as CoreLocalMap
from csam_ros.core.smoothing.local_map_config import LocalMapConfig
from csam_ros.core.smoothing.robot_map import RobotMap
from csam_ros.nodes.common import (
    ROBOT_PARAMETER,
    Declared,
    Live,
    declare_each,
    declare_settings,
    guarded,
    publisher,
    run_node,
    setting_check,
    subscribe,
    watch_parameters,
)
from csam_ros.nodes.smoother_frames import MapToOdom
from csam_ros.nodes.state_services import SmootherServices
from csam_ros.ros.conversions import (
    feature_points_from_message,
    features_from_message,
    ns_to_time,
    odometry_reading_from_message,
    rendezvous_from_message,
    rendezvous_log_from_chunks,
    stamp_to_ns,
    time_to_ns,
    yaw_quaternion,
)
from csam_ros.ros.diagnostics import node_status
from csam_ros.ros.map_messages import (
    local_map_update_message,
    rendezvous_poses_message,
    robot_map_to_message,
)
from csam_ros.ros.signing import SignedPublisher, read_team_key
from csam_ros.ros.topics import (
    FEATURE_POINTS,
    FEATURES,
    LOCAL_MAP,
    LOCAL_MAP_UPDATES,
    ODOM,
    PATH,
    RENDEZVOUS,
    RENDEZVOUS_POSES,
    RESYNC,
    STATUS,
)

# a drop reason: a rendezvous stamp before this robot's first pose (e.g. clocks that differ)
OUTSIDE_TRAJECTORY = "outside_trajectory"
NO_WAIT = Duration(seconds=0)  # asking whether every reliable subscriber acknowledged
# the smoother's own parameters (its settings dataclasses' fields are declared from them)
SMOOTHER_PARAMETERS = (
    ROBOT_PARAMETER,
    Declared(
        "robots",
        [""],
        "every robot's name (peers' rendezvous)",
        made_at_start="this robot alone",
    ),
    Declared("field_of_view_deg", 360.0, "feature sensor field of view (drops beyond)", 0.0, 360.0),
    Declared(
        "checkpoint_path",
        "",
        "write a checkpoint here at every publication and resume from it at start ('': off)",
    ),
    Declared(
        "team_key_file",
        "",
        "file of the team key (at least 16 bytes): sign local map updates and rendezvous "
        "poses with it, for a merger given the same ('': unsigned)",
    ),
)


class Smoother(Node):
    """One robot's sqrt-SAM smoother (see the module docstring)."""

    def __init__(self, **node_options: Any) -> None:
        super().__init__("smoother", **node_options)
        ns = self.get_namespace().strip("/")
        own = declare_each(
            self,
            SMOOTHER_PARAMETERS,
            {"robot": lambda _: ns or "robot1", "robots": lambda values: [values["robot"]]},
        )
        self.robot, peers = own["robot"], own["robots"]
        fov, checkpoint = own["field_of_view_deg"], own["checkpoint_path"]
        self.checkpoint_path = pathlib.Path(checkpoint) if checkpoint else None
        local_map = declare_settings(self, LocalMapConfig)
        self.publish_period = local_map.publish_period
        self.map = CoreLocalMap(self.robot, local_map.options())
        # a new session at every start: a receiver takes up its updates from a whole map
        self.sender = UpdateSender(
            int.from_bytes(os.urandom(4)),
            UpdateTolerance(
                local_map.update_tolerance_m,
                local_map.update_tolerance_rad,
                local_map.update_key_tolerance,
            ),
        )
        self.resyncs = 0
        self.deferred_updates = 0
        self._rendezvous_sent: tuple | None = None
        self.thinning = declare_settings(self, CsamConfig).thinning()
        self.robots = list(dict.fromkeys([self.robot, *peers]))
        bounds = declare_settings(self, InputBounds)
        self.filter = MeasurementFilter(self.robots, np.deg2rad(fov), bounds)
        # the peers' own checks, repeated on their rendezvous streams so that this node keeps
        # poses at the same measurements as their smoothers (drops counted there, not here);
        # their stamps are checked against this robot's odometry (one time for all robots)
        self.peer_filter = MeasurementFilter(
            self.robots, np.deg2rad(fov), bounds, lambda: self.filter.clock(self.robot)
        )
        self.drops = self.filter.counter(self.robot)
        self.frames = MapToOdom(self, self.robot, self.drops)
        self.own_rendezvous: list[tuple[float, dict]] = []
        self.rendezvous_stamps: set[float] = set()
        self.last_odometry_ns = -1
        self.published_ns = -1
        self.dirty = False  # data accepted since the last solve
        self.flushed = False  # the last publication was a flush, and nothing came since
        self.solve_seconds = 0.0
        self.errors = 0
        self.outside_stamps: set[float] = set()  # rendezvous stamps before the first pose
        self.restarts = 0  # restarts from a checkpoint
        self.lost_seconds = 0.0  # odometry time lost while the node was down
        self._resumed_after: float | None = None  # the checkpoint's last odometry stamp
        self._odometry_period: float | None = None
        if self.checkpoint_path is not None:
            self.resume(self.checkpoint_path)

        self.state_services = SmootherServices(self)  # ~/save_state, ~/load_state, ~/reset, ...
        taking = self.state_services.taking  # input dropped while paused
        # this robot's topics by relative name (the node runs in the robot's namespace)
        subscribe(self, ODOM, guarded(self, self.drops, taking(self.on_odometry)))
        subscribe(self, FEATURES, guarded(self, self.drops, taking(self.on_features)))
        subscribe(self, FEATURE_POINTS, guarded(self, self.drops, taking(self.on_feature_points)))
        subscribe(self, RENDEZVOUS, guarded(self, self.drops, taking(self.on_own_rendezvous)))
        on_peer = guarded(self, self.drops, taking(self.on_peer_rendezvous))
        for peer in self.robots:
            if peer != self.robot:
                subscribe(
                    self,
                    RENDEZVOUS,
                    lambda msg, peer=peer: on_peer(peer, msg),
                    RENDEZVOUS.of(peer),
                )
        self.local_map_pub = publisher(self, LOCAL_MAP)
        self.update_pub = publisher(self, LOCAL_MAP_UPDATES)
        self.rendezvous_pub = publisher(self, RENDEZVOUS_POSES)
        if own["team_key_file"]:  # each message after its signature (ros/signing.py)
            key = read_team_key(own["team_key_file"])
            self.update_pub = SignedPublisher(self, self.update_pub, key)
            self.rendezvous_pub = SignedPublisher(self, self.rendezvous_pub, key)
        self.path_pub = publisher(self, PATH)
        self.status_pub = publisher(self, STATUS)
        self.create_service(Trigger, "~/flush", self.on_flush)
        self.create_service(Trigger, f"~/{RESYNC}", self.on_resync)
        self.publish_timer = self.create_timer(
            self.publish_period, guarded(self, self.drops, self.on_timer)
        )
        publish_period = Live(
            self.set_publish_period, setting_check(LocalMapConfig, "publish_period")
        )
        watch_parameters(self, {"publish_period": publish_period}, self.drops)
        if self.restarts and self.published_ns >= 0 and len(self.map.stamps) >= 2:
            guarded(self, self.drops, self.publish)(0)  # the resumed map, latched, at once

    def set_publish_period(self, seconds: float) -> None:
        """Publish every ``seconds`` from now on (the parameter set at run time)."""
        self.publish_period = seconds
        self.publish_timer.timer_period_ns = round(seconds * 1e9)

    # -- input ----------------------------------------------------------------------------------

    def on_odometry(self, msg: Odometry) -> None:
        accepted = self.filter.odometry_reading(self.robot, odometry_reading_from_message(msg))
        if accepted:
            self.frames.add(msg, accepted)
            samples = [sample for sample, _ in accepted]
            if self._resumed_after is not None:
                self._count_lost(samples[0][0])
            stamps, inputs, sigmas, rho = (np.array(a) for a in zip(*samples, strict=True))
            self.map.add_odometry(stamps, inputs, sigmas, rho if rho.any() else None)
            self.last_odometry_ns = time_to_ns(msg.header.stamp)
            self.accepted()

    def on_features(self, msg: FeatureObservations) -> None:
        stamp, a = features_from_message(msg)
        keep = self.filter.features(
            self.robot, stamp, a["ranges"], a["bearings"], a["sigma_range"], a["sigma_bearing"]
        )
        if keep is not None:
            self.map.add_features(
                np.full(int(keep.sum()), stamp),
                a["labels"][keep],
                a["ranges"][keep],
                a["bearings"][keep],
                a["sigma_range"][keep],
                a["sigma_bearing"][keep],
            )
            self.accepted()

    def on_feature_points(self, msg: FeaturePoints) -> None:
        stamp, a = feature_points_from_message(msg)
        keep = self.filter.points(self.robot, stamp, a["points"], a["covariances"])
        if keep is not None:
            self.map.add_points(
                np.full(int(keep.sum()), stamp),
                a["labels"][keep],
                a["points"][keep],
                a["covariances"][keep],
            )
            self.accepted()

    def on_own_rendezvous(self, msg: RendezvousObservations) -> None:
        stamp, a = rendezvous_from_message(msg)
        keep = _checked_rendezvous(self.filter, self.robot, stamp, a)
        if keep is None:
            return
        for i in np.flatnonzero(keep):
            if not self.thinning.offer(self.robot, a["observed"][i], stamp):
                keep[i] = False
        if keep.any():
            self.own_rendezvous.append((stamp, {k: v[keep] for k, v in a.items()}))
            self.request_pose(stamp)

    def on_peer_rendezvous(self, peer: str, msg: RendezvousObservations) -> None:
        """A peer's measurements: only the stamps of kept ones of this robot matter here."""
        stamp, a = rendezvous_from_message(msg)
        keep = _checked_rendezvous(self.peer_filter, peer, stamp, a)
        if keep is None:
            return
        for i in np.flatnonzero(keep):
            if a["observed"][i] == self.robot and self.thinning.offer(peer, self.robot, stamp):
                self.request_pose(stamp)

    def request_pose(self, stamp: float) -> None:
        if stamp not in self.rendezvous_stamps:
            self.rendezvous_stamps.add(stamp)
            self.map.request_poses([stamp])
            self.accepted()

    def accepted(self) -> None:
        """New data went into the local map: the next timer tick (or flush) solves."""
        self.dirty = True
        self.flushed = False

    # -- output ---------------------------------------------------------------------------------

    def on_timer(self) -> None:
        if self.dirty:
            self.solve_and_publish()

    def on_flush(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        """Solve to convergence and publish; always answers (the update itself is guarded).
        A flush with no data since the last one publishes nothing again: its map is the same."""
        if not self.flushed:
            guarded(self, self.drops, self.solve_and_publish)(True)
        response.success = self.published_ns >= 0
        response.message = str(self.published_ns)
        return response

    def on_resync(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        """Publish the whole local map as it was last sent, as one update (a receiver missed
        one, or asks whose a whole map of another session is), also while the last update is
        unacknowledged (that one may be lost); the reply's message names the session and
        that update's sequence number (0: nothing sent yet)."""
        update = self.sender.resend()
        if update is not None:
            self.resyncs += 1
            self.update_pub.publish(
                local_map_update_message(update, self.robot, max(self.published_ns, 0))
            )
        response.success = update is not None
        response.message = resync_answer(self.sender.session, update.sequence if update else 0)
        return response

    def solve_and_publish(self, converge: bool = False) -> None:
        """Update the local map and publish it (``converge``: iterate to the batch optimum,
        else the online policy's capped update); a failure is logged and counted, never fatal
        (the last published map stays valid)."""
        start = time.perf_counter()
        try:
            if self.last_odometry_ns >= 0:
                self._solve_and_publish(converge)
        except Exception as err:  # noqa: BLE001 (a node never dies of its input)
            self.errors += 1
            self.get_logger().error(f"local map update failed: {type(err).__name__}: {err}")
        self.solve_seconds = time.perf_counter() - start
        self.publish_status()

    def _solve_and_publish(self, converge: bool) -> None:
        report = self.map.update(converge=converge)
        self.dirty = False
        if len(self.map.stamps) < 2:  # only the start pose: nothing to publish yet
            return
        self.publish(report.solve.iterations if report.solve is not None else 0, exact=converge)
        self.flushed = converge

    def publish(self, iterations: int, exact: bool = False) -> None:
        """Publish the local map's update (every estimate exactly when ``exact``) and what
        goes with it (and write the checkpoint, when on)."""
        robot_map = robot_map_from_local_map(self.map)
        stamp_ns = self.last_odometry_ns
        rendezvous, content = self.rendezvous_poses(robot_map, stamp_ns)
        if exact or self.update_pub.wait_for_all_acked(NO_WAIT):
            update = self.sender.update(
                robot_map_arrays(robot_map),
                exact=exact,
                key_poses=np.asarray(rendezvous.pose_indices, dtype=np.int64),
            )
            message = local_map_update_message(update, self.robot, stamp_ns, iterations)
            self.update_pub.publish(message)
        else:
            self.deferred_updates += 1
        if self.local_map_pub.get_subscription_count():
            self.local_map_pub.publish(
                robot_map_to_message(
                    robot_map,
                    stamp_ns,
                    self.map.pose_covariances(),
                    self.map.landmark_covariances(),
                    iterations,
                )
            )
        if exact or content != self._rendezvous_sent:  # its poses are for a look only
            self.rendezvous_pub.publish(rendezvous)
            self._rendezvous_sent = content
        if self.path_pub.get_subscription_count():
            self.path_pub.publish(self.path(stamp_ns))
        self.frames.update(float(self.map.stamps[-1]), self.map.poses[-1])
        self.published_ns = stamp_ns
        if self.checkpoint_path is not None:
            self.write_checkpoint(self.checkpoint_path)

    # -- checkpoint -----------------------------------------------------------------------------

    def checkpoint(self) -> SmootherCheckpoint:
        """What this node accepted and its local map, as a checkpoint."""
        return SmootherCheckpoint(
            robot=self.robot,
            local_map=self.map.state(),
            filter=FilterState.of(self.filter),
            peer_filter=FilterState.of(self.peer_filter),
            thinning=ThinningState.of(self.thinning),
            own_rendezvous=rendezvous_log_from_chunks(self.own_rendezvous),
            rendezvous_stamps=np.array(sorted(self.rendezvous_stamps), dtype=float),
            last_odometry_ns=self.last_odometry_ns,
            published_ns=self.published_ns,
            errors=self.errors,
            restarts=self.restarts,
            lost_seconds=self.lost_seconds,
        )

    def write_checkpoint(self, path: pathlib.Path) -> None:
        """Write what this node accepted and its local map to ``path`` (atomically); a
        failure is logged and counted as an error, never fatal."""
        try:
            self.checkpoint().write(path)
        except OSError as err:
            self.errors += 1
            self.get_logger().error(f"checkpoint not written to {path}: {err}")

    def resume(self, path: pathlib.Path) -> None:
        """Take up the state of the checkpoint at ``path`` if there is a usable one of this
        robot (else say why and start empty)."""
        if not path.exists():
            self.get_logger().info(f"no checkpoint at {path} yet: starting empty")
            return
        try:
            saved, local = self.read_checkpoint(path)
        except CheckpointError as err:
            self.drops.add(UNUSABLE_STATE)
            self.get_logger().error(f"checkpoint not used, starting empty: {err}")
            return
        self.take_up(saved, local, f"resumed from {path}")

    def read_checkpoint(self, path: pathlib.Path) -> tuple[SmootherCheckpoint, CoreLocalMap]:
        """The checkpoint of this robot at ``path`` and its local map; any fault (the file's,
        or a map that cannot be rebuilt) is a :class:`CheckpointError` naming it."""
        try:
            saved = SmootherCheckpoint.read(path, self.robot)
            return saved, CoreLocalMap.from_state(self.robot, saved.local_map, self.map.options)
        except CheckpointError:
            raise
        except Exception as err:  # noqa: BLE001 - a node never dies of a bad file
            raise CheckpointError(f"{path}: {type(err).__name__}: {err}") from None

    def load(self, path: pathlib.Path) -> None:
        """``~/load_state``: replace the state by the checkpoint at ``path`` as a restart from
        it would, in a new session, and publish its map; a :class:`CheckpointError` leaves
        the state as it was."""
        saved, local = self.read_checkpoint(path)
        self.forget()
        self.take_up(saved, local, f"loaded {path}")
        if self.published_ns >= 0 and len(self.map.stamps) >= 2:
            self.publish(0, exact=True)  # the whole map: the first update of its session

    def forget(self) -> None:
        """Forget every input, the local map and the counts, in a new update session (the
        first update of which is the whole map): the state of a smoother just started
        without a checkpoint. The drop counters stay the same objects (callbacks hold them)."""
        self.map = CoreLocalMap(self.robot, self.map.options)
        for checks in (self.filter, self.peer_filter):
            checks.restore_streams({})
            for counter in checks.drops.values():
                counter.counts.clear()
        self.thinning.restore({}, {})
        self.own_rendezvous, self.rendezvous_stamps, self.outside_stamps = [], set(), set()
        self.last_odometry_ns = self.published_ns = -1
        self.dirty = self.flushed = False
        self.solve_seconds, self.errors, self.restarts, self.lost_seconds = 0.0, 0, 0, 0.0
        self.resyncs = self.deferred_updates = 0
        self._resumed_after = self._odometry_period = None
        self._rendezvous_sent = None
        self.sender = UpdateSender(int.from_bytes(os.urandom(4)), self.sender.tolerance)
        self.frames.reset()

    def take_up(self, saved: SmootherCheckpoint, local: CoreLocalMap, origin: str) -> None:
        """Go on from ``saved`` and its local map ``local`` (``origin``: where from, logged)
        on a node just started or :meth:`forget`-ful: as a restart from that checkpoint."""
        self.map = local
        saved.filter.restore(self.filter)
        saved.peer_filter.restore(self.peer_filter)
        saved.thinning.restore(self.thinning)
        log = saved.own_rendezvous
        observed = np.array(log.observed, dtype=object)
        self.own_rendezvous = []  # one chunk per run of equal stamps, in arrival order
        for _, rows in _runs(log.stamps):
            self.own_rendezvous.append(
                (
                    float(log.stamps[rows.start]),
                    {
                        "observed": observed[rows],
                        "ranges": log.ranges[rows],
                        "bearings": log.bearings[rows],
                        "sigma_range": log.sigma_range[rows],
                        "sigma_bearing": log.sigma_bearing[rows],
                    },
                )
            )
        self.rendezvous_stamps = set(saved.rendezvous_stamps.tolist())
        if len(self.map.stamps):  # counted before the restart
            first = self.map.stamps[0] - self.map.options.stamp_tolerance
            self.outside_stamps = {t for t in self.rendezvous_stamps if t < first}
        self.last_odometry_ns, self.published_ns = saved.last_odometry_ns, saved.published_ns
        self.errors, self.lost_seconds = saved.errors, saved.lost_seconds
        self.restarts = saved.restarts + 1
        odometry = saved.local_map.odometry_stamps
        self._resumed_after = float(odometry[-1]) if len(odometry) else None
        self._odometry_period = odometry_period(odometry)
        self.frames.resume(odometry, saved.local_map.odometry_inputs)
        self.get_logger().info(
            f"{origin}: {len(self.map.stamps)} poses, "
            f"{len(self.map.landmark_labels)} features, odometry up to "
            f"{self._resumed_after if self._resumed_after is not None else float('nan'):.3f} s"
        )

    def _count_lost(self, first_stamp: float) -> None:
        """Count what came while the node was down: the odometry samples missed between the
        checkpoint's last one and ``first_stamp``, the first accepted after the restart."""
        assert self._resumed_after is not None
        gap = first_stamp - self._resumed_after
        period = self._odometry_period
        missed = missed_samples(gap, period)
        lost = max(gap - (period or 0.0), 0.0)
        self._resumed_after = None
        self.drops.add(LOST_WHILE_DOWN, missed)
        self.lost_seconds += lost
        self.get_logger().warning(
            f"odometry resumed {gap:.3f} s after the checkpoint's last sample: {missed} "
            f"odometry samples ({lost:.3f} s of data, with what else came then) lost while "
            "the smoother was down"
        )

    def rendezvous_poses(self, robot_map: RobotMap, stamp_ns: int) -> tuple[RendezvousPoses, tuple]:
        """The rendezvous poses message, and what the merger reads of it (the measurements,
        and where their poses are) to compare with the last one sent."""
        measurements, stamps = self.kept_rendezvous()
        tolerance = self.map.options.stamp_tolerance
        early = stamps[stamps < self.map.stamps[0] - tolerance]
        for t in set(early.tolist()) - self.outside_stamps:
            # before this robot's first pose (e.g. a peer's clock ahead of this one's): no pose
            # will ever be there; counted once, and the merger leaves the measurement out
            self.outside_stamps.add(t)
            self.drops.add(OUTSIDE_TRAJECTORY)
            self.get_logger().warning(
                f"a rendezvous at {t:.3f} s is before this robot's first pose at "
                f"{self.map.stamps[0]:.3f} s: no pose there (clocks differ?)"
            )
        stamps = stamps[
            (stamps >= self.map.stamps[0] - tolerance) & (stamps <= self.map.stamps[-1])
        ]
        indices = np.unique(self.map.pose_index(stamps)) if len(stamps) else np.zeros(0, int)
        content = (
            indices.tobytes(),
            measurements.stamps.tobytes(),
            tuple(measurements.observed),
            measurements.ranges.tobytes(),
            measurements.bearings.tobytes(),
        )
        return rendezvous_poses_message(robot_map, stamp_ns, indices, measurements), content

    def kept_rendezvous(self) -> tuple[RendezvousLog, np.ndarray]:
        """This robot's kept measurements, and the stamps of every kept measurement that
        involves it (its own and its peers' of it)."""
        own = rendezvous_log_from_chunks(self.own_rendezvous)
        keep = [
            self.thinning.is_kept(self.robot, o, t)
            for o, t in zip(own.observed, own.stamps, strict=True)
        ]
        own = select_rendezvous(own, np.array(keep, dtype=bool))
        peers = [p for p in self.robots if p != self.robot]
        observed_by_peers = [t for p in peers for t in self.thinning.kept_stamps(p, self.robot)]
        return own, np.unique(np.concatenate([own.stamps, observed_by_peers]))

    def path(self, stamp_ns: int) -> Path:
        msg = Path()
        msg.header.stamp = ns_to_time(stamp_ns)
        msg.header.frame_id = f"{self.robot}/map"
        for t, p in zip(self.map.stamps, self.map.poses, strict=True):
            pose = PoseStamped()
            pose.header.frame_id = msg.header.frame_id
            pose.header.stamp = ns_to_time(stamp_to_ns(t))
            pose.pose.position.x, pose.pose.position.y = float(p[0]), float(p[1])
            pose.pose.orientation = yaw_quaternion(p[2])
            msg.poses.append(pose)
        return msg

    def publish_status(self) -> None:
        drops = self.filter.counter(self.robot)
        values = {
            "poses": len(self.map.stamps),
            "features": len(self.map.landmark_labels),
            "rendezvous_poses": len(self.rendezvous_stamps),
            "solve_seconds": round(self.solve_seconds, 4),
            "dropped": drops.total,
            "errors": self.errors,
            "restarts": self.restarts,
            "complete_updates": self.sender.complete_updates,
            "resyncs": self.resyncs,
            "deferred_updates": self.deferred_updates,
            "lost_seconds": round(self.lost_seconds, 3),
            "fold_recoveries": self.map.fold_recoveries,
            ODOMETRY_DEFAULT_SIGMAS: self.filter.defaulted.counts[self.robot],
            **{f"dropped/{k}": v for k, v in drops.as_dict().items()},
        }
        array = node_status(
            f"smoother/{self.robot}",
            self.robot,
            drops.total == 0 and self.errors == 0,
            f"{values['poses']} poses, {values['features']} features, {drops.total} inputs dropped",
            values,
            self.get_clock().now().to_msg(),
        )
        self.status_pub.publish(array)


def _runs(stamps: np.ndarray) -> list[tuple[float, slice]]:
    """The runs of equal consecutive stamps."""
    if len(stamps) == 0:
        return []
    starts = np.flatnonzero(np.r_[True, np.diff(stamps) != 0])
    ends = np.r_[starts[1:], len(stamps)]
    return [(float(stamps[a]), slice(int(a), int(b))) for a, b in zip(starts, ends, strict=True)]


def _checked_rendezvous(
    checks: MeasurementFilter, robot: str, stamp: float, a: dict
) -> np.ndarray | None:
    """``checks``' mask of the accepted observations of one rendezvous message."""
    observations = (a[k] for k in ("ranges", "bearings", "sigma_range", "sigma_bearing"))
    return checks.rendezvous(robot, stamp, a["observed"], *observations)


def main(args: list[str] | None = None) -> int:
    return run_node(Smoother, args, __doc__)


if __name__ == "__main__":
    sys.exit(main())
