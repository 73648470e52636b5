"""The ``csam`` command: demo, replay, import and evaluate (docs/ARCHITECTURE.md)."""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from csam_ros.figures.worker import FigureWorker, figure_worker
from csam_ros.forked import Forked
from csam_ros.run.launch import executable
from csam_ros.run.live import LiveRunError

if TYPE_CHECKING:
    from csam_ros.core.exchange.validation import MeasurementFilter
    from csam_ros.core.joining.result import RunSummary
    from csam_ros.core.model.log import GroundTruth, MultiRobotLog
    from csam_ros.run.live import LiveRun

RUNS_DIR = Path("runs")


class CliError(Exception):
    """A user error: printed as one line, exit code 2."""


def _new_run_dir(name: str) -> Path:
    stamp = time.strftime("%Y%m%d-%H%M%S")
    out = RUNS_DIR / f"{name}-{stamp}"
    k = 1
    while out.exists():
        k += 1
        out = RUNS_DIR / f"{name}-{stamp}-{k}"
    return out


def _fresh_dir(path: Path | None, name: str) -> Path:
    out = path or _new_run_dir(name)
    if out.exists() and not out.is_dir():
        raise CliError(f"{out} exists and is not a directory: choose a new --out directory")
    if out.exists() and any(out.iterdir()):
        raise CliError(f"{out} exists and is not empty: choose a new --out directory")
    out.mkdir(parents=True, exist_ok=True)
    return out


def _robot_numbers(text: str | None) -> list[int] | None:
    """``--robots 1,2,3`` as robot numbers (None: all robots)."""
    if not text:
        return None
    try:
        numbers = [int(r) for r in text.split(",")]
    except ValueError:
        raise CliError(f"--robots: expected robot numbers such as 1,2,3, got {text!r}") from None
    if any(n < 1 for n in numbers):
        raise CliError(f"--robots: robot numbers start at 1, got {text!r}")
    return numbers


MERGER_KEYS = {"solve_period", "stale_after", "provisional_period", "provisional_quiet"}  # s


def _node_params(document: dict, section: str, cls: type, node: str) -> dict:
    """The keys given in a file section that ``node`` takes as parameters (the dataclass
    fields whose Setting names it), checked and typed as declared, before any node starts."""
    from csam_ros.core.model.config_file import settings

    given = document.get(section)
    try:
        config = cls.from_dict(given, section)
    except ValueError as err:
        raise CliError(str(err)) from None
    return {
        name: getattr(config, name)
        for name, (rule, _) in settings(cls).items()
        if rule.node == node and name in (given or {})
    }


def _csam_params(document: dict) -> dict:
    """The merger's parameters: its fields of the ``csam:`` section and the ``merger:``
    section's ``solve_period``, ``stale_after``, ``provisional_period`` and
    ``provisional_quiet`` (seconds)."""
    from csam_ros.core.joining.csam import MERGER, CsamConfig

    csam = _node_params(document, "csam", CsamConfig, MERGER)
    merger = document.get("merger") or {}
    unknown = sorted(set(merger) - MERGER_KEYS) if isinstance(merger, dict) else ["(not a map)"]
    if unknown:
        raise CliError(f"merger: unknown key(s) {unknown}; allowed: {sorted(MERGER_KEYS)}")
    seconds = {"solve_period": 0.5, **merger}
    for key, value in seconds.items():
        if isinstance(value, bool) or not isinstance(value, int | float) or not value >= 0:
            raise CliError(f"merger.{key}: expected seconds >= 0, got {value!r}")
    return {**csam, **{key: float(value) for key, value in seconds.items()}}


def _smoother_params(document: dict) -> dict:
    """The smoothers' parameters: their fields of the ``local_map:`` section (all but the
    offline-only ``batch_window``), of the ``csam:`` section (the rendezvous thinning) and the
    ``input:`` section (bounds on sensor messages)."""
    from csam_ros.core.exchange.validation import InputBounds
    from csam_ros.core.joining.csam import CsamConfig
    from csam_ros.core.smoothing.local_map import SMOOTHER, LocalMapConfig

    return {
        **_node_params(document, "local_map", LocalMapConfig, SMOOTHER),
        **_node_params(document, "csam", CsamConfig, SMOOTHER),
        **_node_params(document, "input", InputBounds, SMOOTHER),
    }


def _finish(out: Path, summary: RunSummary, worker: FigureWorker | None = None) -> None:
    """Write ``summary.json`` and the figures into ``out`` (by ``worker`` if given) and say
    what the run gave."""
    summary.write(out / "summary.json")
    result = summary.result
    if worker is not None:
        figures = worker.draw(out / "summary.json", out)
    else:
        from csam_ros.figures.draw import draw_all

        figures = draw_all(result, out, scenario=summary.scenario)
    print(f"result in {out}/")
    for name, r in result.robots.items():
        print(f"  {name}: {r.alignment}, {len(r.stamps)} poses")
    for note in result.notes:
        if ": no local map: " in note or " not converged: " in note:  # from core.csam
            print(f"  {note}")
    print(f"  {len(result.features)} features, {len(result.associations)} associations")
    print("  summary.json, " + ", ".join(p.name for p in figures))


def _print_latency(bag: Path, summary: RunSummary) -> None:
    """Say how long the live run's local maps took to reach the joined map, and how long the
    merger's solves took (from the run's bag; the merger's count from its summary)."""
    from csam_ros.bag import BagError
    from csam_ros.run.lag import read_timeline

    try:
        timeline = read_timeline(bag, on_damage=_warn)
    except BagError as err:
        _warn(f"no lag figures: {err}")
        return
    print(f"  {timeline.lag_stats()}")
    provisional = timeline.provisional_lag_stats()
    if provisional is not None:
        print(f"  {provisional}")
    print(f"  {timeline.solve_stats(summary.merger.solves if summary.merger else None)}")


def demo_live_run(
    scenario_name: str | Path, out: Path, seed: int, rate: float, isolated: bool = False
) -> LiveRun:
    """The live run of ``csam demo``: the simulator playing a scenario (a name in config/ or
    a YAML file, whose ``csam:``, ``local_map:``, ``input:`` and ``merger:`` sections
    configure the nodes) into smoothers and a merger, recorded to ``out/bag``."""
    from csam_ros.datasets.scenario import load_document, load_scenario
    from csam_ros.run.live import LiveRun

    scenario = load_scenario(scenario_name)
    document = load_document(scenario_name)
    fov = max(np.rad2deg(r.feature_sensor.field_of_view) for r in scenario.robots)
    return LiveRun(
        out_dir=out,
        robots=[r.name for r in scenario.robots],
        source_name="simulator",
        source_argv=[executable("simulator")],
        source_ros_args=[
            "-p",
            f"scenario:={scenario_name}",
            "-p",
            f"seed:={seed}",
            "-p",
            f"rate:={rate}",
            "-p",
            "exit_when_done:=true",
            # every sensor topic: the recorder and at least the robot's own smoother
            "-p",
            "min_subscribers:=2",
            "-p",
            'required_subscriber_nodes:=["recorder"]',
        ],
        smoother_params={"field_of_view_deg": float(fov), **_smoother_params(document)},
        merger_params=_csam_params(document),
        isolated=isolated,
    )


def _link_cut(text: str | None) -> tuple[str, float, float] | None:
    """``--cut ROBOT:START-END`` as (robot, start, end); ValueError naming what does not read."""
    if text is None:
        return None
    robot, _, window = text.partition(":")
    start, _, end = window.partition("-")
    try:
        return robot, float(start), float(end)
    except ValueError:
        raise ValueError(f"--cut: expected ROBOT:START-END (seconds), got {text!r}") from None


def cmd_demo(args: argparse.Namespace) -> int:
    from csam_ros.datasets.scenario import load_scenario
    from csam_ros.run.hosts import HostsError, Links, missing_requirements, run_hosts
    from csam_ros.run.live import run_live

    if (args.loss or args.link_rate or args.base_link_rate or args.cut) and not args.hosts:
        raise CliError(
            "--loss, --link-rate, --base-link-rate and --cut need --hosts (links between hosts)"
        )
    if args.hosts:
        try:
            links = Links(args.loss, args.link_rate, _link_cut(args.cut), args.base_link_rate)
        except ValueError as err:
            raise CliError(f"--hosts: {err}") from None
        if (reason := missing_requirements(links)) is not None:
            raise CliError(f"--hosts: {reason}")
    scenario = load_scenario(args.scenario)
    out = _fresh_dir(args.out, scenario.name)
    seed = scenario.seed if args.seed is None else args.seed
    print(
        f"csam demo: scenario {scenario.name} ({len(scenario.robots)} robots), seed {seed}, "
        f"rate {args.rate}, output {out}/"
    )
    run = demo_live_run(args.scenario, out, seed, args.rate, args.isolated)
    # forked before the nodes start (this process has no thread yet): it imports matplotlib
    # while the run goes on, and draws the figures once it has ended
    worker = figure_worker()
    try:
        if args.hosts:
            try:
                summary = run_hosts(run, links)
            except HostsError as err:
                raise CliError(f"--hosts: {err}") from None
        else:
            summary = run_live(run)
        _finish(out, replace(summary, scenario=scenario.name), worker)
    finally:
        if worker is not None:
            worker.close()
    _print_latency(out / "bag", summary)
    return 0


_warned: set[str] = set()


def _warn(line: str) -> None:
    """Print a warning about the input once, e.g. a bag cut short or with a damaged chunk
    (what was read and what was lost)."""
    if line not in _warned:
        _warned.add(line)
        print(f"warning: {line}", file=sys.stderr)


def _bag_robots(bag: Path) -> list[str]:
    return _bag_contents(bag)[0]


def _bag_contents(bag: Path) -> tuple[list[str], float, list[str]]:
    """The robots of a bag's sensor topics, the bag's duration [s] and its topics."""
    from csam_ros.bag import inspect_bag
    from csam_ros.ros.topics import parse

    info = inspect_bag(bag)
    for line in info.warnings:
        _warn(line)
    declared = [parse(t) for t in info.topics]
    robots = sorted({d[1] for d in declared if d is not None and d[0].sensor})
    if not robots:
        raise CliError(f"{bag}: no sensor topics (/<robot>/odom, features or rendezvous)")
    return robots, max(info.end_ns - info.start_ns, 0) * 1e-9, list(info.topics)


def read_offline_log(
    bag: Path, config_document: dict | None = None, resume: Path | None = None
) -> tuple[MultiRobotLog, MeasurementFilter]:
    """A bag's sensor data and truth as the core's log, through the smoothers' input filter
    (its ``input:`` bounds), and that filter with its drop counts.

    ``resume``: the data after the state an earlier replay saved, joined to its accepted logs
    and through its measurement filter."""
    from csam_ros.bag import read_bag_messages
    from csam_ros.core.exchange.checkpoint import CheckpointError, OfflineState, joined_logs
    from csam_ros.core.exchange.validation import InputBounds
    from csam_ros.core.model.log import MultiRobotLog
    from csam_ros.ros.conversions import LogBuilder
    from csam_ros.ros.topics import FEATURES_TRUTH, sensor_topics

    try:
        bounds = InputBounds.from_dict((config_document or {}).get("input"), "input")
    except ValueError as err:
        raise CliError(str(err)) from None
    robots = _bag_robots(bag)
    saved = None
    if resume is not None:
        try:
            saved = OfflineState.read(resume)
        except CheckpointError as err:
            raise CliError(f"--resume: {err}") from None
        robots = [*saved.logs, *(r for r in robots if r not in saved.logs)]
    builder = LogBuilder(robots, bounds=bounds)
    if saved is not None:
        saved.filter.restore(builder.filter)
    topics = [*sensor_topics(robots), FEATURES_TRUTH.name]
    for m in read_bag_messages(bag, topics, on_damage=_warn, decoder="rosbags"):
        builder.add(m.topic, m.message)
    log = builder.build()
    if saved is not None:
        try:
            log = MultiRobotLog(joined_logs(saved.logs, log.robots), log.truth)
        except ValueError as err:
            raise CliError(f"--resume {resume}: {err}") from None
    return log, builder.filter


def offline_summary(
    bag: Path,
    config_document: dict | None = None,
    resume: Path | None = None,
    save_state: Path | None = None,
    reading: Forked[tuple[MultiRobotLog, MeasurementFilter]] | None = None,
) -> tuple[RunSummary, GroundTruth | None]:
    """The summary of a bag run through the core in stamp order (no DDS), and its truth.

    ``resume``: continue from the state an earlier replay saved (its accepted logs and its
    measurement filter), the bag's data after them; ``save_state``: write the state of this
    replay there (a replay continued from it equals one over all the data). ``reading``: the
    :func:`read_offline_log` of the same arguments, already under way in another process."""
    from csam_ros.core.exchange.checkpoint import FilterState, OfflineState
    from csam_ros.core.joining.csam import CsamConfig, run_csam
    from csam_ros.core.joining.result import RunSummary
    from csam_ros.core.smoothing.local_map import LocalMapConfig

    document = config_document or {}
    try:
        config = CsamConfig.from_dict(document.get("csam"), "csam")
        local_map = LocalMapConfig.from_dict(document.get("local_map"), "local_map")
    except ValueError as err:
        raise CliError(str(err)) from None
    if reading is None:
        log, measurement_filter = read_offline_log(bag, document, resume)
    else:
        log, measurement_filter = reading.result()
    dropped = {r: c.as_dict() for r, c in measurement_filter.drops.items()}
    try:
        result = run_csam(log, config, local_map)
    except ValueError as err:  # no robot with a local map: named with the reason of each
        drops = "; ".join(f"{r} dropped {d}" for r, d in dropped.items() if d)
        raise CliError(f"{bag}: {err}" + (f" ({drops})" if drops else "")) from None
    if save_state is not None:
        state = OfflineState(log.robots, FilterState.of(measurement_filter), result)
        size = state.write(save_state)
        print(f"  state saved to {save_state} ({size / 1e6:.2f} MB)")
    return RunSummary(result, dropped=dropped), log.truth


def cmd_replay(args: argparse.Namespace) -> int:
    from csam_ros.bag import BagError

    bag = args.bag
    if not bag.exists():
        raise CliError(f"{bag}: no such bag")
    if (args.save_state or args.resume) and not args.offline:
        raise CliError(
            "--save-state and --resume go with --offline (a live merger saves its state "
            "through its state_path parameter)"
        )
    document = {}
    if args.config is not None:
        from csam_ros.core.model.config_file import ConfigFileError, load_document

        try:
            document = load_document(args.config)
        except (ConfigFileError, OSError) as err:
            raise CliError(f"--config: {err}") from None
    # offline, the bag is read on the other core while the core's modules are imported here,
    # and then the figures' worker imports matplotlib there while the core computes here (live,
    # while the nodes run)
    reading = Forked(read_offline_log, bag, document, args.resume) if args.offline else None
    worker = None
    try:
        merger_params, smoother_params = _csam_params(document), _smoother_params(document)
        out = _fresh_dir(args.out, f"replay-{bag.name}")
        worker = figure_worker()
        if args.offline:
            summary, _ = offline_summary(
                bag, document, args.resume, args.save_state, reading=reading
            )
        else:
            from csam_ros.ros.topics import FEATURES_TRUTH, sensor_topics
            from csam_ros.run.live import LiveRun, run_live

            robots, duration, in_bag = _bag_contents(bag)
            # the sensor topics a bag has (a 2D SLAM file's has feature points, no features)
            sensors = [t for t in sensor_topics(robots) if t in in_bag]
            topics = [t for t in [*sensors, FEATURES_TRUTH.name] if t in in_bag]
            run = LiveRun(
                out_dir=out,
                robots=robots,
                source_name="player",
                source_argv=[
                    executable("player"),
                    str(bag),
                    "--rate",
                    str(args.rate),
                    "--topics",
                    *topics,
                    "--delay",  # let discovery settle both ways: odometry is best effort
                    "2.0",
                    "--wait-for-subscribers",
                    *sensors,
                    "--min-subscribers",  # the recorder and at least the robot's smoother
                    "2",
                ],
                smoother_params=smoother_params,
                merger_params=merger_params,
                # the playback itself plus a margin (a replay at --rate 0 is not paced)
                timeout_s=600.0 + (1.2 * duration / args.rate if args.rate > 0 else duration),
                isolated=args.isolated,
            )
            summary = run_live(run)
        summary = replace(summary, source=str(bag), scenario=summary.scenario or bag.resolve().name)
        _finish(out, summary, worker)
    except BagError as err:
        raise CliError(str(err)) from None
    finally:
        if reading is not None:
            reading.close()
        if worker is not None:
            worker.close()
    if not args.offline:
        _print_latency(out / "bag", summary)
    return 0


def cmd_evaluate(args: argparse.Namespace) -> int:
    from csam_ros.core.joining.result import RunSummary, SummaryError
    from csam_ros.core.truth.evaluation import evaluate

    run_dir = args.dir
    summary_path = run_dir / "summary.json"
    if not summary_path.exists():
        raise CliError(f"{summary_path}: no such file (a run directory holds summary.json)")
    try:
        summary = RunSummary.read(summary_path)
    except SummaryError as err:
        raise CliError(str(err)) from None
    truth = _truth_of(run_dir, summary.source)
    if truth is None:
        raise CliError(f"{run_dir}: no ground truth (/sim/features_truth) in the run's bag")
    metrics = evaluate(summary.result, truth)
    (run_dir / "metrics.json").write_text(json.dumps(metrics, indent=1))
    error, assoc = metrics["landmark_error"], metrics["association"]
    print(f"{run_dir}/metrics.json")
    if error["rmse_m"] is None:
        print("  landmarks: no feature of the joined map could be scored")
    else:
        print(
            f"  landmarks: RMSE {error['rmse_m']:.3f} m, max {error['max_m']:.3f} m over "
            f"{error['n_features']} features (after a rigid 2D alignment to the truth)"
        )
    print(
        f"  associations: precision {assoc['precision']:.3f}, recall {assoc['recall']:.3f} "
        f"({assoc['true_positives']} of {assoc['true_pairs']} true pairs)"
    )
    for name, robot in metrics["robots"].items():
        own = robot.get("local_map_error") or {}
        alone = (
            f"; its local map alone: RMSE {own['rmse_m']:.3f} m, max {own['max_m']:.3f} m"
            if own.get("rmse_m") is not None
            else ""
        )
        print(f"  {name}: {robot['alignment']}{alone}")
    if error.get("transform") is not None:
        from csam_ros.core.model import se2
        from csam_ros.figures.draw import draw_joined_map

        # the truth brought into the reference frame by the inverse of the scoring alignment
        true_xy = se2.inverse_transform_point(
            np.asarray(error["transform"]), truth.feature_positions
        )
        figure = draw_joined_map(
            summary.result, run_dir / "joined_map.png", truth=true_xy, scenario=summary.scenario
        )
        print(f"  {figure}: the joined map over the true features (grey crosses)")
    return 0


def _truth_of(run_dir: Path, source: str | None) -> GroundTruth | None:
    """The ground truth in the run's bag, or in the bag it replayed (``source``, the path as
    given to ``csam replay``: a relative one is relative to where replay ran, as is the
    current directory's). Only a bag is opened: CliError for anything else."""
    from csam_ros.bag import BagError, inspect_bag, read_bag_messages
    from csam_ros.ros.conversions import truth_from_message
    from csam_ros.ros.topics import FEATURES_TRUTH

    candidates = [(run_dir / "bag", "the run's bag")]
    if source:
        candidates.append((Path(source), "the source named in summary.json"))
    for bag, what in candidates:
        if not bag.exists():
            continue
        try:
            info = inspect_bag(bag)
        except BagError as err:
            raise CliError(f"{bag} ({what}) is not a readable bag: {err}") from None
        if FEATURES_TRUTH.name not in info.topics:
            continue
        for line in info.warnings:
            _warn(line)
        for m in read_bag_messages(bag, [FEATURES_TRUTH.name], on_damage=_warn):
            return truth_from_message(m.message)
    return None


def cmd_bag_recover(args: argparse.Namespace) -> int:
    """Write every message of a cut or damaged bag that still verifies into a new bag."""
    from csam_ros.bag import BagError, recover_bag

    try:
        report = recover_bag(args.bag, args.out)
    except BagError as err:
        raise CliError(str(err)) from None
    for line in report.lines():
        print(line)
    return 0


def cmd_bandwidth(args: argparse.Namespace) -> int:
    """Print what each robot's topics carried, and how it grew over the run."""
    from csam_ros.bag import BagError
    from csam_ros.run.bandwidth import bandwidth_lines, measure_bandwidth

    try:
        bandwidth = measure_bandwidth(args.bag, on_damage=_warn)
    except BagError as err:
        raise CliError(str(err)) from None
    for line in bandwidth_lines(bandwidth):
        print(line)
    return 0


def cmd_import(args: argparse.Namespace) -> int:
    from csam_ros.run.bag_io import write_log_bag

    if args.out.exists():
        raise CliError(f"{args.out} exists: an import never overwrites a bag")
    if args.format == "mrclam":
        from csam_ros.core.model.config_file import ConfigFileError, resolve_config_path
        from csam_ros.datasets.mrclam import (
            MrclamFormatError,
            import_mrclam,
            landmark_swaps_of,
            load_config,
            parse_occlusion,
        )

        try:
            config = load_config(resolve_config_path(args.config or "mrclam"))
        except (ConfigFileError, OSError, ValueError) as err:
            raise CliError(f"--config: {err}") from None
        robots = _robot_numbers(args.robots)
        try:
            occlusion = parse_occlusion(args.occlude) if args.occlude is not None else None
        except ValueError as err:
            raise CliError(f"--occlude: {err}") from None
        try:
            log, report = import_mrclam(
                args.source,
                robots=robots,
                start=args.start,
                duration=args.duration,
                noise=config["noise"],
                landmark_swaps=landmark_swaps_of(config),
                range_scale=config.get("range_scale"),
                occlusion=occlusion,
            )
        except (MrclamFormatError, ValueError) as err:
            raise CliError(str(err)) from None
        print(report.summary())
    else:
        from csam_ros.datasets.slam2d import Slam2dFormatError
        from csam_ros.datasets.slam2d_log import read_slam2d_log

        if args.occlude is not None:
            raise CliError("--occlude is an option of import mrclam")

        try:
            log = read_slam2d_log(args.source)
        except Slam2dFormatError as err:
            raise CliError(str(err)) from None
    count = write_log_bag(log, args.out)
    print(f"wrote {count} messages of {len(log.robots)} robot(s) to {args.out}")
    return 0


def cmd_calibrate(args: argparse.Namespace) -> int:
    """Estimate a data set's noise model and range scales; write them as a config file."""
    from csam_ros.core.model.config_file import ConfigFileError, resolve_config_path
    from csam_ros.datasets.mrclam import MrclamFormatError, landmark_swaps_of, load_config
    from csam_ros.datasets.mrclam_calibration import (
        calibrate_mrclam,
        calibration_config,
        range_scales,
    )

    if args.out.exists():
        raise CliError(f"{args.out} exists: calibrate never overwrites a file")
    if not args.source.is_dir():
        raise CliError(f"{args.source}: no such data set directory")
    if args.rounds < 1:
        raise CliError(f"--rounds must be at least 1, got {args.rounds}")
    try:
        base = resolve_config_path(args.config or "mrclam")
        swaps = landmark_swaps_of(load_config(base))
    except (ConfigFileError, OSError, ValueError) as err:
        raise CliError(f"--config: {err}") from None
    robots = _robot_numbers(args.robots)
    window = f"[{args.start}, {'end' if args.duration is None else args.start + args.duration}] s"
    print(f"calibrating on {args.source}, window {window} (about 40 s for all of Dataset 1)")
    began = time.perf_counter()
    try:
        estimate = calibrate_mrclam(
            args.source,
            landmark_swaps=[] if args.no_swaps else swaps,
            robots=robots,
            start=args.start,
            duration=args.duration,
            rounds=args.rounds,
            progress=lambda line: print(line, flush=True),
        )
    except (MrclamFormatError, ValueError) as err:
        raise CliError(str(err)) from None
    source = f"{args.source} (window {window}, robots {args.robots or 'all'})"
    text = calibration_config(estimate, base, source)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    try:
        with open(args.out, "x") as stream:
            stream.write(text)
    except FileExistsError:
        raise CliError(f"{args.out} exists: calibrate never overwrites a file") from None
    n = estimate.noise
    print(
        f"noise: sigma_range {n.sigma_range:.4f} + {n.sigma_range_per_m:.4f} r m, "
        f"sigma_bearing {n.sigma_bearing:.4f} rad, q = ({n.q_v:.4f}, {n.q_vlat:.4f}, "
        f"{n.q_omega:.4f}), rendezvous factors {n.rendezvous_range_factor:.2f}, "
        f"{n.rendezvous_bearing_factor:.2f}"
    )
    scales = ", ".join(f"robot{k} {v:.4f}" for k, v in range_scales(estimate).items())
    print(f"range scale (measured / true): {scales}")
    print(f"wrote {args.out} ({time.perf_counter() - began:.0f} s)")
    return 0


ISOLATED_HELP = (
    "run the nodes on a private ROS domain, discovery on this host only (default: the "
    "caller's ROS_DOMAIN_ID and discovery range, where RViz, Foxglove or ros2 topic echo see "
    "the run)"
)


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="csam", description=__doc__)
    sub = p.add_subparsers(dest="command", required=True)

    demo = sub.add_parser("demo", help="simulate, smooth, merge and record a scenario")
    demo.add_argument(
        "--scenario",
        default="map_joining",
        help="map_joining, sensor_extension, chain, or a scenario YAML file",
    )
    demo.add_argument("--out", type=Path, help="output directory (default: runs/<name>-<time>)")
    demo.add_argument("--seed", type=int, help="noise seed (default: the scenario's)")
    demo.add_argument(
        "--rate",
        type=float,
        default=8.0,
        help="simulation speed relative to real time (0: as fast as possible)",
    )
    demo.add_argument("--isolated", action="store_true", help=ISOLATED_HELP)
    demo.add_argument(
        "--hosts",
        action="store_true",
        help="each robot (its simulator and smoother) and the base station (merger, recorder) "
        "on a host of its own: network namespaces joined by a bridge (needs root)",
    )
    demo.add_argument(
        "--loss",
        type=float,
        default=0.0,
        help="with --hosts: probability that a host's link drops a packet (e.g. 0.1)",
    )
    demo.add_argument(
        "--link-rate",
        type=float,
        default=0.0,
        metavar="KBIT_S",
        help="with --hosts: each host's link carries at most this many kbit/s each way",
    )
    demo.add_argument(
        "--base-link-rate",
        type=float,
        default=0.0,
        metavar="KBIT_S",
        help="with --hosts: the base station's link (the one every robot's data shares) "
        "carries at most this many kbit/s each way, whatever --link-rate gives the others",
    )
    demo.add_argument(
        "--cut",
        metavar="ROBOT:START-END",
        help="with --hosts: cut that robot's link from START to END wall-clock seconds after "
        "its data starts (the robot goes on alone and comes back)",
    )
    demo.set_defaults(func=cmd_demo)

    replay = sub.add_parser("replay", help="run a recorded bag's sensor topics through C-SAM")
    replay.add_argument("bag", type=Path)
    replay.add_argument("--out", type=Path)
    replay.add_argument("--rate", type=float, default=1.0, help="playback speed (0: max)")
    replay.add_argument(
        "--offline",
        action="store_true",
        help="feed the bag through the core in stamp order, no DDS",
    )
    replay.add_argument(
        "--config",
        type=Path,
        help="YAML with csam:, local_map:, merger: and input: sections (e.g. config/mrclam.yaml)",
    )
    replay.add_argument("--isolated", action="store_true", help=ISOLATED_HELP)
    replay.add_argument(
        "--save-state",
        type=Path,
        help="with --offline: write the replay's state (accepted data, result) to this .npz",
    )
    replay.add_argument(
        "--resume",
        type=Path,
        help="with --offline: continue from a state saved by --save-state (this bag's data "
        "follows its data)",
    )
    replay.set_defaults(func=cmd_replay)

    imp = sub.add_parser("import", help="convert a data set into a bag of sensor topics")
    imp.add_argument("format", choices=["mrclam", "slam2d"])
    imp.add_argument("source", type=Path, help="MR.CLAM data set directory or 2D SLAM file")
    imp.add_argument("--out", type=Path, required=True)
    imp.add_argument("--robots", help="MR.CLAM robots, e.g. 1,2,3")
    imp.add_argument("--start", type=float, default=0.0, help="MR.CLAM: seconds after start")
    imp.add_argument("--duration", type=float, help="MR.CLAM: seconds to import")
    imp.add_argument(
        "--config",
        type=Path,
        help="MR.CLAM: config with the noise model, range scales and truth swaps "
        "(default: the installed mrclam.yaml; see csam calibrate)",
    )
    imp.add_argument(
        "--occlude",
        metavar="ROBOT:START-END[,...]|stress",
        help="MR.CLAM: drop a robot's landmark observations (not those of other robots) over "
        "windows of seconds after the data set's first stamp; 'stress': the robot that sees "
        "landmarks least often, every other 90 s window from 90 s after its start (half its "
        "run)",
    )
    imp.set_defaults(func=cmd_import)

    ev = sub.add_parser("evaluate", help="compare a run with its ground truth: metrics.json")
    ev.add_argument("dir", type=Path)
    ev.set_defaults(func=cmd_evaluate)

    cal = sub.add_parser(
        "calibrate", help="estimate a data set's noise model and range scales: a config file"
    )
    cal.add_argument("format", choices=["mrclam"])
    cal.add_argument("source", type=Path, help="MR.CLAM data set directory")
    cal.add_argument("--out", type=Path, required=True, help="config file to write (new)")
    cal.add_argument(
        "--config",
        type=Path,
        help="config whose window, truth swaps and other sections the new file keeps "
        "(default: the installed mrclam.yaml)",
    )
    cal.add_argument("--no-swaps", action="store_true", help="ignore the config's truth swaps")
    cal.add_argument("--robots", help="robots to calibrate on, e.g. 1,2,3 (default: all)")
    cal.add_argument("--start", type=float, default=0.0, help="seconds after the data start")
    cal.add_argument("--duration", type=float, help="seconds of data to calibrate on")
    cal.add_argument("--rounds", type=int, default=12, help="most expectation-maximisation rounds")
    cal.set_defaults(func=cmd_calibrate)

    bandwidth = sub.add_parser(
        "bandwidth",
        help="bytes per robot, topic and second of a bag, and by tenth of the run what each "
        "robot sent to the base station",
    )
    bandwidth.add_argument("bag", type=Path, help="bag directory or .mcap file")
    bandwidth.set_defaults(func=cmd_bandwidth)

    bag = sub.add_parser("bag", help="bag tools: recover a killed or damaged recording")
    bag_tools = bag.add_subparsers(dest="bag_command", required=True)
    recover = bag_tools.add_parser(
        "recover",
        help="rewrite a bag cut short (recording killed) or with damaged chunks into a "
        "complete one that every reader opens; the bag itself is left as it is",
    )
    recover.add_argument("bag", type=Path, help="bag directory or .mcap file")
    recover.add_argument("--out", type=Path, help="the new bag directory (default: BAG-recovered)")
    recover.set_defaults(func=cmd_bag_recover)
    return p


def _input_errors() -> tuple[type[BaseException], ...]:
    """The errors that bad input raises (each reader names the file and line or key): a
    missing or unreadable file, a file that is not text, a malformed config, scenario, data
    set, 2D SLAM file, summary.json or bag."""
    from csam_ros.bag import BagError
    from csam_ros.core.joining.result import SummaryError
    from csam_ros.core.model.config_file import ConfigFileError
    from csam_ros.datasets.mrclam import MrclamFormatError
    from csam_ros.datasets.slam2d import Slam2dFormatError

    return (
        CliError,
        ConfigFileError,  # and ScenarioError
        MrclamFormatError,
        Slam2dFormatError,
        SummaryError,
        BagError,
        OSError,
        UnicodeDecodeError,
    )


def _one_line(err: BaseException) -> str:
    """An error as one line; an OSError names its file."""
    if isinstance(err, OSError) and err.filename is not None and err.strerror:
        text = f"{err.filename}: {err.strerror}"
    else:
        text = str(err) or type(err).__name__
    return " ".join(text.split())


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    try:
        return args.func(args)
    except _input_errors() as err:  # the last resort: readers raise their own named errors
        print(f"csam {args.command}: {_one_line(err)}", file=sys.stderr)
        return 2
    except LiveRunError as err:
        print(f"csam {args.command}: the run failed: {err}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 130
    except Exception as err:  # the nodes' shutdown on SIGTERM surfaces here
        if type(err).__name__ == "ExternalShutdownException":
            return 143
        raise


if __name__ == "__main__":
    sys.exit(main())
