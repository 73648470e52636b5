"""The offline replay (``csam replay --offline``): a bag's sensor data through the core in
stamp order, no DDS; optionally continued from, or saved as, a replay's state."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING

from csam_ros.forked import Forked
from csam_ros.run.errors import RunError, warn

if TYPE_CHECKING:
    from csam_ros.core.exchange.measurement_filter import MeasurementFilter
    from csam_ros.core.joining.result import RunSummary
    from csam_ros.core.model.log import GroundTruth, MultiRobotLog


def bag_contents(bag: Path) -> tuple[list[str], float, list[str]]:
    """The robots of a bag's sensor topics, the bag's duration [s] and its topics."""
    from csam_ros.bag import inspect_bag
    from csam_ros.ros.topics import parse

    info = inspect_bag(bag)
    for line in info.warnings:
        warn(line)
    declared = [parse(t) for t in info.topics]
    robots = sorted({d[1] for d in declared if d is not None and d[0].sensor})
    if not robots:
        raise RunError(f"{bag}: no sensor topics (/<robot>/odom, features or rendezvous)")
    return robots, max(info.end_ns - info.start_ns, 0) * 1e-9, list(info.topics)


def read_offline_log(
    bag: Path, config_document: dict | None = None, resume: Path | None = None
) -> tuple[MultiRobotLog, MeasurementFilter]:
    """A bag's sensor data and truth as the core's log, through the smoothers' input filter
    (its ``input:`` bounds), and that filter with its drop counts.

    ``resume``: the data after the state an earlier replay saved, joined to its accepted logs
    and through its measurement filter."""
    from csam_ros.bag import read_bag_messages
    from csam_ros.core.exchange.checkpoint import OfflineState, joined_logs
    from csam_ros.core.exchange.state_files import CheckpointError
    from csam_ros.core.exchange.validation import InputBounds
    from csam_ros.core.model.log import MultiRobotLog
    from csam_ros.ros.conversions import LogBuilder
    from csam_ros.ros.topics import FEATURES_TRUTH, sensor_topics

    try:
        bounds = InputBounds.from_dict((config_document or {}).get("input"), "input")
    except ValueError as err:
        raise RunError(str(err)) from None
    robots = bag_contents(bag)[0]
    saved = None
    if resume is not None:
        try:
            saved = OfflineState.read(resume)
        except CheckpointError as err:
            raise RunError(f"--resume: {err}") from None
        robots = [*saved.logs, *(r for r in robots if r not in saved.logs)]
    builder = LogBuilder(robots, bounds=bounds)
    if saved is not None:
        saved.filter.restore(builder.filter)
    topics = [*sensor_topics(robots), FEATURES_TRUTH.name]
    for m in read_bag_messages(bag, topics, on_damage=warn, decoder="rosbags"):
        builder.add(m.topic, m.message)
    log = builder.build()
    if saved is not None:
        try:
            log = MultiRobotLog(joined_logs(saved.logs, log.robots), log.truth)
        except ValueError as err:
            raise RunError(f"--resume {resume}: {err}") from None
    return log, builder.filter


def offline_summary(
    bag: Path,
    config_document: dict | None = None,
    resume: Path | None = None,
    save_state: Path | None = None,
    reading: Forked[tuple[MultiRobotLog, MeasurementFilter]] | None = None,
    progress: Callable[[str], None] = print,
) -> tuple[RunSummary, GroundTruth | None]:
    """The summary of a bag run through the core in stamp order (no DDS), and its truth.

    ``resume``: continue from the state an earlier replay saved (its accepted logs and its
    measurement filter), the bag's data after them; ``save_state``: write the state of this
    replay there (a replay continued from it equals one over all the data), and say so to
    ``progress``, as the odometry samples given default sigmas (odometry as drivers publish
    it is read as by the smoothers: ``LogBuilder``, ``MeasurementFilter.odometry_reading``).
    ``reading``: the :func:`read_offline_log` of the same arguments, already under way in
    another process."""
    from csam_ros.core.exchange.checkpoint import FilterState, OfflineState
    from csam_ros.core.joining.config import CsamConfig
    from csam_ros.core.joining.pipeline import run_csam
    from csam_ros.core.joining.result import RunSummary
    from csam_ros.core.smoothing.local_map_config import LocalMapConfig

    document = config_document or {}
    try:
        config = CsamConfig.from_dict(document.get("csam"), "csam")
        local_map = LocalMapConfig.from_dict(document.get("local_map"), "local_map")
    except ValueError as err:
        raise RunError(str(err)) from None
    if reading is None:
        log, measurement_filter = read_offline_log(bag, document, resume)
    else:
        log, measurement_filter = reading.result()
    dropped = {r: c.as_dict() for r, c in measurement_filter.drops.items()}
    defaulted = measurement_filter.defaulted.as_dict()
    if defaulted:  # the odometry without a covariance (smoother status: odometry_default_sigmas)
        counts = ", ".join(f"{r} {n}" for r, n in defaulted.items())
        progress(f"  odometry samples given default sigmas (no covariance): {counts}")
    try:
        result = run_csam(log, config, local_map)
    except ValueError as err:  # no robot with a local map: named with the reason of each
        drops = "; ".join(f"{r} dropped {d}" for r, d in dropped.items() if d)
        raise RunError(f"{bag}: {err}" + (f" ({drops})" if drops else "")) from None
    if save_state is not None:
        state = OfflineState(log.robots, FilterState.of(measurement_filter), result)
        size = state.write(save_state)
        progress(f"  state saved to {save_state} ({size / 1e6:.2f} MB)")
    return RunSummary(result, dropped=dropped), log.truth


@contextmanager
def reading_ahead(
    bag: Path, config_document: dict, resume: Path | None = None
) -> Iterator[Forked[tuple[MultiRobotLog, MeasurementFilter]]]:
    """:func:`read_offline_log` under way in a forked process (where this one may fork) while
    the caller goes on, e.g. imports the core's modules; the process is ended on leaving."""
    reading = Forked(read_offline_log, bag, config_document, resume)
    try:
        yield reading
    finally:
        reading.close()
